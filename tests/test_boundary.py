"""Boundaries, direction bins, portal cells, twin buffers and the barrier transfer."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from dcrad.division.boundary import Boundary, TwinBuffer, coarsen_directions, direction_levels, make_boundary, transfer
from dcrad.errors import ExchangeError, PartitionError
from dcrad.transport.sampling import concentric_disk, cosine_hemisphere

AXES = [0, 1, 2]


def boundary(axis=2, solid=6, cells=(3, 4), bid=7):
    return Boundary(
        id=bid, axis=axis, offset=1.25, lo=(-1.0, 0.5), hi=(2.0, 2.5),
        side_a=0, side_b=1, cells=cells, solid=solid,
    )


def polar_cosine(rng, m):
    """Independent cosine sampler around +z (Malley on the polar disk map, not the concentric one)."""
    r = np.sqrt(rng.random(m))
    phi = 2 * np.pi * rng.random(m)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - r * r)])


def to_world(b: Boundary, local: np.ndarray, sign: float) -> np.ndarray:
    t, bb, n = b.frame
    return local[:, :1] * t + local[:, 1:2] * bb + sign * local[:, 2:] * n


# -- geometry -------------------------------------------------------------------


@pytest.mark.parametrize("axis", AXES)
def test_frame_and_triangles(axis):
    b = boundary(axis)
    t, bb, n = b.frame
    assert np.allclose(np.cross(t, bb), n) and np.allclose(n, b.normal)
    tri = b.triangles()
    assert tri.shape == (2, 3, 3)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(normals @ n > 0)  # front faces +n
    assert np.isclose(0.5 * np.linalg.norm(normals, axis=1).sum(), b.area)
    assert np.all(tri[..., axis] == b.offset)


def test_make_boundary_cells():
    b = make_boundary(3, 0, 0.0, (0.0, 0.0), (1.0, 0.3), 2, 5, cell_size=0.1, solid=4)
    assert b.cells == (10, 3) and b.n_cells == 30 and b.n_bins == 16
    b = make_boundary(3, 0, 0.0, (0.0, 0.0), (1.05, 0.01), 2, 5, cell_size=0.1, solid=4)
    assert b.cells == (11, 1)
    with pytest.raises(PartitionError):
        make_boundary(3, 0, 0.0, (0.0, 0.0), (1.0, 1.0), 2, 2, cell_size=0.1, solid=4)
    with pytest.raises(PartitionError):
        make_boundary(3, 0, 0.0, (1.0, 0.0), (1.0, 1.0), 2, 3, cell_size=0.1, solid=4)


# -- direction bins -------------------------------------------------------------


@pytest.mark.parametrize("axis", AXES)
def test_every_direction_has_one_bin(axis):
    rng = np.random.default_rng(1)
    b = boundary(axis, solid=5)
    d = rng.normal(size=(50_000, 3))
    d = np.vstack([d, np.eye(3), -np.eye(3), [[1, 1, 0], [0, 0, 0]]])  # poles, grazing, zero
    k = b.bin_of(d)
    assert k.dtype == np.int64 and k.shape == (len(d),)
    assert k.min() >= 0 and k.max() < b.n_bins
    assert set(np.unique(k[:50_000])) == set(range(b.n_bins))
    cr = b.crossing(d)
    assert np.all(cr[d[:, axis] > 0] == 0) and np.all(cr[d[:, axis] < 0] == 1)


@pytest.mark.parametrize("axis", AXES)
@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize("sampler", ["polar", "concentric"])
def test_bins_equal_projected_solid_angle_chi2(axis, sign, sampler):
    """Cosine-distributed directions fill the bins uniformly: chi-square at p = 0.001."""
    rng = np.random.default_rng(20240601 + axis)
    b = boundary(axis, solid=8)
    m = 128_000
    local = polar_cosine(rng, m) if sampler == "polar" else cosine_hemisphere(rng.random((m, 2)))
    d = to_world(b, local, sign)
    assert np.all(b.crossing(d) == (0 if sign > 0 else 1))
    counts = np.bincount(b.bin_of(d), minlength=b.n_bins)
    expected = m / b.n_bins
    chi2 = ((counts - expected) ** 2 / expected).sum()
    threshold = stats.chi2.ppf(0.999, b.n_bins - 1)  # about 103.4 for 63 degrees of freedom
    assert chi2 < threshold, (chi2, threshold)


@pytest.mark.parametrize("solid", [1, 3, 8])
def test_bins_equal_projected_solid_angle_analytic(solid):
    """Each bin's square cell maps to a disk region of area pi / solid^2 (its projected solid angle)."""
    edge = np.linspace(0.0, 1.0, 257)[:-1]
    # the boundary of the unit square cell, counter-clockwise, as (p, 2) offsets in [0,1]^2
    path = np.vstack([
        np.column_stack([edge, 0 * edge]), np.column_stack([1 + 0 * edge, edge]),
        np.column_stack([1 - edge, 1 + 0 * edge]), np.column_stack([0 * edge, 1 - edge]),
    ])
    i0, i1 = np.divmod(np.arange(solid * solid), solid)
    corners = (np.stack([i0, i1], 1)[:, None, :] + path[None]) / solid  # (bins, p, 2)
    disk = concentric_disk(corners.reshape(-1, 2)).reshape(corners.shape)
    x, y = disk[..., 0], disk[..., 1]
    area = 0.5 * np.abs((x * np.roll(y, -1, 1) - np.roll(x, -1, 1) * y).sum(axis=1))
    assert np.allclose(area, np.pi / solid**2, rtol=2e-4)
    assert np.isclose(area.sum(), np.pi, rtol=1e-4)
    # and the bin centres map back to their own bins, on both sides
    b = boundary(2, solid=solid)
    c = concentric_disk((np.stack([i0, i1], 1) + 0.5) / solid)
    z = np.sqrt(1 - (c**2).sum(1))
    for s in (1, -1):
        d = np.column_stack([c, s * z])
        assert np.array_equal(b.bin_of(d), np.arange(solid * solid))


