"""Illuminance from the direct light by exact form factors (photometry.direct_irradiance), against
independent truths: the closed form of a rectangle to a parallel differential area (corner
superposition) and Gauss-Legendre quadrature of cos cos / (pi d^2) over the emitter, computed
here, not by the code under test.

The room is CIE 171:2006 test case 5.3's layout: 4 x 4 x 3 m (x, z across, y up), every
surface black (rho = 0), a 1 x 1 m Lambertian panel at the ceiling's centre facing down.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dcrad.meshing.patches import Patches
from dcrad.outputs import photometry
from dcrad.transport.rays import Tracer

#: the panel: x, z in [1.5, 2.5] at y = 3, exitance E W/m^2 (grey: lux = 179 E F)
PANEL = (1.5, 2.5, 1.5, 2.5)
HEIGHT = 3.0
E = 100.0
#: Dunavant's degree-5 rule of a triangle (barycentric coordinates, weights): a patch's mean
DUNAVANT5 = (
    [(1 / 3, 1 / 3, 1 / 3, 0.225)]
    + [(a, b, b, 0.132394152788506) for a, b in [(0.059715871789770, 0.470142064105115)]]
    + [(b, a, b, 0.132394152788506) for a, b in [(0.059715871789770, 0.470142064105115)]]
    + [(b, b, a, 0.132394152788506) for a, b in [(0.059715871789770, 0.470142064105115)]]
    + [(a, b, b, 0.125939180544827) for a, b in [(0.797426985353087, 0.101286507323456)]]
    + [(b, a, b, 0.125939180544827) for a, b in [(0.797426985353087, 0.101286507323456)]]
    + [(b, b, a, 0.125939180544827) for a, b in [(0.797426985353087, 0.101286507323456)]]
)


# -- the scene ------------------------------------------------------------------------------------
def _grid(origin, a, b, nu, nv):
    """A rectangle origin + s a + t b in nu x nv squares, two triangles each, facing a x b."""
    s, t = np.meshgrid(np.arange(nu + 1) / nu, np.arange(nv + 1) / nv, indexing="ij")
    v = np.asarray(origin, float) + s.reshape(-1, 1) * np.asarray(a, float) + t.reshape(-1, 1) * np.asarray(b, float)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    p00 = (i * (nv + 1) + j).reshape(-1)
    p10, p01 = p00 + nv + 1, p00 + 1
    p11 = p10 + 1
    f = np.concatenate([np.stack([p00, p10, p11], 1), np.stack([p00, p11, p01], 1)])
    return v, f


def black_room(floor_step=0.1, wall_step=0.1, blocker=False, wall_rho=0.0, l_shaped=False):
    """The room as a Patches table: floor (y = 0) and the wall x = 0 in squares of the given
    steps, the other walls and the ceiling in 0.5 m squares, the panel the ceiling's centre 2 x 2
    squares (emitting E, obj 'panel').  ``blocker``: a black plane at y = 2 over x in [0, 2]
    (facing down).  ``wall_rho``: the four walls' reflectance (grey).  ``l_shaped``: the panel's
    quarter x, z in [2, 2.5] is ceiling, not panel."""
    nf, nw = round(4 / floor_step), round(4 / wall_step)
    parts = [  # (name, origin, a, b, nu, nv) with a x b pointing into the room
        ("floor", (0, 0, 0), (0, 0, 4), (4, 0, 0), nf, nf),
        ("wall_x0", (0, 0, 0), (0, 3, 0), (0, 0, 4), round(3 / wall_step), nw),
        ("wall_x4", (4, 0, 0), (0, 0, 4), (0, 3, 0), 8, 6),
        ("wall_z0", (0, 0, 0), (4, 0, 0), (0, 3, 0), 8, 6),
        ("wall_z4", (0, 0, 4), (0, 3, 0), (4, 0, 0), 6, 8),
        ("ceiling", (0, 3, 0), (4, 0, 0), (0, 0, 4), 8, 8),
    ]
    if blocker:
        parts.append(("blocker", (0, 2, 0), (2, 0, 0), (0, 0, 4), 4, 8))
    verts, faces, obj, names = [], [], [], []
    base = 0
    for k, (name, o, a, b, nu, nv) in enumerate(parts):
        v, f = _grid(o, a, b, nu, nv)
        verts.append(v)
        faces.append(f + base)
        obj.append(np.full(len(f), k))
        names.append(f"{name}/black")
        base += len(v)
    v, f = np.concatenate(verts), np.concatenate(faces)
    obj = np.concatenate(obj)
    names.append("panel/lamp")
    c = v[f].mean(axis=1)
    lamp = ((obj == 5) & (c[:, 0] > PANEL[0]) & (c[:, 0] < PANEL[1]) & (c[:, 2] > PANEL[2]) & (c[:, 2] < PANEL[3]))
    if l_shaped:
        lamp &= ~((c[:, 0] > 2.0) & (c[:, 2] > 2.0))
    obj[lamp] = len(names) - 1
    emission = np.where(lamp[:, None], E, 0.0) * np.ones(3)
    rho = np.zeros((len(f), 3))
    rho[(obj >= 1) & (obj <= 4)] = wall_rho
    return Patches(vertices=v, faces=f, rho=rho, emission=emission, source=np.arange(len(f)), obj=obj, names=names)


# -- independent truths -------------------------------------------------------------------------
def parallel_ff(p, x0=PANEL[0], x1=PANEL[1], z0=PANEL[2], z1=PANEL[3], y=HEIGHT):
    """Form factor from points p (m,3) facing up to the rectangle [x0,x1] x [z0,z1] at height y
    facing down: the corner formula F(a, b, c) = 1/(2 pi) [a/sqrt(a^2+c^2) atan(b/sqrt(a^2+c^2))
    + b/sqrt(b^2+c^2) atan(a/sqrt(b^2+c^2))] (odd in a and b) superposed over the corners."""
    p = np.asarray(p, float)
    c = y - p[:, 1]

    def corner(a, b):
        ra, rb = np.sqrt(a * a + c * c), np.sqrt(b * b + c * c)
        return (a / ra * np.arctan(b / ra) + b / rb * np.arctan(a / rb)) / (2 * math.pi)

    ax0, ax1, bz0, bz1 = x0 - p[:, 0], x1 - p[:, 0], z0 - p[:, 2], z1 - p[:, 2]
    return corner(ax1, bz1) - corner(ax0, bz1) - corner(ax1, bz0) + corner(ax0, bz0)


def quadrature_ff(p, n, nodes=48, x0=PANEL[0], x1=PANEL[1], z0=PANEL[2], z1=PANEL[3], y=HEIGHT):
    """Form factor from points p (m,3) facing n (3,) to the rectangle [x0,x1] x [z0,z1] at height y
    facing down, by nodes x nodes Gauss-Legendre quadrature of cos cos / (pi d^2) (unoccluded,
    every panel point above the points' horizon)."""
    g, w = np.polynomial.legendre.leggauss(nodes)
    xs, wx = x0 + (g + 1) * (x1 - x0) / 2, w * (x1 - x0) / 2
    zs, wz = z0 + (g + 1) * (z1 - z0) / 2, w * (z1 - z0) / 2
    q = np.stack(np.meshgrid(xs, zs, indexing="ij"), axis=-1).reshape(-1, 2)
    wq = np.outer(wx, wz).reshape(-1)
    out = np.empty(len(p))
    for i in range(0, len(p), 256):
        dx = q[None, :, 0] - p[i:i + 256, None, 0]
        d = np.stack([dx, np.broadcast_to(y - p[i:i + 256, None, 1], dx.shape),
                      q[None, :, 1] - p[i:i + 256, None, 2]], axis=-1)
        r2 = (d * d).sum(axis=2)
        cos_x = (d @ np.asarray(n, float)) / np.sqrt(r2)
        cos_l = d[..., 1] / np.sqrt(r2)
        out[i:i + 256] = (np.clip(cos_x, 0, None) * cos_l / (math.pi * r2)) @ wq
    return out


def patch_mean(tri, point_ff):
    """Mean over each triangle (k,3,3) of point_ff(points) by Dunavant's degree-5 rule."""
    total = np.zeros(len(tri))
    for a, b, c, wgt in DUNAVANT5:
        total += wgt * point_ff(a * tri[:, 0] + b * tri[:, 1] + c * tri[:, 2])
    return total


def lux_of(ff):
    return 179.0 * E * ff  # grey: Y = 1


# -- tests ----------------------------------------------------------------------------------------
def test_references_agree():
    """The two truths agree (the corner formula and quadrature), so each checks the other."""
    rng = np.random.default_rng(1)
    p = np.column_stack([rng.uniform(0, 4, 50), rng.uniform(0, 2.5, 50), rng.uniform(0, 4, 50)])
    np.testing.assert_allclose(parallel_ff(p), quadrature_ff(p, [0, 1, 0]), rtol=1e-9)
    # the point under the panel's centre: F = 4 F(0.5, 0.5, 3) (symmetry)
    a, c = 0.5, 3.0
    r = math.hypot(a, c)
    assert parallel_ff([[2, 0, 2]])[0] == pytest.approx(4 * 2 * a / r * math.atan(a / r) / (2 * math.pi), rel=1e-12)


def test_black_room_floor_and_wall_are_the_closed_form():
    """Every floor and x = 0 wall patch (0.1 m squares' halves) reads the closed form's mean over
    the patch within 1% (it is exact: about 1e-6 is left); no ray is gathered (nothing reflects)."""
    p = black_room()
    tracer = Tracer.mesh(p)
    calls = {"intersect": 0}
    real = tracer.intersect

    def counting(o, d, *args, **kw):
        calls["intersect"] += len(o)
        return real(o, d, *args, **kw)

    tracer.intersect = counting  # type: ignore[method-assign]
    h, gathered = photometry.irradiance(p, tracer)
    lux = photometry.to_lux(h)
    assert gathered.all() and calls["intersect"] == 0  # all black: no gather ray
    floor = np.flatnonzero(p.obj == 0)
    tri = p.corners(floor)
    want = lux_of(patch_mean(tri, parallel_ff))
    err = np.abs(lux[floor] / want - 1)
    assert err.max() < 0.01, err.max()
    wall = np.flatnonzero(p.obj == 1)
    want_w = lux_of(patch_mean(p.corners(wall), lambda x: quadrature_ff(x, [1, 0, 0], nodes=24)))
    err_w = np.abs(lux[wall] / want_w - 1)
    assert err_w.max() < 0.01, err_w.max()
    print(f"\nfloor: {len(floor)} patches, max error {err.max():.2e}; wall: {len(wall)}, max error {err_w.max():.2e}")
    # the ceiling around the panel sees nothing (coplanar), the panel nothing either
    ceiling = p.obj >= 5
    np.testing.assert_allclose(lux[ceiling], 0.0, atol=1e-6)


def test_points_are_the_closed_form_at_the_point():
    """direct_irradiance at points (not patches): the closed form at the point, floor and wall."""
    p = black_room(floor_step=0.5, wall_step=0.5)
    tracer = Tracer.mesh(p)
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(0.01, 3.99, 200), np.zeros(200), rng.uniform(0.01, 3.99, 200)])
    h, rays = photometry.direct_irradiance(p, tracer, pts + [0, 1e-9, 0], np.tile([0.0, 1.0, 0.0], (200, 1)))
    np.testing.assert_allclose(h[:, 0], E * parallel_ff(pts), rtol=1e-6)
    assert rays == 200 * photometry.SHADOW_RAYS  # seen whole: the first rays only
    wall = np.column_stack([np.zeros(100), rng.uniform(0.01, 2.99, 100), rng.uniform(0.01, 3.99, 100)])
    hw, _ = photometry.direct_irradiance(p, tracer, wall, np.tile([1.0, 0.0, 0.0], (100, 1)))
    np.testing.assert_allclose(hw[:, 1], E * quadrature_ff(wall, [1, 0, 0]), rtol=1e-6)


