"""The exact direct gather's kernels (lights.form_factors, direct.pair_form_factors, light_pairs'
plane tests, _visibility's light points) against independent truths: closed forms, and the
formula they replaced written out again here as it was (einsum, np.cross and a
Sutherland-Hodgman gather for every point).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dcrad.pipeline import prepare, resolve_scene
from dcrad.transport import direct
from dcrad.transport.lights import form_factors, light_polygons, polygon_form_factor
from dcrad.transport.rays import Tracer


def _reference(x: np.ndarray, nx: np.ndarray, loops: np.ndarray, ny: np.ndarray) -> np.ndarray:
    """The form factor kernel as it was before it was written out per component (every point
    clipped to its horizon by Sutherland-Hodgman): the formula the new one must match."""
    p, w, _ = loops.shape
    u = loops - x[:, None, :]
    h = np.einsum("pvk,pk->pv", u, nx)
    inside = h > 0.0
    u_next = np.roll(u, -1, axis=1)
    h_next = np.roll(h, -1, axis=1)
    crossing = inside != np.roll(inside, -1, axis=1)
    t = h / np.where(crossing, h - h_next, 1.0)
    meet = u + t[..., None] * (u_next - u)
    pts = np.stack([u, meet], axis=2).reshape(p, 2 * w, 3)
    valid = np.stack([inside, crossing], axis=2).reshape(p, 2 * w)
    idx = np.maximum.accumulate(np.where(valid, np.arange(2 * w)[None, :], -1), axis=1)
    last = idx[:, -1]
    idx = np.where(idx < 0, last[:, None], idx)
    q = np.take_along_axis(pts, np.maximum(idx, 0)[..., None], axis=1)
    qn = np.roll(q, -1, axis=1)
    c = np.cross(q, qn)
    cn = np.sqrt(np.einsum("pvk,pvk->pv", c, c))
    theta = np.arctan2(cn, np.einsum("pvk,pvk->pv", q, qn))
    term = theta * np.einsum("pvk,pk->pv", c, nx) / np.where(cn > 0, cn, 1.0)
    ff = -term.sum(axis=1) / (2.0 * math.pi)
    front = np.einsum("pk,pk->p", x - loops[:, 0], ny) > 0.0
    return np.where((last >= 0) & front, ff, 0.0)


def _corner(a: float, b: float, height: float) -> float:
    """Closed form: a point at ``height`` under a corner of a parallel a x b rectangle."""
    a, b = a / height, b / height
    x, y = a / math.sqrt(1 + a * a), b / math.sqrt(1 + b * b)
    return (x * math.atan(b / math.sqrt(1 + a * a)) + y * math.atan(a / math.sqrt(1 + b * b))) / (2 * math.pi)


def _random_loops(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n planar loops of 5 slots (triangles and quads padded by their last vertex, convex and
    not, and pentagons) at random places and facings, counter-clockwise about their normal."""
    loops = np.empty((n, 5, 3))
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    e1 = np.cross(normal, rng.normal(size=(n, 3)))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(normal, e1)  # (e1, e2, normal) right-handed: angles grow counter-clockwise
    centre = rng.normal(size=(n, 3)) * 3.0
    kind = rng.integers(0, 4, size=n)
    for i in range(n):
        size = rng.uniform(0.05, 2.0)
        if kind[i] == 0:  # triangle
            ang = np.sort(rng.uniform(0, 2 * math.pi, 3))
            rad = np.full(3, size)
        elif kind[i] == 1:  # convex quad
            ang = np.sort(rng.uniform(0, 2 * math.pi, 4))
            rad = np.full(4, size)
        elif kind[i] == 2:  # a non-convex quad (a dart)
            ang = np.array([0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi]) + rng.uniform(0, 1)
            rad = size * np.array([1.0, 0.3, 1.0, 1.0])
        else:  # a star-shaped pentagon (angles apart by less than pi: simple)
            ang = 2 * math.pi * np.arange(5) / 5 + rng.uniform(0, 0.5, 5)
            rad = size * rng.uniform(0.3, 1.0, 5)
        pts = centre[i] + (rad * np.cos(ang))[:, None] * e1[i] + (rad * np.sin(ang))[:, None] * e2[i]
        loops[i] = np.concatenate([pts, np.repeat(pts[-1:], 5 - len(pts), axis=0)])
    return loops, normal


