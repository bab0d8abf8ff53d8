"""Boundaries across open space: a 1 x 1 m floor (rho 0.7) under a 1 x 1 m light (E = 10 W/m^2)
1 m above it, nothing else, cut into k subscenes, against the closed form.

Every boundary of such a partition crosses open space.  Prints the floor's mean B and the
per-patch RMS error against the point-to-rectangle form factor (at each patch centroid)
for the unsplit solve and for exact and binned boundaries at each k, with the rays each
traced.  Both sides shoot the direct light (``direct=False``: divided runs do not gather
it).  Asserts nothing.  Run: ``.venv/bin/python bench/bench_open_floor.py [--seeds 3]``.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from dcrad.config import DivideConfig, SolverConfig
from dcrad.division.divide import solve_divided
from dcrad.solving.energy import rms_error
from dcrad.solving.solver import Solver
from scenes.open_floor import open_floor, point_to_square


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cells", type=int, default=40, help="floor squares per side (2 triangles each)")
    ap.add_argument("--ks", default="2,4,8,16,64")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--rays-per-power", type=float, default=1e6)
    args = ap.parse_args(argv)
    g = (np.arange(400) + 0.5) / 400
    exact = 0.7 * 10.0 * point_to_square(*np.meshgrid(g, g)).mean()
    p0, floor = open_floor(args.cells)
    print(f"open floor: {len(p0)} patches; closed-form floor mean {exact:.4f} W/m^2; "
          f"{args.rays_per_power:.3g} rays per emitted power, tol 1e-3, mean of {args.seeds} seeds")
    print(f"{'run':>12} {'floor mean':>10} {'/closed':>8} {'RMS err':>8} {'/unsplit':>8} {'rays':>11}")

    def stats(p):
        c = p.centroid[floor]
        truth = 0.7 * 10.0 * point_to_square(c[:, 0], c[:, 1])
        return (np.average(p.radiosity[floor, 0], weights=p.area[floor]),
                rms_error(p.radiosity[floor, :1], truth[:, None], p.area[floor]))

    base = None
    runs = [("unsplit", 1)] + [(m, int(k)) for m in ("exact", "binned") for k in args.ks.split(",")]
    for mode, k in runs:
        out = []
        for seed in range(args.seeds):
            cfg = SolverConfig(tol=1e-3, rays_per_power=args.rays_per_power, seed=seed, direct=False)
            p, _ = open_floor(args.cells)
            if k == 1:
                s = Solver(p, cfg)
                s.run()
                rays = s.stats.rays
            else:
                run, *_ = solve_divided(p, cfg, DivideConfig(subscenes=k, mode=mode))
                rays = run.snapshots[-1].rays
            out.append((*stats(p), rays))
        mean, err, mean_rays = (float(np.mean([o[i] for o in out])) for i in range(3))
        base = err if base is None else base
        name = "unsplit" if k == 1 else f"{mode} k={k}"
        print(f"{name:>12} {mean:10.4f} {mean / exact:8.4f} {err:8.4f} {err / base:8.3f} {int(mean_rays):11,d}",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
