"""Built-in scenes, written as Wavefront OBJ + MTL text files.

Conventions (all generators): metres, +Y up, triangles only, counter-clockwise
seen from the front side (the side that receives / emits light); MTL ``Kd`` is
the diffuse reflectance in [0, 1) and ``Ke`` the emitted exitance in W/m^2.
See :mod:`scenes.objwriter` for the file format details.

>>> from scenes import write_builtin
>>> path = write_builtin("cornell", "out/")            # doctest: +SKIP
>>> path = write_builtin("office", "out/", seed=3)     # doctest: +SKIP
"""

from __future__ import annotations

import pathlib
from collections.abc import Callable
from typing import NamedTuple

from .cie import cie_room
from .cornell import cornell_box
from .furnace import furnace_box, furnace_expected
from .office import office_floor

__all__ = [
    "BUILTIN",
    "names",
    "describe",
    "write_builtin",
    "cornell_box",
    "office_floor",
    "furnace_box",
    "furnace_expected",
    "cie_room",
]


class Builtin(NamedTuple):
    """A registered generator: ``generator(folder, stem=..., **params) -> Path``."""

    generator: Callable[..., pathlib.Path]
    description: str


BUILTIN: dict[str, Builtin] = {
    "cornell": Builtin(
        cornell_box,
        "Cornell box (measured geometry, 0.55 m, open front at z=0, camera on -Z looking +Z)",
    ),
    "office": Builtin(
        office_floor,
        "office storey: rows x cols rooms joined by doors, seeded lights and furniture, closed",
    ),
    "cie_room": Builtin(
        cie_room,
        "CIE 171:2006 case 5.3 layout: 4 x 4 x 3 m black room, 1 x 1 m ceiling panel, floor and a wall gridded",
    ),
    "furnace": Builtin(
        furnace_box,
        "closed 1 m cube, uniform reflectance, ceiling light square: exact energy-balance test",
    ),
}


def names() -> list[str]:
    """Sorted names of the built-in scenes."""
    return sorted(BUILTIN)


def _get(name: str) -> Builtin:
    try:
        return BUILTIN[name]
    except KeyError:
        raise ValueError(f"unknown scene {name!r}; known scenes: {', '.join(names())}") from None


def describe(name: str) -> str:
    """One-line description of built-in scene ``name``."""
    return _get(name).description


def write_builtin(name: str, folder, **params) -> pathlib.Path:
    """Write ``<folder>/<name>.obj`` and ``<name>.mtl`` (folder created) and
    return the OBJ path.  ``params`` go to the generator (e.g. ``seed`` for the
    office).  Unknown ``name`` -> ``ValueError`` listing the known names."""
    entry = _get(name)
    params.setdefault("stem", name)
    return entry.generator(pathlib.Path(folder), **params)
