"""Luminaires from photometric files (luminaires.py), against closed forms and against each other.

The photometric files are written here, by hand as LM-63 and EULUMDAT text (full precision, so the
table is the distribution the test means) or with photompy's own ``create_ies``.  The truths:
E = I cos / d^2 under a cosine downlight (CIE 171:2006 case 5.2's layout), every lumen of an
isotropic source absorbed in a closed black room (case 5.4), the utilisation factor of a cosine
downlight on a rectangle (the point-to-parallel-rectangle form factor), a symmetric file against
its full table, a rotated luminaire against its table rotated by hand, a Z-up millimetre file
against the same room Y-up in metres, an IES file against an EULUMDAT one, and every bad input
refused in one line naming its file.
"""

from __future__ import annotations

import base64
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import dcrad
from dcrad.errors import ConfigError
from dcrad.outputs.photometry import EFFICACY, workplane
from dcrad.transport.luminaires import Distribution, Luminaire, load_schedule, read_photometric
from dcrad.transport.rays import Tracer
from scenes.objwriter import ObjWriter

GAMMA_HALF = np.arange(0.0, 90.5, 1.0)  # 0-90 every degree: cos interpolates to 4e-5
GAMMA_FULL = np.arange(0.0, 180.1, 5.0)
C_FULL = np.arange(0.0, 360.1, 15.0)


def box(folder, size=(4.0, 3.0, 4.0), rho=0.0, stem="room") -> Path:
    """A closed box of one reflectance, its faces facing in, each face its own object; Y up."""
    x, y, z = size
    w = ObjWriter()
    w.material("surface", rho)
    for name, axis, value, facing in [("floor", 1, 0.0, 1), ("ceiling", 1, y, -1), ("wall_x0", 0, 0.0, 1),
                                      ("wall_x1", 0, x, -1), ("wall_z0", 2, 0.0, 1), ("wall_z1", 2, z, -1)]:
        w.begin(name, "surface")
        lo, hi = {0: ((0.0, 0.0), (y, z)), 1: ((0.0, 0.0), (x, z)), 2: ((0.0, 0.0), (x, y))}[axis]
        w.add_rect(axis, value, lo, hi, facing)
    Path(folder).mkdir(parents=True, exist_ok=True)
    return w.write(folder, stem)


def _row(values) -> str:
    return " ".join(repr(float(v)) for v in values)


def ies(path: Path, gamma, c, cd, *, version="IESNA:LM-63-2002", lumens=-1.0, lamps=1, multiplier=1.0,
        ptype=1, units=2, opening=(0.0, 0.0, 0.0), ballast=1.0, future=1.0, watts=0.0, tilt="NONE") -> Path:
    """An LM-63 file written by hand: candela ``cd`` (len(c), len(gamma))."""
    cd = np.asarray(cd, np.float64).reshape(len(c), len(gamma))
    lines = ([version] if version else []) + ["[TEST] dcrad", "[MANUFAC] dcrad tests"]
    lines += [f"TILT={tilt}"] if isinstance(tilt, str) else ["TILT=INCLUDE", "1", str(len(tilt[0])), _row(tilt[0]),
                                                            _row(tilt[1])]
    lines += [f"{lamps} {lumens!r} {multiplier!r} {len(gamma)} {len(c)} {ptype} {units} {_row(opening)}",
              f"{ballast!r} {future!r} {watts!r}", _row(gamma), _row(c), *(_row(r) for r in cd)]
    path.write_text("\n".join(lines) + "\n", encoding="latin-1")
    return path


def ldt(path: Path, isym: int, c_all, gamma, cd_stored, *, flux=1000.0, lamps=1, watts=0.0, sets=1,
        comma=False) -> Path:
    """A EULUMDAT file written by hand: all C angles listed, the stored planes' candela (cd, turned into
    cd/klm of ``flux`` here) in ``cd_stored`` (planes, len(gamma))."""
    f = (lambda v: repr(float(v)).replace(".", ",")) if comma else (lambda v: repr(float(v)))
    lines = ["dcrad tests", "1", str(isym), str(len(c_all)), f(c_all[1] - c_all[0]) if len(c_all) > 1 else "0",
             str(len(gamma)), f(gamma[1] - gamma[0]), "report", "luminaire", "L-1", path.name, "2026-01-01"]
    lines += ["100", "100", "50", "60", "0", "0", "0", "0", "0", "100", "100", "1", "0", str(sets)]
    for _ in range(sets):
        lines += [str(lamps), "LED", f(flux), "3000K", "1B", f(watts)]
    lines += ["0.5"] * 10
    lines += [f(v) for v in c_all] + [f(v) for v in gamma]
    lines += [f(v) for v in (np.asarray(cd_stored, np.float64) * 1000.0 / flux).reshape(-1)]
    path.write_text("\r\n".join(lines) + "\r\n")
    return path


def schedule(path: Path, entries) -> Path:
    path.write_text(json.dumps(entries))
    return path


def table(fn, c=C_FULL, gamma=GAMMA_FULL) -> np.ndarray:
    """fn(gamma deg, C deg) on the grid: (len(c), len(gamma))."""
    cc, gg = np.meshgrid(c, gamma, indexing="ij")
    return fn(gg, cc)


def down(g):
    """cos(gamma) below the horizontal, 0 above (a downlight's shape over 0-180)."""
    return np.maximum(np.cos(np.radians(g)), 0.0)


def random_dirs(n=4000, seed=7) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1)[:, None]


def cosine_downlight(tmp_path, i0=1000.0) -> Path:
    return ies(tmp_path / "downlight.ies", GAMMA_HALF, [0.0], [i0 * np.cos(np.radians(GAMMA_HALF))],
               lumens=1000.0, watts=12.5)


def test_a_cosine_downlight_above_a_black_floor_gives_i_cos_over_d2(tmp_path):
    """I(gamma) = 1000 cos(gamma) cd 3 m above the black floor of a closed room: E = I cos / d^2 =
    I0 h^2 / d^4 lux at every floor point (one shadow ray a point: exact but for the table's
    interpolation of cos at 1 degree, 4e-5), and the lumens are its pi I0 (lm)."""
    path = box(tmp_path, size=(4.0, 3.2, 4.0))
    lights = schedule(tmp_path / "lights.json", {"file": "downlight.ies", "position": [2.0, 3.0, 2.0]})
    cosine_downlight(tmp_path)
    result = dcrad.solve(path, accuracy=0.05, patch_size=0.5, luminaires=lights, seed=1)
    (lum,) = result.patches.sources
    assert isinstance(lum, Luminaire) and lum.photometric.lamp_lumens == 1000.0
    assert lum.lumens == pytest.approx(math.pi * 1000.0, rel=1e-4)
    wp = workplane(result.patches, 1e-4, spacing=0.37, tracer=Tracer.mesh(result.patches), border=0.0)
    d = np.array([2.0, 3.0, 2.0]) - wp["points"]
    r2 = (d * d).sum(axis=1)
    h = 3.0 - 1e-4
    expected = 1000.0 * h * h / r2 ** 2
    assert len(expected) > 80
    np.testing.assert_allclose(wp["lux"], expected, rtol=1e-4)
    section = result.report["luminaires"]
    assert section["count"] == 1 and section["types"][0]["input_watts_each"] == 12.5
    assert section["lumens"] == pytest.approx(lum.lumens, rel=1e-12)
    assert not any("no emitters" in w for w in result.report["warnings"])


