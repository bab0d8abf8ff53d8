"""Error analysis the paper left qualitative: converged divided vs converged unsplit,
as SOLIDANGLES and portal cell size vary, for both boundary modes, and with
adaptive direction bins (``SolverConfig.adaptive_bins``: weak twin light shot from
coarser blocks) on and off.  ``--quick`` runs only the default cell size; ``--short``
(for ``make bench``) also only the default solid, with 5x fewer rays to tol 1e-2.

Prints figures; asserts nothing.  Run: ``.venv/bin/python bench/bench_binning.py``.
Scene: a two-room office floor (1x2) split in two through the wall (k=2), one lit room.
Every run converges to tol 1e-3 with 1e6 rays per unit of emitted power.  The noise
floor is the same comparison between two unsplit runs with different seeds.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import scenes
from dcrad.config import SolverConfig
from dcrad.division.divide import DivideConfig, solve_divided
from dcrad.pipeline import prepare
from dcrad.solving.energy import rms_error
from dcrad.solving.solver import Solver


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    short = "--short" in argv  # `make bench`: the default cell and solid only, 5x fewer rays, tol 1e-2
    quick = short or "--quick" in argv
    path = scenes.write_builtin("office", Path(tempfile.mkdtemp()), rows=1, cols=2, lit_fraction=0.01, seed=3)
    cfg = dict(tol=1e-2, rays_per_power=2e5) if short else dict(tol=1e-3, rays_per_power=1e6)
    _, ref, _ = prepare(path)
    Solver(ref, SolverConfig(seed=1, **cfg)).run()
    _, other, _ = prepare(path)
    Solver(other, SolverConfig(seed=2, **cfg)).run()
    scale = float(np.sqrt(np.dot((ref.radiosity ** 2).mean(axis=1), ref.area) / ref.area.sum()))
    lamps = ref.emission.sum(axis=1) > 0
    mid = 0.5 * (ref.bounds[0, 0] + ref.bounds[1, 0])
    lit_left = ref.centroid[lamps, 0].mean() < mid
    dark = (ref.centroid[:, 0] > mid) if lit_left else (ref.centroid[:, 0] < mid)

    def errors(b):
        all_ = rms_error(b, ref.radiosity, ref.area) / scale
        d = rms_error(b[dark], ref.radiosity[dark], ref.area[dark]) / scale
        mean_dark = np.average(b[dark].mean(axis=1), weights=ref.area[dark])
        return all_, d, mean_dark

    ref_dark = np.average(ref.radiosity[dark].mean(axis=1), weights=ref.area[dark])
    n_all, n_dark, m = errors(other.radiosity)
    print(f"two-room office, {len(ref)} patches, diagonal {ref.scale:.2f} m; dark-room mean B* {ref_dark:.5f}")
    print(f"{'mode':>7} {'adapt':>5} {'solid':>5} {'cell m':>7} {'nRMS all':>9} {'nRMS dark':>9} {'dark mean/B*':>12} "
          f"{'lost %':>7} {'twin MB':>8} {'rays':>11} {'wall s':>7}")
    print(f"{'unsplit':>7} {'-':>5} {'-':>5} {'-':>7} {n_all:9.4f} {n_dark:9.4f} {m / ref_dark:12.4f} {'':>7} {'':>8}"
          f"   (noise floor: another seed)")
    diag = ref.scale
    cases = [("binned", s, d, a) for d in ((128,) if quick else (16, 64, 128, 256))
             for s in ((8,) if short else (2, 4, 8, 16)) for a in (False, True)] + [("exact", 8, 128, False)]
    for mode, solid, div, adaptive in cases:
        _, p, _ = prepare(path)
        t0 = time.perf_counter()
        run, subs, b, part = solve_divided(p, SolverConfig(seed=2, adaptive_bins=adaptive, **cfg),
                                           DivideConfig(subscenes=2, mode=mode, solid=solid, cell_size=diag / div))
        wall = time.perf_counter() - t0
        a, d, m = errors(p.radiosity)
        led = run.ledger
        lost = 100 * (led.back_faces.sum() + led.escaped.sum()) / led.emitted.sum()
        cell = "-" if mode == "exact" else f"{diag / div:.3f}"
        print(f"{mode:>7} {'on' if adaptive else 'off':>5} {solid if mode == 'binned' else '-':>5} {cell:>7} {a:9.4f} "
              f"{d:9.4f} {m / ref_dark:12.4f} {lost:7.2f} {run.max_twin_bytes / 1e6:8.2f} "
              f"{run.snapshots[-1].rays:11,d} "
              f"{wall:7.2f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
