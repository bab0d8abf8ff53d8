"""The real models of ../shared/models solved at defaults, as a new user runs them (issue 26).

Prints, per model: input triangles, elements, element size, rays, solve and total seconds, the
estimated error of the reflected light as the target holds it, per input triangle and per element;
with --reference, also the error measured per input triangle and per object (irradiance) against converged solutions of
the same mesh with no clusters (two other seeds, shot to a residual of 1e-4 at --ref-density times
a default run's density, in this process: the clusters' own bias is measured too, and the references'
noise is taken out).  No assertions.  In one process (--workers 0) unless --workers.

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
sys.path.insert(0, str(ROOT))


def solve(model: Path, out: Path, *extra: str) -> tuple[dict, float]:
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "dcrad.cli", "solve", str(model), "--out", str(out),
                        "--width", "160", "--height", "120", *extra], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{model}: {r.stderr.strip().splitlines()[-1]}")
    return json.loads((out / "report.json").read_text()), time.perf_counter() - t0


def reference(model: Path, size: float, factor: float, scale: float = 1.0,
              up: str | None = None, seed: int = 11) -> tuple[np.ndarray, object, object]:
    """B per input triangle of a converged unclustered solution: (B (T,3), scene, patches).

    Shot until the unshot light is 1e-4 of the emitted power (tol mode), so that it carries no
    bias of its own: a reference stopped by its own accuracy target is short of light the same way
    the run is, and against one the runs' errors read 0.7x to 0.5x of the truth (office2: 1.01%
    against an --accuracy 0.006 reference, 1.39% against this one).  Its noise is measured from two
    seeds (``measured``)."""
    from dcrad.config import SolverConfig
    from dcrad.io.export import input_triangle_radiosity
    from dcrad.pipeline import prepare
    from dcrad.solving.accuracy import rays_for
    from dcrad.solving.passes import solve_to_accuracy

    scene, patches, _ = prepare(model, size, scale=scale, up=up, adapt=True)  # the run's mesh
    density = factor * rays_for(patches.units, 0.02)  # ``factor`` times a default run's whole density
    patches.cluster[:] = -1  # every triangle its own unknown: the truth the clusters are measured against
    solve_to_accuracy(patches, SolverConfig(tol=1e-4, rays_per_power=density, seed=seed))
    return input_triangle_radiosity(patches, len(scene.faces))[0], scene, patches


def measured(run: Path, refs: list[np.ndarray], scene, patches) -> tuple[float, float, float]:
    """(RMS error of B per input triangle over RMS(B* - E) with the references' own noise taken out,
    that noise, area-weighted RMS relative error of the objects' mean irradiance) of ``run`` against
    the mean B* of two references of independent seeds."""
    from dcrad.meshing.patches import triangle_areas

    ref_b = (refs[0] + refs[1]) / 2
    a = np.load(run / "radiosity.npz")
    v = a["valid"] & scene.valid
    area = triangle_areas(scene.vertices[scene.faces])[v]
    e = scene.emission[v]
    w = area[:, None]
    den = (w * (ref_b[v] - e) ** 2).sum()
    raw = (w * (a["B"][v] - ref_b[v]) ** 2).sum() / den
    ref_noise = (w * (refs[0][v] - refs[1][v]) ** 2).sum() / den / 4  # the mean of two: var(diff) / 4
    err = np.sqrt(max(raw - ref_noise, 0.0))
    rho = scene.rho[v].mean(axis=1)
    lit = rho > 0.01
    obj = scene.obj[v][lit]
    h_run = np.bincount(obj, weights=(area * (a["B"][v] - e).mean(axis=1) / np.maximum(rho, 1e-9))[lit])
    h_ref = np.bincount(obj, weights=(area * (ref_b[v] - e).mean(axis=1) / np.maximum(rho, 1e-9))[lit])
    wt = np.bincount(obj, weights=area[lit])
    ok = h_ref > 0
    x = (h_run[ok] - h_ref[ok]) / h_ref[ok]
    return float(err), float(np.sqrt(ref_noise)), float(np.sqrt((wt[ok] * x * x).sum() / wt[ok].sum()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="office2,classroom,office3,icecream_store")
    ap.add_argument("--workers", default="0")
    ap.add_argument("--generated", default="", help="also a built-in scene as another tool would write it, Z-up, "
                    "in millimetres, every face split into 16 (e.g. office:rows=2,cols=5,seed=9)")
    ap.add_argument("--accuracy", default="", help="--accuracy of the runs (default: dcrad's)")
    ap.add_argument("--reference", action="store_true", help="also measure against a converged solution")
    ap.add_argument("--ref-density", type=float, default=8.0,
                    help="the references' ray density over a default run's (each shot to a residual of 1e-4)")
    args = ap.parse_args()
    print(f"bench_corpus: defaults, --workers {args.workers}; errors: RMS of B - B* over RMS(B* - E)")
    with tempfile.TemporaryDirectory() as tmp:
        todo = [(name, MODELS / name / "scene.obj", ()) for name in filter(None, args.models.split(","))]
        if args.generated:
            from dcrad.pipeline import resolve_scene
            from scenes.variants import variant

            path = variant(resolve_scene(args.generated, Path(tmp) / "gen"), Path(tmp) / "gen-z", up="z",
                           split=2, scale=1000.0)
            todo.append((args.generated.replace(":", "-"), path, ("--scale", "0.001")))
        for name, model, flags in todo:
            if args.accuracy:
                flags = (*flags, "--accuracy", args.accuracy)
            rep, wall = solve(model, Path(tmp) / name, "--workers", args.workers, *flags)
            line = (f"{name:15s} {rep['scene']['input_triangles']:7d} triangles -> {rep['scene']['patches']:7d} "
                    f"elements at {rep['settings']['patch_size_m']:.3f} m; {rep['stats']['rays'] / 1e6:6.1f}M rays, "
                    f"solve {rep['timings']['solve_s']:5.1f} s, all {wall:5.1f} s; est. {rep['error']['rms_refl']:.2%} "
                    "held")
            for key, what in (("triangles_refl", "per triangle"), ("elements_refl", "per element")):
                if rep["error"].get(key) is not None:
                    line += f", {rep['error'][key]:.2%} {what}"
            if args.reference:
                t0 = time.perf_counter()
                st = rep["settings"]
                refs = [reference(model, st["patch_size_m"], args.ref_density, st["scale"], st["up"], seed)
                        for seed in (11, 23)]
                scene, patches = refs[0][1], refs[0][2]
                err, ref_noise, obj = measured(Path(tmp) / name, [r[0] for r in refs], scene, patches)
                line += (f"; measured {err:.2%} per triangle (references' noise {ref_noise:.2%} taken out), "
                         f"objects' irradiance {obj:.2%} (references: {time.perf_counter() - t0:.0f} s)")
            print(line, flush=True)


if __name__ == "__main__":
    main()
