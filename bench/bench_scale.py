"""Scale: solver rays/s against raw Embree, seconds per phase and peak memory, 3x3 to 20x20 offices.

Prints figures; asserts nothing.  Run::

    .venv/bin/python bench/bench_scale.py                      # 3x3, 8x8, 20x20 rooms, 0.4 m patches
    .venv/bin/python bench/bench_scale.py --rooms 3,8 --max-rays 20000000
    .venv/bin/python bench/bench_scale.py --src /tmp/dcrad-before   # another checkout's dcrad, same scenes

Each office runs in its own process (``--one``), so its peak RSS is its own.  Per office:

- patches, rays, solve seconds and solver rays/s (rays / solve wall seconds: selection,
  sampling, Embree, tallies, deposits, bookkeeping, snapshots, everything);
- raw embreex rays/s on the same Embree scene in the same process, measured by probes of
  32,768 rays every 4 batches during the solve (so both see the same machine load; the
  probes' time is taken out of the solve's), two ways:
  ``raw`` one ray from each of 262144 random points of random patches (incoherent, the
  issue's reference), and ``raw64`` 64 cosine rays from each of 4096 random patches in
  spatial order (the shape of a solver batch); the ratio is solver / raw;
- seconds per phase: load (OBJ to triangles), mesh (triangles to patches), embree (scene
  build), select, sample (patch_rays), trace (Embree inside the solve), tally (the rest of
  shoot.trace), deposit, book (commit minus deposit: ledger, noise tallies, pool), other
  (snapshots, stop tests, the loop), outputs (write_outputs: npz, PLY, GLB, previews);
- memory: the patch table's arrays (MB), the RSS the Embree build added, the snapshots of B,
  peak RSS after the solve, RSS when the outputs start (the solver freed) and peak RSS after
  the outputs (MB here are MiB, 2^20 bytes).

The kernel is measured as the issue measured it: ``tol=0.01, rays_per_power=2e5``, no
direct-light gather (``direct=False`` where the field exists), one process (``--workers 0``
in CLI terms).  The machine may be shared: compare ratios within one run, not seconds
across runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import inspect
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024
    return 0.0


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def table_mb(p) -> float:
    """MB held by the patch table's arrays, cached geometry included."""
    total = 0
    for v in list(vars(p).values()):
        if hasattr(v, "nbytes"):
            total += v.nbytes
    return total / 2**20


