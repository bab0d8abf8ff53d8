"""Run reports: settings, ledger, rays, timings, snapshots; error-against-time curves."""

from __future__ import annotations

import json
import math
import platform
from pathlib import Path

import numpy as np

from .energy import rms_error

__all__ = ["error_curve", "run_report", "write_json"]


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


def run_report(scene, solver, settings: dict, timings: dict, warnings: list[str], outputs: dict) -> dict:
    """The JSON-ready report of one solve."""
    p = solver.patches
    snaps = [s.as_dict() for s in solver.snapshots]
    for s, b in zip(snaps, solver.snapshot_B):
        s["rms_estimate"] = residual_estimate(s["residual"], b, p.area)
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
        "stats": stats,
        "rays_per_second": stats["rays"] / wall,
        "trace_share": stats["trace_seconds"] / wall,
        "timings": timings,
        "warnings": list(warnings),
        "choices": list(getattr(solver, "choices", [])),
        "snapshots": snaps,
        "snapshot_note": (
            "rms_estimate: live estimate from the residual (B* unknown); "
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
