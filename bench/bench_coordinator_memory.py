"""Peak memory of the embedded coordinator of a ``dcrad solve --workers N`` run.

Runs the command given after ``--`` and samples, every ``--period`` s, the
resident set (VmRSS) and its high-water mark (VmHWM, from ``/proc/PID/status``)
of every process under it whose command line is ``... dcrad.cli coordinator ...``
(the embedded coordinator is a child process).  Prints a coarse timeline and the
peak; the command's own output goes to the terminal.  ``--role worker`` samples
the workers instead.

    .venv/bin/python bench/bench_coordinator_memory.py -- \\
        .venv/bin/dcrad solve office:rows=8,cols=8 --workers 2 --out /tmp/h16run

The coordinator also logs its own RSS at each phase of a job (``coordinator
RSS ... MB after ...`` in its log, and ``divided.coordinator_rss_mb`` in the report).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path


def _status(pid: int) -> dict[str, int]:
    out = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(("VmRSS:", "VmHWM:", "PPid:")):
                key, val = line.split(":", 1)
                out[key] = int(val.split()[0])
    except (OSError, ValueError):
        return {}
    return out


def _cmdline(pid: int) -> list[str]:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return []


def _descendants(root: int) -> list[int]:
    parent = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            st = _status(int(d))
            if "PPid" in st:
                parent[int(d)] = st["PPid"]
    out, frontier = [], {root}
    while frontier:
        kids = {p for p, pp in parent.items() if pp in frontier}
        out += sorted(kids)
        frontier = kids
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--period", type=float, default=0.2, help="s between samples")
    ap.add_argument("--every", type=float, default=10.0, help="s between timeline lines")
    ap.add_argument("--role", default="coordinator", choices=("coordinator", "worker"))
    ap.add_argument("command", nargs=argparse.REMAINDER)
    args = ap.parse_args()
    cmd = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not cmd:
        sys.exit("give the command after --")
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd)
    peak: dict[int, int] = {}
    rss: dict[int, int] = {}
    last_line = -1e9
    while proc.poll() is None:
        for pid in _descendants(proc.pid):
            argv = _cmdline(pid)
            if "dcrad.cli" in argv and args.role in argv:
                st = _status(pid)
                if "VmHWM" in st:
                    peak[pid] = max(peak.get(pid, 0), st["VmHWM"])
                    rss[pid] = st["VmRSS"]
        now = time.monotonic() - t0
        if rss and now - last_line >= args.every:
            last_line = now
            print(f"[mem] t={now:7.1f} s  {args.role} RSS "
                  + ", ".join(f"{pid}: {rss[pid] / 1024:.0f} MB (peak {peak[pid] / 1024:.0f})" for pid in rss),
                  file=sys.stderr, flush=True)
        time.sleep(args.period)
    wall = time.monotonic() - t0
    for pid, kb in sorted(peak.items()):
        print(f"[mem] {args.role} pid {pid}: peak RSS (VmHWM) {kb / 1024:.0f} MB", file=sys.stderr)
    print(f"[mem] command exit {proc.returncode}, wall {wall:.1f} s, load {os.getloadavg()[0]:.2f}",
          file=sys.stderr)
    sys.exit(proc.returncode)


if __name__ == "__main__":
    main()
