"""CPU seconds of the exact direct gather (direct.gather_analytic) and of its form factor kernel.

Prints figures; asserts nothing.  Run: ``.venv/bin/python bench/bench_direct.py``
(options: --scenes, --shadow-rays, --seed, --profile for a cProfile summary,
--save DIR to keep each scene's gathered direct light as DIR/<scene>.npz for
``--compare DIR``: the relative difference of the gathered light against a saved run).

Figures per scene (one process, CPU seconds by time.process_time):
- gather: the whole ``gather_analytic`` (light lists, pilot, form factors, shadow rays),
  the shadow rays traced and the CPU microseconds per (receiver, light) pair entry;
- kernel: ``pair_form_factors`` (2 halves x 3 points) and the centroid form factors
  (``_pair_form_factors(..., None)``) on the same pair entries, alone.
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

from dcrad import pipeline
from dcrad.transport import direct
from dcrad.transport.rays import Tracer
from dcrad.transport.shoot import ray_offset


def setup(spec: str):
    with tempfile.TemporaryDirectory() as tmp:
        path = pipeline.resolve_scene(spec, Path(tmp))
        _, p, _ = pipeline.prepare(path, None, 1.0)
    tracer = Tracer(p.triangles)
    em = np.flatnonzero(p.emission.any(axis=1) & p.unshot.any(axis=1))
    power = p.unshot[em] * p.area[em, None]
    rec = np.flatnonzero(p.rho.any(axis=1))
    return p, tracer, em, power, rec


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default="cornell;office;office:rows=8,cols=8",
                    help="';'-separated scenes (office = the 3x3 office)")
    ap.add_argument("--shadow-rays", type=int, default=32)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--save", default="", help="directory: keep each gathered direct light as <scene>.npz")
    ap.add_argument("--compare", default="", help="directory of a --save run: relative differences against it")
    args = ap.parse_args(argv)
    for spec in filter(None, args.scenes.split(";")):
        p, tracer, em, power, rec = setup(spec)
        lights = direct.analytic_lights(p, em, power, len(rec))
        if lights is None:
            print(f"{spec}: no exact gather (analytic_lights refused)")
            continue
        lists = direct.light_lists(p, lights, rec)
        slot, light, _, _ = direct.light_pairs(p, lights, rec, np.random.default_rng(0), lists)
        pairs = len(slot)
        prof = cProfile.Profile() if args.profile else None
        t0 = time.process_time()
        if prof:
            prof.enable()
        tally = direct.gather_analytic(p, tracer, em, power, lights, args.shadow_rays,
                                       np.random.default_rng(args.seed), ray_offset(p), 262144, rec)
        if prof:
            prof.disable()
        gather_s = time.process_time() - t0
        t0 = time.process_time()
        direct.pair_form_factors(p, lights, rec[slot], light, np.random.default_rng(0))
        kernel_s = time.process_time() - t0
        t0 = time.process_time()
        direct._pair_form_factors(p, lights, rec[slot], light, None)
        centroid_s = time.process_time() - t0
        print(f"{spec}: {len(p)} patches, {len(rec)} receivers, {len(lights)} lights, {pairs} pair entries; "
              f"gather {gather_s:.2f} CPU s ({tally.rays} shadow rays, {1e6 * gather_s / max(pairs, 1):.1f} us "
              f"a pair); kernel: 2x3 points {kernel_s:.2f} s, centroid {centroid_s:.2f} s")
        name = spec.replace(":", "_").replace(",", "_").replace("=", "")
        received = np.zeros((len(p), 3))
        received[tally.hit] = tally.received
        if args.save:
            Path(args.save).mkdir(parents=True, exist_ok=True)
            np.savez(Path(args.save) / f"{name}.npz", received=received, rays=tally.rays)
        if args.compare:
            old = np.load(Path(args.compare) / f"{name}.npz")
            ref = old["received"]
            diff = np.abs(received - ref).sum(axis=1)
            mag = np.abs(ref).sum(axis=1)
            print(f"  against {args.compare}: rays {int(old['rays'])} -> {tally.rays}; total "
                  f"{ref.sum():.9g} -> {received.sum():.9g} W; sum |diff| / sum |old| {diff.sum() / mag.sum():.3g}; "
                  f"max per-patch relative {np.max(diff / np.where(mag > 0, mag, 1.0)):.3g}; patches differing "
                  f"{int((diff > 0).sum())} of {int((mag > 0).sum())}")
        if prof:
            pstats.Stats(prof, stream=sys.stdout).sort_stats("tottime").print_stats(18)
    return 0


if __name__ == "__main__":
    sys.exit(main())
