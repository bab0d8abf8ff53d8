"""Solver throughput against raw Embree, and wall time to 1% residual.

Prints figures; asserts nothing.  Run: ``.venv/bin/python bench/bench_solver.py``
(options: --rows/--cols for the office size, --profile for a cProfile summary).

Figures:
- raw embreex rays/s: ``Tracer.intersect`` alone on a pre-sampled batch of the
  solver's own rays (cosine rays from the office patches), same scene, same run;
- solver rays/s: rays / wall seconds of a whole solve to 1% (sampling, tracing,
  tallying, selection, bookkeeping);
- the ratio of the two (aim >= 0.5: Python overhead at most half the time).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import scenes
from dcrad.config import SolverConfig
from dcrad.pipeline import prepare
from dcrad.solving.solver import Solver
from dcrad.transport.rays import Tracer
from dcrad.transport.shoot import patch_rays


def raw_embree_rate(patches, tracer, rays=1_000_000, repeats=3) -> float:
    rng = np.random.default_rng(0)
    power = patches.area[:, None] * np.ones((1, 3))
    shooters = rng.choice(len(patches), size=min(len(patches), rays // 64), replace=False)
    counts = np.full(len(shooters), 64, np.int64)
    batch = patch_rays(patches, shooters, counts, power[shooters], rng)
    best = 0.0
    for _ in range(repeats):
        t0 = time.perf_counter()
        tracer.intersect(batch.origins, batch.dirs)
        best = max(best, len(batch) / (time.perf_counter() - t0))
    return best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rows", type=int, default=2)
    ap.add_argument("--cols", type=int, default=3)
    ap.add_argument("--tol", type=float, default=0.01)
    ap.add_argument("--patch-size", type=float, default=0.0, help="max patch edge in m (default: automatic)")
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args(argv)

    with tempfile.TemporaryDirectory() as tmp:
        path = scenes.write_builtin("office", Path(tmp), rows=args.rows, cols=args.cols)
        scene, patches, size = prepare(path, args.patch_size or None)
    print(f"office floor {args.rows}x{args.cols}: {len(scene.faces)} input triangles, "
          f"{len(patches)} patches (edge <= {size:.3f} m)")

    t0 = time.perf_counter()
    tracer = Tracer(patches.triangles)
    print(f"embree scene build: {time.perf_counter() - t0:.3f} s")
    raw = raw_embree_rate(patches, tracer)

    solver = Solver(patches, SolverConfig(tol=args.tol), tracer=tracer)
    prof = cProfile.Profile() if args.profile else None
    if prof:
        prof.enable()
    stats = solver.run()
    if prof:
        prof.disable()
    rate = stats.rays / stats.wall_seconds
    print(f"raw embreex:     {raw / 1e6:6.2f} Mrays/s")
    print(f"solver:          {rate / 1e6:6.2f} Mrays/s  ({stats.rays:,} rays, {stats.shots:,} shots, "
          f"{stats.batches} batches)")
    print(f"ratio solver/raw: {rate / raw:.2f}   (trace share of wall: {stats.trace_seconds / stats.wall_seconds:.2f})")
    print(f"wall time to residual {args.tol:g}: {stats.wall_seconds:.2f} s  (stopped by {stats.stopped_by}; "
          f"ledger closure {solver.ledger.closure():.1e})")
    if prof:
        pstats.Stats(prof, stream=sys.stdout).sort_stats("tottime").print_stats(12)
    return 0


if __name__ == "__main__":
    sys.exit(main())
