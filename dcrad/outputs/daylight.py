"""Daylight results: the daylight factor DF = E / E_hz x 100 (E_hz: the unobstructed horizontal
illuminance of the sky alone, transport/sky.py) per patch and on the work plane, and the report's
``daylight`` section: the sky, per surface and per work plane (and room) the average and minimum
DF and the uniformity DF_min / DF_avg.

E counts all the light of the run: with the sun, or luminaires, in the run, the DF is theirs too
(the section says so); the classic daylight factor is a run under an overcast sky alone.  Where
every surface is black, the interior reflects nothing and the DF is the sky component (SC).
"""

from __future__ import annotations

import numpy as np

__all__ = ["sky_of", "factor", "section", "picture_scale"]


def sky_of(patches):
    """The SkyModel of the run's sky (transport/sky.py), or None when the run is not daylit."""
    for s in patches.sources:
        model = getattr(s, "model", None)
        if model is not None and hasattr(model, "horizontal_lux"):
            return model
    return None


def factor(lux, model) -> np.ndarray:
    """Daylight factor, percent, of illuminance ``lux`` (lux, an array or a number) under ``model``."""
    return np.asarray(lux, np.float64) * (100.0 / model.horizontal_lux())


def _df_stats(entry: dict, scale: float) -> dict:
    """A photometry.stats entry (lux) as daylight factors (percent)."""
    return {"DF_avg_pct": entry["E_avg_lux"] * scale, "DF_min_pct": entry["E_min_lux"] * scale,
            "DF_max_pct": entry["E_max_lux"] * scale, "uniformity": entry["uniformity"]}


def section(patches, surfaces: list[dict] | None, grid: dict | None) -> dict | None:
    """The report's ``daylight`` section (None when the run is not daylit)."""
    model = sky_of(patches)
    if model is None:
        return None
    scale = float(factor(1.0, model))
    others = [getattr(s, "name", "?") for s in patches.sources
              if not getattr(s, "outside", False)]
    sun = any(getattr(s, "outside", False) and getattr(s, "exact", False) for s in patches.sources)
    counts = ["sky", *(["sun"] if sun else []), *(["emitting surfaces"] if np.any(patches.emission > 0) else []),
              *others]
    out: dict = {"sky": model.describe(), "E_hz_lux": model.horizontal_lux(),
                 "sky_component": not bool(np.any(patches.rho > 0)), "counts": ", ".join(counts),
                 "method": "DF = E / E_hz x 100, E the illuminance of the run (photometry), E_hz the sky's "
                           "unobstructed horizontal illuminance"}
    if surfaces is not None:
        out["surfaces"] = [{"name": s["name"], "area_m2": s["area_m2"], **_df_stats(s, scale)} for s in surfaces]
    if grid is not None:
        wp = {"height_m": grid["height_m"], "n_points": grid["n_points"], **_df_stats(grid, scale)}
        if grid.get("rooms"):
            wp["rooms"] = [{"area_m2": r.get("area_m2"), **_df_stats(r, scale)} for r in grid["rooms"]]
        out["workplane"] = wp
    return out


def picture_scale(patches) -> float | None:
    """Lux -> DF percent for the daylight-factor picture (None: not daylit)."""
    model = sky_of(patches)
    return None if model is None else float(factor(1.0, model))

