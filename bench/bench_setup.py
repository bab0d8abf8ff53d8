"""A divided job's set-up as the coordinator does it (coordinator/jobs.py ``_solve``): the
subscene specs (partition, clip, boundaries), the RemoteSubscene handles, and placing the
subscenes on real worker processes (``dcrad worker``), all at once as the job does.

Prints, per repetition: wall and CPU s of this process (the coordinator's part) for each step,
and the workers' CPU s while they load (from /proc).  Asserts nothing.  Run:
``.venv/bin/python bench/bench_setup.py`` (``--scene office:rows=20,cols=20 --patch-size 0.4
--subscenes 4 --workers 2 --reps 2``).  The patch table's cached geometry (areas, centroids) is
dropped before each repetition: the coordinator computes it during its set-up.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from coordinator.embedded import _read_port
from coordinator.remote import RemoteSubscene, WorkerPool
from dcrad.config import DivideConfig, SolverConfig
from dcrad.division.divide import subscene_specs
from dcrad.division.placement import expected_work, placement
from dcrad.pipeline import prepare, resolve_scene

TABLE = {"vertices", "faces", "rho", "emission", "source", "obj", "names", "radiosity", "unshot", "twin"}


def cpu_of(pid: int) -> float:
    """User + system CPU s of a process so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="office:rows=20,cols=20")
    ap.add_argument("--patch-size", type=float, default=0.4)
    ap.add_argument("--accuracy", type=float, default=0.05)
    ap.add_argument("--subscenes", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--reps", type=int, default=2)
    args = ap.parse_args(argv)

    procs = [subprocess.Popen([sys.executable, "-m", "dcrad.cli", "worker", "--port", "0"], stdout=subprocess.PIPE,
                              stderr=subprocess.DEVNULL, text=True, stdin=subprocess.DEVNULL)
             for _ in range(args.workers)]
    try:
        ports = [_read_port(p, "worker", 60) for p in procs]
        with tempfile.TemporaryDirectory() as tmp:
            _, patches, _ = prepare(resolve_scene(args.scene, Path(tmp)), args.patch_size)
            pool = WorkerPool()
            for port in ports:
                pool.register(f"127.0.0.1:{port}", 4, f"worker-{port}")
            config, divide = SolverConfig(accuracy=args.accuracy), DivideConfig(subscenes=args.subscenes)
            print(f"{args.scene} at {args.patch_size} m: {len(patches)} patches, {args.subscenes} subscenes "
                  f"on {args.workers} workers")
            for rep in range(args.reps):
                for name in set(patches.__dict__) - TABLE:
                    del patches.__dict__[name]
                w0 = [cpu_of(p.pid) for p in procs]
                t0, c0 = time.perf_counter(), time.process_time()
                subs, _, _, _ = subscene_specs(patches, config, divide)
                t1, c1 = time.perf_counter(), time.process_time()
                handles = [RemoteSubscene(f"bench{rep}", s, pool, 600.0, Path(tmp) / f"rep{rep}") for s in subs]
                t2, c2 = time.perf_counter(), time.process_time()
                workers = pool.live()
                slots = placement([expected_work(s.patches) for s in subs], len(workers))
                with ThreadPoolExecutor(max_workers=len(handles)) as ex:
                    list(ex.map(lambda h, w: h.place(prefer=w), handles, [workers[i] for i in slots]))
                t3, c3 = time.perf_counter(), time.process_time()
                w1 = [cpu_of(p.pid) for p in procs]
                print(f"rep {rep}: specs {t1 - t0:.2f} s (CPU {c1 - c0:.2f}), handles {t2 - t1:.2f} s "
                      f"(CPU {c2 - c1:.2f}), place {t3 - t2:.2f} s (CPU here {c3 - c2:.2f}, workers "
                      f"{', '.join(f'{b - a:.2f}' for a, b in zip(w0, w1))}), total {t3 - t0:.2f} s", flush=True)
                for h in handles:
                    h.drop()
                del subs
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(10)


if __name__ == "__main__":
    main()
