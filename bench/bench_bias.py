"""Where the estimate's bias term is right: the systematic part of a run's error, by layout.

For each scene (unclustered, in this process): a run at defaults, then a reference of the same
mesh at --accuracy 0.004 with another seed; the difference B* - B is fitted as a (B - E) + b rho
(area-weighted least squares: the relative layout the estimate assumes, and a uniform irradiance).
Prints the estimate's bias and noise, the measured total, the fitted systematic part and the mean
relative shortfall.  No assertions.

Run: .venv/bin/python bench/bench_bias.py [scene ...]   (default: ../shared/models/office2 and cornell)
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dcrad.config import SolverConfig  # noqa: E402
from dcrad.pipeline import prepare, resolve_scene  # noqa: E402
from dcrad.solving.passes import solve_to_accuracy  # noqa: E402


def one(spec: str, tmp: Path) -> str:
    _, p, _ = prepare(resolve_scene(spec, tmp))
    p.cluster[:] = -1
    s = solve_to_accuracy(p, SolverConfig(seed=3))
    est = s.estimate()
    b_run = p.radiosity.copy()
    e, rho = p.emission, p.rho
    p.reset()
    solve_to_accuracy(p, SolverConfig(accuracy=0.004, seed=11))
    b_ref = p.radiosity.copy()
    d, r, q = (b_ref - b_run).ravel(), (b_run - e).ravel(), rho.ravel()
    w = np.repeat(p.area, 3)
    (a, b), *_ = np.linalg.lstsq(np.stack([r, q], 1) * np.sqrt(w)[:, None], d * np.sqrt(w), rcond=None)
    ref = np.sqrt((w * (b_ref - e).ravel() ** 2).sum() / w.sum())
    fit = np.sqrt((w * (a * r + b * q) ** 2).sum() / w.sum()) / ref
    total = np.sqrt((w * d ** 2).sum() / w.sum()) / ref
    short = (w * d).sum() / (w * (b_ref - e).ravel()).sum()
    return (f"{spec}: stopped by {s.stats.stopped_by}; estimated bias {est.bias_refl:.4f}, noise {est.noise_refl:.4f}; "
            f"measured {total:.4f}, of it systematic {fit:.4f} (a = {a:.4f}, b = {b:.3g} W/m^2); mean relative "
            f"shortfall {short:.4f}")


def main() -> None:
    specs = sys.argv[1:] or [str(ROOT.parent / "shared" / "models" / "office2" / "scene.obj"), "cornell"]
    with tempfile.TemporaryDirectory() as tmp:
        for spec in specs:
            print(one(spec, Path(tmp)), flush=True)


if __name__ == "__main__":
    main()
