"""Divide and conquer on office floors: time and iterations to a target error, twin memory,
and the divided-versus-unsplit converged error for each boundary mode.

Prints figures; asserts nothing.  Run: ``.venv/bin/python bench/bench_divide.py``
(``--sizes 2x3,3x4 --ks 1,2,4 --tol 0.01``).

- Error is the area-weighted RMS against a reference (an unsplit run with 10x the
  rays per unit power, tol 1e-3), normalised by the RMS of the reference.
- "iterations" are shots summed over all subscenes (the paper's n).  This machine
  has 2 cores and subscenes run one after another here, so iterations are the
  figure that does not depend on cores.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

import scenes
from dcrad.config import SolverConfig
from dcrad.division.divide import DivideConfig, solve_divided
from dcrad.pipeline import prepare
from dcrad.solving.energy import rms_error
from dcrad.solving.solver import Solver


def first_below(xs, errs, target):
    """Log-interpolated x where the error first falls below target (nan if never)."""
    for i in range(1, len(errs)):
        if errs[i] <= target < errs[i - 1]:
            a, b = np.log(errs[i - 1]), np.log(errs[i])
            f = (np.log(target) - a) / (b - a)
            return xs[i - 1] + f * (xs[i] - xs[i - 1])
    return 0.0 if errs and errs[0] <= target else float("nan")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="2x3,3x4")
    ap.add_argument("--ks", default="1,2,4")
    ap.add_argument("--tol", type=float, default=0.01)
    ap.add_argument("--targets", default="0.2,0.1")
    args = ap.parse_args(argv)
    ks = [int(k) for k in args.ks.split(",")]
    targets = [float(t) for t in args.targets.split(",")]
    tmp = Path(tempfile.mkdtemp())

    for size in args.sizes.split(","):
        rows, cols = map(int, size.split("x"))
        path = scenes.write_builtin("office", tmp / size, rows=rows, cols=cols)
        _, ref, _ = prepare(path)
        Solver(ref, SolverConfig(tol=1e-3, rays_per_power=2e6, seed=1234)).run()
        scale = float(np.sqrt(np.dot((ref.radiosity ** 2).mean(axis=1), ref.area) / ref.area.sum()))
        print(f"\noffice {size}: {len(ref)} patches; reference RMS(B*) = {scale:.4f} W/m^2")
        head = "  ".join(f"t@{t:g} / n@{t:g}" for t in targets)
        print(f"{'k':>2} {'mode':>6} {'wall s':>7} {'shots':>8} {'rays':>10} {'final nRMS':>10}  {head}"
              "  twin bytes (max) / per portal cell")
        for k in ks:
            for mode in (["binned", "exact"] if k > 1 else ["-"]):
                _, p, _ = prepare(path)
                cfg = SolverConfig(tol=args.tol, seed=7)
                if k == 1:
                    s = Solver(p, cfg)
                    s.run()
                    snaps, bs, wall, twin, cells = s.snapshots, s.snapshot_B, s.stats.wall_seconds, 0, 0
                else:
                    run, subs, bnds, part = solve_divided(p, cfg, DivideConfig(subscenes=k, mode=mode))
                    snaps, bs, wall, twin = run.snapshots, run.snapshot_B, run.wall_seconds, run.max_twin_bytes
                    cells = sum(b.n_cells for b in bnds)
                errs = [rms_error(b, ref.radiosity, ref.area) / scale for b in bs]
                times = [s.time for s in snaps]
                shots = [s.shots for s in snaps]
                cols_t = "  ".join(f"{first_below(times, errs, t):6.2f}s / {first_below(shots, errs, t):8.0f}"
                                   for t in targets)
                per_cell = f"{twin / cells:.1f}" if cells else "-"
                print(f"{k:>2} {mode:>6} {wall:7.2f} {snaps[-1].shots:8d} {snaps[-1].rays:10d} {errs[-1]:10.4f}"
                      f"  {cols_t}  {twin} / {per_cell}")
    print("\nDense twins would take solid^2 * 2 directions * 3 channels * 8 B = 3072 B per portal cell (solid 8).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