def test_work_plane_is_the_closed_form():
    """The work plane 0.8 m above the black room's floor: each grid point within 1% of the closed
    form at that point (E at a point, no patch mean)."""
    p = black_room(floor_step=0.5, wall_step=0.5)
    wp = photometry.workplane(p, 0.8, spacing=0.25)
    pts = wp["points"]
    assert wp["n_points"] == len(pts) == 144  # 16 x 16 less the 0.4 m border zone
    np.testing.assert_allclose(pts[:, 1], 0.8)
    want = lux_of(parallel_ff(pts))
    err = np.abs(wp["lux"] / want - 1)
    assert err.max() < 0.01, err.max()
    assert wp["E_max_lux"] == pytest.approx(want.max(), rel=0.01)


def _visible_ff(x):
    """Floor points x (m,3) under the blocker (y = 2, x in [0, 2]): the panel's part they see is
    x_p >= 3 - x/2 (the ray to (x_p, 3) passes y = 2 at x + 2 (x_p - x) / 3 >= 2), a rectangle."""
    lo = np.maximum(PANEL[0], 3.0 - x[:, 0] / 2.0)
    out = np.zeros(len(x))
    some = lo < PANEL[1]
    out[some] = parallel_ff(x[some], x0=lo[some])
    return out


def test_partly_occluded_emitter():
    """A black blocker plane between the panel and part of the floor: points in full shadow
    (x < 1) read 0, points fully lit (x > 3) read the closed form, points in the penumbra lie in
    between and near the visible part's own closed form (a rectangle of the panel)."""
    p = black_room(floor_step=0.5, wall_step=0.5, blocker=True)
    tracer = Tracer.mesh(p)
    xs = np.linspace(0.05, 3.95, 80)
    pts = np.column_stack([xs, np.zeros(80), np.full(80, 1.7)])
    up = np.tile([0.0, 1.0, 0.0], (80, 1))
    h, _ = photometry.direct_irradiance(p, tracer, pts, up)
    got, whole = h[:, 0], E * parallel_ff(pts)
    shadow, lit = xs < 0.99, xs > 3.01
    pen = ~shadow & ~lit
    assert np.all(got[shadow] == 0.0)
    np.testing.assert_allclose(got[lit], whole[lit], rtol=1e-9)
    assert np.all((got[pen] >= 0) & (got[pen] <= whole[pen] * (1 + 1e-9)))
    want = E * _visible_ff(pts)
    inner = pen & (want > 0.1 * whole) & (want < 0.9 * whole)
    assert np.all((got[inner] > 0) & (got[inner] < whole[inner]))
    # the penumbra's ratio estimate: 128 stratified rays; a sliver of the panel seen (or hidden)
    # that none of the first 16 rays found reads 0 (or the whole), hence the larger max
    err = (got[pen] - want[pen]) / whole[pen]
    assert np.abs(err).max() < 0.05 and np.sqrt(np.mean(err ** 2)) < 0.015, err
    assert np.all(np.diff(got) >= -0.02 * whole.max())  # brighter away from the blocker
    # and per patch: the floor patches wholly in shadow or wholly lit are exact too
    hp, _ = photometry.irradiance(p, tracer)
    floor = np.flatnonzero(p.obj == 0)
    cx = p.corners(floor)[:, :, 0]
    dark, bright = floor[cx.max(axis=1) < 0.99], floor[cx.min(axis=1) > 3.01]
    assert len(dark) and len(bright)
    assert np.all(hp[dark] == 0.0)
    # (the patch mean by irradiance's degree-2 rule: 3e-5 off the exact mean on 0.5 m squares)
    np.testing.assert_allclose(hp[bright, 0], E * patch_mean(p.corners(bright), parallel_ff), rtol=1e-3)