def test_form_factors_match_the_formula_they_replace():
    """form_factors (per component, clipping only where the horizon cuts the outline) against the
    old kernel on random points, facings and loops: triangles, quads, darts, pentagons, lights
    wholly above, cut by and below the horizon, behind their plane, near and 100x farther off.
    Agreement: 1e-9 of the light's form factor, relative, past 1e-15 absolute (the float
    order differs; the two agree to round-off: ~1e-14 here)."""
    rng = np.random.default_rng(7)
    n, m = 3000, 6
    loops, ny = _random_loops(rng, n)
    far = rng.random(n) < 0.3
    loops[far] *= 100.0
    x = rng.normal(size=(n, m, 3))
    nx = rng.normal(size=(n, 3))
    nx /= np.linalg.norm(nx, axis=1, keepdims=True)
    got = form_factors(x, nx, loops, ny)
    want = np.stack([_reference(x[:, j], nx, loops, ny) for j in range(m)], axis=1)
    # every case is there: nothing to clip, clipped, nothing above, behind the light
    h = np.einsum("pvk,pk->pv", loops, nx)[:, None, :] - np.einsum("pmk,pk->pm", x, nx)[:, :, None]
    above = (h > 0).sum(axis=2)
    assert (above == 5).sum() > 1000 and ((above > 0) & (above < 5)).sum() > 1000 and (above == 0).sum() > 1000
    assert (want == 0).sum() > 3000 and (want > 1e-3).sum() > 2000 and (want < 0).sum() == 0
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-15)
    # the one-point form is the same kernel
    np.testing.assert_array_equal(polygon_form_factor(x[:, 2], nx, loops, ny), got[:, 2])


def test_form_factors_against_the_closed_form_of_a_parallel_rectangle():
    """Points at several places and heights under a parallel rectangle (Lambert's corner formula,
    by inclusion-exclusion over the four corner rectangles for a point outside it): 1e-12."""
    rect = np.array([[0.0, 0.0, 0.0], [0.0, 2.0, 0.0], [1.5, 2.0, 0.0], [1.5, 0.0, 0.0]])  # ccw about -z
    pts = [(0.3, 0.5, -1.0), (0.0, 0.0, -0.5), (-0.7, 0.4, -2.0), (2.5, -1.0, -0.3), (0.75, 1.0, -10.0),
           (0.75, 1.0, -1e-3)]

    def closed(px: float, py: float, hz: float) -> float:
        def signed(ax: float, ay: float) -> float:  # the rectangle from the foot (px,py) to (ax,ay)
            if ax == px or ay == py:
                return 0.0
            return math.copysign(1.0, (ax - px) * (ay - py)) * _corner(abs(ax - px), abs(ay - py), hz)

        return signed(1.5, 2.0) - signed(0.0, 2.0) - signed(1.5, 0.0) + signed(0.0, 0.0)

    x = np.array(pts)[None]
    f = form_factors(x, np.array([[0.0, 0.0, 1.0]]), rect[None], np.array([[0.0, 0.0, -1.0]]))[0]
    for j, (px, py, pz) in enumerate(pts):
        assert f[j] == pytest.approx(closed(px, py, -pz), rel=1e-12, abs=1e-15), (j, pts[j])


@pytest.fixture(scope="module")
def office(tmp_path_factory):
    """The 2x2 office (lamps of four rooms, doorways), its lights, receivers and their pairs."""
    _, p, _ = prepare(resolve_scene("office:rows=2,cols=2", tmp_path_factory.mktemp("office")), 0.2)
    em = np.flatnonzero(p.emission.any(axis=1))
    power = p.emission[em] * p.area[em, None]
    lights = light_polygons(p, em, power)
    assert lights is not None
    rec = np.flatnonzero(p.rho.any(axis=1))
    return p, em, power, lights, rec


def _old_rotated(p, lights, rec, light, u):
    """pair_form_factors as it was: the three rotated points of each half one at a time."""
    v = p.vertices
    f = p.faces[rec]
    corners = (v[f[:, 0]], v[f[:, 1]], v[f[:, 2]])
    ff = np.zeros((len(rec), 2))
    for h in range(2):
        s = np.sqrt(u[:, h, 0])
        bary = (1.0 - s, s * (1.0 - u[:, h, 1]), s * u[:, h, 1])
        for k in range(3):
            b = (bary[k % 3], bary[(k + 1) % 3], bary[(k + 2) % 3])
            x = b[0][:, None] * corners[0] + b[1][:, None] * corners[1] + b[2][:, None] * corners[2]
            ff[:, h] += _reference(x, p.normal[rec], lights.loops[light], lights.normal[light]) / 3.0
    return np.maximum(ff, 0.0)


