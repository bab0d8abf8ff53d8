"""Partition (subDivideScene): k-d planes through walls, clipping, explicit cells."""

from __future__ import annotations

import re

import numpy as np
import pytest

import scenes
from dcrad.division.partition import Cell, clip, faces_between, openness, partition, split_planes
from dcrad.errors import PartitionError
from dcrad.meshing.patches import Patches, triangle_areas
from scenes.office import room_rect

ROOM, WALL = 4.0, 0.12


@pytest.fixture(scope="module")
def office(tmp_path_factory):
    from dcrad.pipeline import prepare

    path = scenes.write_builtin("office", tmp_path_factory.mktemp("office"), rows=2, cols=3)
    return prepare(path)[1]


def office_walls():
    """Interior wall slabs of the 2x3 office: {axis: [(lo, hi), ...]}."""
    x = [(room_rect(0, j)[0] - WALL, room_rect(0, j)[0]) for j in (1, 2)]
    z = [(room_rect(1, 0)[1] - WALL, room_rect(1, 0)[1])]
    return {0: x, 2: z}


def in_wall(axis, offset):
    return any(lo < offset < hi for lo, hi in office_walls().get(axis, []))


def make_patches(tris, emission=0.0, rho=0.5):
    tris = np.asarray(tris, np.float64).reshape(-1, 3, 3)
    n = len(tris)
    return Patches(
        vertices=tris.reshape(-1, 3), faces=np.arange(3 * n).reshape(-1, 3),
        rho=np.broadcast_to(np.asarray(rho, float), (n, 3)) if np.ndim(rho) < 2 else rho,
        emission=np.broadcast_to(np.asarray(emission, float), (n, 3)) if np.ndim(emission) < 2 else emission,
        source=np.arange(n) + 100, obj=np.arange(n) % 3, names=["a", "b", "c"],
    )


def quad(p0, p1, p2, p3):
    """Two triangles p0 p1 p2, p0 p2 p3 (counter-clockwise seen from the front)."""
    return [[p0, p1, p2], [p0, p2, p3]]