@pytest.mark.parametrize("axis", AXES)
def test_same_world_direction_same_bin_both_sides(axis):
    rng = np.random.default_rng(5)
    b = boundary(axis, solid=7)
    d = rng.normal(size=(20_000, 3))
    d[:, axis] = np.abs(d[:, axis]) + 1e-3  # A -> B
    # recorded on side A: bin_of(d); re-emitted on side B: sample() in that bin must reproduce it
    k = b.bin_of(d)
    mirror = d * np.where(np.arange(3) == axis, -1.0, 1.0)
    assert np.array_equal(b.bin_of(mirror), k)  # same (t, b) frame on both hemispheres
    assert np.all(b.crossing(d) == 0) and np.all(b.crossing(mirror) == 1)
    # a twin boundary built for the neighbour (same plane, same sides) bins identically
    twin = make_boundary(b.id, axis, b.offset, b.lo, b.hi, b.side_a, b.side_b, 0.5, 7)
    assert np.array_equal(twin.bin_of(d), k)


@pytest.mark.parametrize("axis", AXES)
@pytest.mark.parametrize("crossing", [0, 1])
def test_sample_round_trip_every_cell_and_bin(axis, crossing):
    rng = np.random.default_rng(11 + axis)
    b = boundary(axis, solid=6, cells=(3, 4))
    reps = 8
    cell = np.repeat(np.arange(b.n_cells), b.n_bins * reps)
    bn = np.tile(np.repeat(np.arange(b.n_bins), reps), b.n_cells)
    cr = np.full(len(cell), crossing, np.int8)
    u = 0.001 + 0.998 * rng.random((len(cell), 4))
    o, d = b.sample(cell, bn, cr, u)
    assert o.dtype == np.float64 and d.dtype == np.float64 and o.shape == d.shape == (len(cell), 3)
    assert np.all(o[:, axis] == b.offset)  # exactly on the plane
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.all(d[:, axis] > 0) if crossing == 0 else np.all(d[:, axis] < 0)
    assert np.array_equal(b.crossing(d), cr)
    assert np.array_equal(b.bin_of(d), bn)
    assert np.array_equal(b.cell_of(o), cell)
    # origins inside the rectangle and inside their portal cell's sub-rectangle
    uax, vax = b.uv
    iu, iv = np.divmod(cell, b.cells[1])
    du = (b.hi[0] - b.lo[0]) / b.cells[0]
    dv = (b.hi[1] - b.lo[1]) / b.cells[1]
    assert np.all((o[:, uax] >= b.lo[0] + iu * du - 1e-12) & (o[:, uax] <= b.lo[0] + (iu + 1) * du + 1e-12))
    assert np.all((o[:, vax] >= b.lo[1] + iv * dv - 1e-12) & (o[:, vax] <= b.lo[1] + (iv + 1) * dv + 1e-12))


