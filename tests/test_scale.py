"""The scale kernel (issue 12): per-batch work that follows the rays, not the patch count.

Each piece is checked against the plain computation it replaces: the pool's
shooters against a full sort of the table, the sparse tally against a dense
scatter of the same rays, the incremental ledger against a full recount, and a
whole solve against the full-sort, full-recount solver (same random stream, so
equal to round-off, not merely within noise).  The snapshot store is checked
against its stated cap and precision.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import scenes
from dcrad.config import SolverConfig
from dcrad.io.scene import load_scene
from dcrad.meshing.patches import Patches
from dcrad.pipeline import default_patch_size
from dcrad.solving.snapshots import SnapshotStore
from dcrad.solving.solver import Solver
from dcrad.transport.rays import MISS
from dcrad.transport.shoot import compact, patch_rays, trace
from dcrad.transport.shooters import ShooterPool, priority


def cornell(tmp_path, size: float = 0.08) -> Patches:
    return load_scene(scenes.write_builtin("cornell", tmp_path)).patches(size)


def random_table(n: int, rng) -> Patches:
    v = rng.random((3 * n, 3))
    f = np.arange(3 * n).reshape(n, 3)
    return Patches(v, f, rng.uniform(0.1, 0.9, (n, 3)), 0.0, np.arange(n), np.zeros(n), ["x"],
                   unshot=rng.exponential(1.0, (n, 3)) ** 3)


def full_top(p: Patches, k: int) -> set:
    pr = priority(p)
    return set(np.argsort(-pr, kind="stable")[:k].tolist())


def test_compact_is_unique_with_inverse():
    rng = np.random.default_rng(1)
    index = rng.integers(0, 500, 3000)
    rows, slot = compact(index, np.full(500, 7, np.int32))
    assert np.array_equal(np.sort(rows), np.unique(index))
    assert np.array_equal(rows[slot], index)
    empty_rows, empty_slot = compact(np.zeros(0, np.int64), np.zeros(4, np.int32))
    assert len(empty_rows) == 0 and len(empty_slot) == 0


def test_pool_candidates_hold_the_true_top_k_under_deposits_and_shots():
    """Random shots (top k zeroed) and deposits on random rows, 200 rounds: the top k of the
    pool's candidates is the top k of a full sort every round, with few rebuilds."""
    rng = np.random.default_rng(2)
    n, k = 20000, 50
    p = random_table(n, rng)
    pool = ShooterPool(p, 16 * k)
    for _ in range(200):
        rows, pr = pool.candidates(k)
        top = rows[np.argsort(-pr, kind="stable")[:k]]
        assert set(top.tolist()) == full_top(p, k)
        p.unshot[top] = 0.0  # shot
        hit = np.unique(rng.integers(0, n, 400))
        p.unshot[hit] += rng.exponential(0.3, (len(hit), 3))
        pool.update(np.concatenate([top, hit[~np.isin(hit, top)]]))
    assert pool.rebuilds < 200 / 4


def test_pool_handles_ties_and_small_tables():
    p = random_table(10, np.random.default_rng(3))
    p.unshot[:] = 1.0 / p.area[:, None]  # all tied
    pool = ShooterPool(p, 4)
    rows, pr = pool.candidates(6)
    assert len(rows) >= 6 and np.allclose(pr, 3.0, rtol=1e-12)
    p.unshot[:] = 0.0
    pool.invalidate()
    rows, _ = pool.candidates(3, negligible=1e-12)
    assert len(rows) == 0


def test_sparse_tally_equals_a_dense_scatter(tmp_path):
    """trace's compact received/hit against np.add.at of the same rays into an (n,3) table."""
    p = cornell(tmp_path)
    s = Solver(p, SolverConfig(seed=4))
    idx, counts, power, _, _ = s.select()
    batch = patch_rays(p, idx, counts, power, np.random.default_rng(5))
    tally = trace(s.tracer, batch, p)
    prim, _ = s.tracer.intersect(batch.origins, batch.dirs)
    ok = prim != MISS
    front = np.zeros(len(prim), bool)
    front[ok] = np.einsum("ij,ij->i", batch.dirs[ok], p.normal[prim[ok]]) < 0
    dense = np.zeros((len(p), 3))
    np.add.at(dense, prim[front], batch.power[front])
    assert len(np.unique(tally.hit)) == len(tally.hit)
    assert set(tally.hit.tolist()) == set(np.flatnonzero(dense.any(axis=1)).tolist())
    np.testing.assert_allclose(tally.received, dense[tally.hit], rtol=1e-12, atol=0)
    back = ok & ~front
    np.testing.assert_allclose(tally.back_faces, batch.power[back].sum(axis=0), rtol=1e-10)
    np.testing.assert_allclose(tally.escaped, batch.power[~ok].sum(axis=0), rtol=1e-10, atol=1e-300)