def test_an_isotropic_10000_lm_luminaire_in_a_closed_black_room_puts_every_lumen_on_its_surfaces(tmp_path):
    """CIE 171:2006 case 5.4 from a file: absolute photometry (-1 lm) of 10,000 / (4 pi) cd every way;
    the ledger books 10,000 lm / 179 lm/W in each channel, all absorbed, none escaping."""
    ies(tmp_path / "iso.ies", GAMMA_FULL, [0.0], [np.full(len(GAMMA_FULL), 10_000.0 / (4 * math.pi))])
    lights = schedule(tmp_path / "lights.json", [{"file": "iso.ies", "position": [2.0, 1.5, 2.0], "name": "bulb"}])
    result = dcrad.solve(box(tmp_path), accuracy=0.05, patch_size=0.5, luminaires=lights, seed=2)
    led = result.report["ledger"]
    assert sum(led["emitted"]) == pytest.approx(3 * 10_000.0 / 179.0, rel=1e-12)
    assert sum(led["absorbed"]) == pytest.approx(3 * 10_000.0 / 179.0, rel=1e-9)
    assert sum(led["escaped"]) == 0.0 and led["closure"] < 1e-9
    t = result.report["luminaires"]["types"][0]
    assert t["lamp_lumens"] is None and t["lumens_each"] == pytest.approx(10_000.0, rel=1e-12)
    assert result.patches.sources[0].name == "bulb"


def _pair(tmp_path, name, *files_and_entries):
    """The luminaires of one schedule, in the Y-up 4 x 3 x 4 room."""
    scene = dcrad.load(box(tmp_path / "room"))
    return load_schedule(schedule(tmp_path / f"{name}.json", list(files_and_entries)), scene)


@pytest.mark.parametrize("kind", ["axial", "half", "quadrant_uneven"])
def test_a_symmetric_file_gives_the_intensities_of_its_full_table(tmp_path, kind):
    """One plane, 0-180 and 0-90 (its planes unevenly spaced) against the 0-360 table of the same
    distribution, its mirrored planes where the symmetry puts them: the same candela every way,
    the same lumens."""
    if kind == "axial":
        fn, stored = (lambda g, c: 1000 * np.cos(np.radians(g)) ** 2 + 50 + 0 * c), np.array([0.0])
        full_c = C_FULL
    elif kind == "half":
        fn, stored = (lambda g, c: 1000 * down(g) * (1 + 0.5 * np.cos(np.radians(c))) + 20), \
            np.arange(0.0, 180.1, 15.0)
        full_c = C_FULL
    else:
        fn = lambda g, c: 1000 * down(g) * (1 + 0.5 * np.cos(np.radians(2 * c))) + 20
        stored = np.array([0.0, 10.0, 30.0, 60.0, 90.0])
        full_c = np.unique(np.concatenate([stored, 180 - stored, 180 + stored, 360 - stored]))
    ies(tmp_path / "sym.ies", GAMMA_FULL, stored, table(fn, stored))
    ies(tmp_path / "full.ies", GAMMA_FULL, full_c, table(fn, full_c))
    sym, full = _pair(tmp_path, "both", {"file": "sym.ies", "position": [1, 1, 1], "aim": [0.2, -1, 0.4]},
                      {"file": "full.ies", "position": [1, 1, 1], "aim": [0.2, -1, 0.4]})
    dirs = random_dirs()
    np.testing.assert_allclose(sym.candela(dirs), full.candela(dirs), rtol=1e-12, atol=1e-9)
    assert sym.lumens == pytest.approx(full.lumens, rel=1e-12)
    # and at the table's own knots the candela are the file's, mirrored where the symmetry says
    gg, cc = np.meshgrid(GAMMA_FULL, full_c)
    np.testing.assert_allclose(sym.photometric.distribution.at(gg, cc), table(fn, full_c), rtol=1e-12)


def test_a_symmetric_and_a_full_file_light_a_room_alike(tmp_path):
    """The same solve with the one-plane and the 0-360 file: the same lumens booked, the same lux on
    the work plane (black room: the exact direct light)."""
    fn = lambda g, c: 1000 * np.cos(np.radians(g)) ** 3 + 0 * c
    ies(tmp_path / "one.ies", GAMMA_HALF, [0.0], table(fn, [0.0], GAMMA_HALF))
    ies(tmp_path / "all.ies", GAMMA_HALF, C_FULL, table(fn, C_FULL, GAMMA_HALF))
    runs = []
    for f in ("one.ies", "all.ies"):
        lights = schedule(tmp_path / f"{f}.json", {"file": f, "position": [1.5, 2.9, 2.5]})
        r = dcrad.solve(box(tmp_path / "room"), tmp_path / f"out_{f}", accuracy=0.05, patch_size=0.5,
                        luminaires=lights, workplane=0.8, seed=3, width=32, height=24)
        runs.append((r, np.load(tmp_path / f"out_{f}" / "radiosity.npz")["workplane_lux"]))
    (a, lux_a), (b, lux_b) = runs
    assert a.report["ledger"]["emitted"] == pytest.approx(b.report["ledger"]["emitted"], rel=1e-12)
    np.testing.assert_allclose(lux_a, lux_b, rtol=1e-9)
    assert lux_a.max() > 10


def test_a_luminaire_rotated_about_its_aim_is_its_table_rotated_by_hand(tmp_path):
    """An asymmetric table (brighter towards C0) turned 90 degrees about its aim equals the file whose
    table is shifted by hand, B(C) = A(C - 90), unturned; and the frame is the documented one: C0
    along the file's +X, C90 = C0 x aim (-Z under a downlight in a Y-up room)."""
    fn = lambda g, c: 1000 * down(g) * (1 + 0.8 * np.cos(np.radians(c))) + 10
    ies(tmp_path / "a.ies", GAMMA_FULL, C_FULL, table(fn, C_FULL))
    ies(tmp_path / "b.ies", GAMMA_FULL, C_FULL, table(lambda g, c: fn(g, c - 90.0), C_FULL))
    turned, by_hand, plain = _pair(tmp_path, "turn", {"file": "a.ies", "position": [2, 2, 2], "rotation": 90},
                                   {"file": "b.ies", "position": [2, 2, 2]},
                                   {"file": "a.ies", "position": [2, 2, 2]})
    dirs = random_dirs()
    np.testing.assert_allclose(turned.candela(dirs), by_hand.candela(dirs), rtol=1e-12, atol=1e-9)
    s = math.sqrt(0.5)
    towards = np.array([[s, -s, 0], [-s, -s, 0], [0, -s, -s], [0, -s, s]])  # 45 degrees below +X, -X, -Z, +Z
    expected = fn(45.0, np.array([0.0, 180.0, 90.0, 270.0]))
    np.testing.assert_allclose(plain.candela(towards), expected, rtol=1e-12)
    np.testing.assert_allclose(turned.candela(towards), fn(45.0, np.array([-90.0, 90.0, 0.0, 180.0])), rtol=1e-12)