def test_sample_float32_matches_float64():
    rng = np.random.default_rng(3)
    b = boundary(1, solid=4)
    m = 10_000
    cell, bn = rng.integers(0, b.n_cells, m), rng.integers(0, b.n_bins, m)
    u = rng.random((m, 4))
    o64, d64 = b.sample(cell, bn, np.zeros(m, np.int8), u)
    o32, d32 = b.sample(cell, bn, np.zeros(m, np.int8), u.astype(np.float32))
    assert d32.dtype == np.float64
    # tangent components agree to float32 precision; the normal one near grazing is
    # sqrt(1 - r^2) and amplifies that, but the angle between the two stays tiny
    uax, vax = b.uv
    assert np.allclose(d32[:, [uax, vax]], d64[:, [uax, vax]], atol=1e-6)
    assert np.all(np.linalg.norm(np.cross(d32, d64), axis=1) < 1e-4)
    assert np.allclose(o32, o64, atol=1e-5)
    assert np.allclose(np.linalg.norm(d32, axis=1), 1.0)


@pytest.mark.parametrize("crossing", [0, 1])
def test_sample_is_cosine_distributed_over_hemisphere(crossing):
    rng = np.random.default_rng(99)
    b = boundary(0, solid=5)
    m = 200_000
    cell, bn = rng.integers(0, b.n_cells, m), rng.integers(0, b.n_bins, m)
    o, d = b.sample(cell, bn, np.full(m, crossing), rng.random((m, 4)))
    cos = d @ b.normal * (1 if crossing == 0 else -1)
    assert np.all(cos >= 0)
    # E[cos] = 2/3 for a cosine density; std of the mean ~ sqrt(1/18 / m) = 5e-4
    assert abs(cos.mean() - 2 / 3) < 3e-3
    # cos^2 is uniform on [0, 1] under a cosine density
    assert stats.kstest(cos**2, "uniform").pvalue > 1e-3
    # and origins cover the rectangle uniformly (area fractions of the portal grid)
    counts = np.bincount(b.cell_of(o), minlength=b.n_cells)
    assert np.allclose(counts / m, 1 / b.n_cells, rtol=0.05)


@pytest.mark.parametrize("solid", [6, 8])
def test_sample_from_a_block_of_bins_is_uniform_over_its_bins(solid):
    """A level-l block: every direction falls in one of the block's bins (cut at the square's
    edge for solid 6), equally often (equal projected solid angle)."""
    b = boundary(axis=1, solid=solid)
    rng = np.random.default_rng(3)
    for level, corner in ((1, (2, 4)), (2, (4, 4)), (direction_levels(solid) - 1, (0, 0))):
        m = 40000
        start = corner[0] * solid + corner[1]
        _, d = b.sample(np.zeros(m, np.int64), np.full(m, start), np.zeros(m, np.int8), rng.random((m, 4)),
                        np.full(m, level))
        i0, i1 = np.divmod(b.bin_of(d), solid)
        span = 1 << level
        inside = (i0 >= corner[0]) & (i0 < corner[0] + span) & (i1 >= corner[1]) & (i1 < corner[1] + span)
        assert inside.all()
        expected = {(a, c) for a in range(corner[0], min(corner[0] + span, solid))
                    for c in range(corner[1], min(corner[1] + span, solid))}
        counts = np.bincount(i0 * solid + i1, minlength=solid * solid)[[a * solid + c for a, c in expected]]
        assert stats.chisquare(counts).pvalue > 1e-4


