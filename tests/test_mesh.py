"""The mesh follows the light, not the file's triangulation (mesh.py): independent truths."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import scenes
from dcrad.config import SolverConfig
from dcrad.export import input_triangle_radiosity
from dcrad.mesh import AREA_SHARE, refine
from dcrad.passes import solve_to_accuracy
from dcrad.patches import triangle_areas
from dcrad.pipeline import default_patch_size, prepare
from dcrad.scene import load_scene
from scenes.variants import variant


def test_a_finely_triangulated_copy_solves_like_the_coarse_file(tmp_path):
    """Cornell as written and with every triangle split into 16: the same element size (from the
    light, not the edges), about the same elements and rays, and the same B per original
    triangle within the two runs' estimated errors (3 sigma of their combined estimate)."""
    coarse = scenes.write_builtin("cornell", tmp_path / "coarse")
    fine = variant(coarse, tmp_path / "fine", up="y", split=2)
    runs = []
    for path in (coarse, fine):
        scene, patches, size = prepare(path)
        solver = solve_to_accuracy(patches, SolverConfig(accuracy=0.05, seed=3))
        b, valid = input_triangle_radiosity(patches, len(scene.faces))
        runs.append((scene, patches, size, solver, b, valid))
    (sc, pc, size_c, solver_c, bc, _), (sf, pf, size_f, solver_f, bf, vf) = runs
    assert len(sf.faces) == 16 * len(sc.faces)
    parent = np.arange(len(sf.faces)) // 16  # the split keeps the file's order
    assert size_f == pytest.approx(size_c, rel=0.05)
    assert len(pf) == pytest.approx(len(pc), rel=0.25)
    assert solver_f.stats.rays == pytest.approx(solver_c.stats.rays, rel=0.5)
    # B per original triangle: the fine file's pieces' area-weighted mean
    area_f = triangle_areas(sf.vertices[sf.faces])
    w = np.bincount(parent, weights=area_f)
    back = np.stack([np.bincount(parent, weights=area_f * bf[:, c]) for c in range(3)], axis=1) / w[:, None]
    area_c = triangle_areas(sc.vertices[sc.faces])
    refl = bc - sc.emission
    rms_refl = np.sqrt((area_c[:, None] * refl ** 2).sum() / area_c.sum() / 3)
    diff = np.sqrt((area_c[:, None] * (back - bc) ** 2).sum() / area_c.sum() / 3) / rms_refl
    est = np.hypot(solver_c.estimate().rms_refl, solver_f.estimate().rms_refl)
    assert diff < 3 * est, (diff, est)


def test_a_room_with_millimetre_furniture_is_meshed_by_its_rooms(tmp_path):
    """A 4 x 3 x 4 m room holding a cushion of 1 mm triangles (the old rule, a third of the median
    input edge, meshed the walls at 0.3 mm: 1e8 patches, refused): the element size comes from the
    room, the cushion's triangles are kept whole, and the mesh stays within 3x the larger of the
    input triangles and area / size^2."""
    room = trimesh.creation.box(extents=(4.0, 3.0, 4.0))
    room.invert()  # faces point into the room
    grid = 60
    xs = np.linspace(0.0, 0.06, grid + 1)
    gx, gz = np.meshgrid(xs, xs)
    cv = np.stack([gx.ravel() - 0.03, np.full(gx.size, -1.0), gz.ravel() - 0.03], axis=1)
    i = np.arange(grid)[:, None] * (grid + 1) + np.arange(grid)[None, :]
    i = i.ravel()
    cf = np.concatenate([np.stack([i, i + grid + 1, i + 1], 1), np.stack([i + 1, i + grid + 1, i + grid + 2], 1)])
    lamp = np.array([[-0.5, 1.49, -0.5], [0.5, 1.49, -0.5], [0.5, 1.49, 0.5], [-0.5, 1.49, 0.5]])
    lines = ["mtllib room.mtl", "o room", "usemtl wall"]
    verts = [*room.vertices.tolist(), *cv.tolist(), *lamp.tolist()]
    lines = [f"v {x} {y} {z}" for x, y, z in verts] + lines
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in room.faces]
    n0 = len(room.vertices)
    lines += ["o cushion", "usemtl cloth"] + [f"f {a + n0 + 1} {b + n0 + 1} {c + n0 + 1}" for a, b, c in cf]
    n1 = n0 + len(cv)
    lines += ["o lamp", "usemtl lamp", f"f {n1 + 1} {n1 + 3} {n1 + 2}", f"f {n1 + 1} {n1 + 4} {n1 + 3}"]
    (tmp_path / "room.obj").write_text("\n".join(lines) + "\n")
    (tmp_path / "room.mtl").write_text("newmtl wall\nKd 0.5 0.5 0.5\nnewmtl cloth\nKd 0.3 0.2 0.2\n"
                                       "newmtl lamp\nKd 0 0 0\nKe 10 10 10\n")
    scene = load_scene(tmp_path / "room.obj", up="y")
    size = default_patch_size(scene)
    assert 0.2 < size < 1.0  # the room's: its mean free path (4V/S = 1.45 m) / 6, not the cushion's 1 mm
    _, patches, used = prepare(tmp_path / "room.obj", up="y")
    area = float(patches.total_area)
    assert len(patches) <= 3 * max(len(scene.faces), area / used ** 2)
    cushion = patches.obj == scene.names.index(next(n for n in scene.names if n.startswith("cushion")))
    assert cushion.sum() == len(cf)  # kept whole, one patch per triangle ...
    groups = np.unique(patches.cluster[cushion])
    assert (groups >= 0).all() and len(groups) <= 4  # ... grouped by the cells of the size it spans
    assert patches.units == (patches.cluster < 0).sum() + len(groups)  # the unknowns: the room's, and a few
    solver = solve_to_accuracy(patches, SolverConfig(accuracy=0.1, seed=1, max_rays=3_000_000))
    assert solver.ledger.closure() < 1e-9
    patches.pool()
    assert len(np.unique(patches.radiosity[cushion], axis=0)) <= len(groups)  # a cluster shares one B


def test_refine_keeps_area_orientation_and_bounds_the_elements():
    """Bisection: the pieces tile each triangle (areas sum to it, normals agree), none is larger than
    the size asks, and a 3 m x 1 cm sliver is split along its length only (a 4-way split cut it
    into hundreds)."""
    v = np.array([[0, 0, 0], [3, 0, 0], [0, 0.01, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1]], float)
    f = np.array([[0, 1, 2], [3, 4, 5]])
    rv, rf, idx = refine(v, f, 0.2)
    tri = rv[rf]
    a = triangle_areas(tri)
    np.testing.assert_allclose(np.bincount(idx, weights=a), triangle_areas(v[f]), rtol=1e-12)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n0 = np.cross(v[f][:, 1] - v[f][:, 0], v[f][:, 2] - v[f][:, 0])
    assert (np.einsum("ij,ij->i", n, n0[idx]) > 0).all()
    assert (a[idx == 1] <= AREA_SHARE * 0.2 ** 2 * (1 + 1e-12)).all()
    assert 2 <= (idx == 0).sum() <= 16  # the sliver: a few pieces along its length (trimesh: 256)