def test_reflecting_walls_add_a_gathered_indirect_part():
    """Walls of rho 0.5 with a given B (the solution irradiance reads), black floor and ceiling:
    the floor's H is the exact direct part plus a non-negative indirect part, and agrees with a
    brute-force gather of 65,536 rays per patch reading B (emitters included) from uniform points
    of the patch (an estimate of the patch's mean H) within the two estimates' statistical error;
    its indirect part alone agrees with the brute force reading B - E."""
    p = black_room(floor_step=0.5, wall_step=0.5, wall_rho=0.5)
    walls = (p.obj >= 1) & (p.obj <= 4)
    c = p.centroid
    p.radiosity = p.emission.copy()
    p.radiosity[walls] += (1.0 + 0.5 * c[walls, 1] + 0.2 * c[walls, 0])[:, None] * [1.0, 0.8, 0.6]
    p.radiosity[p.emission[:, 0] > 0] += 0.7  # the panel reflects a little too (B - E = 0.7)
    tracer = Tracer.mesh(p)
    rays = 4096
    h, gathered = photometry.irradiance(p, tracer, rays=rays)
    floor = np.flatnonzero(p.obj == 0)
    assert gathered[floor].all() and not gathered[walls].any()
    direct = E * patch_mean(p.corners(floor), parallel_ff)
    indirect = h[floor] - direct[:, None]
    assert np.all(indirect >= -1e-9)
    assert np.all(indirect[:, 0] > 0.5)  # the walls do light the floor
    # brute force at a few patches: uniform points of the patch, cosine directions, reading B
    rng = np.random.default_rng(7)
    n = 1 << 16
    for i in floor[[0, 17, 35, 62]]:
        tri = p.corners([i])[0]
        s, t = np.sqrt(rng.random(n)), rng.random(n)
        x = tri[0] + (s * (1 - t))[:, None] * (tri[1] - tri[0]) + (s * t)[:, None] * (tri[2] - tri[0])
        r, phi = np.sqrt(rng.random(n)), 2 * math.pi * rng.random(n)
        d = np.column_stack([r * np.cos(phi), np.sqrt(1 - r * r), r * np.sin(phi)])  # about +y
        prim, _ = tracer.intersect(x + [0, 1e-6, 0], d)
        assert np.all(prim >= 0)  # a closed room
        seen, refl = p.radiosity[prim], (p.radiosity - p.emission)[prim]
        # irradiance's own gather: rays reading B - E (iid, an upper bound of its stratified error)
        sigma_new = refl.std(axis=0) / math.sqrt(rays)
        brute, sigma = seen.mean(axis=0), seen.std(axis=0) / math.sqrt(n)
        assert np.all(np.abs(h[i] - brute) < 4.0 * np.sqrt(sigma ** 2 + sigma_new ** 2)), (h[i], brute, sigma)
        # the indirect part alone, against the brute force reading B - E (far less noisy)
        j = np.searchsorted(floor, i)
        brute_r, sigma_r = refl.mean(axis=0), refl.std(axis=0) / math.sqrt(n)
        assert np.all(np.abs(indirect[j] - brute_r) < 4.0 * np.sqrt(sigma_r ** 2 + sigma_new ** 2)), (
            indirect[j], brute_r, sigma_r, sigma_new)