def test_coarsen_directions_keeps_strong_bins_and_sums_weak_ones():
    solid = 8
    # boundary 0, crossing 0, cell 5: one strong bin, three weak ones in one 2x2 block,
    # and weak ones scattered; cell 6: a + and a - that cancel; cell 9 (crossing 1): one weak entry
    bins = np.array([0 * 8 + 0, 2 * 8 + 2, 2 * 8 + 3, 3 * 8 + 3, 7 * 8 + 7, 6 * 8 + 0, 1, 2, 5])
    cell = np.array([5, 5, 5, 5, 5, 5, 6, 6, 9])
    crossing = np.array([0, 0, 0, 0, 0, 0, 0, 0, 1])
    power = np.array([5.0, 0.4, 0.4, 0.4, 0.1, 0.2, 0.7, -0.7, 0.01])[:, None] * np.ones(3) / 3
    group, g = coarsen_directions(np.zeros(9), crossing, cell, bins, power, solid, threshold=1.0)
    assert (group >= 0).all()
    # exact: every group holds the sum of its members, and nothing else
    for k in range(len(g["bin"])):
        assert np.allclose(g["power"][k], power[group == k].sum(axis=0), rtol=0, atol=1e-15)
    # the strong bin stays on its own, at level 0
    k0 = group[0]
    assert (group == k0).sum() == 1 and g["level"][k0] == 0 and g["bin"][k0] == 0
    # the three weak bins of the block (2..3, 2..3) sum to 1.2 >= 1: one level-1 group
    k1 = group[1]
    assert set(np.flatnonzero(group == k1)) == {1, 2, 3} and g["level"][k1] == 1 and g["bin"][k1] == 2 * 8 + 2
    # weak leftovers climb to the whole hemisphere of their cell and crossing
    top = direction_levels(solid) - 1
    for i in (4, 5, 8):
        assert g["level"][group[i]] == top and g["bin"][group[i]] == 0
    assert group[4] == group[5] and group[4] != group[8]
    # + and - in one cell cancel into one group with no power
    assert group[6] == group[7] and np.allclose(g["power"][group[6]], 0)
    assert all(g["cell"][group[i]] == cell[i] and g["crossing"][group[i]] == crossing[i] for i in range(9))


def test_coarsen_directions_empty_and_one_bin():
    group, g = coarsen_directions([], [], [], [], np.zeros((0, 3)), 8, 1.0)
    assert len(group) == 0 and g["power"].shape == (0, 3)
    group, g = coarsen_directions([1], [0], [2], [0], np.array([[1e-9] * 3]), 1, 1.0)
    assert group.tolist() == [0] and g["level"].tolist() == [0]


def test_cell_of_clamps():
    b = boundary(2, cells=(3, 4))
    p = np.array([[-5.0, -5.0, 1.25], [5.0, 5.0, 1.25], [-1.0, 0.5, 1.25], [2.0, 2.5, 1.25]])
    assert b.cell_of(p).tolist() == [0, 11, 0, 11]


def test_sample_rejects_bad_indices():
    b = boundary()
    u = np.zeros((1, 4))
    with pytest.raises(ExchangeError):
        b.sample([b.n_cells], [0], [0], u)
    with pytest.raises(ExchangeError):
        b.sample([0], [-1], [0], u)


# -- twin buffers -----------------------------------------------------------------


def random_entries(rng, m, n_bid=3, n_cells=50, n_bins=36):
    return (
        rng.integers(0, n_bid, m), rng.integers(0, 2, m).astype(np.int8),
        rng.integers(0, n_cells, m), rng.integers(0, n_bins, m), rng.random((m, 3)),
    )


