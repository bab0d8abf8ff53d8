"""Peak memory of a large upload: the client's and the coordinator's high-water mark (VmHWM).

Writes a furnace OBJ padded with comment lines to ``--mb`` MB, starts a coordinator
with one worker (``LocalCluster``, ``--max-upload`` above the file), submits it from a
separate client process, and prints both processes' peak resident memory.  The job
is cancelled after it is accepted: what is measured is the upload and the scene check.

    .venv/bin/python bench/bench_upload.py [--mb 200]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import scenes
from coordinator.embedded import LocalCluster


def vm_hwm_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


CLIENT = """
import resource, sys
from coordinator import client
job = client.submit(sys.argv[1], sys.argv[2], {"tol": 0.5}, {"subscenes": 1})
client.cancel(sys.argv[1], job.job_id)
print(job.job_id, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mb", type=float, default=200.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="dcrad-bench-upload-") as tmp:
        path = scenes.write_builtin("furnace", Path(tmp) / "scene")
        pad = ("#" + "x" * 126 + "\n").encode()
        with open(path, "ab") as f:
            for _ in range(int(args.mb * 1e6 / len(pad))):
                f.write(pad)
        size = path.stat().st_size + path.with_suffix(".mtl").stat().st_size
        with LocalCluster(workers=1, data=Path(tmp) / "data", web=False,
                          coordinator_args=("--max-upload", str(2 * size))) as cluster:
            before = vm_hwm_mb(cluster.coordinator.pid)
            t0 = time.perf_counter()
            out = subprocess.run([sys.executable, "-c", CLIENT, cluster.address, str(path)], capture_output=True,
                                 text=True, check=True).stdout.split()
            dt = time.perf_counter() - t0
            coord = vm_hwm_mb(cluster.coordinator.pid)
        print(f"upload {size / 1e6:.0f} MB in {dt:.1f} s: client peak {float(out[1]):.0f} MB, coordinator peak "
              f"{coord:.0f} MB (at start {before:.0f} MB)")


if __name__ == "__main__":
    main()
