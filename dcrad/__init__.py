"""dcrad: divide-and-conquer radiosity (diffuse global illumination), in one process or on workers.

The public API, for use from Python (the ``dcrad`` command and the gRPC services in
``coordinator`` and ``worker`` are the other ways in):

``load(path, scale=1.0, up=None, *, two_sided=False) -> Scene``
    Read and validate a scene file (.obj/.mtl, .gltf, .glb).
``solve(scene_or_path, out=None, accuracy=0.02, patch_size=None, *, ..., **settings) -> Result``
    Solve in this process; the ``Result`` holds B per patch and per input triangle, the error
    estimate and the report; ``out`` (a folder) also writes every output file, as ``dcrad solve``.
``Result``, ``Scene``, ``Patches``, ``Estimate``, ``SolverConfig``
    What those return and take (``SolverConfig``'s fields are ``solve``'s ``settings``).
``PointSource``
    A point light with an intensity distribution, for ``solve``'s ``sources`` (emitters.py).
``DaylightSpec``
    The sky, the sun and the ground outside, for ``solve``'s ``sky`` (transport/sky.py).
``DcradError``, ``SceneError``, ``ConfigError``
    The errors: every error dcrad raises on bad input is a ``DcradError``.

``import dcrad`` loads neither numpy nor Embree: the names above other than the errors are
imported when first used (PEP 562), since the command and the workers import this package at
start.  ``dcrad.solve`` is the function; the solver itself is ``dcrad.solving.solver.Solver``.

Example: the built-in Cornell box, coarsely meshed (a second or two):

>>> import tempfile
>>> from pathlib import Path
>>> import dcrad
>>> from dcrad.pipeline import resolve_scene
>>> with tempfile.TemporaryDirectory() as tmp:
...     scene = dcrad.load(resolve_scene("cornell", Path(tmp)))
...     result = dcrad.solve(scene, accuracy=0.05, patch_size=0.1)
>>> result.triangle_radiosity.shape == (len(scene.faces), 3)
True
>>> result.estimate.rms_refl <= 0.05  # the estimated error met the target
True
>>> result.report["stats"]["stopped_by"], result.report["ledger"]["closure"] < 1e-9
('accuracy', True)
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from dcrad.errors import ConfigError, DcradError, SceneError

if TYPE_CHECKING:
    from dcrad.api import Result, load, solve
    from dcrad.config import SolverConfig
    from dcrad.estimate.noise import Estimate
    from dcrad.io.scene import Scene
    from dcrad.meshing.patches import Patches
    from dcrad.transport.emitters import PointSource
    from dcrad.transport.sky import DaylightSpec

__all__ = ["load", "solve", "Result", "Scene", "Patches", "Estimate", "SolverConfig", "PointSource", "DaylightSpec",
           "DcradError", "SceneError", "ConfigError"]


def __getattr__(name: str) -> Any:
    """The API's names other than the errors, imported when first used (PEP 562)."""
    value: Any
    if name in ("load", "solve", "Result"):
        from dcrad import api

        value = getattr(api, name)
    elif name == "Scene":
        from dcrad.io.scene import Scene as value
    elif name == "Patches":
        from dcrad.meshing.patches import Patches as value
    elif name == "Estimate":
        from dcrad.estimate.noise import Estimate as value
    elif name == "SolverConfig":
        from dcrad.config import SolverConfig as value
    elif name == "PointSource":
        from dcrad.transport.emitters import PointSource as value
    elif name == "DaylightSpec":
        from dcrad.transport.sky import DaylightSpec as value
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value