def test_twin_buffer_add_accumulates_sparse_and_sorted():
    rng = np.random.default_rng(0)
    buf = TwinBuffer(max_cells=10**6, max_bins=4096)
    bid, cr, cell, bn, p = random_entries(rng, 5000)
    buf.add(bid[:2500], cr[:2500], cell[:2500], bn[:2500], p[:2500])
    buf.add(bid[2500:], cr[2500:], cell[2500:], bn[2500:], p[2500:])
    assert np.all(np.diff(buf.keys) > 0)
    # only touched entries are stored: as many as distinct (bid, crossing, cell, bin)
    distinct = {tuple(x) for x in np.column_stack([bid, cr, cell, bn]).tolist()}
    assert len(buf) == len(distinct)
    assert np.allclose(buf.total(), p.sum(axis=0), rtol=1e-13, atol=0)
    # each entry holds the sum of its rows
    eb, ec, ecell, ebin, ep = buf.entries()
    assert eb.dtype == np.int64 and ec.dtype == np.int8 and ep.dtype == np.float64
    ref = {}
    for row, pw in zip(np.column_stack([bid, cr, cell, bn]).tolist(), p):  # reference, test only
        ref[tuple(row)] = ref.get(tuple(row), 0) + pw
    got = {tuple(r): w for r, w in zip(np.column_stack([eb, ec, ecell, ebin]).tolist(), ep)}
    assert got.keys() == ref.keys()
    assert all(np.allclose(got[k], ref[k], rtol=1e-13) for k in ref)
    # scalar boundary id / crossing broadcast
    one = TwinBuffer(100, 16)
    one.add(4, 1, np.array([3, 3, 5]), np.array([2, 2, 0]), np.ones((3, 3)))
    assert len(one) == 2 and np.array_equal(one.entries()[0], [4, 4])
    assert np.array_equal(one.power, [[2, 2, 2], [1, 1, 1]])


def test_twin_buffer_nbytes_grows_with_entries_not_grid():
    small = TwinBuffer(max_cells=16, max_bins=16)
    huge = TwinBuffer(max_cells=2**24, max_bins=2**12)
    assert small.nbytes() == huge.nbytes() == 0
    for buf in (small, huge):
        buf.add(0, 0, np.arange(10), np.arange(10), np.ones((10, 3)))
    assert small.nbytes() == huge.nbytes() == 10 * (8 + 3 * 8)
    huge.add(1, 1, np.arange(10), np.arange(10), np.ones((10, 3)))
    assert huge.nbytes() == 20 * 32
    # zero power creates nothing
    huge.add(2, 0, [1], [1], np.zeros((1, 3)))
    assert len(huge) == 20


def test_twin_buffer_merge_take_drain_conserve():
    rng = np.random.default_rng(4)
    a, b = TwinBuffer(64, 64), TwinBuffer(64, 64)
    a.add(*random_entries(rng, 3000))
    b.add(*random_entries(rng, 2000))
    ta, tb = a.total(), b.total()
    a.merge(b)
    assert np.allclose(a.total(), ta + tb, rtol=1e-13, atol=0)
    assert np.all(np.diff(a.keys) > 0)
    # merge across different packings repacks
    c = TwinBuffer(1000, 100)
    c.merge(a)
    assert np.allclose(c.total(), a.total(), rtol=1e-13, atol=0) and len(c) == len(a)
    assert all(np.array_equal(x, y) for x, y in zip(c.entries(), a.entries()))

    before, n = a.total(), len(a)
    taken = a.take(np.arange(0, n, 3))
    assert len(taken) + len(a) == n
    assert np.allclose(taken.total() + a.total(), before, rtol=1e-13, atol=0)
    assert np.all(np.diff(taken.keys) > 0) and np.all(np.diff(a.keys) > 0)
    mask = a.entries()[1] == 1
    taken2 = a.take(mask)
    assert np.all(taken2.entries()[1] == 1) and np.all(a.entries()[1] == 0)
    rest = a.drain()
    assert len(a) == 0 and a.nbytes() == 0 and np.all(a.total() == 0)
    assert np.allclose(rest.total() + taken.total() + taken2.total(), before, rtol=1e-13, atol=0)


