"""The `dcrad` command end to end, as a real process: outputs, bad input, Ctrl-C."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
import trimesh

DCRAD = [sys.executable, "-m", "dcrad.cli"]


def run(*args, timeout=300):
    return subprocess.run([*DCRAD, *map(str, args)], capture_output=True, text=True, timeout=timeout)


def read_image(path: Path) -> np.ndarray:
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    try:
        return inp.read_image(format=oiio.FLOAT)
    finally:
        inp.close()


def _rms(x: np.ndarray, area: np.ndarray) -> float:
    return float(np.sqrt((x * x).mean(axis=1) @ area / area.sum()))


def _check_outputs(out: Path) -> tuple[dict, dict]:
    """The files of one solve are complete and consistent; returns (report, radiosity.npz)."""
    report = json.loads((out / "report.json").read_text())
    # the ledger closes to round-off on every built-in scene
    assert report["ledger"]["closure"] < 1e-9
    # every choice says what it is about by a known code (choices.py), beside its sentence
    from dcrad.choices import CODES
    assert report["choices"] and all(set(c) == {"code", "text"} and c["code"] in CODES and c["text"]
                                     for c in report["choices"]), report["choices"]
    assert report["residual"] <= 0.05 and report["stats"]["stopped_by"] == "tolerance"
    assert report["snapshots"][0]["rays"] == 0 and len(report["snapshots"]) >= 3

    npz = dict(np.load(out / "radiosity.npz"))
    assert npz["B"].shape == (report["scene"]["input_triangles"], 3)
    for key, value in npz.items():
        if value.dtype.kind == "f":
            assert np.all(np.isfinite(value)), key
    patch_b, area, source = npz["patch_B"], npz["patch_area"], npz["patch_source"]
    rho, emission = npz["patch_rho"], npz["patch_emission"]
    # B per input triangle is the area-weighted mean of its patches
    t = len(npz["B"])
    for c in range(3):
        num = np.bincount(source, weights=patch_b[:, c] * area, minlength=t)
        den = np.bincount(source, weights=area, minlength=t)
        ok = den > 0
        assert np.allclose(npz["B"][ok, c], num[ok] / den[ok], rtol=1e-12, atol=0)
    # energy: a patch keeps rho of what lands on it (B - E) and absorbs 1 - rho, so the power
    # absorbed read from B alone is sum A (B - E) (1 - rho) / rho: the ledger's absorbed account
    assert rho.min() > 0.01  # (every built-in surface reflects something)
    from_b = ((patch_b - emission) * area[:, None] * (1 - rho) / rho).sum(axis=0)
    assert np.allclose(from_b, report["ledger"]["absorbed"], rtol=1e-9, atol=0), (from_b, report["ledger"])
    assert np.all(patch_b >= 0)

    # PLY: faces in patch order, radiosity as face properties
    ply = trimesh.load(out / "patches.ply", process=False)
    raw = ply.metadata["_ply_raw"]["face"]["data"]
    assert len(ply.faces) == len(patch_b)
    for c, name in enumerate(("radiosity_r", "radiosity_g", "radiosity_b")):
        assert np.allclose(raw[name].ravel(), patch_b[:, c], rtol=1e-6, atol=1e-6 * patch_b.max())

    # GLB opens and has one coloured vertex per patch corner
    glb = trimesh.load(out / "scene.glb", force="mesh", process=False)
    assert len(glb.faces) == len(patch_b)

    # previews: EXR is linear and finite, PNG is 8-bit and not black
    exr = read_image(out / "preview.exr")
    png = read_image(out / "preview.png")
    assert exr.shape == (120, 160, 3) and np.all(np.isfinite(exr)) and exr.max() > 0
    assert png.shape == (120, 160, 3) and png.max() > 0.2
    return report, npz


@pytest.mark.parametrize("scene", ["cornell", "office", "furnace"])
def test_builtin_scene_outputs_agree(tmp_path, scene):
    """In this process (--workers 0, one subscene) and through the embedded service (two worker
    processes, two subscenes each): complete outputs, each consistent, and the same solution."""
    runs = {}
    for workers in (0, 2):
        out = tmp_path / f"w{workers}"
        r = run("solve", scene, "--workers", workers, "--out", out, "--tol", "0.05", "--width", "160",
                "--height", "120")
        assert r.returncode == 0, r.stderr
        assert "Traceback" not in r.stderr
        runs[workers] = _check_outputs(out)
    (rep0, a), (rep2, b) = runs[0], runs[2]
    assert rep2["divided"]["subscenes"] == 4 and rep0["divided"] is None  # two per worker
    # the same scene: the same patches, materials and emitted power on both paths
    for key in ("patch_area", "patch_rho", "patch_emission", "patch_source"):
        assert np.array_equal(a[key], b[key]), key
    assert np.allclose(rep0["ledger"]["emitted"], rep2["ledger"]["emitted"], rtol=1e-12, atol=0)  # summation order
    area, e = a["patch_area"], a["patch_emission"]
    # reflected power: each run is short of the converged one by at most what it still holds
    # (unshot + in flight) times rho/(1 - rho), the most that light can still reflect
    refl0, refl2 = (((x["patch_B"] - e) * area[:, None]).sum(axis=0) for x in (a, b))
    rmax = float(a["patch_rho"].max())
    held = max(rep0["residual"], rep2["residual"]) * np.asarray(rep0["ledger"]["emitted"])
    assert np.all(np.abs(refl0 - refl2) <= held * rmax / (1 - rmax)), (refl0, refl2, held)
    # per patch: two independent noisy solutions differ by about sqrt(e0^2 + e2^2) (their
    # estimated errors); a path that loses or misplaces light differs by far more
    diff = _rms(a["patch_B"] - b["patch_B"], area) / _rms(a["patch_B"] - e, area)
    expect = float(np.hypot(rep0["error"]["rms_refl"], rep2["error"]["rms_refl"]))
    assert diff < 2.0 * expect, (diff, expect)


def write(tmp: Path, obj: str, mtl: str | None = None, name="s.obj") -> Path:
    if mtl is not None:
        (tmp / "s.mtl").write_text(mtl)
    (tmp / name).write_text(obj)
    return tmp / name


MTL = "newmtl white\nKd 0.5 0.5 0.5\nnewmtl lamp\nKd 0.5 0.5 0.5\nKe 10 10 10\n"
QUADS = (
    "mtllib s.mtl\no floor\nusemtl white\nv 0 0 0\nv 1 0 0\nv 1 0 1\nv 0 0 1\nf 1 3 2\nf 1 4 3\n"
    "o lamp\nusemtl lamp\nv 0 1 0\nv 1 1 0\nv 1 1 1\nv 0 1 1\nf 5 6 7\nf 5 7 8\n"
)

BAD = {
    "missing file": (None, None, "no such file"),
    "malformed vertex": ("mtllib s.mtl\no thing\nv 1 2\nf 1 2 3\n", MTL, "line"),
    "face index out of range": ("mtllib s.mtl\no thing\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", MTL, "line"),
    "nan coordinate": (QUADS.replace("v 1 0 1", "v nan 0 1"), MTL, "floor"),
    "reflectance one": (QUADS, MTL.replace("Kd 0.5 0.5 0.5\nnewmtl lamp", "Kd 1.0 0.5 0.5\nnewmtl lamp"), "white"),
    "negative emission": (QUADS, MTL.replace("Ke 10 10 10", "Ke 10 -1 10"), "lamp"),
    "empty scene": ("mtllib s.mtl\no nothing\nv 0 0 0\n", MTL, "no faces"),
    "mtllib outside folder": (QUADS.replace("mtllib s.mtl", "mtllib ../evil.mtl"), MTL, "../evil.mtl"),
    "unsupported format": ("solid x\n", None, "unsupported"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_gives_one_clear_line(tmp_path, case):
    obj, mtl, needle = BAD[case]
    if obj is None:
        path = tmp_path / "nope.obj"
    else:
        path = write(tmp_path, obj, mtl, name="s.stl" if case == "unsupported format" else "s.obj")
    r = run("solve", path, "--out", tmp_path / "out")
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = [ln for ln in r.stderr.strip().splitlines() if ln]
    assert len(lines) == 1 and lines[0].startswith("dcrad: error:"), r.stderr
    assert needle.lower() in lines[0].lower(), lines[0]
    assert "Traceback" not in r.stderr
    assert not (tmp_path / "out" / "radiosity.npz").exists()


def test_degenerate_triangles_dropped_with_warning(tmp_path):
    obj = QUADS + "o sliver\nusemtl white\nv 0 0.5 0\nv 1 0.5 0\nv 2 0.5 0\nf 9 10 11\n"
    path = write(tmp_path, obj, MTL)
    r = run("solve", path, "--out", tmp_path / "out", "--tol", "0.01")
    assert r.returncode == 0, r.stderr
    assert "degenerate" in r.stderr and "sliver" in r.stderr
    npz = np.load(tmp_path / "out" / "radiosity.npz")
    assert npz["B"].shape == (5, 3) and not npz["valid"][4] and np.all(npz["B"][4] == 0)
    assert all(np.all(np.isfinite(npz[k])) for k in npz.files if npz[k].dtype.kind == "f")


def test_no_emitters_gives_zero_solution_and_warning(tmp_path):
    path = write(tmp_path, QUADS, MTL.replace("Ke 10 10 10", "Ke 0 0 0"))
    r = run("solve", path, "--out", tmp_path / "out")
    assert r.returncode == 0, r.stderr
    assert "no emitters" in r.stderr
    npz = np.load(tmp_path / "out" / "radiosity.npz")
    assert np.all(npz["B"] == 0)


def test_ctrl_c_stops_cleanly_and_writes_results(tmp_path):
    out = tmp_path / "out"
    # a stiff furnace with an unreachable tolerance: only Ctrl-C ends it
    proc = subprocess.Popen(
        [*DCRAD, "solve", "furnace:rho=0.99", "--out", str(out), "--tol", "1e-9", "--progress",
         "--width", "64", "--height", "48"],
        stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1,
    )
    # wait for the progress bar to appear: the solver is running
    buf = ""
    while "residual" not in buf:
        ch = proc.stderr.read(1)
        assert ch, f"dcrad ended early: {buf}"
        buf += ch
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr
    report = json.loads((out / "report.json").read_text())
    assert report["stats"]["stopped_by"] == "stopped"
    assert report["ledger"]["closure"] < 1e-9
    assert (out / "preview.png").exists() and (out / "radiosity.npz").exists()


def test_a_stop_while_the_scene_loads_ends_the_command_at_once(tmp_path):
    """SIGTERM while a large scene is still being written, loaded and meshed: the command ends
    promptly (nothing to solve yet, so nothing to write), exit 130, one line naming the phase,
    no traceback and no report."""
    out = tmp_path / "out"
    proc = subprocess.Popen([*DCRAD, "solve", "office:rows=10,cols=10", "--workers", "0", "--out", str(out)],
                            stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    time.sleep(3.0)  # imported, the handler in place; the 10x10 office takes far longer to load and mesh
    assert proc.poll() is None, proc.communicate()[1]
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    assert "stopped while the scene loaded and meshed: nothing solved, no results written" in stderr
    assert "Traceback" not in stderr and not (out / "report.json").exists()


@pytest.mark.parametrize("mode", ["binned", "exact"])
def test_solve_divided_from_the_command_line(tmp_path, mode):
    out = tmp_path / "out"
    r = run("solve", "office", "--subscenes", "2", "--boundary", mode, "--out", out, "--tol", "0.05",
            "--width", "80", "--height", "60")
    assert r.returncode == 0, r.stderr
    report = json.loads((out / "report.json").read_text())
    div = report["divided"]
    assert div["subscenes"] == 2 and div["mode"] == mode and div["barriers"] >= 1
    assert div["max_barrier_closure"] < 1e-10 and report["ledger"]["closure"] < 1e-10
    assert report["residual"] <= 0.05
    npz = np.load(out / "radiosity.npz")
    assert np.all(np.isfinite(npz["B"])) and npz["B"].max() > 0


def test_explicit_planes_on_the_command_line(tmp_path):
    out = tmp_path / "out"
    # the 2x3 office: a wall spans x in [4.00, 4.12] and another z in [4.00, 4.12]
    r = run("solve", "office", "--workers", "0", "--planes", "x=4.06,z=4.06", "--out", out, "--tol", "0.05",
            "--width", "80", "--height", "60")
    assert r.returncode == 0, r.stderr
    div = json.loads((out / "report.json").read_text())["divided"]
    assert div["subscenes"] == 4 and div["max_barrier_closure"] < 1e-10
    planes = {(p["axis"], round(p["offset"], 3)) for p in div["partition"]["planes"]}
    assert planes == {("x", 4.06), ("z", 4.06)}
    bad = run("solve", "office", "--workers", "0", "--planes", "w=3", "--out", tmp_path / "bad")
    assert bad.returncode == 2 and "'w=3'" in bad.stderr and "Traceback" not in bad.stderr


@pytest.mark.parametrize("workers", [0, 2])
def test_z_up_textured_mixed_winding_model(tmp_path, workers):
    """A Cornell box exported Z-up, textured and with a third of its faces wound the wrong way,
    on both paths: the up axis is detected and reported, --two-sided lights both sides (no
    back-face loss, no warning), the texture is listed, lux statistics and the false-colour
    image are written; one-sided, the flipped-normals warning names objects on both paths."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    import scenes
    from scenes.variants import variant

    model = variant(scenes.write_builtin("cornell", tmp_path / "y"), tmp_path / "m", up="z", flip=0.35,
                    texture=True, seed=4)
    out = tmp_path / "two"
    r = run("solve", model, "--workers", workers, "--out", out, "--tol", "0.05", "--width", "96", "--height", "72",
            "--two-sided", "--workplane", "0.3")
    assert r.returncode == 0, r.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["settings"]["up"] == "z" and rep["settings"]["up_source"].startswith("detected")
    assert rep["settings"]["two_sided"] is True and rep["settings"]["textured_materials"]
    assert rep["ledger"]["back_faces"] == [0.0, 0.0, 0.0] or sum(rep["ledger"]["back_faces"]) == 0
    assert not any("flipped" in w for w in rep["warnings"])
    names = {s["name"] for s in rep["photometry"]["surfaces"]}
    assert {"floor", "ceiling", "light"} <= names
    floor = next(s for s in rep["photometry"]["surfaces"] if s["name"] == "floor")
    assert floor["E_avg_lux"] > 0 and 0 <= floor["uniformity"] <= 1
    assert rep["photometry"]["workplane"]["n_points"] > 0
    img = read_image(out / "illuminance.png")
    assert img.shape[1] > 96  # the legend is drawn to the right of the view
    out1 = tmp_path / "one"
    r = run("solve", model, "--workers", workers, "--out", out1, "--tol", "0.05", "--width", "64", "--height", "48")
    assert r.returncode == 0, r.stderr
    rep1 = json.loads((out1 / "report.json").read_text())
    flipped = [w for w in rep1["warnings"] if "flipped" in w]
    assert flipped and any(n in flipped[0] for n in ("floor", "ceiling", "back_wall", "left_wall", "right_wall"))


