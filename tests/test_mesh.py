"""The mesh follows the light, not the file's triangulation (mesh.py): independent truths."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import scenes
from dcrad.config import SolverConfig
from dcrad.io.export import input_triangle_radiosity
from dcrad.io.scene import load_scene
from dcrad.meshing.mesh import AREA_SHARE, refine
from dcrad.meshing.patches import triangle_areas
from dcrad.pipeline import default_patch_size, prepare
from dcrad.solving.passes import solve_to_accuracy
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
    # the unknowns: the room's patches that reflect (not the black lamp's), and a few clusters
    assert patches.units == ((patches.cluster < 0) & patches.rho.any(axis=1)).sum() + len(groups)
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


def test_clusters_settle_where_their_patches_agree_within_their_noise():
    """NoiseTally.settle on a hand-made table: cluster 0's patches differ by what their noise
    spreads (kept, its spread beyond the noise booked as bias), cluster 1's differ far beyond
    theirs (undone: each patch keeps its own B); the numbers are computed here from the
    definitions, S = sum A |r - r_mean|^2 against N = sum A |D/2|^2 (1 - A/A_c)."""
    from dcrad.estimate.noise import NoiseTally
    from dcrad.meshing.patches import Patches

    n = 8
    v = np.array([[i, 0.0, 0.0] for i in range(n + 2)] + [[i, 1.0, 0.0] for i in range(n + 2)], float)
    f = np.array([[i, i + 1, n + 2 + i] for i in range(n)])
    cluster = np.array([0, 0, 0, 0, 1, 1, 1, 1])
    p = Patches(v, f, 0.5, 0.0, np.arange(n), np.zeros(n), ["x"], cluster=cluster)
    tally = NoiseTally(p)
    p.radiosity = np.repeat(np.array([1.0, 1.1, 0.9, 1.0, 0.2, 2.0, 0.3, 1.9])[:, None], 3, axis=1)
    tally.diff = np.repeat(np.array([0.4, 0.4, 0.4, 0.4, 0.01, 0.01, 0.01, 0.01])[:, None], 3, axis=1)
    kept, undone = tally.settle(p)
    assert (kept, undone) == (1, 1)
    np.testing.assert_array_equal(p.cluster, [0, 0, 0, 0, -1, -1, -1, -1])
    a = p.area[:4]
    r = p.radiosity[:4, 0]
    spread = float((a * (r - (a * r).sum() / a.sum()) ** 2).sum())
    noise = float((a * 0.2 ** 2 * (1 - a / a.sum())).sum())
    assert tally.pool_bias == pytest.approx(max(spread - noise, 0.0), abs=1e-15)
    assert not tally.pooled or p.units == 5  # one cluster of four, four patches alone


def test_pooling_a_uniform_furnace_lowers_its_error_per_triangle(tmp_path):
    """A closed cube whose every surface emits E and reflects rho: B* = E / (1 - rho) on every
    patch, exactly.  Every face split 256-fold: the small triangles form clusters, which settle
    (their light is uniform: nearly all kept), and pooled B per triangle is closer to B* than
    each triangle's own."""
    from dcrad.meshing.patches import Patches
    from scenes.furnace import furnace_box

    rho = 0.5
    fine = variant(furnace_box(tmp_path / "f", rho=rho), tmp_path / "fine", up="y", split=4)
    _, q, _ = prepare(fine)
    # all but the cells next to its lamp (within an element, a fifth of the 0.67 m free path, of it)
    assert (q.cluster >= 0).mean() > 0.3
    p = Patches(q.vertices, q.faces, q.rho, np.ones((len(q), 3)), q.source, q.obj, q.names, cluster=q.cluster)
    clusters = len(np.unique(p.cluster[p.cluster >= 0]))
    solver = solve_to_accuracy(p, SolverConfig(accuracy=0.05, seed=4))
    kept = len(np.unique(p.cluster[p.cluster >= 0]))
    assert kept >= 0.9 * clusters
    exact = 1.0 / (1.0 - rho)
    kept_rows = p.cluster >= 0
    a = p.area[kept_rows, None]

    def rms() -> float:
        return float(np.sqrt((a * (p.radiosity[kept_rows] - exact) ** 2).sum() / a.sum() / 3))

    own = rms()
    p.pool()
    members = kept_rows.sum() / kept  # a cluster's patches, on average
    assert rms() < 2.0 * own / np.sqrt(members), (rms(), own, members)  # noise averages as 1/sqrt(members)
    assert solver.ledger.closure() < 1e-9