def test_twin_buffer_arrays_round_trip():
    rng = np.random.default_rng(8)
    buf = TwinBuffer(200, 49)
    buf.add(*random_entries(rng, 1000, n_cells=200, n_bins=49))
    d = buf.to_arrays()
    assert d["keys"].dtype == np.int64 and d["power"].dtype == np.float64
    back = TwinBuffer.from_arrays(d)
    assert np.array_equal(back.keys, buf.keys) and np.array_equal(back.power, buf.power)
    assert (back.max_cells, back.max_bins) == (200, 49)
    bad = dict(d, keys=d["keys"][::-1].copy())
    with pytest.raises(ExchangeError):
        TwinBuffer.from_arrays(bad)
    with pytest.raises(ExchangeError):
        TwinBuffer.from_arrays(dict(d, power=d["power"][:-1]))
    with pytest.raises(ExchangeError):
        TwinBuffer.from_arrays({"keys": d["keys"]})


def test_twin_buffer_limits():
    buf = TwinBuffer(max_cells=2**20, max_bins=2**12)
    assert buf.max_boundary_id == (2**63 - 1) // (2 * 2**32) - 1  # about 1.07e6 boundaries
    buf.add(buf.max_boundary_id, 1, 2**20 - 1, 2**12 - 1, np.ones((1, 3)))
    assert 0 < buf.keys[0] <= 2**63 - 1
    assert buf.entries()[0][0] == buf.max_boundary_id  # no wrap-around
    for args in [
        (buf.max_boundary_id + 1, 0, 0, 0), (-1, 0, 0, 0), (0, 2, 0, 0),
        (0, 0, 2**20, 0), (0, 0, 0, 2**12),
    ]:
        with pytest.raises(ExchangeError):
            buf.add(*args, np.ones((1, 3)))
    with pytest.raises(ExchangeError):
        TwinBuffer(max_cells=2**40, max_bins=2**30)
    with pytest.raises(ExchangeError):
        buf.add(0, 0, [0, 1], [0, 1, 2], np.ones((3, 3)))
    with pytest.raises(ExchangeError):
        buf.add(0, 0, 0, 0, np.array([[np.nan, 0, 0]]))


# -- transfer -----------------------------------------------------------------------


def three_cells():
    """Cells 0 | 1 | 2 along x with boundaries 10 (0|1) and 11 (1|2), and 12 (1 below 3 along z)."""
    return [
        Boundary(10, 0, 1.0, (0.0, 0.0), (1.0, 1.0), 0, 1, (2, 2), 4),
        Boundary(11, 0, 2.0, (0.0, 0.0), (1.0, 1.0), 1, 2, (3, 3), 4),
        Boundary(12, 2, 1.0, (1.0, 0.0), (2.0, 1.0), 1, 3, (2, 5), 6),
    ]


def test_transfer_moves_and_conserves():
    rng = np.random.default_rng(21)
    bs = three_cells()
    inc = {c: TwinBuffer(16, 64) for c in range(4)}
    m = 400
    # cell 0 records A->B on 10; cell 1 records B->A on 10, A->B on 11 and 12; 2 B->A on 11; 3 B->A on 12
    plan = {0: [(10, 0)], 1: [(10, 1), (11, 0), (12, 0)], 2: [(11, 1)], 3: [(12, 1)]}
    by_id = {b.id: b for b in bs}
    for c, items in plan.items():
        for bid, cr in items:
            b = by_id[bid]
            cells, bins = rng.integers(0, b.n_cells, m), rng.integers(0, b.n_bins, m)
            inc[c].add(bid, cr, cells, bins, rng.random((m, 3)))
    recorded = sum(buf.total() for buf in inc.values())
    snapshot = {c: (buf.keys.copy(), buf.power.copy()) for c, buf in inc.items()}
    out = transfer(inc, bs)
    assert set(out) == {0, 1, 2, 3}
    assert np.allclose(sum(buf.total() for buf in out.values()), recorded, rtol=1e-13, atol=0)
    # incoming untouched
    for c, (k, p) in snapshot.items():
        assert np.array_equal(inc[c].keys, k) and np.array_equal(inc[c].power, p)
    # who gets what: exactly the entries recorded by the other side, same cell and bin
    expect = {1: [(0, 10, 0)], 0: [(1, 10, 1)], 2: [(1, 11, 0)], 3: [(1, 12, 0)]}
    expect[1] += [(2, 11, 1), (3, 12, 1)]
    for dst, sources in expect.items():
        got = out[dst].entries()
        rows = set()
        for src, bid, cr in sources:
            eb, ec, ecell, ebin, ep = inc[src].entries()
            sel = (eb == bid) & (ec == cr)
            rows |= {(bid, cr, a, b_, *w) for a, b_, w in zip(ecell[sel], ebin[sel], map(tuple, ep[sel]))}
        have = {(b_, c_, a, k, *w) for b_, c_, a, k, w in zip(*got[:4], map(tuple, got[4]))}
        assert have == rows
        # crossing 0 arrives on side B, crossing 1 on side A
        for bid, cr in zip(*got[:2]):
            b = by_id[int(bid)]
            assert dst == (b.side_b if cr == 0 else b.side_a)


