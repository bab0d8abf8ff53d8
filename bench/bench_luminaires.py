"""Rooms lit by luminaires from a photometric file, as a lighting study lights them.

The built-in office (``office:rows=R,cols=C,seed=S``) with its glowing ceiling panels turned into
plain white surfaces and, instead, one luminaire under each panel's centre, aimed down: a
downlight whose candela goes as cos^1.5 (``--shape 1.5``; 0: isotropic below the horizontal),
3000 lm.  Each run is `dcrad solve ... --luminaires lights.json --workers 0` at the accuracy
given; the bench prints rays, seconds, the estimate per input triangle, how the run ended and
its plan, and the error measured per input triangle against a converged reference of the same
mesh (another seed, shot to a residual of 1e-4 at ``--ref-density`` times a default run's
density; its own noise is measured from two seeds and taken out).  No assertions.

Run: .venv/bin/python bench/bench_luminaires.py [--scene office:rows=2,cols=3,seed=4]
     [--accuracy 0.02,0.01] [--ref-density 8]
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

LUMENS = 3000.0


def downlight(path: Path, shape: float) -> Path:
    """An LM-63 file: I(gamma) = I0 cos^shape(gamma) below the horizontal, 0 above, scaled to LUMENS."""
    gamma = np.arange(0.0, 180.1, 2.5)
    rel = np.where(gamma < 90.0, np.cos(np.radians(np.minimum(gamma, 90.0))) ** shape, 0.0)
    g = np.radians(gamma)
    # the flux of a rotationally symmetric distribution: 2 pi integral I sin(gamma) d gamma
    flux = 2 * np.pi * np.trapezoid(rel * np.sin(g), g)
    cd = rel * LUMENS / flux
    lines = ["IESNA:LM-63-2002", "[TEST] dcrad bench", "[MANUFAC] dcrad bench", "TILT=NONE",
             f"1 {LUMENS} 1.0 {len(gamma)} 1 1 2 0.0 0.0 0.0", "1.0 1.0 30.0",
             " ".join(f"{v:g}" for v in gamma), "0.0", " ".join(f"{v:.6g}" for v in cd)]
    path.write_text("\n".join(lines) + "\n")
    return path


def lit_office(spec: str, folder: Path, shape: float) -> tuple[Path, Path, int]:
    """(scene.obj, lights.json, luminaires): the office with its panels dark and a luminaire under each."""
    import scenes
    from dcrad.io.scene import load_scene

    obj = scenes.write_builtin(spec.partition(":")[0], folder,
                               **{k: int(v) for k, v in (kv.split("=") for kv in spec.partition(":")[2].split(",")
                                                         if kv)})
    scene = load_scene(obj)
    entries = []
    for k, name in enumerate(scene.names):
        if not name.startswith("light_"):
            continue
        tri = scene.vertices[scene.faces[scene.obj == k]]
        centre = scene.to_input_frame(tri.reshape(-1, 3).mean(axis=0, keepdims=True))[0]
        entries.append({"file": "downlight.ies", "position": [centre[0], centre[1] - 0.05, centre[2]],
                        "name": name})
    mtl = obj.with_suffix(".mtl")
    mtl.write_text(re.sub(r"^Ke .*$", "Ke 0 0 0", mtl.read_text(), flags=re.M))
    downlight(folder / "downlight.ies", shape)
    lights = folder / "lights.json"
    lights.write_text(json.dumps(entries))
    return obj, lights, len(entries)


def reference(obj: Path, lights: Path, size: float, factor: float, seed: int) -> tuple[np.ndarray, object, object]:
    """B per input triangle of a converged unclustered solution of the run's mesh, in tol mode."""
    from dcrad.config import SolverConfig
    from dcrad.io.export import input_triangle_radiosity
    from dcrad.pipeline import prepare
    from dcrad.solving.accuracy import rays_for
    from dcrad.solving.passes import solve_to_accuracy
    from dcrad.transport.luminaires import load_schedule

    scene, patches, _ = prepare(obj, size, adapt=True, sources=lambda sc: load_schedule(lights, sc))
    patches.cluster[:] = -1
    solve_to_accuracy(patches, SolverConfig(tol=1e-4, rays_per_power=factor * rays_for(patches.units, 0.02),
                                            seed=seed))
    return input_triangle_radiosity(patches, len(scene.faces))[0], scene, patches


def measured(run: Path, refs: list[np.ndarray], scene) -> float:
    """RMS error per input triangle of the run's B over the RMS of the reference's reflected light,
    the references' own noise (half their difference's square) taken out."""
    b = np.load(run / "radiosity.npz")["B"]
    area = np.linalg.norm(np.cross(*(scene.vertices[scene.faces][:, i] - scene.vertices[scene.faces][:, 0]
                                     for i in (1, 2))), axis=1) / 2
    ok = scene.valid & (area > 0)
    ref = 0.5 * (refs[0] + refs[1])
    w = area[ok, None]
    refl = ((ref - scene.emission)[ok] ** 2 * w).sum()
    err2 = ((b - ref)[ok] ** 2 * w).sum()
    ref_noise2 = (((refs[0] - refs[1]) / 2)[ok] ** 2 * w).sum()
    return float(np.sqrt(max(err2 - ref_noise2, 0.0) / refl))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="office:rows=2,cols=3,seed=4")
    ap.add_argument("--accuracy", default="0.02,0.01")
    ap.add_argument("--shape", type=float, default=1.5)
    ap.add_argument("--ref-density", type=float, default=8.0)
    ap.add_argument("--no-reference", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-lum-") as tmp:
        folder = Path(tmp)
        obj, lights, n = lit_office(args.scene, folder / "scene", args.shape)
        print(f"{args.scene}: {n} luminaires of {LUMENS:g} lm (cos^{args.shape:g} downlights), panels dark")
        runs = []
        for acc in args.accuracy.split(","):
            out = folder / f"run-{acc}"
            t0 = time.perf_counter()
            r = subprocess.run([sys.executable, "-m", "dcrad.cli", "solve", str(obj), "--luminaires", str(lights),
                                "--workers", "0", "--accuracy", acc, "--out", str(out), "--width", "64",
                                "--height", "48"], capture_output=True, text=True)
            if r.returncode != 0:
                raise SystemExit(r.stderr.strip().splitlines()[-1])
            rep = json.loads((out / "report.json").read_text())
            runs.append((acc, out, rep, time.perf_counter() - t0))
        refs, scene = [], None
        if not args.no_reference:
            size = runs[0][2]["settings"]["patch_size_m"]
            for seed in (11, 12):
                b, scene, _ = reference(obj, lights, size, args.ref_density, seed)
                refs.append(b)
        for acc, out, rep, wall in runs:
            st, err = rep["stats"], rep["error"]
            plan = [c["text"][:60] for c in rep["choices"] if c["code"] in ("plan", "final_gather")]
            row = {"accuracy": float(acc), "elements": rep["mesh"]["elements"], "rays": st["rays"],
                   "solve_s": round(rep["timings"]["solve_s"], 2), "wall_s": round(wall, 1),
                   "stopped_by": st["stopped_by"],
                   "est_triangles_refl": round(100 * err["triangles_refl"], 2), "plan": plan}
            if refs:
                row["measured_triangles_refl"] = round(100 * measured(out, refs, scene), 2)
            print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
