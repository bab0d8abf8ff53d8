"""One solve from scene file to output folder, without networking.

``prepare`` loads and meshes a scene; ``solve_to`` runs the solver and writes
every output (radiosity.npz, patches.ply, scene.glb, preview images,
report.json).  The CLI and the services call these; they hold no numerics.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from .config import SolverConfig
from .errors import SceneError
from .patches import Patches
from .report import run_report, write_json
from .solve import Solver

__all__ = ["default_patch_size", "prepare", "write_outputs", "solve_to", "resolve_scene", "adopt_divided"]

log = logging.getLogger("dcrad")


def default_patch_size(scene) -> float:
    """Automatic maximum patch edge (m): 1/40 of the scene's box diagonal."""
    used = scene.vertices[np.unique(scene.faces[scene.valid])]
    diag = float(np.linalg.norm(used.max(axis=0) - used.min(axis=0)))
    return diag / 40.0


def resolve_scene(spec: str, workdir: Path) -> Path:
    """A scene path, or a built-in scene name with optional parameters.

    ``office``, ``cornell``, ``furnace`` or ``office:rows=3,cols=4,seed=2`` write the
    generated OBJ/MTL into ``workdir`` and return its path.
    """
    import scenes

    name, _, params = spec.partition(":")
    if Path(spec).exists() or name not in scenes.names():
        return Path(spec)
    kwargs = {}
    for item in filter(None, params.split(",")):
        key, _, value = item.partition("=")
        try:
            kwargs[key.strip()] = int(value) if value.strip().lstrip("-").isdigit() else float(value)
        except ValueError:
            raise SceneError(f"built-in scene '{name}': parameter '{item}' is not key=number") from None
    try:
        return scenes.write_builtin(name, workdir, **kwargs)
    except TypeError as exc:
        raise SceneError(f"built-in scene '{name}': {exc}") from None


def prepare(path, patch_size: float | None = None, scale: float = 1.0):
    """Load, validate and mesh a scene: returns (scene, patches, patch_size used)."""
    from .scene import load_scene

    scene = load_scene(path, scale=scale)
    size = patch_size if patch_size and patch_size > 0 else default_patch_size(scene)
    return scene, scene.patches(size), size


def _is_floor_plan(patches: Patches) -> bool:
    """A multi-room floor: much wider than it is tall (Y up)."""
    ext = patches.bounds[1] - patches.bounds[0]
    return max(ext[0], ext[2]) > 2.5 * max(ext[1], 1e-12)


def write_outputs(out: Path, scene, patches: Patches, width: int = 640, height: int = 480) -> dict:
    """Write every output file; return {name: relative path} of what was written."""
    from . import export, render

    out.mkdir(parents=True, exist_ok=True)
    written = {}
    corners = render.corner_radiosity(patches)
    export.write_radiosity_npz(out / "radiosity.npz", patches, len(scene.faces), {"valid_input": scene.valid})
    written["radiosity"] = "radiosity.npz"
    export.write_patches_ply(out / "patches.ply", patches)
    written["patches"] = "patches.ply"
    export.write_glb(out / "scene.glb", patches, corners)
    written["mesh"] = "scene.glb"

    camera = render.camera_from_dict(scene.camera, width, height) if scene.camera else render.auto_camera(patches, width, height)
    img = render.render(patches, camera, corner_values=corners)
    export.write_png(out / "preview.png", render.tonemap(img))
    export.write_exr(out / "preview.exr", img)
    written["preview_png"] = "preview.png"
    written["preview_exr"] = "preview.exr"
    if _is_floor_plan(patches):
        top = render.topdown_camera(patches, width, height)
        img = render.render(patches, top, mask=render.cutaway_mask(patches), corner_values=corners)
        export.write_png(out / "preview_top.png", render.tonemap(img))
        export.write_exr(out / "preview_top.exr", img)
        written["preview_top_png"] = "preview_top.png"
        written["preview_top_exr"] = "preview_top.exr"
    return written