def lamp_floor(n, pitch=2.0, lamp=0.6, height=3.0):
    """An open floor of n x n square lamps (each its own object, facing down, at ``height``) over
    a black floor in 0.5 m squares: (Patches, the lamps' rectangles)."""
    size = n * pitch
    v, f = _grid((0, 0, 0), (0, 0, size), (size, 0, 0), 2 * n * round(pitch), 2 * n * round(pitch))
    verts, faces, obj, rects = [v], [f], [np.zeros(len(f), np.int64)], []
    base = len(v)
    for i in range(n):
        for j in range(n):
            x0, z0 = (i + 0.5) * pitch - lamp / 2, (j + 0.5) * pitch - lamp / 2
            v, f = _grid((x0, height, z0), (lamp, 0, 0), (0, 0, lamp), 1, 1)
            verts.append(v)
            faces.append(f + base)
            obj.append(np.full(len(f), 1 + len(rects)))
            base += len(v)
            rects.append((x0, x0 + lamp, z0, z0 + lamp))
    f, o = np.concatenate(faces), np.concatenate(obj)
    return Patches(vertices=np.concatenate(verts), faces=f, rho=np.zeros((len(f), 3)),
                   emission=np.where((o > 0)[:, None], E, 0.0) * np.ones(3), source=np.arange(len(f)), obj=o,
                   names=["floor/black"] + [f"lamp{i}/lamp" for i in range(len(rects))]), rects