def one(rooms: int, patch_size: float, max_rays: int, outputs: bool) -> dict:
    import numpy as np

    import dcrad.solving.solver as solve_mod
    from dcrad.config import SolverConfig
    from dcrad.io.scene import load_scene
    from dcrad.pipeline import resolve_scene, write_outputs
    from dcrad.transport.rays import Tracer
    from dcrad.transport.shoot import patch_rays

    work = Path(tempfile.mkdtemp(prefix="bench_scale_"))
    row: dict = {"rooms": f"{rooms}x{rooms}"}
    t0 = time.perf_counter()
    scene = load_scene(resolve_scene(f"office:rows={rooms},cols={rooms}", work))
    row["load_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    p = scene.patches(patch_size)
    row["mesh_s"] = time.perf_counter() - t0
    row["patches"] = len(p)
    rss0 = rss_mb()
    t0 = time.perf_counter()
    tracer = Tracer(p.triangles)
    row["embree_s"] = time.perf_counter() - t0
    row["embree_mb"] = rss_mb() - rss0

    # raw Embree on this scene, in this process
    rng = np.random.default_rng(0)
    m = 262144

    def rate(batch) -> float:
        best = 0.0
        for _ in range(3):
            t = time.perf_counter()
            tracer.intersect(batch.origins, batch.dirs)
            best = max(best, len(batch) / (time.perf_counter() - t))
        return best

    points = rng.choice(len(p), m)
    raw = patch_rays(p, points, np.ones(m, np.int64), np.ones((m, 3)), rng)
    row["raw_start_rays_s"] = rate(raw)
    shooters = np.sort(rng.choice(len(p), m // 64, replace=False))
    c = p.vertices[p.faces[shooters, 0]]
    lo, hi = p.bounds
    q = ((c - lo) * (1023.0 / (hi - lo).max())).astype(np.int64)
    code = sum(((q[:, a] >> b) & 1) << (3 * b + a) for a in range(3) for b in range(10))
    shooters = shooters[np.argsort(code, kind="stable")]
    raw64 = patch_rays(p, shooters, np.full(len(shooters), 64, np.int64), np.ones((len(shooters), 3)), rng)
    row["raw64_start_rays_s"] = rate(raw64)

    fields = {f.name for f in dataclasses.fields(SolverConfig)}
    kw = dict(tol=0.01, rays_per_power=2e5, max_rays=max_rays)
    if "direct" in fields:
        kw["direct"] = False
    cfg = SolverConfig(**kw)
    rss0 = rss_mb()
    solver = solve_mod.Solver(p, cfg, tracer=tracer)
    row["solver_init_mb"] = rss_mb() - rss0

    # phase timers: wrap what Solver.step calls (module globals and methods), time them
    phases = {k: 0.0 for k in ("select", "sample", "trace", "tally", "deposit", "commit")}

    def timed(fn, key):
        def wrapper(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                phases[key] += time.perf_counter() - t
        return wrapper

    solve_mod.patch_rays = timed(solve_mod.patch_rays, "sample")
    solve_mod.trace = timed(solve_mod.trace, "tally")
    solve_mod.deposit = timed(solve_mod.deposit, "deposit")
    raw_intersect = tracer.intersect
    tracer.intersect = timed(tracer.intersect, "trace")
    solver.select = timed(solver.select, "select")
    solver.commit = timed(solver.commit, "commit")
    # raw Embree probes between batches, so raw and solver rays/s see the same machine load
    # (the machine is shared: the load changes within a run); their time is not solve time
    probe = {"raw": [0, 0.0], "raw64": [0, 0.0], "s": 0.0, "batches": 0}
    probe_rays = {"raw": raw, "raw64": raw64}
    step = solver.step

    def probed_step():
        if probe["batches"] % 4 == 0:
            t_all = time.perf_counter()
            for key, b in probe_rays.items():
                j = (probe["batches"] // 4 * 32768) % (len(b) - 32768 + 1)
                t = time.perf_counter()
                raw_intersect(b.origins[j:j + 32768], b.dirs[j:j + 32768])
                probe[key][0] += 32768
                probe[key][1] += time.perf_counter() - t
            probe["s"] += time.perf_counter() - t_all
        probe["batches"] += 1
        return step()

    solver.step = probed_step
    solver.run()
    st = solver.stats
    st.wall_seconds -= probe["s"]
    row["raw_rays_s"] = probe["raw"][0] / max(probe["raw"][1], 1e-12)
    row["raw64_rays_s"] = probe["raw64"][0] / max(probe["raw64"][1], 1e-12)
    row["rays"] = st.rays
    row["batches"] = st.batches
    row["solve_s"] = st.wall_seconds
    row["stopped_by"] = st.stopped_by
    row["rays_s"] = st.rays / max(st.wall_seconds, 1e-12)
    row["ratio"] = row["rays_s"] / row["raw_rays_s"]
    row["ratio64"] = row["rays_s"] / row["raw64_rays_s"]
    ph = dict(phases)
    ph["tally"] -= ph["trace"]
    ph["book"] = ph.pop("commit") - ph["deposit"]
    ph["other"] = st.wall_seconds - sum(ph.values())
    row["phases_s"] = ph
    pool = getattr(solver, "pool", None)
    row["pool_rebuilds"] = getattr(pool, "rebuilds", None)
    snaps = solver.snapshot_B
    row["snapshots"] = len(snaps)
    row["snapshot_mb"] = (snaps.nbytes if hasattr(snaps, "nbytes") else sum(s.nbytes for s in snaps)) / 2**20
    row["table_mb"] = table_mb(p)
    row["peak_solve_mb"] = peak_mb()
    del solver, snaps  # as pipeline.solve_to does: the outputs reuse the Embree scene only
    probe_rays.clear()  # the probes' rays are not the run's
    del raw, raw64, points, shooters
    tracer.intersect = raw_intersect
    gc.collect()  # the timers and the probe above tie the solver into reference cycles
    row["rss_outputs_mb"] = rss_mb()
    if outputs:
        t0, c0 = time.perf_counter(), time.process_time()
        reuse = "tracer" in inspect.signature(write_outputs).parameters  # older checkouts build their own
        write_outputs(work / "out", scene, p, **({"tracer": tracer} if reuse else {}))
        row["outputs_s"] = time.perf_counter() - t0
        row["outputs_cpu_s"] = time.process_time() - c0
    row["peak_mb"] = peak_mb()
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rooms", default="3,8,20", help="office sizes, rooms per side (comma list)")
    ap.add_argument("--patch-size", type=float, default=0.4, help="m, the same for every office")
    ap.add_argument("--max-rays", type=int, default=0, help="ray budget per solve (0: to tol 0.01)")
    ap.add_argument("--no-outputs", action="store_true", help="skip write_outputs")
    ap.add_argument("--src", default="", help="import dcrad from this checkout instead (a before/after run)")
    ap.add_argument("--one", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(one(args.one, args.patch_size, args.max_rays, not args.no_outputs)))
        return 0

    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [args.src or str(ROOT), str(ROOT)])))
    rows = []
    for r in [int(x) for x in args.rooms.split(",")]:
        cmd = [sys.executable, __file__, "--one", str(r), "--patch-size", str(args.patch_size),
               "--max-rays", str(args.max_rays)] + (["--no-outputs"] if args.no_outputs else [])
        done = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if done.returncode != 0:
            print(f"{r}x{r}: failed\n{done.stderr[-2000:]}", file=sys.stderr)
            continue
        rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), file=sys.stderr)

    print(f"\nbench_scale: office, {args.patch_size} m patches, tol 0.01, rays_per_power 2e5, no direct gather"
          + (f", at most {args.max_rays} rays" if args.max_rays else "")
          + (f", dcrad from {args.src}" if args.src else ""))
    print("| rooms | patches | rays | solve s | solver Mrays/s | raw Mrays/s | ratio | raw64 Mrays/s | ratio64 |"
          " peak MB |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for w in rows:
        print(f"| {w['rooms']} | {w['patches']} | {w['rays'] / 1e6:.1f}M | {w['solve_s']:.1f} | "
              f"{w['rays_s'] / 1e6:.2f} | {w['raw_rays_s'] / 1e6:.2f} | {w['ratio']:.2f} | "
              f"{w['raw64_rays_s'] / 1e6:.2f} | {w['ratio64']:.2f} | {w['peak_mb']:.0f} |")
    keys = ["load", "mesh", "embree", "select", "sample", "trace", "tally", "deposit", "book", "other", "outputs"]
    print("\nseconds per phase")
    print("| rooms | " + " | ".join(keys) + " |")
    print("|---" * (len(keys) + 1) + "|")
    for w in rows:
        ph = w["phases_s"] | {k: w.get(f"{k}_s", 0.0) for k in ("load", "mesh", "embree", "outputs")}
        print(f"| {w['rooms']} | " + " | ".join(f"{ph.get(k, 0.0):.2f}" for k in keys) + " |")
    print("\noutputs (write_outputs: npz, PLY, GLB, previews, false colour): wall and CPU seconds")
    print("| rooms | patches | wall s | CPU s | CPU us a patch |")
    print("|---|---|---|---|---|")
    for w in rows:
        if "outputs_cpu_s" in w:
            print(f"| {w['rooms']} | {w['patches']} | {w['outputs_s']:.2f} | {w['outputs_cpu_s']:.2f} | "
                  f"{1e6 * w['outputs_cpu_s'] / w['patches']:.1f} |")
    print("\nmemory (MB)")
    print("| rooms | patch table | embree build | solver init | snapshots (count) | peak after solve |"
          " RSS before outputs | peak after outputs |")
    print("|---|---|---|---|---|---|---|---|")
    for w in rows:
        print(f"| {w['rooms']} | {w['table_mb']:.0f} | {w['embree_mb']:.0f} | {w['solver_init_mb']:.0f} | "
              f"{w['snapshot_mb']:.0f} ({w['snapshots']}) | {w['peak_solve_mb']:.0f} | "
              f"{w.get('rss_outputs_mb', 0.0):.0f} | {w['peak_mb']:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