def box_mesh(lo, hi):
    """Closed box with outward faces."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    t = []
    t += quad((x0, y0, z0), (x0, y0, z1), (x0, y1, z1), (x0, y1, z0))  # -x
    t += quad((x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1))  # +x
    t += quad((x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1))  # -y
    t += quad((x0, y1, z0), (x0, y1, z1), (x1, y1, z1), (x1, y1, z0))  # +y
    t += quad((x0, y0, z0), (x0, y1, z0), (x1, y1, z0), (x1, y0, z0))  # -z
    t += quad((x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1))  # +z
    return t


def check_normals_outward(tris, lo, hi):
    p = make_patches(tris)
    c = 0.5 * (np.asarray(lo) + np.asarray(hi))
    assert np.all(np.einsum("ij,ij->i", p.normal, p.centroid - c) > 0)


# -- automatic planes -----------------------------------------------------------------------
def test_box_mesh_faces_outward():
    check_normals_outward(box_mesh((0, 0, 0), (1, 2, 3)), (0, 0, 0), (1, 2, 3))


def test_k2_plane_goes_through_a_wall(office):
    part = partition(office, 2)
    assert len(part.cells) == 2 and len(part.planes) == 1 and len(part.faces) == 1
    axis, off = part.planes[0]
    assert axis in (0, 2) and in_wall(axis, off), f"plane {axis}={off} is not inside a wall"
    # the log explains the choice: low openness, good balance, alternatives listed
    assert len(part.log) == 1
    op = float(re.search(r"openness ([0-9.]+)", part.log[0]).group(1))
    assert op < 0.3 and "work below" in part.log[0] and "other axes" in part.log[0]
    # a plane across the middle of a room is far more open than the chosen one
    across = openness(office, 2, [2.0])[0]
    assert across > 0.8 and openness(office, axis, [off])[0] < 0.3
    # the boundary face spans the whole building section
    f = part.faces[0]
    assert (f.axis, f.side_a, f.side_b) == (axis, 0, 1) and f.offset == off
    assert split_planes(office, 2) == part.planes  # deterministic


@pytest.mark.parametrize("k", [3, 4, 6])
def test_k_cells_balanced_and_through_walls(office, k):
    part = partition(office, k)
    assert len(part.cells) == k and len(part.planes) == k - 1 and len(part.log) == k - 1
    for axis, off in part.planes:
        assert in_wall(axis, off), f"k={k}: plane {'xyz'[axis]}={off} is not inside a wall"
    work = np.array(part.work)
    assert np.isclose(work.sum(), office.area.sum())
    assert work.max() / work.min() <= 2.5, f"k={k}: work {work}"
    # the cells tile the root box
    vol = sum(np.prod(np.subtract(c.hi, c.lo)) for c in part.cells)
    box = np.subtract(part.cells[-1].hi, part.cells[0].lo)
    assert np.isclose(vol, np.prod(box))
    d = part.as_dict()
    assert d["k"] == k and len(d["planes"]) == k - 1 and d["work_unit"] == "m^2"


def test_work_count_and_bad_args(office):
    part = partition(office, 2, work="count")
    assert part.work_unit == "patches" and sum(part.work) == len(office)
    with pytest.raises(PartitionError, match="work"):
        partition(office, 2, work="volume")
    with pytest.raises(PartitionError, match="k"):
        partition(office, 0)
    with pytest.raises(PartitionError, match="needs k"):
        partition(office)
    assert len(partition(office, 1).cells) == 1


# -- clipping --------------------------------------------------------------------------------
def test_straddling_triangle_is_clipped_on_both_sides():
    tri = [[(0, 0, 0), (2, 0, 0), (0, 0, 2)], [(1, 0, 3), (1.5, 0, 3), (1, 1, 3)]]
    p = make_patches(tri, emission=[[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]], rho=[[0.1, 0.2, 0.3], [0.5] * 3])
    part = partition(p, planes=[(0, 0.7), (2, 1.3)])  # a 2 x 1 x 2 grid
    assert len(part.cells) == 4 and len(part.faces) == 4
    cells = clip(p, part)
    scale = p.scale
    pieces_area = 0.0
    for cell, (sub, parent) in zip(part.cells, cells):
        assert parent.dtype == np.int64 and len(parent) == len(sub)
        lo, hi = np.array(cell.lo), np.array(cell.hi)
        v = sub.triangles.reshape(-1, 3)
        assert np.all(v >= lo - 1e-9 * scale) and np.all(v <= hi + 1e-9 * scale)
        np.testing.assert_array_equal(sub.source, p.source[parent])
        np.testing.assert_array_equal(sub.obj, p.obj[parent])
        np.testing.assert_array_equal(sub.rho, p.rho[parent])
        np.testing.assert_array_equal(sub.emission, p.emission[parent])
        np.testing.assert_array_equal(sub.radiosity, p.radiosity[parent])
        np.testing.assert_array_equal(sub.unshot, p.unshot[parent])
        assert np.all(np.einsum("ij,ij->i", sub.normal, p.normal[parent]) > 1 - 1e-12)  # same side
        pieces_area += sub.area[parent == 0].sum()
    # triangle 0 straddles both planes: pieces in 3 cells, areas summing to the original
    holders = [i for i, (sub, parent) in enumerate(cells) if np.any(parent == 0)]
    assert len(holders) == 3
    assert pieces_area == pytest.approx(p.area[0], rel=1e-12)
    # triangle 1 lies wholly in one cell and is kept as it is
    whole = [(sub, parent) for sub, parent in cells if np.any(parent == 1)]
    assert len(whole) == 1 and np.sum(whole[0][1] == 1) == 1
    assert np.allclose(whole[0][0].triangles[whole[0][1] == 1][0], p.triangles[1])


def test_office_clip_conserves_area_and_power(office):
    part = partition(office, 4)
    cells = clip(office, part)
    area = sum(sub.area.sum() for sub, _ in cells)
    power = sum(sub.emitted_power for sub, _ in cells)
    assert area == pytest.approx(office.area.sum(), rel=1e-9)
    np.testing.assert_allclose(power, office.emitted_power, rtol=1e-9)
    per_parent = np.zeros(len(office))
    for (sub, parent), cell in zip(cells, part.cells):
        np.add.at(per_parent, parent, sub.area)
        v = sub.triangles.reshape(-1, 3)
        assert np.all(v >= np.array(cell.lo) - 1e-9 * office.scale)
        assert np.all(v <= np.array(cell.hi) + 1e-9 * office.scale)
        np.testing.assert_array_equal(sub.source, office.source[parent])
        # the areas clip fills in are those of the pieces' own corners
        np.testing.assert_array_equal(sub.area, triangle_areas(sub.triangles))
    np.testing.assert_allclose(per_parent, office.area, rtol=1e-9, atol=1e-12)


def _canonical(tri):
    """Triangles as sorted rows of 9 numbers, each rotated to start at its least corner
    (the winding kept): equal sets of triangles compare equal."""
    tri = np.asarray(tri, np.float64)
    first = np.array([min(range(3), key=lambda j: tuple(t[j])) for t in tri], np.int64)
    rot = tri[np.arange(len(tri))[:, None], (first[:, None] + np.arange(3)) % 3].reshape(len(tri), 9)
    return rot[np.lexsort(rot.T[::-1])]


@pytest.mark.parametrize("two_sided", [False, True])
def test_openness_traces_the_input_triangles(tmp_path, two_sided):
    """The openness traces each input triangle once, rebuilt from its patches (the same corner
    coordinates and winding; of a two-sided surface its front), not the patches, and
    measures the same as tracing the (front) patches."""
    from dcrad.division.partition import _openness, _surfaces
    from dcrad.pipeline import prepare
    from dcrad.transport.rays import Tracer

    path = scenes.write_builtin("office", tmp_path, rows=1, cols=2)
    scene, p, _ = prepare(path, 0.3, two_sided=two_sided)
    tri, normals = _surfaces(p)
    given = scene.vertices[scene.faces[scene.valid]]
    fronts = np.flatnonzero(p.twin < 0) if not two_sided else np.flatnonzero(p.twin > np.arange(len(p)))
    assert len(fronts) > 10 * len(given) and (len(fronts) < len(p)) == two_sided
    np.testing.assert_array_equal(_canonical(tri), _canonical(given))
    front = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(np.einsum("ij,ij->i", front, normals) > 0)
    # the same openness as tracing the patches themselves, along every axis
    lo, hi = p.bounds
    for axis in range(3):
        offsets = np.linspace(lo[axis], hi[axis], 9)[1:-1]
        mine = openness(p, axis, offsets)
        theirs = _openness(Tracer(p.triangles[fronts]), p.normal[fronts], axis, offsets, lo, hi, 24, 0.02 * p.scale,
                           np.random.default_rng(0))
        np.testing.assert_allclose(mine, theirs, atol=2 / 24 ** 2)


def test_surfaces_keep_patches_that_tile_no_triangle(office):
    """Clipped pieces of a triangle (a quadrilateral, say) and patches sharing a source by
    chance stay as they are: the surfaces cover the same area."""
    from dcrad.division.partition import _surfaces

    part = partition(office, 4)
    for sub, _ in clip(office, part):
        tri, _ = _surfaces(sub)
        assert triangle_areas(tri).sum() == pytest.approx(sub.area.sum(), rel=1e-9)
        assert len(tri) < len(sub)
    # an L of three unit squares' triangles, all with one source: no triangle is their union
    sq = [quad((x, 0, z), (x, 0, z + 1), (x + 1, 0, z + 1), (x + 1, 0, z)) for x, z in [(0, 0), (1, 0), (0, 1)]]
    ell = make_patches(np.concatenate(sq))
    ell.source[:] = 7
    tri, _ = _surfaces(ell)
    assert len(tri) == len(ell) and triangle_areas(tri).sum() == pytest.approx(3.0)


# -- explicit partitions -----------------------------------------------------------------------
def test_explicit_planes_grid(office):
    part = partition(office, planes=[(0, 4.06), (2, 4.06), (0, 8.18)])
    assert len(part.cells) == 6 and part.planes == [(0, 4.06), (2, 4.06), (0, 8.18)]
    xs = sorted({c.lo[0] for c in part.cells} | {c.hi[0] for c in part.cells})
    zs = sorted({c.lo[2] for c in part.cells} | {c.hi[2] for c in part.cells})
    assert xs[1:3] == [4.06, 8.18] and zs[1:2] == [4.06] and len(xs) == 4 and len(zs) == 3
    assert len(part.faces) == 7  # 2 x 3 grid: 4 faces across x, 3 across z
    with pytest.raises(PartitionError, match="outside the scene box"):
        partition(office, planes=[(0, 50.0)])


def test_explicit_boxes(office):
    lo, hi = office.bounds
    mid = 4.06
    boxes = [(lo, (mid, hi[1], hi[2])), ((mid, lo[1], lo[2]), hi)]
    part = partition(office, boxes=boxes)
    assert [c.lo for c in part.cells] == [tuple(lo), (mid, lo[1], lo[2])]
    assert len(part.faces) == 1 and part.faces[0].axis == 0 and part.faces[0].offset == mid
    assert part.faces[0].area == pytest.approx((hi[1] - lo[1]) * (hi[2] - lo[2]))
    cells = clip(office, part)
    assert sum(s.area.sum() for s, _ in cells) == pytest.approx(office.area.sum(), rel=1e-9)

    overlap = [(lo, (5.0, hi[1], hi[2])), ((mid, lo[1], lo[2]), hi)]
    with pytest.raises(PartitionError, match=r"box 0 .* and box 1 .* overlap"):
        partition(office, boxes=overlap)
    gap = [(lo, (mid, hi[1], hi[2])), ((mid, lo[1], lo[2]), (hi[0], hi[1], 6.0)),
           ((mid, lo[1], 6.5), hi)]
    with pytest.raises(PartitionError, match=r"box 0 .* \+x side at x=4.06 is only 93.8% covered .* gap"):
        partition(office, boxes=gap)
    short = [(lo, (mid, hi[1], hi[2])), ((mid, lo[1], lo[2]), (10.0, hi[1], hi[2]))]
    with pytest.raises(PartitionError, match="scene spans"):
        partition(office, boxes=short)
    with pytest.raises(PartitionError, match="box 1 .*lo < hi"):
        partition(office, boxes=[(lo, hi), (hi, lo)])


def test_faces_between_2x2_grid():
    cells = [Cell(i * 2 + j, (i * 1.0, 0.0, j * 2.0), (i + 1.0, 3.0, j * 2.0 + 2.0))
             for i in range(2) for j in range(2)]
    faces = faces_between(cells)
    assert len(faces) == 4
    got = {(f.axis, f.offset, f.side_a, f.side_b, f.lo, f.hi) for f in faces}
    assert got == {
        (0, 1.0, 0, 2, (0.0, 0.0), (3.0, 2.0)),  # x = 1 plane: rectangle in (y, z)
        (0, 1.0, 1, 3, (0.0, 2.0), (3.0, 4.0)),
        (2, 2.0, 0, 1, (0.0, 0.0), (1.0, 3.0)),  # z = 2 plane: rectangle in (x, y)
        (2, 2.0, 2, 3, (1.0, 0.0), (2.0, 3.0)),
    }
    assert sorted(f.area for f in faces) == [3.0, 3.0, 6.0, 6.0]
    # boxes touching only along an edge or not at all share no face; partial overlap is clipped
    assert faces_between([Cell(0, (0, 0, 0), (1, 1, 1)), Cell(1, (1, 1, 0), (2, 2, 1))]) == []
    f = faces_between([Cell(0, (0, 0, 0), (1, 1, 1)), Cell(1, (0.5, 0.5, 1), (2, 2, 2))])
    assert len(f) == 1 and (f[0].axis, f[0].lo, f[0].hi) == (2, (0.5, 0.5), (1.0, 1.0))


# -- no plane on a surface ------------------------------------------------------------------
def thin_wall_scene():
    floor = quad((0, 0, 0), (0, 0, 2), (2, 0, 2), (2, 0, 0))  # +y up
    return make_patches(floor + box_mesh((1.0, 0.0, 0.0), (1.1, 1.0, 2.0)), emission=1.0)


def test_plane_on_a_surface_is_nudged():
    p = thin_wall_scene()
    part = partition(p, planes=[(0, 1.0)])
    (axis, off), = part.planes
    assert axis == 0 and off != 1.0 and abs(off - 1.0) <= 1e-3 * p.scale
    assert any("nudged" in line for line in part.log)
    assert part.cells[0].hi[0] == off and part.faces[0].offset == off
    total = 0.0
    for sub, _ in clip(p, part):
        x = sub.triangles[:, :, 0]
        assert not np.any(np.all(np.abs(x - off) <= 1e-9, axis=1)), "a patch lies in the plane"
        total += sub.area.sum()
    assert total == pytest.approx(p.area.sum(), rel=1e-9)
    # boxes are nudged consistently too
    lo, hi = p.bounds
    part = partition(p, boxes=[(lo, (1.1, hi[1], hi[2])), ((1.1, lo[1], lo[2]), hi)])
    assert part.cells[0].hi[0] == part.cells[1].lo[0] != 1.1
    # automatic planes never land on a surface either
    for axis, off in partition(p, 2).planes:
        assert not np.any(np.all(np.abs(p.triangles[:, :, axis] - off) <= 1e-4 * p.scale, axis=1))
