"""Daylight against closed forms and against Radiance (issue 29).

Part 1, the CIE 171:2006 daylight cases from their integrals: a black 4 x 4 x 3 m room with a roof
opening (1 x 1 and 4 x 4 m) under the uniform and the CIE overcast sky, a 2 x 1 m facade opening
with the ground outside (rho 0.3), and the 1 x 1 m opening glazed (tau_n 0.8788, index 1.52):
dcrad's direct sky light at floor, wall and ceiling points (photometry.direct_irradiance, the path
of the work plane and of black surfaces) against the integral of the sky's luminance over the
opening; relative error at each point, rays a point.

Part 2, the peer: a side-lit office (4 x 6 x 2.8 m, Z up, a 3 x 1.5 m glazed window in its south
wall, floor 0.3, walls 0.6, ceiling 0.8, a desk), CIE overcast sky, ground 0.2.  The daylight factor
on the work plane (0.85 m, dcrad's grid) from

* ``dcrad solve --sky cie-overcast --workplane 0.85`` at defaults (2%), and at 1%;
* the same divided (``--subscenes 2`` and ``4``): the sky gathered on the whole office before the
  cut, each subscene handed what landed on it, the window's pane carried across the boundaries;
* Radiance 6.0a (pyradiance's binaries): gensky -c and rtrace -I at the same points, at typical
  settings (-ab 5 -ad 1024 -as 512 -aa 0.1 -ar 256) and at high ones;
* the reference: dcrad at ``--reference-accuracy`` (0.004), another seed.

Printed: wall seconds (the command's, outputs included; Radiance's oconv + rtrace), the RMS and
the largest difference of the work plane's DF against the reference, and the two converged
solutions against each other.  No assertions.

Run: .venv/bin/python bench/bench_daylight.py [--skip-peer] [--skip-closed-forms] [--skip-radiance]
     [--reference-accuracy 0.004] [--radiance-high "-ab 6 -ad 2048 ..."]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

E_HZ = 10_000.0
TAU_N = 0.8788
TYPICAL = "-ab 5 -ad 1024 -as 512 -aa 0.1 -ar 256 -lw 1e-4"
HIGH = "-ab 6 -ad 2048 -as 1024 -aa 0.05 -ar 512 -lw 1e-5"


def part1() -> None:
    sys.path.insert(0, str(ROOT / "tests"))
    import test_daylight as td  # the tests' rooms and integrals: one definition of the cases

    from dcrad.pipeline import prepare
    from dcrad.transport.rays import Tracer
    from dcrad.transport.sky import SkyModel

    print("== part 1: the CIE 171 daylight cases from their integrals (direct sky light at points)")
    print(f"{'case':44s} {'points':>6s} {'rays/pt':>8s} {'max |err|':>10s} {'rms err':>9s} {'s':>6s}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        cases = []
        for hole in (1.0, 4.0):
            for sky in ("uniform", "cie-overcast"):
                cases.append((f"roof opening {hole:g} x {hole:g} m, {sky}", *td.roof_room(tmp, hole, stem=f"r{hole}"),
                              SkyModel(sky, E_HZ), None, td.black_points()))
        path, opening = td.facade_room(tmp)
        pts = np.array([[1.0, 0, 2], [2.5, 0, 2], [1.5, 0, 0.5], [2, 1.5, 0], [4, 1.5, 2], [1.0, 3, 2], [2.5, 3, 1]],
                       float)
        nrm = np.array([td.UP, td.UP, td.UP, [0, 0, 1.0], [-1.0, 0, 0], -td.UP, -td.UP])
        cases.append(("facade 2 x 1 m, cie-overcast, ground 0.3", path, opening,
                      SkyModel("cie-overcast", E_HZ, ground=0.3), None, (pts, nrm)))
        for name, path, opening, model, _glazed, (points, normals) in cases:
            _, patches, _ = prepare(path, 0.5, up="y")
            patches.sources = (td.sky_light(patches, model),)
            tracer = Tracer.mesh(patches)
            for rays in (4096, 16384):
                t0 = time.perf_counter()
                got = patches.sources[0].irradiance(points, normals, tracer, 1e-6, rays=rays)[:, 0]
                sec = time.perf_counter() - t0
                truth = td.opening_integral(points, normals, opening, model.radiance)
                err = got / truth - 1
                print(f"{name:44s} {len(points):6d} {rays:8d} {np.abs(err).max():10.2%} "
                      f"{np.sqrt(np.mean(err ** 2)):9.2%} {sec:6.2f}", flush=True)
    print("(the glazed opening: tests/test_daylight.py::test_a_glazed_opening_passes_tau_theta_point_by_point)")


# -- part 2: the peer -------------------------------------------------------------------------------
def office(folder: Path) -> Path:
    """The side-lit office, Z up, metres: OBJ + MTL (the pane: illum 4, Tf, Ni)."""
    v: list[tuple[float, float, float]] = []
    faces: dict[str, list[tuple[int, int, int]]] = {}

    def quad(mat, p0, p1, p2, p3):
        base = len(v) + 1
        v.extend([p0, p1, p2, p3])
        faces.setdefault(mat, []).extend([(base, base + 1, base + 2), (base, base + 2, base + 3)])

    W, D, H = 4.0, 6.0, 2.8
    quad("floor", (0, 0, 0), (W, 0, 0), (W, D, 0), (0, D, 0))  # facing +z
    quad("ceiling", (0, 0, H), (0, D, H), (W, D, H), (W, 0, H))  # facing -z
    quad("wall", (0, D, 0), (W, D, 0), (W, D, H), (0, D, H))  # north wall, facing -y
    quad("wall", (0, 0, 0), (0, D, 0), (0, D, H), (0, 0, H))  # west, facing +x
    quad("wall", (W, 0, 0), (W, 0, H), (W, D, H), (W, D, 0))  # east, facing -x
    # the south wall (y = 0, facing +y) around the window x 0.5..3.5, z 0.9..2.4
    for (x0, x1, z0, z1) in ((0, 0.5, 0, H), (3.5, W, 0, H), (0.5, 3.5, 0, 0.9), (0.5, 3.5, 2.4, H)):
        quad("wall", (x0, 0, z0), (x0, 0, z1), (x1, 0, z1), (x1, 0, z0))
    quad("glass", (0.5, 0, 0.9), (0.5, 0, 2.4), (3.5, 0, 2.4), (3.5, 0, 0.9))
    # a desk: a box 1.6 x 0.8 x 0.75 (its top and sides, facing out)
    x0, x1, y0, y1, top = 1.2, 2.8, 3.0, 3.8, 0.75
    quad("desk", (x0, y0, top), (x1, y0, top), (x1, y1, top), (x0, y1, top))
    quad("desk", (x0, y0, 0), (x1, y0, 0), (x1, y0, top), (x0, y0, top))
    quad("desk", (x1, y1, 0), (x0, y1, 0), (x0, y1, top), (x1, y1, top))
    quad("desk", (x0, y1, 0), (x0, y0, 0), (x0, y0, top), (x0, y1, top))
    quad("desk", (x1, y0, 0), (x1, y1, 0), (x1, y1, top), (x1, y0, top))
    lines = ["mtllib office.mtl"] + [f"v {x:g} {y:g} {z:g}" for x, y, z in v]
    for mat, fs in faces.items():
        lines += [f"o {mat}", f"usemtl {mat}"] + [f"f {a} {b} {c}" for a, b, c in fs]
    (folder / "office.obj").write_text("\n".join(lines) + "\n")
    (folder / "office.mtl").write_text(
        "newmtl floor\nKd 0.3 0.3 0.3\nnewmtl ceiling\nKd 0.8 0.8 0.8\nnewmtl wall\nKd 0.6 0.6 0.6\n"
        f"newmtl desk\nKd 0.4 0.4 0.4\nnewmtl glass\nKd 0 0 0\nillum 4\nTf {TAU_N} {TAU_N} {TAU_N}\nNi 1.52\n")
    rad = []
    for mat, rho in (("floor", 0.3), ("ceiling", 0.8), ("wall", 0.6), ("desk", 0.4)):
        rad.append(f"void plastic {mat}\n0\n0\n5 {rho} {rho} {rho} 0 0\n")
    # Radiance's glass takes the transmissivity tn (its internal transmittance) that gives tau_n at normal incidence
    tn = (math.sqrt(0.8402528435 + 0.0072522239 * TAU_N ** 2) - 0.9166530661) / 0.0036261119 / TAU_N
    rad.append(f"void glass glass\n0\n0\n3 {tn:.6f} {tn:.6f} {tn:.6f}\n")
    k = 0
    for mat, fs in faces.items():
        for a, b, c in fs:
            k += 1
            pts = " ".join(f"{x:g} {y:g} {z:g}" for x, y, z in (v[a - 1], v[b - 1], v[c - 1]))
            rad.append(f"{mat} polygon t{k}\n0\n0\n9 {pts}\n")
    (folder / "office.rad").write_text("\n".join(rad))
    return folder / "office.obj"


def radiance_bin() -> Path | None:
    spec = importlib.util.find_spec("pyradiance")
    if spec is None or spec.origin is None:
        return None
    return Path(spec.origin).parent


def radiance_df(folder: Path, points: np.ndarray, settings: str) -> tuple[np.ndarray, float]:
    """(DF at ``points`` facing up, seconds of oconv + rtrace) under gensky -c at E_HZ."""
    base = radiance_bin()
    assert base is not None
    env = {**os.environ, "RAYPATH": f".:{base / 'lib'}"}
    t0 = time.perf_counter()
    sky = subprocess.run([str(base / "bin" / "gensky"), "-ang", "45", "0", "-c", "-B", f"{E_HZ / 179.0:.6f}",
                          "-g", "0.2"], capture_output=True, text=True, check=True, env=env).stdout
    sky += ("\nskyfunc glow sky_glow\n0\n0\n4 1 1 1 0\nsky_glow source sky\n0\n0\n4 0 0 1 180\n"
            "skyfunc glow ground_glow\n0\n0\n4 1 1 1 0\nground_glow source ground\n0\n0\n4 0 0 -1 180\n")
    (folder / "sky.rad").write_text(sky)
    with open(folder / "office.oct", "wb") as fh:
        subprocess.run([str(base / "bin" / "oconv"), "sky.rad", "office.rad"], cwd=folder, stdout=fh, check=True,
                       env=env)
    text = "\n".join(f"{x:.6f} {y:.6f} {z:.6f} 0 0 1" for x, y, z in points) + "\n"
    out = subprocess.run([str(base / "bin" / "rtrace"), "-I", "-h", *settings.split(), "office.oct"], input=text,
                         capture_output=True, text=True, check=True, cwd=folder, env=env).stdout
    sec = time.perf_counter() - t0
    rgb = np.array([[float(x) for x in line.split()[:3]] for line in out.splitlines() if line.strip()])
    lux = 179.0 * (rgb @ np.array([0.265, 0.670, 0.065]))
    return lux / E_HZ * 100.0, sec


def dcrad_df(obj: Path, out: Path, *flags: str) -> tuple[np.ndarray, np.ndarray, float, dict]:
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "dcrad.cli", "solve", str(obj), "--sky", "cie-overcast",
                           "--workplane", "0.85", "--out", str(out), "--width", "160", "--height", "120", *flags],
                          capture_output=True, text=True, cwd=ROOT)
    sec = time.perf_counter() - t0
    if proc.returncode:
        raise SystemExit(proc.stderr)
    z = np.load(out / "radiosity.npz")
    report = json.loads((out / "report.json").read_text())
    return z["workplane_points"], z["workplane_daylight_factor"], sec, report


def part2(high: str, ref_accuracy: float, radiance: bool = True) -> None:
    print("\n== part 2: the side-lit office against Radiance (CIE overcast, the work plane's daylight factor)")
    if radiance and radiance_bin() is None:
        print("Radiance (pyradiance) is not installed: skipped")
        return
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        obj = office(folder)
        pts, ref, ref_s, ref_rep = dcrad_df(obj, folder / "ref", "--accuracy", f"{ref_accuracy:g}", "--seed", "7")
        print(f"reference: dcrad --accuracy {ref_accuracy:g} --seed 7: {len(pts)} points, {ref_s:.1f} s, "
              f"{ref_rep['stats']['rays']:,} rays, DF avg {ref.mean():.3f}%", flush=True)
        print(f"{'run':46s} {'seconds':>8s} {'rays':>12s} {'DF avg':>7s} {'rms diff':>9s} {'max diff':>9s}")

        def line(name, df, sec, rays=""):
            d = df / ref - 1
            print(f"{name:46s} {sec:8.1f} {rays:>12s} {df.mean():6.3f}% {np.sqrt(np.mean(d * d)):9.2%} "
                  f"{np.abs(d).max():9.2%}")

        for acc, k in (("0.02", 1), ("0.01", 1), ("0.02", 2), ("0.02", 4)):
            divide = ("--subscenes", str(k)) if k > 1 else ()
            _, df, sec, rep = dcrad_df(obj, folder / f"d{acc}_{k}", "--accuracy", acc, *divide)
            line(f"dcrad --accuracy {acc}" + (f" --subscenes {k}" if k > 1 else ""), df, sec,
                 f"{rep['stats']['rays']:,}")
        for name, settings in (("radiance typical", TYPICAL), ("radiance high", high)) if radiance else ():
            df, sec = radiance_df(folder, pts, settings)
            line(f"{name} ({settings})"[:46], df, sec)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--skip-peer", action="store_true")
    ap.add_argument("--skip-closed-forms", action="store_true")
    ap.add_argument("--skip-radiance", action="store_true", help="dcrad's rows only (Radiance high takes 13 min)")
    ap.add_argument("--radiance-high", default=HIGH)
    ap.add_argument("--reference-accuracy", type=float, default=0.004)
    args = ap.parse_args()
    if not args.skip_closed_forms:
        part1()
    if not args.skip_peer:
        part2(args.radiance_high, args.reference_accuracy, not args.skip_radiance)


if __name__ == "__main__":
    main()
