"""Run reports: settings, ledger, rays, timings, snapshots; error-against-time curves.

Every path (in process, in process divided, the coordinator's jobs) hands its
run's books to ``run_report`` as a ``RunBooks`` (a ``Solver`` has the same
attributes), so the three reports are one document: the same sections, the same
``stats`` and ``timings`` keys, warnings and choices from the same code.

timings (s): ``load_and_mesh_s`` (scene file to patches), ``setup_s`` (the Embree
scene; divided: partition, clipping and subscenes), ``solve_s`` (the solve loop),
``outputs_s`` (files and previews).
"""

from __future__ import annotations

import json
import math
import platform
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dcrad.choices import Choices
from dcrad.config import SolverConfig
from dcrad.estimate.noise import SHOWN_SLACK
from dcrad.meshing.patches import Patches
from dcrad.solving.energy import Ledger, escaped_light, flipped_normals, rms_error

if TYPE_CHECKING:  # an annotation only: importing this module does not load the solver
    from dcrad.solving.stiffness import Stiffness

__all__ = ["RunBooks", "TIMINGS", "error_curve", "escaped_light", "flipped_normals", "run_report", "write_json"]

#: the keys of every report's ``timings``
TIMINGS = ("load_and_mesh_s", "setup_s", "solve_s", "outputs_s")


@dataclass
class RunBooks:
    """What a finished run hands to its report: the same for every path.

    patches   : the whole scene's patch table, with the final radiosity and unshot
    stats     : ``solve.Stats`` (shots, rays, batches, barriers, trace and wall s, stopped_by)
    snapshots : ``solve.Snapshot`` list, with B of each in ``snapshot_B``
    back_by_obj : (n_objects,) W that hit back faces, by object index
    choices   : what the run chose and why (choices.Choices: a code and a sentence each)
    divided   : the report's ``divided`` section (None: one subscene)
    """

    patches: Patches
    config: SolverConfig
    ledger: Ledger
    stats: object
    snapshots: list = field(default_factory=list)
    snapshot_B: list = field(default_factory=list)
    back_by_obj: np.ndarray = field(default_factory=lambda: np.zeros(0))
    choices: Choices = field(default_factory=Choices)
    timings: dict[str, float] = field(default_factory=dict)
    divided: dict | None = None
    #: the error estimate at the end (``noise.Estimate``; None: not available)
    estimate: object = None
    #: colour channels tallied (1: a grey scene, copied to the other two)
    channels: int = 3
    #: the ``stiffness.Stiffness`` that last changed how the run shot (None: never stiff)
    stiff: Stiffness | None = None

    @classmethod
    def of_solver(cls, solver, timings: dict[str, float] | None = None) -> "RunBooks":
        """The books of a single ``Solver`` run."""
        return cls(solver.patches, solver.config, solver.ledger, solver.stats, list(solver.snapshots),
                   solver.snapshot_B, solver.back_by_obj.copy(), Choices(solver.choices), dict(timings or {}),
                   estimate=solver.estimate(), channels=solver.channels, stiff=solver.stiff)

    def stiffness(self) -> dict | None:
        """The report's ``stiffness``: the measured return ratio and what it changed (None: not stiff)."""
        st = self.stiff
        if st is None:
            return None
        return {"return_ratio": float(st.ret), "overshoot": bool(st.scale.any()), "ray_factor": float(st.ray_factor)}

    def residual(self) -> float:
        return self.ledger.residual()

    def warnings(self) -> list[str]:
        if any(getattr(s, "outside", False) for s in self.patches.sources):
            # daylight comes from outside the model: most of it meets the model's outside (one-sided
            # interiors: back faces) or misses it, which these two warnings would read as mistakes
            return []
        return flipped_normals(self.ledger, self.back_by_obj, self.patches.names) + escaped_light(self.ledger,
                                                                                                  self.patches)


def error_curve(snapshot_B: list, reference: np.ndarray, area: np.ndarray) -> list[float]:
    """Area-weighted RMS error (W/m^2) of each snapshot against a reference solution."""
    return [rms_error(b, reference, area) for b in snapshot_B]


def residual_estimate(residual: float, radiosity: np.ndarray, area: np.ndarray) -> float:
    """Live RMS estimate while B* is unknown: residual times the area-weighted RMS of B.

    The unshot share of the energy bounds how much B can still change on average;
    this is an estimate, not a measurement, and reports say so.
    """
    total = float(area.sum())
    if total <= 0:
        return 0.0
    mean_sq = float(np.dot((radiosity * radiosity).mean(axis=1), area) / total)
    return residual * math.sqrt(mean_sq)


def error_section(est) -> dict | None:
    """report.json ``error``: the estimated RMS error of the returned B against the converged
    solution of the same discrete problem (noise.Estimate), with a note on what it covers."""
    if est is None:
        return None
    out = {k: (v if not isinstance(v, float) or math.isfinite(v) else None) for k, v in est.as_dict().items()}
    out["note"] = ("estimate, not a measurement: rms in W/m^2, rms_norm over RMS(B), rms_refl/noise_refl/"
                   "bias_refl over RMS(B - E) of the reading the accuracy target holds (B per input triangle, "
                   f"the elements within {SHOWN_SLACK:g}x of it), triangles_refl per input triangle "
                   "(radiosity.npz's B), elements_refl per element (the previews and meshes, rendered from "
                   "this B, unfiltered)")
    return out


def run_report(scene, solver, settings: dict, timings: dict, warnings: list[str], outputs: dict) -> dict:
    """The JSON-ready report of one solve; ``solver``: its ``RunBooks`` (or a ``Solver``)."""
    p = solver.patches
    snaps = [s.as_dict() for s in solver.snapshots]
    for s in snaps:
        s["rms_estimate"] = s.get("error_rms")
    est = getattr(solver, "estimate", None)
    est = est() if callable(est) else est
    # measured error of every snapshot against the final state (the run's own limit)
    final = p.radiosity
    for s, b in zip(snaps, solver.snapshot_B):
        s["rms_vs_final"] = rms_error(b, final, p.area)
    stats = solver.stats.as_dict()
    wall = max(stats["wall_seconds"], 1e-12)
    return {
        "dcrad_report": 1,
        "scene": {
            "path": str(scene.path),
            "input_triangles": int(len(scene.faces)),
            "valid_triangles": int(scene.valid.sum()),
            "patches": int(len(p)),
            "objects": len(scene.names),
            "total_area_m2": float(p.area.sum()),
            "bounds_m": p.bounds.tolist(),
        },
        "settings": settings,
        "ledger": solver.ledger.as_dict(),
        "residual": solver.residual(),
        "error": error_section(est),
        "stats": stats,
        "rays_per_second": stats["rays"] / wall,
        "trace_share": stats["trace_seconds"] / wall,
        "timings": timings,
        "warnings": list(warnings),
        "choices": Choices(getattr(solver, "choices", [])).as_json(),
        "snapshots": snaps,
        "snapshot_note": (
            "rms_estimate (= error_rms; error_refl over RMS(B - E)): the live error estimate, "
            "noise from two independent half-solutions plus the unshot bias (B* unknown); "
            "rms_vs_final: measured against this run's final state, which "
            "itself carries the final residual"
        ),
        "outputs": outputs,
        "platform": {"python": platform.python_version(), "machine": platform.machine()},
    }


def write_json(path: Path, data: dict) -> None:
    def default(o):
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, np.generic):
            return o.item()
        raise TypeError(f"not JSON serialisable: {type(o)}")

    Path(path).write_text(json.dumps(data, indent=1, default=default, allow_nan=False))