@pytest.mark.parametrize("shared_cells", [False, True])
def test_many_lamps(monkeypatch, shared_cells):
    """36 lamps (at most EXACT_PAIRS): every lamp exact, no noise.  225 lamps (an open-plan floor,
    past EXACT_PAIRS): the near lamps exact, the far tail by next-event estimation, unbiased, and
    within a few percent at each point.  ``shared_cells``: the lamps' importance per cell of
    nearby points, not per point (what points x lights past IMPORTANCE_ENTRIES does): 200 cells
    for 400 points here, coarse cells (about 2 m) whose looser bounds cost some precision."""
    if shared_cells:
        monkeypatch.setattr(photometry, "IMPORTANCE_ENTRIES", 225 * 200)
    rms, top = (0.025, 0.12) if shared_cells else (0.015, 0.06)
    rng = np.random.default_rng(5)
    for n in (6, 15):
        p, rects = lamp_floor(n)
        assert len(photometry._Emitters(p)) == n * n
        size = 2.0 * n
        k = 400
        pts = np.column_stack([rng.uniform(0.1, size - 0.1, k), np.zeros(k), rng.uniform(0.1, size - 0.1, k)])
        truth = E * sum(parallel_ff(pts, *r) for r in rects)
        h, rays = photometry.direct_irradiance(p, Tracer.mesh(p), pts, np.tile([0.0, 1.0, 0.0], (k, 1)))
        err = h[:, 0] / truth - 1
        assert rays < k * (2 * photometry.RAYS_PER_POINT + photometry.EXACT_PAIRS)
        if n * n <= photometry.EXACT_PAIRS:
            assert np.abs(err).max() < 1e-9
        else:
            print(f"\n{n * n} lamps: rms {np.sqrt(np.mean(err ** 2)):.2%}, max {np.abs(err).max():.2%}")
            assert abs(err.mean()) < 0.003 and np.sqrt(np.mean(err ** 2)) < rms and np.abs(err).max() < top, (
                err.mean(), np.sqrt(np.mean(err ** 2)), np.abs(err).max())
    # patches too (each a point's cell of its own, or shared)
    floor = np.flatnonzero(p.obj == 0)[::7]
    hp, _ = photometry.direct_irradiance(p, Tracer.mesh(p), p.corners(floor), p.normal[floor])
    want = E * patch_mean(p.corners(floor), lambda x: sum(parallel_ff(x, *r) for r in rects))
    err = hp[:, 0] / want - 1
    print(f"patches: rms {np.sqrt(np.mean(err ** 2)):.2%}, max {np.abs(err).max():.2%}")
    assert abs(err.mean()) < 0.003 and np.sqrt(np.mean(err ** 2)) < rms, (err.mean(), np.sqrt(np.mean(err ** 2)))


