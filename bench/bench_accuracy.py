"""Error against rays and seconds at several accuracy targets, estimate beside measured.

For each scene: a reference solution from a long plain-shooting run with another
seed (its own estimated noise is subtracted in quadrature from the measured
error, and the raw figure is printed too), then one run per accuracy target with
and without the direct-light gather (``--no-direct``: the emitters are shot
with rays).  Prints a markdown table: rays, seconds, how the run stopped, the
estimate (over RMS of B - E), the measured error over RMS(B - E) and over RMS(B),
and estimate / measured, and the measured error times sqrt(rays / 1e6) (lower: more accuracy
per ray), and the CPU seconds of the solve (the machine is shared: wall seconds are loose).
With the direct light gathered from exact form factors, an accuracy run shoots the
reflected light coarsely and gathers it again at the end (final.py, accuracy.FinalPlan).
``--fixed 4e6`` runs converged solves at fixed densities instead of targets (no final gather).
``--budgets 1e6,2e6`` runs the first accuracy target under each ray budget (``--max-rays``).

    .venv/bin/python bench/bench_accuracy.py --scenes cornell,office --accuracies 0.1,0.05,0.03,0.02
    .venv/bin/python bench/bench_accuracy.py --scenes cornell --fixed 4e6 --cache /tmp/refs
    .venv/bin/python bench/bench_accuracy.py --scenes office --gather on --budgets 1e6,2e6,3e6 --ref-accuracy 0.004
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dcrad.config import SolverConfig  # noqa: E402
from dcrad.pipeline import prepare, resolve_scene  # noqa: E402
from dcrad.solving.energy import rms_error  # noqa: E402
from dcrad.solving.passes import solve_to_accuracy  # noqa: E402
from dcrad.solving.solver import Solver  # noqa: E402
from dcrad.transport.rays import Tracer  # noqa: E402


def rms(x: np.ndarray, area: np.ndarray) -> float:
    return math.sqrt(float(np.dot((x * x).mean(axis=1), area) / area.sum()))


def reference(patches, tracer, rays_per_power: float, cache: Path | None, accuracy: float = 0.0):
    """B* from a long plain-shooting run (seed 999), and its own estimated RMS noise (W/m^2).

    accuracy > 0: from an accuracy run at that target instead (seed 999; with the direct
    light gathered and the final gather: far less noise per ray, but the same method as
    the runs measured, so the plain-shooting reference is the check on its bias).
    """
    if cache is not None and cache.exists():
        z = np.load(cache)
        return z["B"], float(z["noise"])
    patches.reset()
    t = time.perf_counter()
    if accuracy > 0:
        s = solve_to_accuracy(patches, SolverConfig(seed=999, accuracy=accuracy), tracer)
    else:
        s = Solver(patches, SolverConfig(seed=999, tol=1e-4, rays_per_power=rays_per_power, direct=False),
                   tracer=tracer)
        s.run()
    est = s.estimate()
    print(f"reference: {s.stats.rays / 1e6:.1f} M rays, {time.perf_counter() - t:.0f} s, estimated noise "
          f"{est.noise_refl:.4f} of the reflected light", flush=True)
    if cache is not None:
        np.savez(cache, B=patches.radiosity, noise=est.rms)
    return patches.radiosity.copy(), est.rms


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="cornell,office",
                    help="comma-separated, or ;-separated when a scene has parameters ('office:rows=8,cols=8;cornell')")
    ap.add_argument("--accuracies", default="0.1,0.05,0.03,0.02")
    ap.add_argument("--ref-rays-per-power", type=float, default=2e7)
    ap.add_argument("--ref-accuracy", type=float, default=0.0, help="reference from an accuracy run at this target "
                    "(direct gather + final gather) instead of plain shooting at --ref-rays-per-power")
    ap.add_argument("--cache", default="", help="folder to keep reference solutions in between runs")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--gather", default="on,off", help="direct-light gather: on, off or on,off")
    ap.add_argument("--fixed", default="", help="instead of accuracy targets: converged runs (tol 1e-3) at these "
                    "rays per power, e.g. 4e6 (error per ray at a fixed density)")
    ap.add_argument("--budgets", default="", help="instead of targets: runs at the first accuracy target within "
                    "these ray budgets (--max-rays), e.g. 1e6,2e6")
    ap.add_argument("--shadow-rays", type=int, default=0, help="shadow rays per patch (0: automatic)")
    args = ap.parse_args()
    accuracies = [float(a) for a in args.accuracies.split(",")]
    fixed = [float(a) for a in args.fixed.split(",") if a.strip()]
    budgets = [int(float(b)) for b in args.budgets.split(",") if b.strip()]
    gathers = [g.strip() == "on" for g in args.gather.split(",")]
    what = "rays per power" if args.fixed else "budget" if budgets else "target"
    print(f"| scene | patches | gather | {what} | rays (M) | s | stopped by | "
          "estimate refl | measured refl | measured norm | est/meas | refl x sqrt(Mrays) | cpu s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name in [n for n in args.scenes.split(";" if ";" in args.scenes else ",") if n]:
            path = resolve_scene(name, Path(tmp) / name)
            _, patches, _ = prepare(path)
            tracer = Tracer(patches.triangles)
            key = f"acc{args.ref_accuracy:g}" if args.ref_accuracy > 0 else f"{args.ref_rays_per_power:g}"
            cache = Path(args.cache) / f"ref_{name}_{key}.npz" if args.cache else None
            ref, ref_noise = reference(patches, tracer, args.ref_rays_per_power, cache, args.ref_accuracy)
            area = patches.area
            rms_b, rms_r = rms(ref, area), rms(ref - patches.emission, area)
            for gather in gathers:
                for acc in fixed or budgets or accuracies:
                    patches.reset()
                    cfg = (SolverConfig(seed=args.seed, tol=1e-3, rays_per_power=acc, direct=gather,
                                        shadow_rays=args.shadow_rays) if fixed else
                           SolverConfig(seed=args.seed, accuracy=accuracies[0], direct=gather,
                                        shadow_rays=args.shadow_rays, max_rays=int(acc)) if budgets else
                           SolverConfig(seed=args.seed, accuracy=acc, direct=gather, shadow_rays=args.shadow_rays))
                    t, cpu = time.perf_counter(), time.process_time()
                    s = solve_to_accuracy(patches, cfg, tracer)
                    dt, cpu = time.perf_counter() - t, time.process_time() - cpu
                    est = s.estimate()
                    raw = rms_error(patches.radiosity, ref, area)
                    meas = math.sqrt(max(raw * raw - ref_noise * ref_noise, 1e-300))
                    print(f"| {name} | {len(patches)} | {'on' if gather else 'off'} | {acc:g} | "
                          f"{s.stats.rays / 1e6:.2f} | {dt:.1f} | {s.stats.stopped_by} | {est.rms_refl:.4f} | "
                          f"{meas / rms_r:.4f} (raw {raw / rms_r:.4f}) | {meas / rms_b:.4f} | "
                          f"{est.rms_refl / (meas / rms_r):.2f} | {meas / rms_r * math.sqrt(s.stats.rays / 1e6):.4f} | "
                          f"{cpu:.1f} |",
                          flush=True)


if __name__ == "__main__":
    main()