def test_pair_form_factors_match_the_old_kernel_on_the_office(office):
    """Every (receiver, light) pair of the 2x2 office: the two halves' three-point means and the
    centroid form factor as the old code computed them, to 1e-9 relative (one loop a light)."""
    p, _, _, lights, rec = office
    slot, light, _, _ = direct.light_pairs(p, lights, rec, np.random.default_rng(3))
    r = rec[slot]
    assert np.all(np.bincount(lights.loop_light) == 1) and len(r) > 10_000
    got = direct.pair_form_factors(p, lights, r, light, np.random.default_rng(5))
    want = _old_rotated(p, lights, r, light, np.random.default_rng(5).random((len(r), 2, 2)))
    assert (want > 0).mean() > 0.9
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-15)
    f0 = direct._pair_form_factors(p, lights, r, light, None)[:, 0]
    np.testing.assert_allclose(f0, np.maximum(_reference(p.centroid[r], p.normal[r], lights.loops[light],
                                                         lights.normal[light]), 0.0), rtol=1e-9, atol=1e-15)


def test_light_pairs_cell_bounds_change_no_pair(office):
    """The light lists' per-cell bounds settle most plane tests (``sure``); the pairs, halves and
    weights are exactly those of testing every pair."""
    p, _, _, lights, rec = office
    lists = direct.light_lists(p, lights, rec)
    assert lists.sure is not None and 0.5 < lists.sure.mean() < 1.0
    got = direct.light_pairs(p, lights, rec, np.random.default_rng(11), lists)
    lists.sure = None
    want = direct.light_pairs(p, lights, rec, np.random.default_rng(11), lists)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)


def test_visibility_samples_lights_uniformly_both_ways(office):
    """_visibility's light points, a parallelogram light as a whole or (marked otherwise) a
    triangle by area then a point on it, in one batch: for an unoccluded receiver the mean of
    A_L G over its rays is the exact form factor (Lambert), within 1%."""
    p, em, _, lights, rec = office
    tracer = Tracer(p.triangles)
    floor = rec[np.flatnonzero(p.normal[rec, 2] > 0.99)]
    pick = floor[np.random.default_rng(1).choice(len(floor), 40, replace=False)]
    f = direct._pair_form_factors(p, lights, pick, np.zeros(len(pick), np.int64), None)[:, 0]
    pick = pick[f > 1e-3][:6]
    light = np.zeros(len(pick), np.int64)
    exact = direct._pair_form_factors(p, lights, pick, light, None)[:, 0]
    para = lights.parallelogram.copy()
    try:
        for flag in (True, False):
            lights.parallelogram[0] = flag
            rows = np.repeat(pick, 2)
            counts = np.full(len(rows), 40_000)
            num, den, vis, traced = direct._visibility(p, tracer, lights, em, rows, np.repeat(light, 2), counts,
                                                       np.random.default_rng(2), 1e-6 * p.scale, 1 << 16)
            est = (lights.area[0] * den / counts).reshape(-1, 2).mean(axis=1)
            # a receiver's own point average of F is its centroid's F to within its curvature
            np.testing.assert_allclose(est, exact, rtol=1e-2)
    finally:
        lights.parallelogram[:] = para


def test_probe_grid_bitmaps_and_sets_mark_the_same_neighbourhoods(office, monkeypatch):
    """The pilot's findings as bit-packed maps (dense) and as sorted sets of spread codes: each
    marks exactly the codes within one grid cell per axis of a marked one, same light (a
    boolean (cells, lights) grid dilated by hand is the truth), for 13 lights (two bytes a
    cell, the second partly used) and marks that repeat."""
    p, _, _, _, rec = office
    rng = np.random.default_rng(4)
    n_l = 13  # two bytes a cell, the second partly used
    for dense in (True, False):
        monkeypatch.setattr(direct, "DENSE_CODES", 1 << 40 if dense else 0)
        grid = direct._ProbeGrid(p, rec, n_l)
        grid.start(2)
        assert grid.dense == dense
        d = tuple(int(x) for x in grid.dims)
        truth = np.zeros((2,) + d + (n_l,), bool)
        for flag in range(2):
            for _ in range(3):  # several runs of marks, some codes twice
                rows = rng.choice(rec, 200)
                lt = rng.integers(0, n_l, 200)
                cells = grid.cells(rows)
                grid.mark(flag, np.concatenate([grid.code(cells, lt), grid.code(cells[:50], lt[:50])]))
                for (a, b, c), light in zip(cells, lt):
                    truth[flag, a - 1:a + 2, b - 1:b + 2, c - 1:c + 2, light] = True
        grid.finish()
        every = np.stack(np.meshgrid(*[np.arange(1, x - 1) for x in d], indexing="ij"), axis=-1).reshape(-1, 3)
        for flag in range(2):
            lt = rng.integers(0, n_l, len(every))
            got = grid.near(flag, grid.code(every, lt))
            want = truth[flag, every[:, 0], every[:, 1], every[:, 2], lt]
            assert want.any() and not want.all()
            np.testing.assert_array_equal(got, want)