@pytest.mark.parametrize("per_triangle", [False, True])
def test_l_shaped_panel_and_per_triangle_lights(monkeypatch, per_triangle):
    """The panel less its quarter x, z in [2, 2.5] (an L: one polygon of 6 triangles, sampled a
    triangle at a time; or, past lights.MAX_LOOP_VERTICES, a light per triangle) under the
    blocker: exact where lit, 0 in full shadow, the visible part's closed form in the penumbra."""
    from dcrad.transport import lights

    if per_triangle:
        monkeypatch.setattr(lights, "MAX_LOOP_VERTICES", 0)
    p = black_room(floor_step=0.5, wall_step=0.5, blocker=True, l_shaped=True)
    src = photometry._Emitters(p)
    assert len(src) == (6 if per_triangle else 1) and not src.para.any()
    squares = [(1.5, 2.0, 1.5, 2.0), (2.0, 2.5, 1.5, 2.0), (1.5, 2.0, 2.0, 2.5)]
    xs = np.linspace(0.05, 3.95, 60)
    pts = np.column_stack([xs, np.zeros(60), np.full(60, 2.3)])
    h, _ = photometry.direct_irradiance(p, Tracer.mesh(p), pts, np.tile([0.0, 1.0, 0.0], (60, 1)))
    whole = E * sum(parallel_ff(pts, *q) for q in squares)
    seen = np.zeros(60)
    for x0, x1, z0, z1 in squares:  # the part of each square seen past the blocker: x_p >= 3 - x/2
        lo = np.maximum(x0, 3.0 - xs / 2.0)
        some = lo < x1
        seen[some] += E * parallel_ff(pts[some], x0=lo[some], x1=x1, z0=z0, z1=z1)
    shadow, lit = xs < 0.99, xs > 3.01
    pen = ~shadow & ~lit
    assert np.all(h[shadow, 0] == 0.0)
    np.testing.assert_allclose(h[lit, 0], whole[lit], rtol=1e-9)
    err = (h[pen, 0] - seen[pen]) / whole[pen]
    # the penumbra's estimate: a light of several triangles spreads its rays thinner over its
    # shape than a parallelogram (about 1.8% rms here as one polygon, 0.8% as six lights with
    # twice the rays); unbiased either way
    rms, top = (0.015, 0.06) if per_triangle else (0.03, 0.15)
    assert abs(err.mean()) < 0.01 and np.sqrt(np.mean(err ** 2)) < rms and np.abs(err).max() < top, err