def test_a_luminaire_aimed_sideways_lights_a_wall_not_the_floor(tmp_path):
    """A 25-degree beam aimed along +X from the room's middle: wall x = 4 is lit (straight ahead, 2 m
    away: I / d^2 = 250 lux), the floor, ceiling and other walls get nothing."""
    g = np.arange(0.0, 90.5, 5.0)
    ies(tmp_path / "spot.ies", g, [0.0], [np.where(g <= 25, 1000.0, np.where(g <= 30, 1000.0 * (30 - g) / 5, 0.0))])
    lights = schedule(tmp_path / "lights.json", {"file": "spot.ies", "position": [2, 1.5, 2], "aim": [1, 0, 0]})
    result = dcrad.solve(box(tmp_path), tmp_path / "out", accuracy=0.05, patch_size=0.25, luminaires=lights,
                         seed=4, width=32, height=24)
    surfaces = {s["name"]: s for s in result.report["photometry"]["surfaces"]}
    assert surfaces["wall_x1"]["E_max_lux"] > 100
    for other in ("floor", "ceiling", "wall_x0", "wall_z0", "wall_z1"):
        assert surfaces[other]["E_max_lux"] == 0.0, other
    (lum,) = result.patches.sources
    tracer = Tracer.mesh(result.patches)
    h = lum.irradiance(np.array([[4.0 - 1e-9, 1.5, 2.0]]), np.array([[-1.0, 0, 0]]), tracer, 1e-6)
    assert 179.0 * h[0, 0] == pytest.approx(250.0, rel=1e-9)


def test_a_z_up_millimetre_schedule_lands_where_the_y_up_metre_one_does(tmp_path):
    """The same room and light written Z-up in millimetres (positions and aims in the file's own
    coordinates, scale 0.001, the up axis detected from a scene without emitters) and Y-up in
    metres: the same luminaire in the solver's frame, the same lux on the work plane."""
    yup = box(tmp_path / "yup")
    text = yup.read_text().splitlines()
    zup_dir = tmp_path / "zup"
    zup_dir.mkdir()
    out_lines = []
    for line in text:  # (x, y, z) metres Y-up -> (x, -z, y) millimetres Z-up: a rotation, winding kept
        if line.startswith("v "):
            x, y, z = map(float, line.split()[1:])
            line = f"v {1000 * x!r} {-1000 * z!r} {1000 * y!r}"
        out_lines.append(line)
    (zup_dir / "room.obj").write_text("\n".join(out_lines) + "\n")
    (zup_dir / "room.mtl").write_text((tmp_path / "yup" / "room.mtl").read_text())
    fn = lambda g, c: 800 * np.cos(np.radians(g)) * (1 + 0.6 * np.sin(np.radians(c))) + 5
    for folder in (tmp_path / "yup", zup_dir):
        ies(folder / "asym.ies", GAMMA_HALF, C_FULL, table(fn, C_FULL, GAMMA_HALF))
    schedule(tmp_path / "yup" / "lights.json",
             {"file": "asym.ies", "position": [1.5, 2.5, 1.0], "aim": [0.3, -1, 0.2], "rotation": 30})
    schedule(zup_dir / "lights.json",
             {"file": "asym.ies", "position": [1500, -1000, 2500], "aim": [0.3, -0.2, -1], "rotation": 30})
    a = dcrad.solve(yup, tmp_path / "out_y", accuracy=0.05, patch_size=0.5, luminaires=tmp_path / "yup" / "lights.json",
                    workplane=0.8, seed=5, width=32, height=24)
    b = dcrad.solve(zup_dir / "room.obj", tmp_path / "out_z", accuracy=0.05, patch_size=0.5, scale=0.001,
                    luminaires=zup_dir / "lights.json", workplane=0.8, seed=5, width=32, height=24)
    assert b.scene.up == "z" and b.scene.up_source.startswith("detected")
    la, lb = a.patches.sources[0], b.patches.sources[0]
    for attr in ("position", "aim", "c0", "c90"):
        np.testing.assert_allclose(getattr(lb, attr), getattr(la, attr), atol=1e-12)
    dirs = random_dirs()
    np.testing.assert_allclose(lb.candela(dirs), la.candela(dirs), rtol=1e-12, atol=1e-9)
    lux_a = np.load(tmp_path / "out_y" / "radiosity.npz")["workplane_lux"]
    lux_b = np.load(tmp_path / "out_z" / "radiosity.npz")["workplane_lux"]
    np.testing.assert_allclose(lux_b, lux_a, rtol=1e-9)


def test_an_ies_and_an_ldt_file_of_one_distribution_are_one_luminaire(tmp_path):
    """EULUMDAT's symmetries read as the standard lays them out (all Mc C angles listed, then only the
    stored planes: Isym 1 one, 2 and 3 Mc/2 + 1 from C0 or C90, 4 Mc/4 + 1) against the IES file of
    the whole table; a decimal-comma file too; and one solve with each gives the same lux."""
    cases = {  # Isym: (distribution, stored planes)
        1: (lambda g, c: 900 * np.cos(np.radians(g)) ** 2 + 30 + 0 * c, np.array([0.0])),
        2: (lambda g, c: 900 * down(g) * (1 + 0.5 * np.cos(np.radians(c))) + 30,
            np.arange(0.0, 180.1, 15.0)),
        3: (lambda g, c: 900 * down(g) * (1 + 0.5 * np.sin(np.radians(c))) + 30,
            np.arange(90.0, 270.1, 15.0)),
        4: (lambda g, c: 900 * down(g) * (1 + 0.5 * np.cos(np.radians(2 * c))) + 30,
            np.arange(0.0, 90.1, 15.0)),
        0: (lambda g, c: 900 * down(g) * (1 + 0.7 * np.cos(np.radians(c - 40))) + 30,
            np.arange(0.0, 359.0, 15.0)),
    }
    dirs = random_dirs()
    for isym, (fn, stored) in cases.items():
        ies(tmp_path / f"s{isym}.ies", GAMMA_FULL, C_FULL, table(fn, C_FULL), lumens=2000.0, watts=20.0)
        ldt(tmp_path / f"s{isym}.ldt", isym, np.arange(0.0, 359.0, 15.0), GAMMA_FULL, table(fn, stored),
            flux=2000.0, watts=20.0, comma=isym == 2)
        a, b = _pair(tmp_path, f"s{isym}", {"file": f"s{isym}.ies", "position": [2, 2.5, 2], "rotation": 20},
                     {"file": f"s{isym}.ldt", "position": [2, 2.5, 2], "rotation": 20})
        np.testing.assert_allclose(b.candela(dirs), a.candela(dirs), rtol=1e-9, atol=1e-9, err_msg=f"Isym {isym}")
        assert b.lumens == pytest.approx(a.lumens, rel=1e-9)
        assert (b.photometric.lamp_lumens, b.photometric.input_watts) == (2000.0, 20.0)
        assert (a.photometric.lamp_lumens, a.photometric.input_watts) == (2000.0, 20.0)
    ldt_lux = []
    for f in ("s3.ies", "s3.ldt"):
        lights = schedule(tmp_path / f"run_{f}.json", {"file": f, "position": [1.5, 2.9, 2.5], "rotation": 20})
        dcrad.solve(box(tmp_path / "room"), tmp_path / f"o_{f}", accuracy=0.05, patch_size=0.5, luminaires=lights,
                    workplane=0.8, seed=6, width=32, height=24)
        ldt_lux.append(np.load(tmp_path / f"o_{f}" / "radiosity.npz")["workplane_lux"])
    np.testing.assert_allclose(ldt_lux[1], ldt_lux[0], rtol=1e-9)


