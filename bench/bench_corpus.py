"""The real models of ../shared/models solved at defaults, as a new user runs them (issue 26).

Prints, per model: input triangles, elements, element size, rays, solve and total seconds, the
estimated error of the reflected light per input triangle; with --reference, also the error
measured per input triangle and per surface (lux) against a converged solution of the same mesh
(another seed, --accuracy 0.006).  No assertions.  In one process (--workers 0) unless --workers.

Run: .venv/bin/python bench/bench_corpus.py [--models office2,classroom] [--reference]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT.parent / "shared" / "models"


def solve(model: Path, out: Path, *extra: str) -> tuple[dict, float]:
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "dcrad.cli", "solve", str(model), "--out", str(out),
                        "--width", "160", "--height", "120", *extra], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{model}: {r.stderr.strip().splitlines()[-1]}")
    return json.loads((out / "report.json").read_text()), time.perf_counter() - t0


def measured(run: Path, ref: Path) -> tuple[float, float]:
    """(RMS error of B per input triangle over RMS(B* - E), area-weighted RMS relative error of the
    surfaces' average lux) of ``run`` against ``ref``."""
    a, b = np.load(run / "radiosity.npz"), np.load(ref / "radiosity.npz")
    n = len(b["B"])
    area = np.bincount(b["patch_source"], weights=b["patch_area"], minlength=n)
    e = np.stack([np.bincount(b["patch_source"], weights=b["patch_area"] * b["patch_emission"][:, c], minlength=n)
                  for c in range(3)], axis=1) / np.maximum(area, 1e-300)[:, None]
    v = a["valid"] & b["valid"]
    w = area[v, None]
    err = np.sqrt((w * (a["B"][v] - b["B"][v]) ** 2).sum() / (w * (b["B"][v] - e[v]) ** 2).sum())
    sa = {s["name"]: s["E_avg_lux"] for s in json.loads((run / "report.json").read_text())["photometry"]["surfaces"]}
    sb = json.loads((ref / "report.json").read_text())["photometry"]["surfaces"]
    rel = [((sa[s["name"]] - s["E_avg_lux"]) / s["E_avg_lux"], s["area_m2"]) for s in sb
           if s["name"] in sa and s["E_avg_lux"] > 0]
    x, wt = np.array(rel).T if rel else (np.zeros(1), np.ones(1))
    return float(err), float(np.sqrt((wt * x * x).sum() / wt.sum()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="office2,classroom,office3,icecream_store")
    ap.add_argument("--workers", default="0")
    ap.add_argument("--reference", action="store_true", help="also measure against a converged solution")
    args = ap.parse_args()
    print(f"bench_corpus: defaults, --workers {args.workers}; error = estimated / measured RMS of B - E per input "
          f"triangle")
    with tempfile.TemporaryDirectory() as tmp:
        for name in filter(None, args.models.split(",")):
            model = MODELS / name / "scene.obj"
            rep, wall = solve(model, Path(tmp) / name, "--workers", args.workers)
            line = (f"{name:15s} {rep['scene']['input_triangles']:7d} triangles -> {rep['scene']['patches']:7d} "
                    f"elements at {rep['settings']['patch_size_m']:.3f} m; {rep['stats']['rays'] / 1e6:6.1f}M rays, "
                    f"solve {rep['timings']['solve_s']:5.1f} s, all {wall:5.1f} s; est. {rep['error']['rms_refl']:.2%}")
            if args.reference:
                ref, _ = solve(model, Path(tmp) / (name + "-ref"), "--workers", "0", "--seed", "11",
                               "--accuracy", "0.006", "--patch-size", repr(rep["settings"]["patch_size_m"]))
                err, lux = measured(Path(tmp) / name, Path(tmp) / (name + "-ref"))
                line += (f", measured {err:.2%} (reference est. {ref['error']['rms_refl']:.2%}); "
                         f"surface lux {lux:.2%}")
            print(line, flush=True)


if __name__ == "__main__":
    main()
