"""One exception tree for dcrad.

::

    DcradError                 base: the CLI catches it, prints one line, exits 2
    ├── SceneError             the scene file or its contents are unusable
    │   ├── SceneFormatError   unreadable / malformed file, unsupported format
    │   └── SceneValueError    bad values: non-finite coordinates, rho outside [0, 1), E < 0
    ├── ConfigError            a setting is out of range (also a ValueError)
    ├── PartitionError         a partition cannot be built as asked
    ├── SolveError             the solver hit an internal problem it can name
    └── ExchangeError          twin buffers or arrays that do not fit their boundary
"""

from __future__ import annotations

__all__ = [
    "DcradError",
    "SceneError",
    "SceneFormatError",
    "SceneValueError",
    "ConfigError",
    "PartitionError",
    "SolveError",
    "ExchangeError",
]


class DcradError(Exception):
    """Base of every error dcrad raises on purpose."""


class SceneError(DcradError):
    """The scene cannot be used; the message names the file and object."""


class SceneFormatError(SceneError):
    """The file cannot be read or parsed."""


class SceneValueError(SceneError):
    """The file parses but holds values dcrad cannot solve."""


class ConfigError(DcradError, ValueError):
    """A setting is out of its allowed range."""


class PartitionError(DcradError):
    """The scene cannot be split as asked."""


class SolveError(DcradError):
    """The solver met a problem it can name."""


class ExchangeError(DcradError):
    """Boundary buffers do not match their boundary."""