def adopt_divided(solver, run, boundaries, part, divide, subscenes: int, trace_seconds: float = 0.0) -> dict:
    """Give ``solver`` a divided run's books and choices; return the report's ``divided`` section.

    Used by ``solve_to`` (in process) and by the coordinator (remote workers), which
    adds its own service figures to the returned dict.
    """
    solver.adopt_divided(run, trace_seconds)
    if divide.mode == "binned":
        # dense: a sent and a pending buffer for each crossing of every portal cell and bin
        dense = sum(2 * b.n_cells * b.n_bins * 2 * 3 * 8 for b in boundaries)
        solver.choices.append(f"twin buffers are sparse: at most {run.max_twin_bytes} bytes held, "
                              f"against {dense} bytes dense (sent and pending, every portal cell, bin "
                              f"and crossing)")
        delivered = sum(s.twins_delivered for s in run.states)
        blocks = sum(s.twin_blocks for s in run.states)
        if solver.config.adaptive_bins and delivered:
            solver.choices.append(f"directional resolution where the energy is: {delivered} twin entries "
                                  f"arrived, kept as {blocks} direction blocks (light weaker than one ray "
                                  f"shares coarser bins)")
    if run.stiff is not None:
        from .solve import stiff_choice

        solver.choices.append(stiff_choice(run.stiff, solver.config) + " (for the whole divided job)")
    return {"subscenes": subscenes, "boundaries": len(boundaries), "barriers": run.barriers,
            "mode": divide.mode, "iterations": divide.iterations, "solid": divide.solid,
            "max_twin_bytes": run.max_twin_bytes, "max_barrier_closure": max(run.barrier_closures),
            "partition": part.as_dict()}


class _DividedView:
    """What the progress bar reads, for a divided run."""

    def __init__(self, run, solver):
        self._run, self.stats = run, solver.stats
        self.stats.rays = run.snapshots[-1].rays

    def residual(self):
        return self._run.snapshots[-1].residual

    def elapsed(self):
        return self._run.snapshots[-1].time

    def eta(self):
        return float("nan")


def solve_to(
    path,
    out: Path,
    config: SolverConfig | None = None,
    patch_size: float | None = None,
    scale: float = 1.0,
    on_progress=None,
    should_stop=None,
    width: int = 640,
    height: int = 480,
    divide=None,
    planes=None,
) -> dict:
    """Load, solve and write everything to ``out``; return the report dict.

    ``divide`` (a DivideConfig) with more than one subscene solves divided, in
    process; one subscene (the default) uses the plain solver: no partition, no twins.
    """
    config = config or SolverConfig()
    out = Path(out)
    t0 = time.perf_counter()
    scene, patches, size = prepare(path, patch_size, scale)
    t_load = time.perf_counter() - t0

    t0 = time.perf_counter()
    solver = Solver(patches, config)
    t_build = time.perf_counter() - t0
    divided = None
    if divide is not None and divide.subscenes > 1:
        from .divide import solve_divided

        progress = (lambda run: on_progress(_DividedView(run, solver))) if on_progress else None
        run, subs, boundaries, part = solve_divided(patches, config, divide, planes=planes,
                                                   on_barrier=progress, should_stop=should_stop)
        divided = adopt_divided(solver, run, boundaries, part, divide, len(subs),
                                sum(s.stats.trace_seconds for s in subs))
    else:
        solver.choices.append("one subscene: no partition, no boundaries, no twin buffers")
        solver.run(on_progress=on_progress, should_stop=should_stop)

    t0 = time.perf_counter()
    warnings = list(scene.warnings) + solver.warnings()
    outputs = write_outputs(out, scene, patches, width, height)
    t_out = time.perf_counter() - t0

    settings = config.as_dict() | {"patch_size_m": size, "scale": scale}
    timings = {"load_and_mesh_s": t_load, "embree_build_s": t_build,
               "solve_s": solver.stats.wall_seconds, "outputs_s": t_out}
    report = run_report(scene, solver, settings, timings, warnings, outputs)
    report["divided"] = divided
    write_json(out / "report.json", report)
    for w in warnings:
        log.warning(w)
    return report