def test_incremental_ledger_equals_a_full_recount_after_many_batches(tmp_path):
    p = cornell(tmp_path, 0.04)
    s = Solver(p, SolverConfig(seed=6, tol=1e-9, batch_rays=4096, max_rays_per_shot=1024, max_shooters=64))
    s.recount_every = 0  # never: the sums are the increments alone
    batches = 0
    while batches < 600 and s.step():
        batches += 1
    assert batches >= 400
    unshot = p.unshot * p.area[:, None]
    emitted = s.ledger.emitted
    np.testing.assert_allclose(s.ledger.unshot, unshot.sum(axis=0), rtol=0, atol=1e-12 * emitted.max())
    np.testing.assert_allclose(s.ledger.unshot_abs, np.abs(unshot).sum(axis=0), rtol=0, atol=1e-12 * emitted.max())
    assert s.ledger.closure() < 1e-12


def test_pool_solver_equals_full_sort_full_recount_solver(tmp_path):
    """Same seed, same scene: the pool picks the same shooters each batch as a full sort,
    so the two runs trace the same rays and end with the same B to round-off."""
    runs = []
    for full in (False, True):
        p = cornell(tmp_path, 0.05)
        s = Solver(p, SolverConfig(seed=7, tol=0.002, max_shooters=64, batch_rays=16384, max_rays_per_shot=4096))
        s.full_selection = full
        s.recount_every = 1 if full else s.recount_every
        picked = []
        s.run(on_progress=lambda sv, picked=picked: picked.append(sv.stats.shots))
        runs.append((p.radiosity.copy(), picked, s.stats.rays, s.pool.rebuilds))
    (b_pool, shots_pool, rays_pool, rebuilds), (b_full, shots_full, rays_full, _) = runs
    assert rays_pool == rays_full and shots_pool == shots_full
    assert len(shots_pool) > 50 and 1 < rebuilds < len(shots_pool) / 4
    np.testing.assert_allclose(b_pool, b_full, rtol=1e-9, atol=1e-12 * b_full.max())


def test_snapshot_store_precision_and_thinning():
    rng = np.random.default_rng(8)
    store = SnapshotStore()
    b = rng.exponential(5.0, (1000, 3)) * np.array([1.0, 1e-3, 1e4])
    store.append(b)
    got = store[0]
    assert got.dtype == np.float32
    scale = np.abs(b).max(axis=0)
    assert np.all(np.abs(got - b) <= 2.0**-11 * np.abs(b) + 2.0**-24 * scale)
    for _ in range(6):
        store.append(b)
    assert store.thin() == [0, 2, 4, 6] and len(store) == 4


def test_snapshot_memory_cap_holds_and_stays_geometric(tmp_path):
    p = cornell(tmp_path, 0.05)
    cap_mb = 4 * len(p) * 3 * 2 / 2**20  # room for four snapshots
    s = Solver(p, SolverConfig(seed=9, tol=1e-3, batch_rays=65536, snapshot_mb=cap_mb))
    sizes = []
    s.run(on_progress=lambda sv: sizes.append(sv.snapshot_B.nbytes))
    assert max(sizes) <= cap_mb * 2**20
    assert len(s.snapshots) == len(s.snapshot_B) >= 3
    rays = [snap.rays for snap in s.snapshots]
    assert rays == sorted(rays) and rays[0] == 0 and rays[-1] == s.stats.rays
    np.testing.assert_allclose(s.snapshot_B[-1], p.radiosity, rtol=2.0**-10, atol=1e-6 * p.radiosity.max())
    uncapped = Solver(cornell(tmp_path, 0.05), SolverConfig(seed=9, tol=1e-3, batch_rays=65536))
    uncapped.run()
    assert len(uncapped.snapshots) > len(s.snapshots)


@pytest.mark.parametrize("rows,cols", [(5, 5), (8, 8), (12, 4)])
def test_default_patch_size_follows_the_rooms_not_the_building(tmp_path, rows, cols):
    """An office of more rooms is meshed like the 3x3 one: the same element size, within 10%,
    while the box diagonal grows 2-3x (the size follows the rays' mean free path, mesh.py)."""
    few = load_scene(scenes.write_builtin("office", tmp_path / "a", rows=3, cols=3))
    many = load_scene(scenes.write_builtin("office", tmp_path / "b", rows=rows, cols=cols))
    assert default_patch_size(many) == pytest.approx(default_patch_size(few), rel=0.1)


@pytest.mark.parametrize("ext", [(1.0, 1.0, 1.0), (4.0, 3.0, 4.0), (12.0, 0.5, 3.0)])
def test_light_scale_of_an_empty_box_is_cauchys_mean_chord(ext):
    """In a closed convex room the mean distance cosine-distributed rays from its surfaces travel
    is 4V/S (Cauchy's mean chord): the light scale the element size comes from, within 3%
    (16k rays: the chords' spread gives a standard error under 1%)."""
    from dcrad.meshing.mesh import light_scale

    box = trimesh.creation.box(extents=ext)
    mfp, seen = light_scale(np.asarray(box.vertices, float), np.asarray(box.faces, np.int64))
    x, y, z = ext
    assert seen == pytest.approx(0.5, abs=0.02)  # both sides are sampled; the outside sees nothing
    assert mfp == pytest.approx(4 * x * y * z / (2 * (x * y + y * z + z * x)), rel=0.03)