def test_photompy_written_files_and_the_file_s_own_factors(tmp_path):
    """A file from photompy's ``create_ies``; the candela multiplier and ballast factor (and 1995's
    ballast-lamp factor, not 2019's file-generation type) scale the table; LM-63-1991 and 1986 files
    read; TILT=INCLUDE scales a luminaire by its factor at the luminaire's tilt from straight down;
    the schedule's multiplier scales the lumens."""
    import photompy

    g = np.arange(0.0, 180.1, 10.0)
    photompy.create_ies(g, np.array([0.0]), np.full((1, len(g)), 100.0), manufacturer="m", lumcat="l", test="t",
                        testlab="x", issuedate="2026-01-01", input_watts=7).write(tmp_path / "made.ies")
    made = read_photometric(tmp_path / "made.ies")
    assert made.lumens == pytest.approx(400 * math.pi, rel=1e-12) and made.input_watts == 7.0
    const = [np.full(len(g), 100.0)]
    lm = 400 * math.pi
    for name, kw, factor in [("mult", {"multiplier": 2.0, "ballast": 0.9}, 1.8),
                             ("v1995", {"version": "IESNA:LM-63-1995", "ballast": 0.9, "future": 0.8}, 0.72),
                             ("v2019", {"version": "IES:LM-63-2019", "future": 1.10000}, 1.0),
                             ("v1991", {"version": "IESNA91"}, 1.0), ("v1986", {"version": ""}, 1.0)]:
        p = read_photometric(ies(tmp_path / f"{name}.ies", g, [0.0], const, **kw))
        assert p.lumens == pytest.approx(lm * factor, rel=1e-12), name
    assert "LM-63-1986" in read_photometric(tmp_path / "v1986.ies").label
    ies(tmp_path / "tilt.ies", g, [0.0], const, tilt=([0.0, 90.0], [1.0, 0.5]))
    down, tilted = _pair(tmp_path, "tilt", {"file": "tilt.ies", "position": [2, 2, 2], "multiplier": 0.5},
                         {"file": "tilt.ies", "position": [2, 2, 2], "aim": [math.sqrt(3), -1, 0]})
    assert down.lumens == pytest.approx(0.5 * lm, rel=1e-12)
    assert tilted.lumens == pytest.approx((1 - 0.5 * 60 / 90) * lm, rel=1e-12)
    assert tilted.power() == pytest.approx(np.full(3, tilted.lumens / 179.0), rel=1e-15)


def test_rays_carry_the_distribution_and_exactly_its_power():
    """Each half of a batch carries exactly half the power; the rays' power by direction is the
    distribution's (the share above 60 degrees from nadir against its closed form)."""
    g = np.arange(0.0, 180.1, 2.0)
    dist = Distribution.expand([0.0], g, [np.cos(np.radians(g)) ** 2], "axial")  # I = cos^2, up and down
    from dcrad.transport.luminaires import Photometric

    ph = Photometric("x.ies", "test", dist, None, None, (0, 0, 0), "point")
    lum = Luminaire(np.zeros(3), photometric=ph, aim=np.array([0.0, -1, 0]), c0=np.array([1.0, 0, 0]))
    batch = lum.rays(200_001, np.random.default_rng(3))
    p = lum.power()
    assert batch.power[batch.half].sum(axis=0) == pytest.approx(p / 2, rel=1e-12)
    assert batch.power[~batch.half].sum(axis=0) == pytest.approx(p / 2, rel=1e-12)
    # the rays' share between 60 and 120 degrees from nadir is the table's (its cells' exact flux),
    # and the table's is I = cos^2's, 1/8, to its interpolation at 2 degrees
    share = batch.power[np.abs(batch.dirs[:, 1]) < 0.5, 0].sum() / p[0]
    flux = dist.cells()[0]
    band = flux[:, (g[:-1] >= 60) & (g[1:] <= 120)].sum() / flux.sum()
    assert share == pytest.approx(band, rel=5e-4)  # its noise at 200k rays: 1e-4
    assert band == pytest.approx(1 / 8, rel=3e-3)
    assert lum.lumens == pytest.approx(4 * math.pi / 3, rel=1e-3)  # chords of cos^2 at 2 degrees: 2e-4 high
    # a batch of one ray (a solver's last batch can be) carries all the power, whichever half it joins
    from dcrad.transport.emitters import PointSource

    point = PointSource(np.zeros(3), np.ones(3))
    for seed in range(8):
        for source in (lum, point):
            one = source.rays(1, np.random.default_rng(seed))
            assert one.half is None and one.power.sum(axis=0) == pytest.approx(source.power(), rel=1e-12)


def test_the_command_reports_the_utilisation_factor_against_the_form_factor(tmp_path):
    """`dcrad solve --luminaires` end to end in a black room: the cosine downlight's utilisation
    factor on the work-plane grid is the form factor from a point facing the grid's rectangle (the
    direct light is all there is), and the command prints the table."""
    path = box(tmp_path)
    cosine_downlight(tmp_path)
    schedule(tmp_path / "lights.json", [{"file": "downlight.ies", "position": [2.0, 3.0, 2.0]}])
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "dcrad.cli", "solve", str(path), "--luminaires",
                           str(tmp_path / "lights.json"), "--workplane", "0.8", "--accuracy", "0.05",
                           "--patch-size", "0.5", "--out", str(out), "--width", "32", "--height", "24"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert "1 luminaire(s)" in proc.stdout and "downlight.ies" in proc.stdout
    report = json.loads((out / "report.json").read_text())
    assert any(c["code"] == "workers" and "this process" in c["text"] for c in report["choices"])
    pts = np.load(out / "radiosity.npz")["workplane_points"]
    s = report["photometry"]["workplane"]["spacing_m"]
    lo, hi = pts[:, [0, 2]].min(axis=0) - s / 2 - 2.0, pts[:, [0, 2]].max(axis=0) + s / 2 - 2.0
    h = 3.0 - 0.8

    def corner(a, b):  # the form factor times pi of a rectangle a x b from above its corner, times 2 / pi
        A, B = abs(a) / h, abs(b) / h
        return (A / math.hypot(1, A) * math.atan(B / math.hypot(1, A)) + B / math.hypot(1, B)
                * math.atan(A / math.hypot(1, B))) / (2 * math.pi)

    form_factor = sum(corner(a, b) for a in (lo[0], hi[0]) for b in (lo[1], hi[1]))
    lum = report["luminaires"]
    assert len(pts) == report["photometry"]["workplane"]["n_points"] and lum["workplane_area_m2"] == pytest.approx(
        (hi - lo).prod(), rel=1e-9)
    assert lum["utilisation_factor"] == pytest.approx(form_factor, rel=2e-3)
    assert lum["types"][0]["workplane_direct_share"] == pytest.approx(lum["utilisation_factor"], rel=1e-9)


