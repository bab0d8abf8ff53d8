"""Adaptive refinement (mesh.adapt): the mesh is split where the direct light varies, against the
exact direct light (photometry.direct_irradiance: contour form factors and shadow rays)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from dcrad.io.scene import load_scene
from dcrad.meshing.mesh import _key
from dcrad.outputs.photometry import shown_direct
from dcrad.pipeline import default_patch_size, prepare


def _room_with_a_table(folder):
    """A closed 4 x 3 x 4 m room, a 0.6 m square lamp in its ceiling, a 1.2 x 0.05 x 1.2 m table top
    at 0.8 m casting its shadow on the floor."""
    room = trimesh.creation.box(extents=(4.0, 3.0, 4.0))
    room.invert()  # faces point into the room
    table = trimesh.creation.box(extents=(1.2, 0.05, 1.2))
    table.apply_translation((0.3, -0.7, 0.2))
    lamp = np.array([[-0.3, 1.49, -0.3], [0.3, 1.49, -0.3], [0.3, 1.49, 0.3], [-0.3, 1.49, 0.3]])
    verts = [*room.vertices.tolist(), *table.vertices.tolist(), *lamp.tolist()]
    lines = ["mtllib room.mtl"] + [f"v {x} {y} {z}" for x, y, z in verts]
    lines += ["o room", "usemtl wall"] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in room.faces]
    n0 = len(room.vertices)
    lines += ["o table", "usemtl wood"] + [f"f {a + n0 + 1} {b + n0 + 1} {c + n0 + 1}" for a, b, c in table.faces]
    n1 = n0 + len(table.vertices)
    lines += ["o lamp", "usemtl lamp", f"f {n1 + 1} {n1 + 2} {n1 + 3}", f"f {n1 + 1} {n1 + 3} {n1 + 4}"]  # facing down
    (folder / "room.obj").write_text("\n".join(lines) + "\n")
    (folder / "room.mtl").write_text("newmtl wall\nKd 0.5 0.5 0.5\nnewmtl wood\nKd 0.4 0.3 0.2\n"
                                     "newmtl lamp\nKd 0 0 0\nKe 20 20 20\n")
    return folder / "room.obj"


def _shown_error(patches, where: np.ndarray, points: int = 6000, seed: int = 3) -> float:
    """RMS over area-sampled points of the patches ``where`` of the direct light a picture shows
    (each patch's exact mean, smoothed over corners as render.CornerSmoother does, interpolated:
    photometry.shown_direct) against the exact direct light at the point, over the RMS of the latter."""
    got = shown_direct(patches, np.flatnonzero(where), points, seed)
    return float(np.sqrt(np.mean((got["shown"] - got["exact"]) ** 2) / np.mean(got["exact"] ** 2)))


def test_the_mesh_is_split_along_the_tables_shadow_and_shows_the_light_better(tmp_path):
    """The floor under a table: refinement splits it where the exact direct light varies (the
    shadow's edge), keeps every input triangle tiled with no hanging vertex, and the light a
    picture shows is closer to the exact one than on the mesh without refinement and than on a
    uniformly finer mesh of as many elements."""
    path = _room_with_a_table(tmp_path)
    scene = load_scene(path, up="y")
    size = default_patch_size(scene)
    plain = scene.patches(size)
    fine = scene.patches(size, adapt=True)
    assert plain.adapted is None and fine.adapted is not None
    assert fine.adapted["split"] > 0 and fine.adapted["added"] == len(fine) - len(plain)
    # the pieces tile each input triangle, facing as it does
    tiled = np.bincount(fine.source, weights=fine.area, minlength=len(scene.faces))
    np.testing.assert_allclose(tiled, np.bincount(plain.source, weights=plain.area, minlength=len(scene.faces)),
                               rtol=1e-12)
    by_input = scene.vertices[scene.faces[fine.source]]
    n_in = np.cross(by_input[:, 1] - by_input[:, 0], by_input[:, 2] - by_input[:, 0])
    assert (np.einsum("ij,ij->i", fine.normal, n_in) > 0).all()
    # no hanging vertex on the floor: an edge of one element only lies on the floor's outline
    floor = np.isclose(fine.centroid[:, 1], -1.5) & (fine.normal[:, 1] > 0.99)
    f = fine.faces[floor]
    keys, counts = np.unique(_key(f, np.roll(f, -1, axis=1)).ravel(), return_counts=True)
    assert counts.max() <= 2
    lone = keys[counts == 1]
    ends = fine.vertices[np.stack([lone >> 31, lone & ((1 << 31) - 1)], axis=1)]
    on_outline = np.isclose(np.abs(ends[..., [0, 2]]), 2.0).all(axis=1).any(axis=1)
    assert on_outline.all()
    # the split floor elements straddle the shadow: their corners' exact light differs
    added = np.bincount(fine.source[floor], minlength=len(scene.faces)) > \
        np.bincount(plain.source[np.isclose(plain.centroid[:, 1], -1.5)], minlength=len(scene.faces))
    assert added.any()
    # the light a picture shows, on the floor
    uniform = scene.patches(size * np.sqrt(len(plain) / len(fine)))
    errs = [_shown_error(p, np.isclose(p.centroid[:, 1], -1.5) & (p.normal[:, 1] > 0.99))
            for p in (plain, fine, uniform)]
    assert errs[1] < 0.75 * errs[0], errs
    assert errs[1] < 0.85 * errs[2], errs


def test_an_experts_patch_size_is_the_mesh_asked_for(tmp_path):
    """--patch-size meshes at that size and is not refined; the automatic size is refined, and a
    second mesh at the size the first one chose with ``adapt`` is the same mesh (what compare and
    the references rely on)."""
    path = _room_with_a_table(tmp_path)
    _, auto, size = prepare(path, up="y")
    assert auto.adapted is not None and auto.adapted["added"] > 0
    _, expert, _ = prepare(path, size, up="y")
    assert expert.adapted is None and len(expert) < len(auto)
    _, again, _ = prepare(path, size, up="y", adapt=True)
    np.testing.assert_array_equal(again.faces, auto.faces)
    np.testing.assert_array_equal(again.vertices, auto.vertices)


@pytest.mark.parametrize("reflect", [0.0, 0.5])
def test_a_room_in_full_shadow_or_black_is_left_as_meshed(tmp_path, reflect):
    """Nothing varies, nothing is split: a lamp facing away from the room (its light leaves through
    nothing: every point sees none of it) and a black room with the lamp lit (no reflected light,
    contrast from the direct light alone, no division by zero)."""
    from dcrad.meshing.mesh import adapt

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1], [1, 0, 1]], float)
    f = np.array([[0, 2, 1], [1, 2, 3]])
    idx = np.arange(2)

    def dark(points, normals):
        return np.zeros(len(points)), 0

    out_v, out_f, out_i, done = adapt(v, f, idx, dark, 0.1, np.zeros(2, bool), reflect=reflect)
    assert done["split"] == 0 and len(out_f) == 2


def test_a_point_light_s_shadow_is_refined_too(tmp_path):
    """A room lit only by a point light (a luminaire, a glTF light: emitters.Emitter) given to
    ``prepare``: its sharp shadow of the table is refined as an emitting surface's is, and the
    patches carry the light."""
    from dcrad.transport.emitters import PointSource

    path = _room_with_a_table(tmp_path)
    text = (tmp_path / "room.mtl").read_text().replace("Ke 20 20 20", "Ke 0 0 0")
    (tmp_path / "room.mtl").write_text(text)
    light = PointSource([0.0, 1.2, 0.0], np.full(3, 5.0), name="bulb")
    _, p, _ = prepare(path, up="y", sources=lambda scene: (light,))
    assert p.sources == (light,)
    assert p.adapted is not None and p.adapted["split"] > 0
    floor = np.isclose(p.centroid[:, 1], -1.5) & (p.normal[:, 1] > 0.99)
    assert len(np.unique(p.area[floor])) > 1  # the floor's elements differ: some were split
    _, unlit, _ = prepare(path, up="y")
    assert unlit.adapted is None  # nothing to follow: no light at all


def test_a_mesh_past_the_looks_size_is_not_refined_and_says_so(tmp_path, monkeypatch):
    """Past mesh.ADAPT_MOST elements the look is not paid for: the mesh is the unrefined one, and
    report.json's mesh says why (here with the limit lowered to this small room's elements)."""
    import json

    import dcrad.io.scene
    from dcrad.pipeline import solve_to

    path = _room_with_a_table(tmp_path)
    plain = load_scene(path, up="y").patches(default_patch_size(load_scene(path, up="y")))
    monkeypatch.setattr(dcrad.io.scene, "ADAPT_MOST", len(plain) - 1)
    _, p, _ = prepare(path, up="y")
    assert p.adapted["skipped"] and p.adapted["added"] == 0
    np.testing.assert_array_equal(p.faces, plain.faces)
    solve_to(path, tmp_path / "out", up="y", width=32, height=24)
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["mesh"]["refined"]["skipped"].startswith(f"{len(plain)} elements, more than")
    line = next(c["text"] for c in report["choices"] if c["code"] == "mesh")
    assert "no adaptive refinement: " in line
