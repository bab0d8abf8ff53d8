"""Checkpoint cost per barrier: whole checkpoints against the store's incremental files.

Runs a divided solve in process (``office:rows=8,cols=8`` by default) and, at every
barrier, takes each subscene's checkpoint (``checkpoint_arrays``, what a worker sends
the coordinator) and hands it to a ``coordinator.store.CheckpointWriter``.  Prints, per
barrier, the bytes of the whole checkpoints, the bytes the writer put on disk, the
writer's seconds (in its thread) and how long ``submit`` held the barrier loop; then
reloads the last barrier from disk and checks it is bit-identical.

    .venv/bin/python bench/bench_checkpoint.py [--rows 8 --cols 8 --subscenes 2]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import scenes
from coordinator.store import CheckpointWriter, JobStore
from dcrad.config import SolverConfig
from dcrad.divide import DivideConfig, build_subscenes, checkpoint_arrays, run_divided
from dcrad.pipeline import prepare


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=8)
    ap.add_argument("--cols", type=int, default=8)
    ap.add_argument("--subscenes", type=int, default=2)
    ap.add_argument("--tol", type=float, default=0.01)
    ap.add_argument("--no-fsync", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="dcrad-bench-ckpt-") as tmp:
        path = scenes.write_builtin("office", Path(tmp) / "scene", rows=args.rows, cols=args.cols)
        _, patches, _ = prepare(path)
        config = SolverConfig(tol=args.tol)
        divide = DivideConfig(subscenes=args.subscenes)
        subs, bnds, _, _ = build_subscenes(patches, config, divide)
        store = JobStore(Path(tmp) / "jobs")
        folder = store.folder("bench") / "checkpoints"
        writer = CheckpointWriter(folder, fsync=not args.no_fsync)
        held, last = [], {}

        def on_barrier(run):
            cells = {s.cell: checkpoint_arrays(s) for s in subs}
            for c, a in cells.items():  # the coordinator holds its own copy of each
                last[c] = {k: np.array(v, copy=True) for k, v in a.items()}
            t0 = time.perf_counter()
            writer.submit(run.barriers, last.copy(), run.snapshots[-1].time)
            held.append(time.perf_counter() - t0)

        t0 = time.perf_counter()
        run = run_divided(subs, bnds, config, divide.batches_per_barrier, on_barrier=on_barrier)
        solve_s = time.perf_counter() - t0
        writer.close()
        print(f"office:rows={args.rows},cols={args.cols}: {len(patches)} patches, {len(subs)} subscenes, "
              f"{run.barriers} barriers, solve {solve_s:.2f} s, fsync {'off' if args.no_fsync else 'on'}")
        print(f"{'barrier':>7} {'whole MB':>9} {'written MB':>10} {'ratio':>6} {'write s':>8}")
        for b, written, whole, dt in writer.stats["per_barrier"]:
            print(f"{b:7d} {whole / 1e6:9.3f} {written / 1e6:10.3f} {written / whole:6.2f} {dt:8.4f}")
        st = writer.stats
        print(f"total: whole {st['full_bytes'] / 1e6:.2f} MB, written {st['bytes'] / 1e6:.2f} MB "
              f"({st['bytes'] / max(st['full_bytes'], 1):.2f}), writer {st['seconds']:.3f} s in its thread, "
              f"barrier loop held {sum(held) * 1e3:.2f} ms in all, {st['skipped']} barriers skipped")
        on_disk = sum(p.stat().st_size for p in folder.iterdir())
        res = store.resume("bench")
        same = res is not None and all(
            all(np.array_equal(res.cells[c][k], last[c][k]) and res.cells[c][k].dtype == last[c][k].dtype
                for k in last[c]) for c in last)
        print(f"on disk now {on_disk / 1e6:.2f} MB; reloaded barrier {res.barrier if res else None}: "
              f"bit-identical {same}")


if __name__ == "__main__":
    main()