def test_default_workers_on_a_small_scene_is_the_one_process_run(tmp_path):
    """`dcrad solve` without --workers on a small scene chooses this process (the report says so)
    and is the `--workers 0` run: the same B bit for bit and the same scene file, which the choice
    wrote and loaded once for the solve to reuse (it was written and loaded twice)."""
    outs = {}
    for flags in ((), ("--workers", "0")):
        out = tmp_path / ("default" if not flags else "w0")
        r = run("solve", "cornell", *flags, "--out", out, "--tol", "0.05", "--width", "80", "--height", "60")
        assert r.returncode == 0, r.stderr
        outs[flags] = out
    default, w0 = outs[()], outs[("--workers", "0")]
    report = json.loads((default / "report.json").read_text())
    first = report["choices"][0]
    assert first["code"] == "workers" and first["text"].startswith("solved in this process")
    assert report["divided"] is None
    assert report["timings"]["load_s"] > 0  # the choice's loading is counted in the solve's timings
    assert np.array_equal(np.load(default / "radiosity.npz")["patch_B"], np.load(w0 / "radiosity.npz")["patch_B"])
    assert (default / "scene" / "cornell.obj").read_bytes() == (w0 / "scene" / "cornell.obj").read_bytes()


def test_divided_run_flags_on_a_run_that_does_not_divide_are_reported(tmp_path):
    """--iterations and --boundary set for a run in one subscene: the run is the plain one (the same B
    bit for bit) and report.json's choices and stderr say the flags were not used (they were
    accepted and silently ignored)."""
    outs = {}
    for flags in ((), ("--iterations", "8", "--boundary", "binned")):
        out = tmp_path / ("plain" if not flags else "flagged")
        r = run("solve", "cornell", "--workers", "0", *flags, "--out", out, "--tol", "0.05", "--width", "80",
                "--height", "60")
        assert r.returncode == 0, r.stderr
        outs[flags] = (out, r.stderr)
    (plain, _), (flagged, stderr) = outs.values()
    note = "--iterations 8, --boundary binned: for divided runs only; this run was one subscene in this process"
    assert any(c["code"] == "unused_flags" and c["text"].startswith(note)
               for c in json.loads((flagged / "report.json").read_text())["choices"])
    assert note in stderr
    assert not any(c["code"] == "unused_flags" for c in json.loads((plain / "report.json").read_text())["choices"])
    assert np.array_equal(np.load(plain / "radiosity.npz")["patch_B"], np.load(flagged / "radiosity.npz")["patch_B"])