def _bad_cases(tmp_path):
    g = np.arange(0.0, 90.1, 10.0)
    good = [np.cos(np.radians(g)) * 100]
    ies(tmp_path / "good.ies", g, [0.0], good)
    ies(tmp_path / "neg.ies", g, [0.0], [good[0] - 50])
    ies(tmp_path / "typea.ies", g, [0.0], good, ptype=3)
    ies(tmp_path / "tiltfile.ies", g, [0.0], good, tilt="lamp.tlt")
    text = ies(tmp_path / "nan.ies", g, [0.0], good).read_text().replace(repr(float(good[0][3])), "nan")
    (tmp_path / "nan.ies").write_text(text)
    (tmp_path / "trunc.ies").write_text((tmp_path / "good.ies").read_text()[:-40])
    (tmp_path / "junk.ies").write_text("hello\nworld\n")
    (tmp_path / "lamp.txt").write_text("x")
    full = ldt(tmp_path / "ok.ldt", 1, np.arange(0.0, 359.0, 30.0), g, good).read_text()
    (tmp_path / "trunc.ldt").write_text(full[: len(full) - 30])
    ldt(tmp_path / "sets.ldt", 1, np.arange(0.0, 359.0, 30.0), g, good, sets=2)
    inside = [2, 2, 2]
    return [  # (schedule text or entries, what the message says)
        ({"file": "nope.ies", "position": inside}, r"nope\.ies: no such photometric file"),
        ({"file": "junk.ies", "position": inside}, r"junk\.ies: not an IES LM-63 file"),
        ({"file": "trunc.ies", "position": inside}, r"trunc\.ies: malformed or truncated"),
        ({"file": "neg.ies", "position": inside}, r"neg\.ies: negative candela"),
        ({"file": "nan.ies", "position": inside}, r"nan\.ies: non-finite candela"),
        ({"file": "typea.ies", "position": inside}, r"typea\.ies: type A photometry is not supported"),
        ({"file": "tiltfile.ies", "position": inside}, r"tiltfile\.ies: TILT=lamp\.tlt .*not supported"),
        ({"file": "trunc.ldt", "position": inside}, r"trunc\.ldt: .*truncated"),
        ({"file": "sets.ldt", "position": inside}, r"sets\.ldt: 2 lamp sets"),
        ({"file": "lamp.txt", "position": inside}, r"lamp\.txt: not a photometric file"),
        ({"file": "good.ies", "position": inside, "colour": "red"}, r"unknown key\(s\) 'colour'"),
        ({"position": inside}, r"needs \"file\""),
        ({"file": "good.ies"}, r"needs \"position\""),
        ({"file": "good.ies", "position": [1, 2]}, r"position must be \[x, y, z\]"),
        ({"file": "good.ies", "position": ["a", 1, 2]}, r"position must be \[x, y, z\]"),
        ({"file": "good.ies", "position": inside, "aim": [0, 0, 0]}, r"aim \[0, 0, 0\] has no direction"),
        ({"file": "good.ies", "position": inside, "multiplier": 0}, r"multiplier 0 must be > 0"),
        ({"file": "good.ies", "position": inside, "multiplier": -2}, r"multiplier -2 must be > 0"),
        ({"file": "good.ies", "position": inside, "rotation": "x"}, r"rotation must be a finite number"),
        ({"file": "good.ies", "position": [50, 1, 1], "name": "far"}, r"luminaire 1 \(far\): position .* outside"),
        ([], r"holds no luminaires"),
        ("{not json", r"not valid JSON"),
        ([1, 2], r"a JSON object or a list of objects"),
    ]


def test_bad_input_is_one_line_naming_the_file_and_the_problem(tmp_path):
    scene = dcrad.load(box(tmp_path / "room"))
    for i, (entries, pattern) in enumerate(_bad_cases(tmp_path)):
        path = tmp_path / f"bad{i}.json"
        path.write_text(entries if isinstance(entries, str) else json.dumps(entries))
        with pytest.raises(ConfigError, match=pattern) as info:
            load_schedule(path, scene)
        message = str(info.value)
        assert "\n" not in message and f"bad{i}.json" in message, message
    with pytest.raises(ConfigError, match=r"missing\.json: no such luminaire schedule"):
        load_schedule(tmp_path / "missing.json", scene)


