"""Daylight (transport/sky.py) against closed forms and Radiance.

The CIE 171:2006 daylight cases 5.9 to 5.12 built from their integrals (its tables carry errata at
some edge points): a black 4 x 4 x 3 m room with a square roof opening under the uniform sky reads,
at floor and wall points, 100 x the configuration factor of the opening (Lambert's contour formula,
checked against a direct numerical integration); under the CIE overcast sky the integral of its
luminance over the opening; a facade opening with an external ground of reflectance 0.3 the
integral of sky and ground luminance through it, points that see only the ground included; a
glazed opening the same integral times tau(theta) point by point.  The sky's normalisation and
zenith luminance against the closed forms and Radiance's gensky; the sun's position against
gensky's; the sun's patch on the floor against E_n sin(altitude).  A run's daylight factor per
patch against the closed form, and bad input refused in one line.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from dcrad.config import SolverConfig
from dcrad.errors import ConfigError
from dcrad.outputs.photometry import EFFICACY, direct_irradiance
from dcrad.pipeline import prepare
from dcrad.transport.lights import polygon_form_factor
from dcrad.transport.optics import Glazing, pane_transmittance
from dcrad.transport.rays import Tracer
from dcrad.transport.sky import (
    ISO_SKIES,
    DaylightSpec,
    Sky,
    SkyModel,
    Sun,
    daylight_sources,
    frame,
    grid_directions,
    sun_direction,
    sun_position,
)
from scenes.objwriter import ObjWriter

E_HZ = 10_000.0  # lux
SIZE, HEIGHT = 4.0, 3.0
UP = np.array([0.0, 1.0, 0.0])


def roof_room(tmp_path, hole: float, rho: float = 0.0, stem: str = "roof"):
    """A 4 x 4 x 3 m room (Y up, surfaces facing in) whose roof has a centred ``hole`` x ``hole`` m
    opening (the whole roof open at 4): (path, the opening's corners)."""
    w = ObjWriter()
    w.material("wall", rho)
    w.begin("room", "wall")
    w.add_box((0, 0, 0), (SIZE, HEIGHT, SIZE), outward=False, skip_faces=("+y",))
    a, b = (SIZE - hole) / 2, (SIZE + hole) / 2
    if a > 0:
        w.begin("roof", "wall")
        for lo, hi in (((0, 0), (SIZE, a)), ((0, b), (SIZE, SIZE)), ((0, a), (a, b)), ((b, a), (SIZE, b))):
            w.add_rect(1, HEIGHT, lo, hi, -1)
    opening = np.array([[a, HEIGHT, a], [b, HEIGHT, a], [b, HEIGHT, b], [a, HEIGHT, b]], float)
    return w.write(tmp_path, stem), opening


def facade_room(tmp_path, rho: float = 0.0):
    """The room with its roof closed and a 2 x 1 m opening in its -X wall, sill at 1 m, z 1..3:
    (path, the opening's corners)."""
    w = ObjWriter()
    w.material("wall", rho)
    w.begin("room", "wall")
    w.add_box((0, 0, 0), (SIZE, HEIGHT, SIZE), outward=False, skip_faces=("-x",))
    w.begin("facade", "wall")
    pieces = (((0, 0), (1.0, SIZE)), ((2.0, 0), (HEIGHT, SIZE)), ((1.0, 0), (2.0, 1.0)), ((1.0, 3.0), (2.0, SIZE)))
    for lo, hi in pieces:
        w.add_rect(0, 0.0, lo, hi, 1)
    opening = np.array([[0, 1, 1], [0, 2, 1], [0, 2, 3], [0, 1, 3]], float)
    return w.write(tmp_path, "facade"), opening


def opening_integral(points, normals, opening, radiance, tau=None, n: int = 1000):
    """E = integral over the planar ``opening`` (4 corners, a parallelogram) of L(s) cos_1 cos_2 / r^2,
    s the unit direction from the point to the opening (midpoint rule, n x n): W/m^2 per point."""
    o, e1, e2 = opening[0], opening[1] - opening[0], opening[3] - opening[0]
    nrm = np.cross(e1, e2)
    area = np.linalg.norm(nrm)
    nrm = nrm / area
    g = (np.arange(n) + 0.5) / n
    uu, vv = np.meshgrid(g, g)
    q = o + uu.reshape(-1, 1) * e1 + vv.reshape(-1, 1) * e2
    out = []
    for x, nx in zip(points, normals):
        d = q - x
        r = np.linalg.norm(d, axis=1)
        s = d / r[:, None]
        c1 = np.maximum(s @ nx, 0.0)
        c2 = np.abs(s @ nrm)
        f = radiance(s) * c1 * c2 / r ** 2
        if tau is not None:
            f = f * tau(c2)
        out.append(f.sum() * area / n ** 2)
    return np.array(out)


def black_points():
    """Floor points (facing up) and wall points (on the -X wall, facing +X), centre to corners."""
    floor = np.array([[2, 0, 2], [0.5, 0, 0.5], [1, 0, 3], [3.9, 0, 2], [0.1, 0, 0.1]], float)
    wall = np.array([[0, 1.5, 2], [0, 2.9, 2], [0, 0.5, 0.5]], float)
    normals = np.vstack([np.tile(UP, (len(floor), 1)), np.tile([1.0, 0, 0], (len(wall), 1))])
    return np.vstack([floor, wall]), normals


def sky_light(patches, model: SkyModel) -> Sky:
    lo, hi = patches.bounds
    return Sky(model, lo, hi)


# -- the sky itself ---------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["uniform", "cie-overcast", "clear", *(f"iso:{t}" for t in ISO_SKIES)])
def test_every_sky_puts_its_horizontal_illuminance_on_an_open_plane(name):
    """The integral of L cos over the upper hemisphere, by a midpoint rule in (theta, phi) finer than
    and independent of the sky's own table, is E_hz, for every sky (the sun at 40 degrees)."""
    up, east, north = frame(np.eye(3))
    sun = sun_direction(40.0, 135.0, up, east, north)
    model = SkyModel(name, E_HZ, sun if name not in ("uniform", "cie-overcast") else None)
    nt, nph = 1500, 3000
    th = (np.arange(nt) + 0.5) * (math.pi / 2 / nt)
    ph = (np.arange(nph) + 0.5) * (2 * math.pi / nph)
    tt, pp = np.meshgrid(th, ph, indexing="ij")
    s = np.stack([np.sin(tt) * np.cos(pp), np.cos(tt), np.sin(tt) * np.sin(pp)], -1).reshape(-1, 3)
    w = (np.cos(tt) * np.sin(tt)).ravel() * (math.pi / 2 / nt) * (2 * math.pi / nph)
    lux = float((model.radiance(s) * w).sum()) * EFFICACY
    assert lux == pytest.approx(E_HZ, rel=2e-4)


def test_the_overcast_sky_is_moon_and_spencer_s_and_radiance_s():
    """CIE overcast: Lz = 9 E_hz / (7 pi), L(theta) = Lz (1 + 2 cos theta) / 3, the ground
    rho_g E_hz / pi; Radiance's gensky -c -B gives the same zenith and ground radiance."""
    model = SkyModel("cie-overcast", E_HZ, ground=0.2)
    lz = 9 * E_HZ / (7 * math.pi)
    assert model.zenith() == pytest.approx(lz, rel=1e-4)
    s = np.array([[math.sin(0.7), math.cos(0.7), 0.0]])
    assert model.radiance(s)[0] * EFFICACY == pytest.approx(lz * (1 + 2 * math.cos(0.7)) / 3, rel=1e-4)
    assert model.ground_radiance() * EFFICACY == pytest.approx(0.2 * E_HZ / math.pi, rel=1e-12)
    gensky = _radiance("gensky")
    if gensky is None:
        pytest.skip("Radiance (pyradiance) is not installed")
    text = subprocess.run([gensky, "-ang", "45", "0", "-c", "-B", f"{E_HZ / EFFICACY:.6f}"], capture_output=True,
                          text=True, check=True, env=_radiance_env()).stdout
    args = text.split("skybright.cal")[1].split()
    zenith, ground = float(args[3]), float(args[4])  # "0 3 2 Lz Lg": W/sr/m^2
    assert zenith == pytest.approx(model.zenith() / EFFICACY, rel=1e-3)
    assert ground == pytest.approx(model.ground_radiance(), rel=1e-3)


def test_the_sun_s_position_is_radiance_s():
    """The sun at a site, date and time (astral: NOAA's equations) against gensky's (its own
    lower-precision formula) within half a degree; gensky's azimuth runs from south toward west."""
    gensky = _radiance("gensky")
    if gensky is None:
        pytest.skip("Radiance (pyradiance) is not installed")
    for lat, lon, when in ((51.5, 0.0, "2026-06-21T12:00"), (40.0, -74.0, "2026-12-21T15:30"),
                           (-33.9, 151.2, "2026-03-20T09:15")):
        t = dt.datetime.fromisoformat(when)
        zone = round(lon / 15.0)
        alt, az = sun_position(lat, lon, t.replace(tzinfo=dt.timezone(dt.timedelta(hours=zone))))
        # gensky: -a latitude, -o longitude and -m meridian both west positive, the time standard time
        text = subprocess.run([gensky, str(t.month), str(t.day), f"{t.hour + t.minute / 60:.4f}", "-a", str(lat),
                               "-o", str(-lon), "-m", str(-15 * zone)], capture_output=True, text=True,
                              check=True, env=_radiance_env()).stdout
        r_alt, r_az = (float(x) for x in text.split("Solar altitude and azimuth:")[1].split()[:2])
        assert alt == pytest.approx(r_alt, abs=0.5)
        assert ((az - 180.0 - r_az + 180.0) % 360.0) - 180.0 == pytest.approx(0.0, abs=0.5)


def test_north_and_east_follow_the_file_s_up_axis():
    """A Z-up file: north +Y, east +X (Radiance's frame); a Y-up file: north -Z.  The internal frame
    is Y-up, so the rotations of scene.UP_AXES take them there."""
    from dcrad.io.scene import UP_AXES

    for axis, north_in in (("z", [0, 1, 0]), ("y", [0, 0, -1])):
        r = np.array(UP_AXES[axis], np.float64)
        up, east, north = frame(r, axis)
        np.testing.assert_allclose(up, r @ np.array([0, 0, 1.0] if axis == "z" else [0, 1.0, 0]), atol=1e-12)
        np.testing.assert_allclose(east, r @ np.array([1.0, 0, 0]), atol=1e-12)
        np.testing.assert_allclose(north, r @ np.array(north_in, np.float64), atol=1e-12)


# -- the CIE 171:2006 daylight cases, from their integrals -------------------------------------------
@pytest.mark.parametrize("hole", [1.0, 4.0])
def test_a_roof_opening_under_the_uniform_sky_gives_100_x_its_configuration_factor(tmp_path, hole):
    """CIE 5.9 / 5.10 (uniform sky): a black room's floor and wall points read E = E_hz F, F the
    configuration factor of the opening (Lambert's contour formula), within 2% (this path: the work
    plane's and black surfaces' direct light, photometry.direct_irradiance)."""
    path, opening = roof_room(tmp_path, hole)
    _, patches, _ = prepare(path, 0.5, up="y")
    model = SkyModel("uniform", E_HZ)
    patches.sources = (sky_light(patches, model),)
    points, normals = black_points()
    tracer = Tracer.mesh(patches)
    got, _ = direct_irradiance(patches, tracer, points, normals)
    loops = np.repeat(opening[None], len(points), 0)  # the opening seen from below: facing down
    f = polygon_form_factor(points, normals, loops, np.tile(-UP, (len(points), 1)))
    truth = opening_integral(points, normals, opening, lambda s: np.ones(len(s)))
    np.testing.assert_allclose(f, truth / math.pi, rtol=1e-4)  # the contour formula, checked
    df = 100 * got[:, 0] * EFFICACY / E_HZ
    np.testing.assert_allclose(df, 100 * f, rtol=0.02)


def test_a_roof_opening_under_the_cie_overcast_sky_reads_the_integral_of_its_luminance(tmp_path):
    """CIE 5.11: the overcast sky's luminance integrated over the 1 x 1 m opening, within 2%."""
    path, opening = roof_room(tmp_path, 1.0)
    _, patches, _ = prepare(path, 0.5, up="y")
    model = SkyModel("cie-overcast", E_HZ)
    patches.sources = (sky_light(patches, model),)
    points, normals = black_points()
    got, _ = direct_irradiance(patches, Tracer.mesh(patches), points, normals)
    truth = opening_integral(points, normals, opening, model.radiance)
    np.testing.assert_allclose(got[:, 0], truth, rtol=0.02)


def test_a_facade_opening_lets_in_the_sky_and_the_ground(tmp_path):
    """CIE 5.12: a 2 x 1 m facade opening, the overcast sky and an external ground of rho 0.3:
    floor, wall and ceiling points against the integral of sky and ground luminance through the
    opening, within 2%; ceiling points see the ground alone (every line through the opening goes down)."""
    path, opening = facade_room(tmp_path)
    _, patches, _ = prepare(path, 0.5, up="y")
    model = SkyModel("cie-overcast", E_HZ, ground=0.3)
    patches.sources = (sky_light(patches, model),)
    points = np.array([[1.0, 0, 2], [2.5, 0, 2], [1.5, 0, 0.5], [2, 1.5, 0], [4, 1.5, 2], [1.0, 3, 2], [2.5, 3, 1]],
                      float)
    normals = np.array([UP, UP, UP, [0, 0, 1.0], [-1.0, 0, 0], -UP, -UP])
    got, _ = direct_irradiance(patches, Tracer.mesh(patches), points, normals)
    truth = opening_integral(points, normals, opening, model.radiance)
    ground = opening_integral(points, normals, opening, lambda s: np.where(s @ UP < 0, model.radiance(s), 0.0))
    assert (ground[-2:] == truth[-2:]).all() and truth[-1] > 0  # the ceiling's points see only the ground
    np.testing.assert_allclose(got[:, 0], truth, rtol=0.02)


def test_a_glazed_opening_passes_tau_theta_point_by_point(tmp_path):
    """The 1 x 1 m roof opening glazed (a pane of 6 mm clear float glass, tau_n 0.8788, index 1.52):
    each point reads the integral of L cos cos / r^2 tau(theta) over it, within 2%."""
    w = ObjWriter()
    w.material("wall", 0.0)
    w.material("glass", 0.0)
    path, opening = roof_room(tmp_path, 1.0, stem="glazedroof")
    # the pane: the opening's square itself, facing down
    w.begin("pane", "glass")
    w.add_rect(1, HEIGHT, (1.5, 1.5), (2.5, 2.5), -1)
    pane_path = w.write(tmp_path, "pane")
    merged = tmp_path / "merged.obj"
    body = path.read_text().replace("mtllib glazedroof.mtl", "mtllib merged.mtl")
    nv = sum(1 for line in body.splitlines() if line.startswith("v "))
    pane = [line for line in pane_path.read_text().splitlines() if not line.startswith("mtllib")]
    pane = [" ".join(["f", *(str(int(i) + nv) for i in line.split()[1:])]) if line.startswith("f ") else line
            for line in pane]
    merged.write_text(body + "\n" + "\n".join(pane) + "\n")
    (tmp_path / "merged.mtl").write_text((tmp_path / "glazedroof.mtl").read_text() + "\nnewmtl glass\nKd 0 0 0\n")
    _, patches, _ = prepare(merged, 0.5, up="y")
    is_pane = np.array([patches.names[o].startswith("pane") for o in patches.obj])
    n = len(patches)
    tau_n = 0.8788
    patches.glazing = Glazing(is_pane, np.where(is_pane[:, None], tau_n, 0.0) * np.ones((n, 3)), np.full(n, 1.52))
    model = SkyModel("uniform", E_HZ)
    patches.sources = (sky_light(patches, model),)
    points, normals = black_points()
    tracer = Tracer.mesh(patches)
    tracer.glazing = patches.glazing
    got, _ = direct_irradiance(patches, tracer, points, normals)

    def tau(cos):
        return pane_transmittance(cos, np.full((len(cos), 3), tau_n), np.full(len(cos), 1.52))[:, 0]

    truth = opening_integral(points, normals, opening, model.radiance, tau=tau)
    np.testing.assert_allclose(got[:, 0], truth, rtol=0.02)
    bare = opening_integral(points, normals, opening, model.radiance)
    assert (truth < 0.9 * bare).all()  # the pane's tau is what is being checked


def test_the_sun_through_a_roof_opening_lights_its_patch_on_the_floor(tmp_path):
    """The sun at 60 degrees through the 1 x 1 m opening: floor points in its patch read E_n sin 60
    exactly (a shadow ray each), points outside it 0; the books of the sun's power close."""
    path, _ = roof_room(tmp_path, 1.0)
    _, patches, _ = prepare(path, 0.5, up="y")
    up, east, north = frame(np.eye(3))
    s = sun_direction(60.0, 180.0, up, east, north)  # from the south: toward -north
    lo, hi = patches.bounds
    sun = Sun(s, 80_000.0, lo, hi)
    level = s - UP * (s @ UP)
    below = np.array([2.0, 0.0, 2.0])  # under the opening's centre
    patch_centre = below - HEIGHT / math.tan(math.radians(60)) * level / np.linalg.norm(level)
    inside = patch_centre + np.array([[0, 0, 0], [0.3, 0, 0.2], [-0.3, 0, -0.2]])
    outside = np.array([below + (below - patch_centre), [0.3, 0, 0.3]])  # the other side, a corner
    pts = np.vstack([inside, outside])
    got = sun.irradiance(pts, np.tile(UP, (len(pts), 1)), Tracer.mesh(patches), 1e-6)[:, 0] * EFFICACY
    np.testing.assert_allclose(got[:3], 80_000.0 * math.sin(math.radians(60)), rtol=1e-9)
    np.testing.assert_array_equal(got[3:], 0.0)
    batch = sun.rays(4096, np.random.default_rng(1))
    np.testing.assert_allclose(batch.power.sum(axis=0), sun.power(), rtol=1e-12)


def test_the_sun_books_what_lands_and_a_sunlit_room_is_not_left_dark(tmp_path):
    """The clear sky's sun at 60 degrees through the 1 x 1 m roof opening of a grey room: its gather
    lands E_n sin 60 x 1 m^2 (the opening's closed form; the landing rays' noise aside) and books
    that as emitted, no back faces (the roof's outside) and nothing escaped.  Booked as emitting
    what met the roof's outside as well, the run at 2% stopped with 6% of the landed light unshot
    and its floor 4% dark, the estimate reading 0.2% of bias: now its unshot light is below 2% of
    what landed, and its floor agrees with a divided run's within 3%."""
    from dcrad.config import DivideConfig
    from dcrad.division.divide import solve_divided
    from dcrad.solving.passes import solve_to_accuracy
    from dcrad.solving.solver import Solver

    path, _ = roof_room(tmp_path, 1.0, 0.5)
    spec = DaylightSpec("clear", sun_altitude=60.0, sun_azimuth=200.0)
    cfg = SolverConfig(accuracy=0.02, seed=2)

    def lit():
        return prepare(path, 0.3, sources=lambda sc: daylight_sources(spec, sc))[1]

    solver = Solver(lit(), cfg)
    solver.direct.kept = []
    solver.direct.shoot_sources()
    sky_tally, sun_tally = solver.direct.kept
    assert sun_tally.received.sum(axis=0)[0] == pytest.approx(80_000.0 / EFFICACY * math.sin(math.radians(60)),
                                                              rel=0.01)
    assert not solver.ledger.back_faces.any() and not solver.ledger.escaped.any()
    np.testing.assert_allclose(solver.ledger.emitted, sky_tally.received.sum(axis=0) + sun_tally.received.sum(axis=0),
                               rtol=1e-12)
    single = lit()
    one = solve_to_accuracy(single, cfg)
    landed = float((sky_tally.received.sum(axis=0) + sun_tally.received.sum(axis=0)).sum())
    assert float(one.ledger.unshot.sum()) < 0.02 * landed
    p = lit()
    solve_divided(p, cfg, DivideConfig(subscenes=2))
    floor = np.flatnonzero((p.normal[:, 1] > 0.9) & (p.centroid[:, 1] < 0.01))
    a = p.area[floor]
    assert np.average(single.radiosity[floor, 0], weights=a) == pytest.approx(
        np.average(p.radiosity[floor, 0], weights=a), rel=0.03)


def test_the_sky_s_rays_carry_its_power_and_light_the_floor_as_its_gather_does(tmp_path):
    """The sky's rays into the bounding box carry exactly its power (the ledger books it), and the
    light they land on a roof-lit room's floor is the gathered light (--no-direct against the
    default) within their noise."""
    path, _ = roof_room(tmp_path, 4.0, rho=0.01)
    _, patches, _ = prepare(path, 1.0, up="y")
    sky = sky_light(patches, SkyModel("uniform", E_HZ))
    batch = sky.rays(1 << 16, np.random.default_rng(3))
    np.testing.assert_allclose(batch.power.sum(axis=0), sky.power(), rtol=1e-12)
    floor = np.flatnonzero((patches.normal[:, 1] > 0.9) & (patches.centroid[:, 1] < 0.01))
    runs = []
    for direct in (True, False):
        _, p, _ = prepare(path, 1.0, up="y")
        p.sources = (sky_light(p, SkyModel("uniform", E_HZ)),)
        from dcrad.solving.passes import solve_to_accuracy

        solver = solve_to_accuracy(p, SolverConfig(accuracy=0.01, direct=direct, seed=5))
        runs.append(p.radiosity[floor, 0] / p.rho[floor, 0] * EFFICACY)
        assert abs(solver.ledger.closure()) < 1e-9
    # the open-roofed room's floor: the sky seen through a 4 x 4 opening 3 m up
    gathered, shot = runs
    assert np.average(shot, weights=patches.area[floor]) == pytest.approx(
        np.average(gathered, weights=patches.area[floor]), rel=0.02)


# -- a run --------------------------------------------------------------------------------------------
def test_a_daylit_run_writes_daylight_factors_that_match_the_closed_form(tmp_path):
    """`dcrad solve --sky uniform` on the black room with a 4 x 4 m roof opening: patch_daylight_factor
    of the floor's patches is 100 x the configuration factor of the opening averaged over each patch
    (RMS within 2%), the work plane's likewise, the report's daylight section gives the sky component
    and its per-surface figures, and the daylight-factor picture is written."""
    path, opening = roof_room(tmp_path, 4.0)
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "dcrad.cli", "solve", str(path), "--up", "y", "--sky", "uniform",
                           "--patch-size", "0.5", "--workplane", "0.8", "--out", str(out), "--width", "64",
                           "--height", "48"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    report = json.loads((out / "report.json").read_text())
    day = report["daylight"]
    assert day["sky_component"] is True and day["E_hz_lux"] == E_HZ
    assert (out / "daylight_factor.png").exists()
    z = np.load(out / "radiosity.npz")
    _, patches, _ = prepare(path, 0.5, up="y")
    floor = np.flatnonzero((patches.normal[:, 1] > 0.9) & (patches.centroid[:, 1] < 0.01))
    corners = patches.corners(floor)
    u = np.random.default_rng(0).random((64, 2))
    s = np.sqrt(u[:, :1])
    bary = np.hstack([1 - s, s * (1 - u[:, 1:]), s * u[:, 1:]])
    pts = np.einsum("rc,kcx->krx", bary, corners).reshape(-1, 3)
    loops = np.repeat(opening[None], len(pts), 0)
    f = polygon_form_factor(pts, np.tile(UP, (len(pts), 1)), loops, np.tile(-UP, (len(pts), 1)))
    truth = 100 * f.reshape(len(floor), -1).mean(axis=1)
    got = z["patch_daylight_factor"][floor]
    assert np.sqrt(np.mean((got / truth - 1) ** 2)) < 0.02
    wp = z["workplane_points"]  # the file's frame is Y-up: the same as the solver's
    lw = np.repeat(opening[None], len(wp), 0)
    fw = polygon_form_factor(wp, np.tile(UP, (len(wp), 1)), lw, np.tile(-UP, (len(wp), 1)))
    np.testing.assert_allclose(z["workplane_daylight_factor"], 100 * fw, rtol=0.03)
    assert day["workplane"]["DF_avg_pct"] == pytest.approx(float(np.mean(100 * fw)), rel=0.02)


def test_the_api_takes_a_sky(tmp_path):
    """dcrad.solve(..., sky=...) lights the scene as `dcrad solve --sky` does: a name or a
    DaylightSpec; the outputs gain the daylight factors; a bad sky is a ConfigError."""
    import dcrad

    path, _ = roof_room(tmp_path, 4.0, rho=0.5)
    result = dcrad.solve(path, tmp_path / "out", accuracy=0.05, patch_size=0.5, up="y", sky="cie-overcast",
                         width=32, height=24)
    assert result.report["daylight"]["sky"]["sky"] == "cie-overcast"
    assert "patch_daylight_factor" in np.load(tmp_path / "out" / "radiosity.npz")
    spec = dcrad.DaylightSpec("clear", sun_altitude=50.0, sun_azimuth=200.0)
    sunny = dcrad.solve(path, accuracy=0.05, patch_size=0.5, up="y", sky=spec)
    assert sunny.report["ledger"]["closure"] < 1e-9 and sunny.estimate.rms_refl <= 0.05
    with pytest.raises(ConfigError, match="unknown sky"):
        dcrad.solve(path, accuracy=0.05, patch_size=0.5, up="y", sky="cloudy")


def test_a_daylit_run_keeps_max_rays(tmp_path):
    """--max-rays holds with the sky: its gather takes at most half of the budget (coarser, every
    receiver still gathered) and the run stops by the budget, the books closed."""
    from dcrad.solving.passes import solve_to_accuracy

    path, _ = roof_room(tmp_path, 1.0, rho=0.5)
    _, p, _ = prepare(path, 0.5, up="y")
    p.sources = (sky_light(p, SkyModel("uniform", E_HZ)),)
    solver = solve_to_accuracy(p, SolverConfig(accuracy=0.02, max_rays=20_000, seed=1))
    assert solver.stats.rays <= 20_000 * 1.01 and solver.stats.stopped_by == "ray_budget"
    assert abs(solver.ledger.closure()) < 1e-9
    assert any("coarsened" in c.text for c in solver.choices)


@pytest.mark.parametrize("flags,words", [
    (["--sky", "overcast"], "unknown sky"),
    (["--sky", "iso:16"], "unknown sky"),
    (["--sky", "iso:12"], "needs the sun's position"),
    (["--sky", "clear", "--sun-altitude", "-5", "--sun-azimuth", "180"], "below the horizon"),
    (["--sky", "clear", "--site", "51.5,0", "--time", "2026-12-21T23:00+00:00"], "below the horizon"),
    (["--sun-altitude", "30", "--sun-azimuth", "180"], "give --sky too"),
    (["--sky", "uniform", "--sun-illuminance", "50000"], "does not apply"),
    (["--sky", "uniform", "--sun-altitude", "30", "--sun-azimuth", "180"], "does not apply"),
    (["--sky", "clear", "--sun-altitude", "30"], "go together"),
    (["--sky", "uniform", "--ground-reflectance", "1.2"], "--ground-reflectance"),
    (["--sky", "uniform", "--sky-illuminance", "-3"], "--sky-illuminance"),
    (["--sky", "clear", "--site", "51.5", "--time", "2026-06-21T12:00+00:00"], "--site"),
    (["--sky", "clear", "--site", "51.5,0", "--time", "2026-06-21T12:00"], "UTC offset"),
])
def test_bad_daylight_flags_get_one_line_and_exit_2(tmp_path, flags, words):
    path, _ = roof_room(tmp_path, 1.0)
    proc = subprocess.run([sys.executable, "-m", "dcrad.cli", "solve", str(path), "--out", str(tmp_path / "o"),
                           *flags], capture_output=True, text=True)
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and words in lines[0], proc.stderr


def test_daylight_spec_checks_its_values_before_the_scene_loads():
    with pytest.raises(ConfigError, match="below the horizon"):
        DaylightSpec("iso:7", sun_altitude=-1.0, sun_azimuth=90.0).check()
    DaylightSpec("iso:7", sun_altitude=10.0, sun_azimuth=90.0).check()


def test_the_sky_travels_exactly():
    """to_wire / from_wire rebuild the sky and the sun to the bit (source_wire.py)."""
    from dcrad.transport.source_wire import sources_from_table, sources_table

    up, east, north = frame(np.eye(3))
    sun_dir = sun_direction(35.0, 200.0, up, east, north)
    model = SkyModel("iso:12", 12_000.0, sun_dir, 70_000.0, 0.25)
    lo, hi = np.zeros(3), np.array([4.0, 3.0, 5.0])
    sources = (Sky(model, lo, hi), Sun(sun_dir, 70_000.0, lo, hi))
    back = sources_from_table(sources_table(sources))
    s, _ = grid_directions()
    np.testing.assert_array_equal(back[0].model.radiance(s[:5000]), model.radiance(s[:5000]))
    np.testing.assert_array_equal(back[0].power(), sources[0].power())
    np.testing.assert_array_equal(back[1].power(), sources[1].power())


def glazed_office(folder) -> "os.PathLike":
    """A 3 x 4 x 2.7 m room, Y up, a 2 x 1.2 m window of 6 mm clear glass (MTL illum 4, Tf, Ni) in
    its z = 0 wall, grey surfaces: the file the coordinator reads its panes from."""
    folder.mkdir(parents=True, exist_ok=True)
    v, f = [], {}

    def quad(mat, *pts):
        base = len(v) + 1
        v.extend(pts)
        f.setdefault(mat, []).extend([(base, base + 1, base + 2), (base, base + 2, base + 3)])

    w_, d_, h_ = 3.0, 4.0, 2.7
    quad("floor", (0, 0, 0), (0, 0, d_), (w_, 0, d_), (w_, 0, 0))
    quad("wall", (0, h_, 0), (w_, h_, 0), (w_, h_, d_), (0, h_, d_))
    quad("wall", (0, 0, d_), (0, h_, d_), (w_, h_, d_), (w_, 0, d_))
    quad("wall", (0, 0, 0), (0, h_, 0), (0, h_, d_), (0, 0, d_))
    quad("wall", (w_, 0, 0), (w_, 0, d_), (w_, h_, d_), (w_, h_, 0))
    for x0, x1, y0, y1 in ((0, 0.5, 0, h_), (2.5, w_, 0, h_), (0.5, 2.5, 0, 0.9), (0.5, 2.5, 2.1, h_)):
        quad("wall", (x0, y0, 0), (x1, y0, 0), (x1, y1, 0), (x0, y1, 0))
    quad("glass", (0.5, 0.9, 0), (2.5, 0.9, 0), (2.5, 2.1, 0), (0.5, 2.1, 0))
    lines = ["mtllib glazed.mtl"] + [f"v {x:g} {y:g} {z:g}" for x, y, z in v]
    for mat, tris in f.items():
        lines += [f"o {mat}", f"usemtl {mat}"] + [f"f {a} {b} {c}" for a, b, c in tris]
    (folder / "glazed.obj").write_text("\n".join(lines) + "\n")
    (folder / "glazed.mtl").write_text("newmtl floor\nKd 0.3 0.3 0.3\nnewmtl wall\nKd 0.6 0.6 0.6\n"
                                       "newmtl glass\nKd 0 0 0\nillum 4\nTf 0.8788 0.8788 0.8788\nNi 1.52\n")
    return folder / "glazed.obj"


def test_a_glazed_daylit_room_runs_shared_as_in_one_process(tmp_path):
    """Shared runs carry glass and sky: the glazed room under the overcast sky, shared by two
    in-process replicas, lights its floor as the run in one process does (within the two runs'
    estimates); on two workers (`dcrad submit` with the daylight settings, the panes read by the
    coordinator from the MTL) it is the in-process shared run to the bit, with its daylight section."""
    from coordinator import client
    from coordinator.embedded import LocalCluster
    from dcrad.solving.passes import solve_to_accuracy
    from dcrad.solving.share import LocalShares, run_shared


    path = glazed_office(tmp_path / "room")
    spec = DaylightSpec("cie-overcast")
    cfg = SolverConfig(accuracy=0.03, seed=4)
    scene, single, _ = prepare(path, 0.3, sources=lambda sc: daylight_sources(spec, sc))
    assert single.glazing is not None and single.glazing.mask.any()
    solve_to_accuracy(single, cfg)
    _, p, _ = prepare(path, 0.3, sources=lambda sc: daylight_sources(spec, sc))
    ref = run_shared(p, cfg, 2, LocalShares(p, cfg, Tracer.mesh(p)))
    assert ref is not None and abs(ref.ledger.closure()) < 1e-9
    p.pool()
    floor = np.flatnonzero((p.normal[:, 1] > 0.9) & (p.centroid[:, 1] < 0.01))
    a = p.area[floor]
    mean_shared = np.average(p.radiosity[floor, 0], weights=a)
    mean_single = np.average(single.radiosity[floor, 0], weights=a)
    assert mean_shared == pytest.approx(mean_single, rel=0.03)
    with LocalCluster(workers=2, data=tmp_path / "cluster") as cluster:
        job = client.submit(cluster.address, path, {"accuracy": 0.03, "seed": 4, "patch_size": 0.3}, {},
                            daylight=spec)
        last = client.watch(cluster.address, job.job_id)
        assert last is not None and last.job.state == "done", last.job.error if last else None
        client.fetch(cluster.address, job.job_id, tmp_path / "out")
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    b = np.load(tmp_path / "out" / "radiosity.npz")["patch_B"]
    assert np.array_equal(b, p.radiosity)
    assert report["shared"]["workers"] == 2 and report["daylight"]["sky"]["sky"] == "cie-overcast"
    assert not any("opaque" in w for w in report["warnings"])


def test_a_daylit_room_divided_reads_as_in_one_process(tmp_path):
    """Divided runs carry the sky and glass: the glazed room under the overcast sky, cut in two (exact
    forwarding, and binned twins) and in four, lights its floor as the run in one process does
    (within 3%), its books closed and its estimate at the target.  The sky is gathered once on the
    whole room: what each cell is handed sums to what landed (clipping conserves area), its rays are
    the run's from the first barrier on, and the job books as emitted what the run in one process
    does (what lands, within the gathers' noise).  Through ``solve_to`` the report has its daylight
    and divided sections and says the sky was gathered before the cut."""
    from dcrad.config import DivideConfig
    from dcrad.division.divide import solve_divided, subscene_specs
    from dcrad.division.outside import gather_outside
    from dcrad.pipeline import solve_to
    from dcrad.solving.passes import solve_to_accuracy
    from dcrad.transport.emitters import Gathered, sources_power

    path = glazed_office(tmp_path / "room")
    spec = DaylightSpec("cie-overcast")
    cfg = SolverConfig(accuracy=0.03, seed=4)

    def lit():
        return prepare(path, 0.3, sources=lambda sc: daylight_sources(spec, sc))[1]

    single = lit()
    one = solve_to_accuracy(single, cfg)
    floor = np.flatnonzero((single.normal[:, 1] > 0.9) & (single.centroid[:, 1] < 0.01))
    a = single.area[floor]
    want = np.average(single.radiosity[floor, 0], weights=a)
    for k, mode in ((2, "exact"), (2, "binned"), (4, "exact")):
        p = lit()
        run, _, _, part = solve_divided(p, cfg, DivideConfig(subscenes=k, mode=mode))
        assert len(part.cells) == k and abs(run.ledger.closure()) < 1e-9
        assert run.stopped_by == "accuracy" and run.estimate is not None and run.estimate.rms_refl <= 0.03
        assert np.average(p.radiosity[floor, 0], weights=a) == pytest.approx(want, rel=0.03)
        assert float(run.ledger.emitted.sum()) == pytest.approx(float(one.ledger.emitted.sum()), rel=0.03)
    p = lit()
    outside = gather_outside(p, cfg)
    assert outside is not None and outside.rays > 0
    specs, *_ = subscene_specs(p, cfg, DivideConfig(subscenes=4), outside=outside)
    handed = [s for spec_ in specs for s in spec_.patches.sources if isinstance(s, Gathered)]
    landed = (outside.irradiance * p.area[:, None]).sum(axis=0)
    np.testing.assert_allclose(sum(g.power() for g in handed), landed, rtol=1e-12)
    assert sum(g.rays for g in handed) == outside.rays
    assert sum(s.state().rays for s in specs) == outside.rays  # traced already: a budget counts them first
    assert not any(getattr(s, "outside", False) for spec_ in specs for s in spec_.patches.sources)
    assert float(sources_power(specs[0].patches.sources).sum()) > 0
    report = solve_to(path, tmp_path / "out", cfg, patch_size=0.3, divide=DivideConfig(subscenes=2), daylight=spec)
    assert report["divided"]["subscenes"] == 2 and report["daylight"]["sky"]["sky"] == "cie-overcast"
    assert report["daylight"]["counts"] and not any("opaque" in w for w in report["warnings"])
    assert any("gathered onto" in c["text"] for c in report["choices"])


def test_a_closed_room_under_the_sky_says_no_daylight_gets_in(tmp_path):
    """A grey box with no opening under the sky: nothing lands, every surface reads 0 lux, and the
    report says why (in one process and divided alike) rather than warning of no emitters."""
    from dcrad.config import DivideConfig
    from dcrad.pipeline import solve_to

    w = ObjWriter()
    w.material("wall", 0.5)
    w.begin("room", "wall")
    w.add_box((0, 0, 0), (SIZE, HEIGHT, SIZE), outward=False)
    path = w.write(tmp_path, "closed")
    for divide in (None, DivideConfig(subscenes=2)):
        report = solve_to(path, tmp_path / str(divide is None), SolverConfig(accuracy=0.05, seed=1), patch_size=0.5,
                          divide=divide, daylight=DaylightSpec("uniform"), width=32, height=24)
        assert any("lets it in" in c["text"] for c in report["choices"])
        assert all(s["E_avg_lux"] == 0.0 for s in report["photometry"]["surfaces"])
        assert not any("no emitters" in w_ for w_ in report["warnings"])


def test_the_gathered_sky_travels_to_a_worker_exactly(tmp_path):
    """A subscene's share of the sky (emitters.Gathered) travels with its patches as arrays, not JSON,
    and comes back to the bit; a rebuilt subscene lays it down as the original does."""
    from dcrad.config import DivideConfig
    from dcrad.division.divide import subscene_specs
    from dcrad.division.subscene import build_subscene, subscene_arrays
    from dcrad.transport.emitters import Gathered
    from dcrad.transport.source_wire import sources_from_table, sources_table

    path = glazed_office(tmp_path / "room")
    spec = DaylightSpec("cie-overcast")
    cfg = SolverConfig(accuracy=0.05, seed=4)
    _, p, _ = prepare(path, 0.3, sources=lambda sc: daylight_sources(spec, sc))
    specs, *_ = subscene_specs(p, cfg, DivideConfig(subscenes=2))
    sub = specs[0].build()
    arrays = subscene_arrays(sub)
    assert arrays["sources"].nbytes < 1000  # the per-patch arrays are beside the JSON, not in it
    (back,) = [s for s in sources_from_table(sources_table(sub.patches.sources)) if isinstance(s, Gathered)]
    (orig,) = [s for s in sub.patches.sources if isinstance(s, Gathered)]
    for name in ("rows", "received", "received_a"):
        assert np.array_equal(getattr(back, name), getattr(orig, name))
    assert back.rays == orig.rays
    twin = build_subscene(specs[0].cell, sub.config, sub.power_per_ray, sub.mode, list(p.names),
                          {k: np.array(v) for k, v in arrays.items()})
    assert sub.iterate(1) == twin.iterate(1)
    assert np.array_equal(sub.patches.radiosity, twin.patches.radiosity)
    with pytest.raises(ValueError, match="missing"):
        sources_from_table({"sources": arrays["sources"]})


def test_a_pane_reads_the_sky_with_fewer_rays_and_its_surface_keeps_its_lux(tmp_path):
    """A pane's own light (its lux, read per surface over its patches) takes PANE_SKY_RAYS a point
    rather than the budget's share (up to 16,384 a point, the peer office's outputs' largest cost):
    the window's area-weighted mean irradiance (the side facing out, which sees the sky and the ground)
    agrees with a read at 8,192 a point within 1%."""
    from dcrad.outputs.photometry import PANE_SKY_RAYS, irradiance

    path = glazed_office(tmp_path / "room")
    _, p, _ = prepare(path, 0.3, sources=lambda sc: daylight_sources(DaylightSpec("cie-overcast"), sc))
    tracer = Tracer.mesh(p)
    assert p.glazing is not None
    pane = np.flatnonzero(p.glazing.mask & (p.normal[:, 2] < -0.9))  # the side facing the sky
    h, gathered = irradiance(p, tracer)
    assert gathered[pane].all() and PANE_SKY_RAYS < 8192
    fine, _ = direct_irradiance(p, tracer, p.corners(pane), p.normal[pane], sampled_rays=8192)
    a = p.area[pane]
    assert np.average(h[pane, 1], weights=a) == pytest.approx(np.average(fine[:, 1], weights=a), rel=0.01)
    assert np.average(h[pane, 1], weights=a) > 0


def test_a_daylit_job_divides_on_workers_as_in_process(tmp_path):
    """`dcrad submit --sky ... --subscenes 2`: the coordinator gathers the sky on the whole room and
    the two workers' subscenes give the in-process divided run's B to round-off, with the daylight
    and divided sections and closed books."""
    from coordinator import client
    from coordinator.embedded import LocalCluster
    from dcrad.config import DivideConfig
    from dcrad.division.divide import solve_divided

    path = glazed_office(tmp_path / "room")
    spec = DaylightSpec("cie-overcast")
    _, p, _ = prepare(path, 0.3, sources=lambda sc: daylight_sources(spec, sc))
    run, *_ = solve_divided(p, SolverConfig(accuracy=0.04, seed=4), DivideConfig(subscenes=2))
    p.pool()
    with LocalCluster(workers=2, data=tmp_path / "cluster") as cluster:
        job = client.submit(cluster.address, path, {"accuracy": 0.04, "seed": 4, "patch_size": 0.3},
                            {"subscenes": 2}, daylight=spec)
        last = client.watch(cluster.address, job.job_id)
        assert last is not None and last.job.state == "done", last.job.error if last else None
        client.fetch(cluster.address, job.job_id, tmp_path / "out")
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    b = np.load(tmp_path / "out" / "radiosity.npz")["patch_B"]
    assert np.allclose(b, p.radiosity, rtol=1e-12, atol=1e-15)
    assert report["divided"]["subscenes"] == 2 and report["daylight"]["sky"]["sky"] == "cie-overcast"
    assert report["ledger"]["closure"] < 1e-9 and report["stats"]["barriers"] == run.barriers


def _radiance(tool: str) -> str | None:
    import importlib.util

    spec = importlib.util.find_spec("pyradiance")
    if spec is None or spec.origin is None:
        return None
    path = os.path.join(os.path.dirname(spec.origin), "bin", tool)
    return path if os.path.exists(path) else None


def _radiance_env() -> dict:
    import importlib.util

    spec = importlib.util.find_spec("pyradiance")
    lib = os.path.join(os.path.dirname(spec.origin), "lib") if spec and spec.origin else ""
    return {**os.environ, "RAYPATH": f".:{lib}"}
