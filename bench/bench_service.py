"""Barrier overhead of the distributed service: bytes per barrier, communication vs computation.

Prints figures; asserts nothing.  Run: ``.venv/bin/python bench/bench_service.py``
(``--rows 2 --cols 3 --workers 2 --tol 0.01``).  Starts a real coordinator and
worker processes on loopback, solves the office floor split in one subscene per
worker, and reads the job's report.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import scenes
from coordinator import client
from coordinator.embedded import LocalCluster
from dcrad.config import SolverConfig
from dcrad.division.divide import DivideConfig, solve_divided
from dcrad.pipeline import prepare


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rows", type=int, default=2)
    ap.add_argument("--cols", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--tol", type=float, default=0.01)
    ap.add_argument("--mode", default="binned")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp())
    path = scenes.write_builtin("office", tmp / "scene", rows=args.rows, cols=args.cols)

    _, p, _ = prepare(path)
    t0 = time.perf_counter()
    run, *_ = solve_divided(p, SolverConfig(tol=args.tol), DivideConfig(subscenes=args.workers, mode=args.mode))
    in_process = time.perf_counter() - t0

    with LocalCluster(workers=args.workers) as cluster:
        t0 = time.perf_counter()
        job = client.submit(cluster.address, path, {"tol": args.tol},
                            {"subscenes": args.workers, "mode": args.mode})
        last = client.watch(cluster.address, job.job_id)
        client.fetch(cluster.address, job.job_id, tmp / "out")
        total = time.perf_counter() - t0
    report = json.loads((tmp / "out" / "report.json").read_text())
    div = report["divided"]
    nb = max(div["barriers"], 1)
    compute = div["compute_seconds"]
    rpc = div["rpc_seconds"]
    comm = [r["iterate"] - c + r["deliver"] + r["checkpoint"] + r["load"] for r, c in zip(rpc, compute)]
    print(f"office {args.rows}x{args.cols}, {report['scene']['patches']} patches, {args.workers} workers, "
          f"mode {args.mode}, tol {args.tol}")
    print(f"barriers: {div['barriers']}   rays: {report['stats']['rays']:,}   residual {last.ledger.residual:.2e}")
    print(f"twin bytes relayed: {div['bytes_relayed']:,} in all, {div['bytes_relayed'] / nb:,.0f} per barrier")
    print(f"checkpoint bytes:   {div['checkpoint_bytes']:,} in all, {div['checkpoint_bytes'] / nb:,.0f} per barrier")
    for i, (c, r, m) in enumerate(zip(compute, rpc, comm)):
        print(f"subscene {i}: compute {c:.3f} s | rpc wall: load {r['load']:.3f}, iterate {r['iterate']:.3f}, "
              f"deliver {r['deliver']:.3f}, checkpoint {r['checkpoint']:.3f} s | communication {m:.3f} s "
              f"({100 * m / max(m + c, 1e-12):.0f}%)")
    print(f"job solve wall (coordinator): {report['stats']['wall_seconds']:.2f} s; submit->fetched: {total:.2f} s; "
          f"same divided solve in one process, subscenes one after another: {in_process:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
