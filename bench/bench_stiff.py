"""Stiff closed rooms: wall time and iterations to 1% residual, with and without acceleration.

Prints figures; asserts nothing.  Run: ``.venv/bin/python bench/bench_stiff.py``
(``--rhos 0.9,0.99,0.999 --patch 0.1 --time-limit 60``).

Scene: the built-in furnace (closed unit cube, uniform rho, emitting square on
the ceiling).  Rows, for each rho:

- sequential: plain progressive refinement; ambient overshooting; overshooting
  plus stiff ray budget (``SolverConfig.stiff_rays``);
- divided k=2 (the cube cut across open space): fixed 4 batches per barrier;
  adaptive barrier iterations; plus the job's overshooting; plus stiff rays.

"shots" are the paper's iterations (patches and twin entries shot).
"identity" is the relative error of the closed-enclosure identity at the end
(exact up to the unsettled power); "nRMS" is the area-weighted RMS error
against a reference run (overshoot + stiff rays, 100x the rays, tol 1e-3,
another seed) divided by the mean B: mostly Monte Carlo noise.
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
from dcrad.division.divide import DivideConfig, solve_divided
from dcrad.io.scene import load_scene
from dcrad.solving.energy import rms_error
from dcrad.solving.solver import Solver

PLAIN = dict(overshoot=0.0, stiff_rays=False)
OVERSHOOT = dict(overshoot=1.0, stiff_rays=False)
ALL = dict(overshoot=1.0, stiff_rays=True)
SEQUENTIAL = [("plain", PLAIN), ("overshoot", OVERSHOOT), ("overshoot+rays", ALL)]
DIVIDED = [("fixed 4", PLAIN, False), ("adaptive", PLAIN, True), ("adapt+overshoot", OVERSHOOT, True),
           ("adapt+over+rays", ALL, True)]


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
    print(f"{'rho':>6} {'run':>10} {'accel':>16} {'stopped':>10} {'wall s':>7} {'shots':>9} {'rays':>12} "
          f"{'barriers':>8} {'residual':>9} {'identity':>9} {'nRMS':>7}")
    for rho in (float(r) for r in args.rhos.split(",")):
        path = scenes.write_builtin("furnace", tmp / f"r{rho}", rho=rho)
        ref = load_scene(path).patches(args.patch)
        Solver(ref, SolverConfig(tol=1e-3, rays_per_power=2e7, seed=99, **ALL)).run()
        mean_b = float((ref.radiosity[:, 0] * ref.area).sum() / ref.area.sum())

        def row(run, accel, p, wall, stopped, shots, rays, barriers, residual, ref=ref, mean_b=mean_b, rho=rho):
            nrms = rms_error(p.radiosity, ref.radiosity, p.area) / mean_b
            print(f"{rho:6g} {run:>10} {accel:>16} {stopped:>10} {wall:7.2f} {shots:9d} {rays:12,d} {barriers:>8} "
                  f"{residual:9.2e} {identity(p, rho):9.2e} {nrms:7.4f}", flush=True)

        for name, kw in SEQUENTIAL:
            p = load_scene(path).patches(args.patch)
            t0 = time.perf_counter()
            s = Solver(p, SolverConfig(tol=0.01, time_limit=args.time_limit, **kw))
            s.run()
            row("sequential", name, p, time.perf_counter() - t0, s.stats.stopped_by, s.stats.shots, s.stats.rays,
                "-", s.residual())
        for name, kw, adaptive in DIVIDED:
            p = load_scene(path).patches(args.patch)
            cfg = SolverConfig(tol=0.01, time_limit=args.time_limit, **kw)
            t0 = time.perf_counter()
            run, *_ = solve_divided(p, cfg, DivideConfig(subscenes=2, iterations=0 if adaptive else 4), record=False)
            last = run.snapshots[-1]
            row("divided k2", name, p, time.perf_counter() - t0, run.stopped_by, last.shots, last.rays,
                run.barriers, run.ledger.residual())
    return 0


if __name__ == "__main__":
    sys.exit(main())