def test_the_work_plane_is_split_into_rooms_where_walls_part_it(tmp_path):
    """Two 4 x 4 m rooms side by side, a full wall between them, a lamp in one: the work plane
    reads two rooms of about 16 m^2 less their border zones, the lit one bright and the other dark
    (no light passes the wall), each with its own EN 12464-1 statistics; one room when the wall
    has gone."""
    from dcrad.config import SolverConfig
    from dcrad.outputs.photometry import workplane
    from dcrad.pipeline import prepare
    from dcrad.solving.passes import solve_to_accuracy
    from scenes.objwriter import ObjWriter

    def rooms(with_wall: bool):
        w = ObjWriter()
        w.material("wall", 0.5)
        w.material("lamp", 0.0, 100.0)
        for name, axis, value, facing, lo, hi in (
                ("floor", 1, 0.0, 1, (0, 0), (8, 4)), ("ceiling", 1, 3.0, -1, (0, 0), (8, 4)),
                ("wx0", 0, 0.0, 1, (0, 0), (3, 4)), ("wx1", 0, 8.0, -1, (0, 0), (3, 4)),
                ("wz0", 2, 0.0, 1, (0, 0), (8, 3)), ("wz1", 2, 4.0, -1, (0, 0), (8, 3))):
            w.begin(name, "wall")
            w.add_rect(axis, value, lo, hi, facing)
        if with_wall:
            w.begin("middle_a", "wall")
            w.add_rect(0, 4.0, (0, 0), (3, 4), -1)
            w.begin("middle_b", "wall")
            w.add_rect(0, 4.0, (0, 0), (3, 4), 1)
        w.begin("lamp", "lamp")
        w.add_rect(1, 2.95, (1.5, 1.5), (2.5, 2.5), -1)
        _, patches, _ = prepare(w.write(tmp_path / str(with_wall), "rooms"), 0.5, up="y")
        solve_to_accuracy(patches, SolverConfig(accuracy=0.1, seed=1))
        return workplane(patches, 0.8, spacing=0.25, tracer=Tracer.mesh(patches))

    split = rooms(True)
    assert len(split["rooms"]) == 2
    lit, dark = sorted(split["rooms"], key=lambda r: -r["E_avg_lux"])
    for room in (lit, dark):
        assert room["area_m2"] == pytest.approx(3.0 * 3.0, rel=0.1)  # 4 x 4 less a 0.5 m border all round
    assert lit["centre"][0] < 4.0 < dark["centre"][0]
    # (a few gather rays slip through the wall's edges in float32: 2e-5 of the lit room's light)
    assert lit["E_avg_lux"] > 10.0 and dark["E_max_lux"] < 1e-3 * lit["E_avg_lux"]
    assert 0.0 < lit["uniformity"] <= 1.0
    assert "rooms" not in rooms(False)  # one room: the whole work plane's statistics say it
