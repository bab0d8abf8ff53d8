"""The public API's functions: ``load``, ``solve`` and the ``Result`` it returns.

``dcrad/__init__.py`` lists the API and imports this module when one of its names is first
used, so that ``import dcrad`` stays cheap.  Both functions call the pipeline every other
path runs (``pipeline.prepare``, ``runs.Single``, ``pipeline.finish_run``): the
numbers and the report are those of ``dcrad solve --workers 0``.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dcrad import pipeline
from dcrad.config import SolverConfig
from dcrad.errors import ConfigError
from dcrad.estimate.noise import Estimate
from dcrad.io.export import input_triangle_radiosity
from dcrad.io.scene import Scene, load_scene
from dcrad.meshing.patches import Patches
from dcrad.runs import RunHooks, Single
from dcrad.transport.emitters import Emitter
from dcrad.transport.sky import DaylightSpec

__all__ = ["Result", "load", "solve"]

log = logging.getLogger("dcrad")


@dataclass(frozen=True, eq=False)  # eq: arrays do not compare to one bool
class Result:
    """A finished solve (``dcrad.solve``).

    scene              : the ``Scene`` solved (input triangles, materials)
    patches            : its ``Patches`` (the elements), with the final B in ``patches.radiosity``
    radiosity          : (n, 3) float64 B per patch, W/m^2 (the same array as ``patches.radiosity``)
    triangle_radiosity : (T, 3) float64 B per input triangle of ``scene.faces``: the area-weighted
                         mean of its patches, front side (radiosity.npz's ``B``)
    triangle_valid     : (T,) bool, False for input triangles without patches (B = 0 there)
    estimate           : the estimated RMS error of B (``Estimate``: ``rms_refl`` is the one
                         ``accuracy`` aims at); None if the run kept none
    report             : the run's report, the dict ``report.json`` holds
    out                : the folder the outputs were written to, or None
    """

    scene: Scene
    patches: Patches
    radiosity: np.ndarray
    triangle_radiosity: np.ndarray
    triangle_valid: np.ndarray
    estimate: Estimate | None
    report: dict
    out: Path | None = None


def load(path: str | os.PathLike, scale: float = 1.0, up: str | None = None, *, two_sided: bool = False) -> Scene:
    """Read and validate a scene file (.obj with its .mtl, .gltf, .glb): its triangles and materials.

    ``scale`` multiplies every coordinate (the solver works in metres); ``up``: the file's up
    axis (x, y, z, -x, -y, -z; None detects it); ``two_sided``: every surface reflects on both
    sides.  Raises ``SceneError`` for a file that cannot be read or holds bad values,
    ``ConfigError`` for a bad ``scale`` or ``up``.  A built-in scene (``cornell``, ``office``,
    ``furnace``, ...) is written to a folder first: ``dcrad.pipeline.resolve_scene(name, folder)``.
    """
    return load_scene(path, scale=scale, up=up, two_sided=two_sided)


def solve(scene_or_path: Scene | str | os.PathLike, out: str | os.PathLike | None = None, accuracy: float = 0.02,
          patch_size: float | None = None, *, scale: float = 1.0, up: str | None = None, two_sided: bool = False,
          workplane: float = 0.0, width: int = 640, height: int = 480,
          on_progress: Callable[[Any], None] | None = None, should_stop: Callable[[], bool] | None = None,
          sources: Sequence[Emitter] = (), luminaires: str | os.PathLike | None = None,
          sky: str | DaylightSpec | None = None, **settings: Any) -> Result:
    """Solve a scene in this process (one subscene: no partition, no workers) and return a ``Result``.

    scene_or_path : a ``Scene`` (``dcrad.load``) or a scene file's path
    out           : a folder to write the outputs to (radiosity.npz, patches.ply, scene.glb, the
                    preview images, report.json), as ``dcrad solve`` does; None (the default):
                    nothing is written, and the report has no ``photometry`` section (the outputs
                    compute the lux) and no ``outputs``
    accuracy      : the target estimated RMS error over the RMS of the reflected light B - E
    patch_size    : element size in metres; None or 0: automatic (from the scene's mean free path)
    scale, up, two_sided : how a path is loaded (see ``load``); a ``Scene`` was loaded with them
                    already, and then ``scale`` only goes into the report's settings
    workplane     : with ``out``, a work-plane illuminance grid this many metres above the floor
    width, height : the preview images' size, with ``out``
    on_progress   : called with the solver after each batch (``dcrad.outputs.progress.Progress`` reads it)
    should_stop   : polled between batches; True stops the run cleanly (the result is still whole)
    sources       : light sources that are not surfaces of the scene (``dcrad.PointSource``, any
                    ``emitters.Emitter``), in the scene's coordinates after ``scale`` (metres),
                    beside the file's own point and spot lights (glTF ``KHR_lights_punctual``,
                    ``Scene.sources``; the report gains a ``gltf_lights`` section)
    luminaires    : a luminaire schedule (JSON: photometric files placed in the scene file's own
                    coordinates and units, ``luminaires.load_schedule``), lighting the scene beside
                    ``sources``; the report gains a ``luminaires`` section
    sky           : daylight from outside: a sky's name ("uniform", "cie-overcast", "iso:N", ...) or a
                    ``DaylightSpec`` (the sun, the site and time, the illuminances, the ground), as
                    ``dcrad solve --sky``; with ``out`` the outputs gain the daylight factors
    settings      : any other ``SolverConfig`` field by name (``seed=3``, ``time_limit=10``, ...)

    Raises ``SceneError`` for a bad scene file and ``ConfigError`` for a bad setting.
    """
    unknown = sorted(set(settings) - {f.name for f in dataclasses.fields(SolverConfig)})
    if unknown:
        raise ConfigError(f"dcrad.solve: unknown setting(s) {', '.join(unknown)}: the keywords after patch_size "
                          f"are those of dcrad.solve and the fields of dcrad.SolverConfig")
    config = SolverConfig(accuracy=accuracy, **settings)
    daylight = DaylightSpec(sky) if isinstance(sky, str) else sky
    if daylight is not None:
        daylight.check()
    lit = pipeline.light_sources(luminaires, daylight, scale)  # as `dcrad solve` and the service
    given = scene_or_path if isinstance(scene_or_path, Scene) else None
    t0 = time.perf_counter()
    phases: dict = {}
    scene, patches, size = pipeline.prepare(
        scene_or_path if given is None else given.path, patch_size, scale, up, two_sided, timings=phases,
        loaded=None if given is None else (given, 0.0), workplane=workplane,
        # the file's own lights (glTF) first, then these: the mesh is refined for them too
        sources=lambda sc: (*sources, *(lit(sc) if lit is not None else ())))
    timings = {"load_and_mesh_s": time.perf_counter() - t0, **phases}
    single = Single()
    books = single.run(patches, config, RunHooks(should_stop=should_stop, on_batch=on_progress), timings)
    folder = Path(out) if out is not None else None
    report = pipeline.finish_run(folder, scene, books, pipeline.scene_settings(scene, size, scale, two_sided,
                                                                                workplane),
                                 width, height, tracer=single.tracer)
    for w in report["warnings"]:
        log.warning(w)
    per_triangle, valid = input_triangle_radiosity(books.patches, len(scene.faces))
    estimate = books.estimate if isinstance(books.estimate, Estimate) else None
    return Result(scene, books.patches, books.patches.radiosity, per_triangle, valid, estimate, report, folder)
