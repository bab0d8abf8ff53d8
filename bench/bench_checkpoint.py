"""Checkpoint cost per barrier: bytes, what changed since the last barrier, and the barrier loop's share.

Runs a divided solve in process (``office:rows=8,cols=8`` by default) and, at every
barrier, writes each subscene's checkpoint (``checkpoint_arrays``, what a worker sends
the coordinator) as the coordinator does: streamed into a ``coordinator.store.ChunkFile``
in the barrier loop, then handed to a ``CheckpointWriter`` thread that fsyncs the files
and writes the manifest.  Prints, per barrier: the checkpoint bytes, the share of the
per-patch rows (radiosity, unshot) that changed since the previous barrier, what an
XOR-with-the-previous delta would take zlib-compressed (the incremental encoding the
store once used), the seconds the file writes held the barrier loop and the writer's
seconds in its thread.  Then the same solve without checkpoints, for the loop's wall
time with and without, and a reload of the last barrier, checked bit-identical.

    .venv/bin/python bench/bench_checkpoint.py [--rows 8 --cols 8 --subscenes 4]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np

import scenes
from coordinator.store import CheckpointWriter, ChunkFile, JobStore, cell_file
from dcrad.config import SolverConfig
from dcrad.division.divide import DivideConfig, build_subscenes, run_divided
from dcrad.division.subscene import checkpoint_arrays
from dcrad.pipeline import prepare
from dcrad.wire import arrays_to_chunks

#: the per-patch arrays the old incremental encoding stored as changes
ROWS = ("radiosity", "unshot", "noise_diff", "noise_unshot")


def _delta_bytes(cur: np.ndarray, prev: np.ndarray) -> tuple[int, int]:
    """(rows changed, zlib bytes of the byte-shuffled XOR with the previous barrier)."""
    xor = cur.view(np.uint64) ^ prev.view(np.uint64)
    changed = int(xor.reshape(len(cur), -1).any(axis=1).sum())
    shuffled = np.ascontiguousarray(xor).view(np.uint8).reshape(-1, 8).T.tobytes()
    return changed, len(zlib.compress(shuffled, 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=8)
    ap.add_argument("--cols", type=int, default=8)
    ap.add_argument("--subscenes", type=int, default=4)
    ap.add_argument("--tol", type=float, default=0.0, help="0: stop by the accuracy target")
    ap.add_argument("--no-fsync", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="dcrad-bench-ckpt-") as tmp:
        path = scenes.write_builtin("office", Path(tmp) / "scene", rows=args.rows, cols=args.cols)
        _, patches, _ = prepare(path)
        config = SolverConfig(tol=args.tol)
        divide = DivideConfig(subscenes=args.subscenes)
        store = JobStore(Path(tmp) / "jobs")
        folder = store.folder("bench") / "checkpoints"
        folder.mkdir(parents=True)
        writer = CheckpointWriter(folder, fsync=not args.no_fsync)
        rows: list[tuple] = []
        prev: dict[int, dict] = {}
        last: dict[int, dict] = {}

        subs, bnds, _, _ = build_subscenes(patches, config, divide)

        def on_barrier(run):
            t0 = time.perf_counter()
            files, nbytes = {}, 0
            for s in subs:
                files[s.cell] = folder / cell_file(s.cell, run.barriers)
                nbytes += ChunkFile.write(files[s.cell], arrays_to_chunks(checkpoint_arrays(s)))[0]
            writer.submit(run.barriers, files, run.snapshots[-1].time)
            held = time.perf_counter() - t0
            # what changed since the previous barrier (measured outside the timed part)
            changed = total = delta = raw = 0
            for s in subs:
                now = {k: checkpoint_arrays(s)[k].copy() for k in ROWS}
                last[s.cell] = checkpoint_arrays(s)
                if s.cell in prev:
                    for k in ROWS:
                        c, z = _delta_bytes(now[k], prev[s.cell][k])
                        changed, total, delta, raw = changed + c, total + len(now[k]), delta + z, raw + now[k].nbytes
                prev[s.cell] = now
            # bytes a delta of the per-patch arrays would have saved, as a share of the checkpoint
            saved = (raw - delta) / nbytes if raw else float("nan")
            rows.append((run.barriers, nbytes, changed / total if total else float("nan"),
                         delta / raw if raw else float("nan"), held, saved))

        t0 = time.perf_counter()
        run = run_divided(subs, bnds, config, divide.batches_per_barrier, on_barrier=on_barrier)
        with_ckpt = time.perf_counter() - t0
        writer.close()

        subs, bnds, _, _ = build_subscenes(patches, config, divide)
        t0 = time.perf_counter()
        run2 = run_divided(subs, bnds, config, divide.batches_per_barrier)
        without = time.perf_counter() - t0

        print(f"office:rows={args.rows},cols={args.cols}: {len(patches)} patches, {len(subs)} subscenes, "
              f"{run.barriers} barriers, fsync {'off' if args.no_fsync else 'on'}, load {os.getloadavg()[0]:.2f}")
        print(f"{'barrier':>7} {'ckpt MB':>8} {'rows changed':>12} {'xor+zlib/raw':>12} {'delta saves':>11} "
              f"{'loop held s':>11} {'writer s':>8}")
        sync = {b: dt for b, _, dt in writer.stats["per_barrier"]}
        for b, nbytes, changed, delta, held, saved in rows:
            print(f"{b:7d} {nbytes / 1e6:8.2f} {changed:12.3f} {delta:12.3f} {saved:11.3f} {held:11.4f} "
                  f"{sync.get(b, float('nan')):8.4f}")
        later = [r for r in rows if r[5] == r[5]]  # barriers with a previous one
        if later:
            share = sum(r[5] * r[1] for r in later) / sum(r[1] for r in later)
            print(f"a delta of {', '.join(ROWS)} would save {share:.1%} of the checkpoint bytes past barrier 1")
        held = sum(r[4] for r in rows)
        st = writer.stats
        print(f"total: {sum(r[1] for r in rows) / 1e6:.1f} MB of checkpoints; file writes held the barrier loop "
              f"{held:.3f} s of {with_ckpt:.2f} s ({100 * held / with_ckpt:.1f}%); the writer thread spent "
              f"{st['seconds']:.3f} s (fsync + manifest), {st['skipped']} barriers skipped")
        print(f"barrier loop wall: with checkpoints {with_ckpt:.2f} s, without {without:.2f} s "
              f"(same barriers: {run.barriers == run2.barriers})")
        res = store.resume("bench")
        same = res is not None and all(
            all(np.array_equal(back[k], last[c][k]) and back[k].dtype == np.asarray(last[c][k]).dtype
                for k in last[c]) for c, back in ((c, ChunkFile.read(p)) for c, p in res.cells.items()))
        print(f"reloaded barrier {res.barrier if res else None}: bit-identical {same}")


if __name__ == "__main__":
    main()
