"""How soon `dcrad solve` answers SIGTERM, by when it arrives: the command as a user runs it.

For each delay, one `dcrad solve SCENE --workers N` (N 0: this process) is started and sent
SIGTERM that many seconds later; the bench prints the exit code, the seconds from the signal to
the exit, the last line of stderr before the exit and, when report.json was written, how the run
stopped and the phase it was in (by its timings).  No assertions.  Run it on a quiet machine:
the seconds are wall time.

Run: .venv/bin/python bench/bench_sigterm.py [scene] [--workers 2] [--delays 8,16,24] [--flags '...']
     (default: office:rows=8,cols=8 on two local workers)
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DCRAD = [sys.executable, "-m", "dcrad.cli"]


def one(scene: str, workers: int, delay: float, extra: list[str]) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench-sigterm-") as tmp:
        out = Path(tmp) / "out"
        proc = subprocess.Popen([*DCRAD, "solve", scene, "--workers", str(workers), "--out", str(out), *extra],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp)
        time.sleep(delay)
        if proc.poll() is not None:
            return {"delay": delay, "exit": proc.returncode, "note": "ended before the signal"}
        t0 = time.perf_counter()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=600)
        took = time.perf_counter() - t0
        lines = [ln for ln in err.splitlines() if ln.strip() and "\r" not in ln]
        row = {"delay": delay, "exit": proc.returncode, "seconds": round(took, 2),
               "last": lines[-1][:110] if lines else ""}
        report = out / "report.json"
        if report.exists():
            r = json.loads(report.read_text())
            row |= {"stopped_by": r["stats"]["stopped_by"], "rays": r["stats"]["rays"],
                    "outputs_s": round(r["timings"].get("outputs_s", 0.0), 2)}
        return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", default="office:rows=8,cols=8")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--delays", default="8,16,24", help="seconds after the start, comma-separated")
    ap.add_argument("--flags", default="", help="more `dcrad solve` flags, one string")
    args = ap.parse_args()
    extra = args.flags.split()
    print(f"dcrad solve {args.scene} --workers {args.workers} {' '.join(extra)}")
    for d in (float(v) for v in args.delays.split(",")):
        print(json.dumps(one(args.scene, args.workers, d, extra)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
