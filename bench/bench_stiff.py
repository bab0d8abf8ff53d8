"""Stiff closed rooms: wall time and iterations to 1% residual, with and without acceleration.

Prints figures; asserts nothing.  Run: ``.venv/bin/python bench/bench_stiff.py``
(``--rhos 0.9,0.99,0.999 --patch 0.1 --time-limit 60``).

Scene: the built-in furnace (closed cube, uniform rho, emitting square on the
ceiling).  Sequential: plain progressive refinement vs ambient overshooting.
Divided (k=2, the cube cut across open space): fixed 4 batches per barrier vs
adaptive barrier iterations.  "identity" is the relative error of the
closed-enclosure identity at the end (exact up to the unsettled power).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import scenes
from dcrad.config import SolverConfig
from dcrad.divide import DivideConfig, solve_divided
from dcrad.scene import load_scene
from dcrad.solve import Solver


def identity(p, rho):
    area = p.area.sum()
    mean = ((p.radiosity - p.emission) * p.area[:, None]).sum(axis=0) / area
    expect = rho * p.emitted_power / ((1 - rho) * area)
    return float(np.abs(mean - expect)[0] / expect[0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rhos", default="0.9,0.99,0.999")
    ap.add_argument("--patch", type=float, default=0.1)
    ap.add_argument("--time-limit", type=float, default=60.0)
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp())
    print(f"{'rho':>6} {'run':>10} {'accel':>14} {'stopped':>10} {'wall s':>7} {'shots':>9} {'rays':>12} "
          f"{'barriers':>8} {'residual':>9} {'identity':>9}")
    for rho in (float(r) for r in args.rhos.split(",")):
        path = scenes.write_builtin("furnace", tmp / f"r{rho}", rho=rho)
        for accel in (False, True):
            p = load_scene(path).patches(args.patch)
            cfg = SolverConfig(tol=0.01, time_limit=args.time_limit, overshoot=1.0 if accel else 0.0)
            t0 = time.perf_counter()
            s = Solver(p, cfg)
            s.run()
            print(f"{rho:6g} {'sequential':>10} {'overshoot' if accel else 'plain':>14} {s.stats.stopped_by:>10} "
                  f"{time.perf_counter() - t0:7.2f} {s.stats.shots:9d} {s.stats.rays:12,d} {'-':>8} "
                  f"{s.residual():9.2e} {identity(p, rho):9.2e}")
        for accel in (False, True):
            p = load_scene(path).patches(args.patch)
            cfg = SolverConfig(tol=0.01, time_limit=args.time_limit)
            t0 = time.perf_counter()
            run, *_ = solve_divided(p, cfg, DivideConfig(subscenes=2, adaptive=accel), record=False)
            last = run.snapshots[-1]
            print(f"{rho:6g} {'divided k2':>10} {'adaptive iters' if accel else 'fixed 4':>14} {run.stopped_by:>10} "
                  f"{time.perf_counter() - t0:7.2f} {last.shots:9d} {last.rays:12,d} {run.barriers:8d} "
                  f"{run.ledger.residual():9.2e} {identity(p, rho):9.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