def test_the_command_refuses_bad_luminaires_in_one_line_and_exit_2(tmp_path):
    """A bad schedule: exit 2 and one line naming the schedule, the luminaire and the file."""
    path = box(tmp_path / "room")
    g = np.arange(0.0, 90.1, 10.0)
    ies(tmp_path / "neg.ies", g, [0.0], [np.cos(np.radians(g)) * 100 - 50])
    bad = schedule(tmp_path / "bad.json", {"file": "neg.ies", "position": [2, 2, 2]})
    proc = subprocess.run([sys.executable, "-m", "dcrad.cli", "solve", str(path), "--luminaires", str(bad),
                           "--workers", "0", "--out", str(tmp_path / "o1")], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "bad.json: luminaire 1: " in proc.stderr and "neg.ies: negative candela" in proc.stderr
    assert not (tmp_path / "o1").exists()


def test_a_divided_run_lights_every_subscene_from_the_luminaires_it_holds(tmp_path):
    """CIE 171:2006 case 5.8 divided: an isotropic 1 W source at the centre of a closed 4 m cube of
    rho 0.5 cut into four subscenes (the source in one of them; its light crosses the boundaries):
    every watt is booked (the ledger at every barrier), and the mean reflected exitance is the
    integrating sphere's rho Phi / (S (1 - rho)) x S within the run's estimate, as undivided."""
    from dcrad.config import DivideConfig
    from dcrad.division.divide import solve_divided
    from dcrad.pipeline import prepare

    rho = 0.5
    path = box(tmp_path, (4.0, 4.0, 4.0), rho=rho)
    g = np.arange(0.0, 180.1, 5.0)
    ies(tmp_path / "iso.ies", g, [0.0], [np.full(len(g), 1.0 / (4 * math.pi) * 179.0)])
    lights = schedule(tmp_path / "lights.json", {"file": "iso.ies", "position": [2.1, 2.05, 1.9]})
    _, p, _ = prepare(path, 0.5, sources=lambda sc: load_schedule(lights, sc))
    power = float(p.sources[0].power()[0])
    assert power == pytest.approx(1.0, rel=1e-3)
    run, subs, *_ = solve_divided(p, dcrad.SolverConfig(accuracy=0.02, seed=2), DivideConfig(subscenes=4))
    assert len(subs) == 4 and sum(len(s.patches.sources) for s in subs) == 1
    assert max(run.barrier_closures) < 1e-10 and run.stopped_by in ("accuracy", "noise_floor")
    reflected = float((p.area[:, None] * (p.radiosity - p.emission)).sum()) / 3
    expected = rho * power / (1 - rho)
    assert reflected == pytest.approx(expected, rel=max(3 * run.estimate.rms_refl, 0.01))


def test_a_divided_luminaire_job_on_workers_is_the_in_process_one(tmp_path):
    """`dcrad submit --luminaires --subscenes 2`: each worker's subscene gets the luminaires it holds
    (source_wire.py) and the job's B is the in-process divided run's to the bit."""
    from coordinator import client
    from coordinator.embedded import LocalCluster
    from dcrad.config import DivideConfig
    from dcrad.division.divide import solve_divided
    from dcrad.pipeline import prepare

    path = box(tmp_path / "room", rho=0.5)
    cosine_downlight(tmp_path)
    lights = schedule(tmp_path / "lights.json", [{"file": "downlight.ies", "position": [1.0, 2.9, 2.0]},
                                                 {"file": "downlight.ies", "position": [3.0, 2.9, 2.0]}])
    _, p, _ = prepare(path, 0.4, sources=lambda sc: load_schedule(lights, sc))
    run, subs, *_ = solve_divided(p, dcrad.SolverConfig(tol=0.01, seed=3), DivideConfig(subscenes=2))
    assert [len(s.patches.sources) for s in subs] == [1, 1]
    p.pool()
    with LocalCluster(workers=2, data=tmp_path / "cluster") as cluster:
        job = client.submit(cluster.address, path, {"tol": 0.01, "seed": 3, "patch_size": 0.4}, {"subscenes": 2},
                            luminaires=lights)
        last = client.watch(cluster.address, job.job_id)
        assert last is not None and last.job.state == "done", last.job.error if last else None
        client.fetch(cluster.address, job.job_id, tmp_path / "out")
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["divided"]["subscenes"] == 2 and report["ledger"]["closure"] < 1e-10
    assert np.array_equal(np.load(tmp_path / "out" / "radiosity.npz")["patch_B"], p.radiosity)


def test_light_sources_travel_to_workers_exactly(tmp_path):
    """Each kind of source that runs on workers (source_wire.py: an isotropic point, a luminaire of a
    file with a tilt table, a glTF point and spot light) comes back from the patch table's arrays
    the same source to the bit: its power, its rays from one random stream, its exact irradiance.
    A point source whose distribution is a Python function cannot travel and says so by name."""
    from dcrad.io.scene import load_scene
    from dcrad.transport.emitters import PointSource
    from dcrad.transport.punctual import PunctualLight, SpotLight
    from dcrad.transport.source_wire import sources_from_table, sources_table

    path = box(tmp_path, rho=0.5)
    tilt = ([0.0, 45.0, 90.0], [1.0, 0.9, 0.7])
    g = np.arange(0.0, 180.1, 15.0)
    ies(tmp_path / "lamp.ies", g, [0.0, 90.0], np.vstack([100 + g, 50 + 2 * g]), tilt=tilt, units=1)
    schedule(tmp_path / "lights.json", [{"file": "lamp.ies", "position": [2.0, 2.5, 2.0], "aim": [0.3, -1.0, 0.2],
                                         "rotation": 30.0, "multiplier": 0.8, "name": "tilted"}])
    scene = load_scene(path)
    sources = (PointSource([1.0, 2.0, 1.0], [0.5, 0.4, 0.3], name="iso"),
               *load_schedule(tmp_path / "lights.json", scene),
               PunctualLight(position=np.array([3.0, 2.0, 1.0]), candela=120.0, color=np.array([1.0, 0.8, 0.6])),
               SpotLight(position=np.array([1.0, 2.8, 3.0]), candela=300.0, axis=np.array([0.2, -1.0, 0.1]),
                         inner=0.2, outer=0.6, name="spot"))
    table = sources_table(sources)
    back = sources_from_table({k: np.frombuffer(v.tobytes(), v.dtype) for k, v in table.items()})
    tracer = Tracer(scene.vertices[scene.faces])
    pts = np.random.default_rng(1).uniform([0.1, 0.1, 0.1], [3.9, 0.1, 3.9], (500, 3))
    normals = np.tile([0.0, 1.0, 0.0], (500, 1))
    assert [type(s) for s in back] == [type(s) for s in sources]
    for a, b in zip(sources, back):
        assert a.name == b.name and np.array_equal(a.power(), b.power())
        ra, rb = a.rays(999, np.random.default_rng(5)), b.rays(999, np.random.default_rng(5))
        assert np.array_equal(ra.dirs, rb.dirs) and np.array_equal(ra.power, rb.power)
        assert np.array_equal(a.irradiance(pts, normals, tracer, 1e-6), b.irradiance(pts, normals, tracer, 1e-6))
    with pytest.raises(ConfigError, match="'?function'?-lit: a point source whose intensity is a Python function"):
        sources_table([PointSource([1.0, 1.0, 1.0], lambda d: np.ones((len(d), 3)), name="'function'-lit")])


def test_a_luminaire_job_runs_shared_on_workers_as_in_process(tmp_path):
    """`dcrad submit --luminaires` as the client uploads it (the schedule and its photometric file
    under luminaires/): the job runs shared on two workers and gives the in-process shared run's B
    to the bit, with the luminaires' report and closed books."""
    from coordinator import client
    from coordinator.embedded import LocalCluster
    from dcrad.config import SolverConfig
    from dcrad.pipeline import prepare
    from dcrad.solving.share import LocalShares, run_shared

    path = box(tmp_path / "room", rho=0.5)
    sub = tmp_path / "photometry"
    sub.mkdir()
    cosine_downlight(sub)
    lights = schedule(tmp_path / "lights.json", [{"file": "photometry/downlight.ies", "position": [2.0, 2.9, 2.0]},
                                                 {"file": "photometry/downlight.ies", "position": [1.0, 2.9, 3.0],
                                                  "multiplier": 0.5}])
    settings = {"accuracy": 0.04, "seed": 3, "patch_size": 0.4}
    _, p, _ = prepare(path, 0.4, sources=lambda sc: load_schedule(lights, sc))
    cfg = SolverConfig(accuracy=0.04, seed=3)
    ref = run_shared(p, cfg, 2, LocalShares(p, cfg, Tracer.mesh(p)))
    p.pool()
    with LocalCluster(workers=2, data=tmp_path / "cluster") as cluster:
        job = client.submit(cluster.address, path, settings, {}, luminaires=lights)
        last = client.watch(cluster.address, job.job_id)
        assert last is not None and last.job.state == "done", last.job.error if last else None
        client.fetch(cluster.address, job.job_id, tmp_path / "out")
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    b = np.load(tmp_path / "out" / "radiosity.npz")["patch_B"]
    assert np.array_equal(b, p.radiosity)
    assert report["stats"]["rays"] == ref.stats.rays and report["ledger"]["closure"] < 1e-9
    assert report["shared"]["workers"] == 2 and report["luminaires"]["types"][0]["count"] == 2
    # pi I0 lm each (a cosine downlight of I0 = 1000 cd, its table interpolated), the second at half
    assert report["luminaires"]["lumens"] == pytest.approx(1.5 * math.pi * 1000.0, rel=1e-4)


def test_a_gltf_ies_light_is_the_scheduled_luminaire_of_its_profile(tmp_path):
    """glTF EXT_lights_ies: a profile at a node rotated so that its local -Z points down and its X
    along the room's +Z lights the floor as the same file placed by a schedule (aim down, C0 along
    +Z: rotation -90 degrees from the default +X) does, point for point; the profile given as a
    data URI is the file's; ``color`` tints it per channel (its lumens scaled by Y(color)),
    ``multiplier`` scales it; a node's profile with neither uri nor bufferView is one error naming
    it; and the upload takes the profile file with the scene."""
    from test_punctual import box_gltf

    from coordinator.client import scene_paths
    from dcrad.errors import SceneFormatError

    g = np.arange(0.0, 180.1, 5.0)
    c = np.arange(0.0, 360.1, 30.0)
    ies(tmp_path / "asym.ies", g, c, table(lambda gg, cc: np.maximum(np.cos(np.radians(gg)), 0) *
                                           (300 + 200 * np.cos(np.radians(cc))), c, g))
    # -90 deg about X takes local -Z to -Y (down); then -90 deg about Y takes local X to +Z
    qx = [math.sin(-math.pi / 4), 0.0, 0.0, math.cos(-math.pi / 4)]
    qy = [0.0, math.sin(-math.pi / 4), 0.0, math.cos(-math.pi / 4)]
    lamp = {"name": "lamp", "translation": [1.5, 3.0, 2.5], "rotation": qy,
            "children": [], "extensions": {}}
    inner = {"name": "lamp_profile", "rotation": qx, "extensions": {"EXT_lights_ies": {"light": 0}}}

    def gltf(name, profile, more=None):
        nodes = [lamp | {"children": [7]}, inner | {"extensions": {"EXT_lights_ies": {"light": 0, **(more or {})}}}]
        ext = {"extensionsUsed": ["EXT_lights_ies"], "extensions": {"EXT_lights_ies": {"lights": [profile]}}}
        return box_gltf(tmp_path / name, light_nodes=nodes, rho=0.0, extra=ext)

    by_file = gltf("file.gltf", {"uri": "asym.ies", "name": "asym"})
    raw = (tmp_path / "asym.ies").read_bytes()
    by_uri = gltf("uri.gltf", {"uri": "data:application/x-ies-lm-63;base64," + base64.b64encode(raw).decode()})
    tinted = gltf("tint.gltf", {"uri": "asym.ies"}, {"color": [1.0, 0.5, 0.0], "multiplier": 2.0})
    schedule(tmp_path / "lights.json", {"file": "asym.ies", "position": [1.5, 3.0, 2.5], "rotation": -90.0})
    scene = dcrad.load(by_file)
    (lum,) = scene.sources
    assert isinstance(lum, Luminaire) and lum.name == "glTF IES light 'asym'"
    (ref,) = load_schedule(tmp_path / "lights.json", scene)
    np.testing.assert_allclose(lum.aim, [0.0, -1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(lum.c0, ref.c0, atol=1e-12)
    tracer = Tracer(scene.vertices[scene.faces])
    pts = np.random.default_rng(3).uniform([0.1, 1e-4, 0.1], [3.9, 1e-4, 3.9], (400, 3))
    up = np.tile([0.0, 1.0, 0.0], (400, 1))
    want = ref.irradiance(pts, up, tracer, 1e-6)
    np.testing.assert_allclose(lum.irradiance(pts, up, tracer, 1e-6), want, rtol=1e-9)
    (same,) = dcrad.load(by_uri).sources
    np.testing.assert_array_equal(same.irradiance(pts, up, tracer, 1e-6), lum.irradiance(pts, up, tracer, 1e-6))
    (tint,) = dcrad.load(tinted).sources
    np.testing.assert_allclose(tint.irradiance(pts, up, tracer, 1e-6), want * [2.0, 1.0, 0.0], rtol=1e-9)
    assert tint.lumens == pytest.approx(2.0 * lum.lumens * (0.2126 + 0.5 * 0.7152), rel=1e-12)
    assert "asym.ies" in scene_paths(by_file)
    with pytest.raises(SceneFormatError, match=r"bad\.gltf: EXT_lights_ies light 0 \('lamp_profile', node "
                                               r"'lamp_profile'\): its profile has neither a 'uri' nor a 'bufferView'"):
        dcrad.load(gltf("bad.gltf", {"name": ""}))


def test_a_luminous_opening_lights_its_near_field_as_the_closed_form(tmp_path):
    """A Lambertian luminaire (I = I0 cos gamma) whose file gives a flat opening is a uniform-luminance
    opening, L = I0 / A: under a 0.6 m square the irradiance on a parallel plane is pi L times the
    point-to-parallel-rectangle form factor, and on the axis of a 0.5 m disc I0 / (h^2 + a^2); both
    within 0.5% from one opening size away to far beyond, where the photometric centre alone (the
    point the file would be without its opening) is 33% high at one size.  Its rays start all over
    the opening and still carry exactly its power."""
    from dcrad.io.scene import load_scene

    i0, s = 1000.0, 0.6
    cosine = [i0 * np.cos(np.radians(GAMMA_HALF))]
    ies(tmp_path / "square.ies", GAMMA_HALF, [0.0], cosine, opening=(s, s, 0.0))
    ies(tmp_path / "disc.ies", GAMMA_HALF, [0.0], cosine, opening=(-0.5, -0.5, 0.0))
    ies(tmp_path / "point.ies", GAMMA_HALF, [0.0], cosine)
    path = box(tmp_path, size=(40.0, 30.0, 40.0))
    scene = load_scene(path)
    tracer = Tracer(scene.vertices[scene.faces])
    top = 20.0

    def lum(file):
        schedule(tmp_path / f"{file}.json", {"file": f"{file}.ies", "position": [20.0, top, 20.0]})
        (one,) = load_schedule(tmp_path / f"{file}.json", scene)
        return one

    square, disc, point = lum("square"), lum("disc"), lum("point")
    assert square.opening == ("rectangle", s, s) and disc.opening == ("disc", 0.5, 0.5) and point.opening[0] == "point"

    def corner(a, b, h):  # the form factor from a point to an a x b rectangle above it, one corner over it
        A, B = a / h, b / h
        return (A / math.hypot(1, A) * math.atan(B / math.hypot(1, A))
                + B / math.hypot(1, B) * math.atan(A / math.hypot(1, B))) / (2 * math.pi)

    def lux(source, pts):
        return EFFICACY * source.irradiance(pts, np.tile([0.0, 1.0, 0.0], (len(pts), 1)), tracer, 1e-6)[:, 0]

    def under_square(x, z, h):
        return math.pi * i0 / s ** 2 * sum(corner(a, b, h) for a in (s / 2 - x, s / 2 + x)
                                           for b in (s / 2 - z, s / 2 + z))

    for h in (0.6, 1.2, 3.0, 9.0, 15.0):
        pts = np.array([[20.0, top - h, 20.0], [20.1, top - h, 19.95]])
        np.testing.assert_allclose(lux(square, pts), [under_square(0.0, 0.0, h), under_square(0.1, -0.05, h)],
                                   rtol=5e-3)
        assert lux(disc, pts[:1])[0] == pytest.approx(i0 / (h * h + 0.25 ** 2), rel=5e-3)
    at_one_size = np.array([[20.0, top - s, 20.0]])
    assert lux(point, at_one_size)[0] > 1.3 * under_square(0.0, 0.0, s)
    rays = square.rays(4000, np.random.default_rng(2))
    off = rays.origins - square.position
    assert np.abs(off[:, 1]).max() < 1e-12 and np.abs(off[:, [0, 2]]).max() <= s / 2 + 1e-12
    assert np.abs(off[:, [0, 2]]).max() > 0.4 * s
    np.testing.assert_allclose(rays.power.sum(axis=0), square.power(), rtol=1e-12)


def _radiance_peer():
    """(bin, lib) of Radiance's programs as pyradiance ships them (a test dependency)."""
    import importlib.util

    spec = importlib.util.find_spec("pyradiance")
    assert spec is not None and spec.origin is not None, "pyradiance (the Radiance peer) is a test dependency"
    root = Path(spec.origin).parent
    return root / "bin", root / "lib"


@pytest.mark.parametrize("kind", ["C", "B"])
def test_an_asymmetric_file_lights_a_plane_as_radiance_does(tmp_path, kind):
    """The peer: Radiance's ies2rad + rtrace (6.0a, as pyradiance ships it) read an asymmetric type C
    file, and a type B one (floodlights: the horizontal polar axis, H and V both -90 to 90), and
    give the direct illuminance on a plane 2 m below, facing the luminaire, at 49 points out to
    56 degrees; dcrad's luminaire in the same frame (nadir -Z, C0 +X) gives the same within 0.1%.
    The tables vary with both angles at different rates, so a mirrored or swapped angle would be off
    by tens of percent."""
    import os
    import subprocess

    from dcrad.outputs.photometry import EFFICACY

    bin_dir, lib = _radiance_peer()
    env = dict(os.environ, RAYPATH=f".{os.pathsep}{lib}")
    if kind == "C":
        g, c = np.arange(0.0, 180.1, 5.0), np.arange(0.0, 360.1, 15.0)
        cd = table(lambda gg, cc: np.maximum(np.cos(np.radians(gg)), 0)
                   * (300 + 200 * np.cos(np.radians(cc)) + 100 * np.sin(np.radians(cc))), c, g)
        path = ies(tmp_path / "lum.ies", g, c, cd)
    else:
        v, h = np.arange(-90.0, 90.1, 10.0), np.arange(-90.0, 90.1, 15.0)
        cd = np.array([[100 + (vv + 90) + 0.5 * (hh + 90) for vv in v] for hh in h])
        path = ies(tmp_path / "lum.ies", v, h, cd, ptype=2)
    subprocess.run([str(bin_dir / "ies2rad"), "-dm", "-o", "lum", "lum.ies"], cwd=tmp_path, env=env, check=True,
                   capture_output=True)
    with open(tmp_path / "lum.oct", "wb") as octree:
        subprocess.run([str(bin_dir / "oconv"), "lum.rad"], cwd=tmp_path, env=env, check=True, stdout=octree)
    xs = np.array([-3.0, -1.5, -0.5, 0.0, 0.7, 2.0, 3.0])
    points = np.array([[x, y, -2.0] for x in xs for y in xs])
    peer = subprocess.run([str(bin_dir / "rtrace"), "-h", "-I", "-ab", "0", "lum.oct"], cwd=tmp_path, env=env,
                          check=True, capture_output=True, text=True,
                          input="".join(f"{x} {y} {z} 0 0 1\n" for x, y, z in points)).stdout
    radiance = 179.0 * np.array([float(line.split()[0]) for line in peer.strip().splitlines()])
    ph = read_photometric(path)
    assert ("type B" in ph.label) == (kind == "B")
    lum = Luminaire(position=np.zeros(3), photometric=ph, aim=np.array([0.0, 0.0, -1.0]),
                    c0=np.array([1.0, 0.0, 0.0]), name="peer")
    far = Tracer(np.array([[[100.0, 100.0, 100.0], [101.0, 100.0, 100.0], [100.0, 101.0, 100.0]]]))
    ours = EFFICACY * lum.irradiance(points, np.tile([0.0, 0.0, 1.0], (len(points), 1)), far, 1e-6)[:, 0]
    assert len(radiance) == len(points) and radiance.min() > 0
    np.testing.assert_allclose(ours, radiance, rtol=1e-3)


def test_a_divided_run_keeps_its_ray_budget_with_luminaires(tmp_path):
    """Under --max-rays a subscene shoots its luminaires at its first iterate with at most half of
    its barrier's share of the budget, coarser if need be but all their power: the run keeps the
    budget within a batch a subscene, and its books close.  (At the run's own density the 2x3 office's
    12 luminaires took 2.5M rays of a 1M budget in one go.)"""
    from dcrad.config import DivideConfig
    from dcrad.division.divide import solve_divided
    from dcrad.pipeline import prepare

    path = box(tmp_path / "room", rho=0.5)
    cosine_downlight(tmp_path)
    lights = schedule(tmp_path / "lights.json", [{"file": "downlight.ies", "position": [1.0, 2.9, 2.0]},
                                                 {"file": "downlight.ies", "position": [3.0, 2.9, 2.0]}])
    _, p, _ = prepare(path, 0.25, sources=lambda sc: load_schedule(lights, sc))
    cfg = dcrad.SolverConfig(accuracy=0.005, seed=3, max_rays=200_000, batch_rays=8192, max_rays_per_shot=8192)
    run, subs, *_ = solve_divided(p, cfg, DivideConfig(subscenes=2))
    assert run.stopped_by == "ray_budget" and all(not s.direct.sources_left for s in subs)
    assert run.snapshots[-1].rays <= 200_000 + 2 * 8192
    assert max(run.barrier_closures) < 1e-10