def test_transfer_rejects_bad_entries():
    bs = three_cells()
    one = np.ones((1, 3))

    def single(cell, bid, cr, pc=0, bn=0):
        buf = TwinBuffer(16, 64)
        buf.add(bid, cr, pc, bn, one)
        return {cell: buf}

    with pytest.raises(ExchangeError, match="unknown boundary"):
        transfer(single(0, 99, 0), bs)
    with pytest.raises(ExchangeError, match="wrong side"):
        transfer(single(1, 10, 0), bs)  # A->B on 10 must come from cell 0
    with pytest.raises(ExchangeError, match="wrong side"):
        transfer(single(0, 10, 1), bs)  # B->A on 10 must come from cell 1
    with pytest.raises(ExchangeError, match="wrong side"):
        transfer(single(2, 10, 0), bs)  # cell 2 does not touch boundary 10
    with pytest.raises(ExchangeError):
        transfer(single(0, 10, 0, pc=4), bs)  # boundary 10 has 4 portal cells
    with pytest.raises(ExchangeError):
        transfer(single(0, 10, 0, bn=16), bs)  # and 16 bins
    assert transfer({}, bs).keys() == {0, 1, 2, 3}
    assert all(len(b) == 0 for b in transfer({0: TwinBuffer(4, 4)}, bs).values())


def test_transfer_rays_routes_every_ray_once_to_the_far_side():
    """Exact forwarding: each recorded ray goes, unchanged, to the cell across its boundary;
    a million rays of random power pass the power check (summed in another order), and a
    parcel naming a boundary its cell does not touch is refused."""
    from dcrad.division.boundary import RayParcel, transfer_rays

    rng = np.random.default_rng(1)
    bs = [make_boundary(0, 0, 1.0, (0, 0), (1, 1), 0, 1, 0.1, 4),
          make_boundary(1, 2, 1.0, (0, 0), (1, 1), 1, 2, 0.1, 4)]
    m = 1_000_000
    bid = rng.integers(0, 2, m)
    parcel = RayParcel(bid, rng.random((m, 3)), rng.normal(size=(m, 3)),
                       rng.random((m, 3)) * rng.choice([-1, 1], (m, 1)))
    out = transfer_rays({1: parcel}, bs)  # cell 1 touches both: boundary 0 to cell 0, 1 to cell 2
    assert len(out[0]) == int((bid == 0).sum()) and len(out[2]) == int((bid == 1).sum()) and len(out[1]) == 0
    order = np.argsort(out[0].power[:, 0])
    mine = np.flatnonzero(bid == 0)
    assert np.array_equal(out[0].power[order], parcel.power[mine][np.argsort(parcel.power[mine, 0])])
    with pytest.raises(ExchangeError, match="does not touch"):
        transfer_rays({0: RayParcel([1], [[0, 0, 1.0]], [[0, 0, 1.0]], [[1.0, 1, 1]])}, bs)
    with pytest.raises(ExchangeError, match="unknown boundary"):
        transfer_rays({0: RayParcel([7], [[0, 0, 1.0]], [[0, 0, 1.0]], [[1.0, 1, 1]])}, bs)
