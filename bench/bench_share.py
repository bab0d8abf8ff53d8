"""`dcrad solve --workers 0` against `--workers N` (a shared run where the light is gathered): whole
process, as a user runs it.

For each scene: wall seconds of the whole command (start-up, load, solve, outputs), its CPU
seconds (children included), rays, the estimated error, the report's timings and, for the
shared run, its phases.  Run on a quiet machine: wall ratios on a loaded one mean little.

    .venv/bin/python bench/bench_share.py --scenes "office:rows=8,cols=8" --accuracy 0.02
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run(scene: str, workers: int, extra: list[str], out: Path) -> dict:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "dcrad.cli", "solve", scene, "--workers", str(workers), *extra,
                           "--out", str(out)], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"dcrad solve failed:\n{proc.stderr}")
    report = json.loads((out / "report.json").read_text())
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall": wall, "cpu": cpu, "report": report}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="office:rows=8,cols=8", help=";-separated built-in scenes or files")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--accuracy", type=float, default=0.02)
    ap.add_argument("--extra", default="", help="more `dcrad solve` flags, space-separated")
    args = ap.parse_args(argv)
    extra = ["--accuracy", str(args.accuracy), *args.extra.split()]
    print("| scene | workers | wall s | CPU s | rays (M) | est. refl | load s | solve s | outputs s | phases |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for scene in [s for s in args.scenes.split(";") if s]:
        walls = {}
        for workers in (0, args.workers):
            with tempfile.TemporaryDirectory(prefix="dcrad-bench-share-") as tmp:
                got = run(scene, workers, extra, Path(tmp) / "out")
            r = got["report"]
            t = r["timings"]
            shared = r.get("shared") or {}
            phases = (", ".join(f"{k[:-2]} {shared[k]:.1f}" for k in ("direct_s", "shoot_s", "gather_s") if k in shared)
                      + (f", rounds {shared['gather_rounds']}" if shared else "")) or (
                          "divided" if r.get("divided") else "one process")
            walls[workers] = got["wall"]
            print(f"| {scene} | {workers} | {got['wall']:.1f} | {got['cpu']:.1f} | {r['stats']['rays'] / 1e6:.1f} | "
                  f"{(r.get('error') or {}).get('rms_refl') or float('nan'):.4f} | {t.get('load_and_mesh_s', 0):.1f} | "
                  f"{t.get('solve_s', 0):.1f} | {t.get('outputs_s', 0):.1f} | {phases} |", flush=True)
        print(f"| {scene} | ratio | {walls[0] / walls[args.workers]:.2f}x | | | | | | | |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
