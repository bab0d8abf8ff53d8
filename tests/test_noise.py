"""The error estimate (noise.py) against independent truths, the accuracy knob, the direct gather.

Truth: a closed cube whose every surface emits E and reflects rho has the exact
discrete solution B_i = E / (1 - rho) on every patch (each row of form factors
sums to one), so the RMS error of a run is measured exactly, without a reference run.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dcrad.config import SolverConfig
from dcrad.division.divide import DivideConfig, solve_divided
from dcrad.estimate.noise import SHOWN_SLACK, NoiseSums, NoiseTally, combine, half_mask, held_factors, split_power
from dcrad.meshing.patches import Patches
from dcrad.pipeline import prepare
from dcrad.solving.accuracy import by_accuracy, rays_for, resolve
from dcrad.solving.energy import read_error
from dcrad.solving.passes import solve_to_accuracy
from dcrad.solving.solver import UNSHOT_SHARE, Solver
from dcrad.transport.lights import light_polygons, polygon_form_factor
from dcrad.transport.rays import Tracer
from dcrad.transport.shoot import deposit, landing
from scenes.furnace import furnace_box

RHO = 0.5


@pytest.fixture(scope="module")
def uniform_furnace(tmp_path_factory):
    """A 1 m cube, 0.2 m patches, every surface emitting 1 W/m^2 with rho 0.5: B* = 2 everywhere."""
    path = furnace_box(tmp_path_factory.mktemp("furnace"), rho=RHO, light_fraction=0.25)
    _, p, _ = prepare(path, patch_size=0.2)
    patches = Patches(p.vertices, p.faces, p.rho, np.ones((len(p), 3)), p.source, p.obj, p.names)
    return patches, Tracer(patches.triangles)


def measured(patches, per_triangle: bool = False) -> float:
    """The RMS error over RMS(B* - E) against the exact B* = E / (1 - rho), of B as it is read: per
    element (a cluster's patches share one B; here every patch stands alone), or per input triangle
    (the area mean of its elements, radiosity.npz's B)."""
    return read_error(patches, patches.radiosity, patches.emission / (1.0 - RHO), per_triangle)


def assert_honest(est, patches, within: float = 1.5) -> float:
    """The estimate per element and per input triangle within ``within`` of the error measured in
    each reading; returns the measured error per input triangle over RMS(B* - E) (the target's)."""
    element = measured(patches)
    triangle = measured(patches, per_triangle=True)
    assert 1 / within < est.elements_refl / element < within, (est, element)
    assert 1 / within < est.triangles_refl / triangle < within, (est, triangle)
    return triangle


@pytest.mark.parametrize("rays_per_power,direct", [(2e4, False), (2e5, False), (2e5, True)])
def test_estimate_matches_the_exact_error(uniform_furnace, rays_per_power, direct):
    """Converged runs (bias ~ 0): the noise estimate is within a factor 1.5 of the measured error."""
    patches, tracer = uniform_furnace
    patches.reset()
    s = Solver(patches, SolverConfig(seed=7, tol=1e-4, rays_per_power=rays_per_power, direct=direct), tracer=tracer)
    s.run()
    est = s.estimate()
    assert est.bias_refl < 0.1 * est.noise_refl
    assert_honest(est, patches)
    assert s.ledger.closure() < 1e-9


@pytest.mark.parametrize("accuracy", [0.1, 0.05])
def test_accuracy_target_stops_the_run_and_is_met(uniform_furnace, accuracy):
    """--accuracy: the run chooses its density, stops by its estimate, and the measured error agrees."""
    patches, tracer = uniform_furnace
    patches.reset()
    s = solve_to_accuracy(patches, SolverConfig(seed=11, accuracy=accuracy), tracer)
    assert s.stats.stopped_by == "accuracy"
    est = s.estimate()
    assert est.rms_refl <= accuracy and est.triangles_refl <= accuracy
    assert est.elements_refl <= SHOWN_SLACK * accuracy
    assert assert_honest(est, patches) < 1.5 * accuracy
    assert s.ledger.closure() < 1e-9


@pytest.mark.parametrize("accuracy", [0.05, 0.02])
def test_a_calibrated_first_pass_and_its_blend_keep_the_estimate_honest(uniform_furnace, accuracy):
    """A run whose light is shot (no direct gather) and whose density is its own choice shoots a
    first pass at passes.CALIBRATION of it (Solver.calibrate); a further pass, if any, starts from
    the density the first one spent and shoots until its unshot light's bias is under a quarter of
    the target.  Against the exact furnace solution the estimate stays within 1.5x of the error,
    the target is met, the ledger closes."""
    from dcrad.solving.passes import CALIBRATION

    patches, tracer = uniform_furnace
    patches.reset()
    s = solve_to_accuracy(patches, SolverConfig(seed=17, accuracy=accuracy, direct=False), tracer)
    whole = rays_for(patches.read_units, accuracy)
    note = s.choices.of("density")
    assert note and f"{CALIBRATION * whole:.3g} rays per emitted power" in note[0].text, s.choices
    # (at 0.05 the furnace takes three passes: a third seeded like the second once repeated its rays,
    # and the blend, taking them for independent, ended on its noise floor above the target)
    assert s.stats.stopped_by == "accuracy"
    est = s.estimate()
    assert est.rms_refl <= accuracy
    assert_honest(est, patches)
    # its light is shot, not merely estimated so: whatever the bias layout reads (solver.UNSHOT_SHARE)
    assert s.residual() <= UNSHOT_SHARE * accuracy
    assert s.ledger.closure() < 1e-9


def test_an_expert_density_is_not_calibrated(uniform_furnace):
    """--rays-per-power given: the run spends it whole (no first pass at a share of it)."""
    patches, tracer = uniform_furnace
    patches.reset()
    s = solve_to_accuracy(patches, SolverConfig(seed=17, accuracy=0.05, direct=False, rays_per_power=5e4), tracer)
    assert not s.choices.of("density")
    assert s.budget.density() == pytest.approx(5e4) or s.choices.of("passes")


def test_divided_estimate_combines_subscenes(uniform_furnace):
    """Exact forwarding (no binning bias): the job's estimate from the subscenes' sums
    is within a factor 1.5 of the exact error of the assembled B."""
    patches, _ = uniform_furnace
    patches.reset()
    run, subs, *_ = solve_divided(patches, SolverConfig(seed=5, tol=1e-3, rays_per_power=5e4),
                                  DivideConfig(subscenes=2, mode="exact"))
    est = run.estimate
    assert est is not None and len(subs) == 2
    # the subscenes' sums are of the reading the target holds: per input triangle, the elements
    # within SHOWN_SLACK of it (its noise alone: the run is converged, no bias)
    held = max(measured(patches, per_triangle=True), measured(patches) / SHOWN_SLACK)
    assert 1 / 1.5 < est.rms_refl / held < 1.5, (est, held)
    assert run.snapshots[-1].error_refl == pytest.approx(est.rms_refl)


def test_split_rays_carry_the_shot_power_exactly():
    """Half A carries (P + W/2)/2, half B (P - W/2)/2 of every shooter; a lone ray carries P."""
    rng = np.random.default_rng(0)
    counts = np.array([1, 2, 5, 8])
    power = rng.random((4, 3))
    diff = rng.normal(size=(4, 3)) * 0.1
    rays = split_power(power, counts, diff)
    half = half_mask(counts)
    owner = np.repeat(np.arange(4), counts)
    for k in range(4):
        mine = owner == k
        assert rays[mine].sum(axis=0) == pytest.approx(power[k])
        if counts[k] > 1:
            assert rays[mine & half].sum(axis=0) == pytest.approx((power[k] + diff[k] / 2) / 2)
    assert half.sum() == 1 + 1 + 3 + 4


def test_combine_normalisations():
    """rms over RMS(B) and over RMS(B - E) from area-weighted sums; noise is |D|/2."""
    sums = NoiseSums(d2=4.0 * 0.01, b2=4.0, r2=1.0, area=1.0, r1=np.ones(3), rho1=np.full(3, 0.5))
    est = combine(sums, np.zeros(3))
    assert est.rms == pytest.approx(0.1)
    assert est.rms_norm == pytest.approx(0.05)
    assert est.rms_refl == pytest.approx(0.1)
    assert est.bias_refl == 0.0
    assert math.isinf(combine(NoiseSums(d2=1.0, b2=1.0, r2=0.0, area=1.0), np.zeros(3)).rms_refl)
    # bias: 0.1 W/m^2 still to arrive on rho 0.5, laid out as a uniform irradiance before any
    # layout was read: 0.05 W/m^2 on every patch, against RMS(B - E) = 1: 5%
    sums.rho2 = np.full(3, 0.25)
    biased = combine(sums, np.full(3, 0.1))
    assert biased.bias_refl == pytest.approx(0.05) and biased.noise_refl == pytest.approx(0.1)
    # a uniform layout read from the light so far (H = 2 W/m^2 everywhere) says the same; the same
    # light still to come, all in one half of the area (H = 4 there, 0 in the other), sqrt(2) more
    sums.l1, sums.l2 = np.full(3, 0.5 * 2.0), np.full(3, 0.25 * 4.0)
    assert combine(sums, np.full(3, 0.1)).bias_refl == pytest.approx(0.05)
    sums.l1, sums.l2 = np.full(3, 0.5 * 0.5 * 4.0), np.full(3, 0.5 * 0.25 * 16.0)
    assert combine(sums, np.full(3, 0.1)).bias_refl == pytest.approx(0.05 * math.sqrt(2.0))
    assert NoiseSums.from_list(sums.as_list()).as_list() == sums.as_list()
    assert NoiseSums.from_list(sums.as_list()[:13]).l1.tolist() == [0.0] * 3  # an older peer's list


def test_bias_layout_follows_the_rooms_the_light_is_in():
    """Two 4 m rooms 20 m apart, light reflected in one only: the tally's layout cells keep the rooms
    apart, and the light still to come is laid out in the lit room (RMS sqrt(2) times a uniform
    irradiance over both), smooth within it however the light so far varies."""
    rng = np.random.default_rng(5)
    n = 4000
    room = rng.integers(0, 2, n)
    centres = rng.random((n, 3)) * 4.0 + room[:, None] * np.array([20.0, 0.0, 0.0])
    tri = np.array([[0.0, 0.0, 0.0], [0.31, 0.0, 0.0], [0.0, 0.31, 0.0]])  # a 4 m room's 96 m^2 in 2,000
    vertices = (centres[:, None, :] + tri[None]).reshape(-1, 3)
    p = Patches(vertices, np.arange(3 * n).reshape(n, 3), np.full((n, 3), 0.5), np.zeros((n, 3)),
                np.arange(n), np.zeros(n, np.int32))
    tally = NoiseTally(p)
    p.radiosity[:] = np.where(room[:, None] == 0, 0.5 * rng.random((n, 1)) * 4.0, 0.0)  # rho H, H ~ U(0, 4)
    tally.resync(p)
    assert tally._cell is not None
    assert not set(tally._cell[room == 0]) & set(tally._cell[room == 1])
    s = tally.sums()
    g = np.full(3, 0.1)
    uniform = combine(NoiseSums(b2=s.b2, r2=s.r2, area=s.area, rho1=s.rho1, rho2=s.rho2), g)
    laid = combine(s, g)
    assert laid.bias_refl == pytest.approx(math.sqrt(1.0 / np.mean(room == 0)) * uniform.bias_refl, rel=0.08)


def test_resolve_is_idempotent_and_tol_is_expert():
    c = SolverConfig()
    assert by_accuracy(c) and c.accuracy == 0.02
    r = resolve(c, 1000)
    assert r.rays_per_power == pytest.approx(rays_for(1000, 0.02)) and resolve(r, 1000) == r
    legacy = resolve(SolverConfig(tol=0.01), 1000)
    assert not by_accuracy(legacy) and legacy.rays_per_power == 2e5 and legacy.accuracy == 0.0
    assert resolve(legacy, 1000) == legacy


def _definition_sums(p, diff):
    """d2, b2, r2, r1 from their definitions (sum A mean_c x^2), with plain numpy."""
    a, b = p.area, p.radiosity
    r = b - p.emission
    return (np.sum(a * np.mean(diff ** 2, axis=1)), np.sum(a * np.mean(b ** 2, axis=1)),
            np.sum(a * np.mean(r ** 2, axis=1)), np.sum(a[:, None] * r, axis=0))


def test_commit_increments_equal_the_sums_recomputed_from_the_arrays():
    """NoiseTally.commit's flat-dot increments (no axis reductions) against the definitions.

    Random table (some rows emit), 60 batches of random distinct sorted rows with signed
    power (overshooting batches carry negative power): after each commit + deposit the
    incremental sums equal the definitions recomputed from B, E and D, and D, V gained
    exactly 2 rho (2 P_A - P) / A on the rows hit.
    """
    rng = np.random.default_rng(3)
    n = 3000
    vertices = rng.random((3 * n, 3))
    faces = np.arange(3 * n).reshape(n, 3)
    emission = np.where(rng.random((n, 1)) < 0.05, rng.random((n, 3)) * 5.0, 0.0)
    p = Patches(vertices, faces, rng.random((n, 3)) * 0.9, emission, np.arange(n), np.zeros(n, np.int32))
    tally = NoiseTally(p)
    assert tally._emits.sum() == np.count_nonzero(emission.any(axis=1)) > 0
    diff, unshot = np.zeros((n, 3)), np.zeros((n, 3))
    for i in range(60):
        hit = np.sort(rng.choice(n, int(rng.integers(1, n)), replace=False))
        received = rng.random((len(hit), 3)) * (1.0 if i % 7 else -0.3)
        received_a = received * rng.random((len(hit), 3))
        gain_d = p.rho[hit] * 2.0 * (2.0 * received_a - received) / p.area[hit, None]
        diff[hit] += gain_d
        unshot[hit] += gain_d
        land = landing(p, hit, received)
        tally.commit(p, land, received_a)
        deposit(p, hit, received, land=land)
        d2, b2, r2, r1 = _definition_sums(p, diff)
        s = tally.sums()
        assert s.d2 == pytest.approx(d2, rel=1e-10) and s.b2 == pytest.approx(b2, rel=1e-10)
        assert s.r2 == pytest.approx(r2, rel=1e-10) and s.r1 == pytest.approx(r1, rel=1e-10)
        np.testing.assert_array_equal(tally.diff, diff)
        np.testing.assert_array_equal(tally.unshot, unshot)
    tally.resync(p)
    s = tally.sums()
    assert (s.d2, s.b2, s.r2) == pytest.approx((d2, b2, r2), rel=1e-13) and s.r1 == pytest.approx(r1, rel=1e-13)
    tally.commit(p, landing(p, np.zeros(0, np.int64), np.zeros((0, 3))), np.zeros((0, 3)))  # empty batch
    assert tally.sums().as_list() == s.as_list()


def _corner_form_factor(a: float, b: float) -> float:
    """Closed form: differential area under a corner of a parallel a x b rectangle at height 1."""
    x, y = a / math.sqrt(1 + a * a), b / math.sqrt(1 + b * b)
    return (x * math.atan(b / math.sqrt(1 + a * a)) + y * math.atan(a / math.sqrt(1 + b * b))) / (2 * math.pi)


def test_polygon_form_factor_against_closed_forms():
    """Lambert's contour formula (lights.py) against the corner formula for a parallel rectangle,
    a loop of many collinear pieces, and horizon clipping: a huge light overhead fills a
    receiver's whole hemisphere (F = 1), and half of it for a receiver standing upright."""
    down = np.array([[0.0, 0.0, -1.0]])
    up = np.array([[0.0, 0.0, 1.0]])
    rect = np.array([[[0.0, 0.0, 1.0], [0.0, 2.0, 1.0], [1.5, 2.0, 1.0], [1.5, 0.0, 1.0]]])  # ccw about -z
    f = polygon_form_factor(np.zeros((1, 3)), up, rect, down)[0]
    assert f == pytest.approx(_corner_form_factor(1.5, 2.0), rel=1e-12)
    centred = rect - np.array([0.75, 1.0, 0.0])
    f = polygon_form_factor(np.zeros((1, 3)), up, centred, down)[0]
    assert f == pytest.approx(4 * _corner_form_factor(0.75, 1.0), rel=1e-12)
    # the same rectangle with each edge cut into collinear pieces
    pieces = np.concatenate([np.linspace(rect[0, k], rect[0, (k + 1) % 4], 5)[:-1] for k in range(4)])[None]
    assert polygon_form_factor(np.zeros((1, 3)), up, pieces, down)[0] == pytest.approx(_corner_form_factor(1.5, 2.0),
                                                                                       rel=1e-12)
    big = np.array([[[-1e5, -1e5, 1.0], [-1e5, 1e5, 1.0], [1e5, 1e5, 1.0], [1e5, -1e5, 1.0]]])
    assert polygon_form_factor(np.zeros((1, 3)), up, big, down)[0] == pytest.approx(1.0, abs=1e-4)
    side = np.array([[1.0, 0.0, 0.0]])
    assert polygon_form_factor(np.zeros((1, 3)), side, big, down)[0] == pytest.approx(0.5, abs=1e-4)
    # behind the light, or the light below the horizon: nothing
    assert polygon_form_factor(np.array([[0.0, 0.0, 2.0]]), down, rect, down)[0] == 0.0
    assert polygon_form_factor(np.zeros((1, 3)), -up, rect, down)[0] == 0.0


def test_cornell_light_is_one_parallelogram(tmp_path):
    """The Cornell light's 128 patches become one light: its outline, 4 corners, a parallelogram."""
    from scenes.cornell import cornell_box

    _, p, _ = prepare(cornell_box(tmp_path))
    em = np.flatnonzero(p.emission.any(axis=1))
    lights = light_polygons(p, em, p.emission[em] * p.area[em, None])
    assert lights is not None and len(lights) == 1 and lights.loops.shape == (1, 4, 3)
    assert lights.parallelogram is not None and lights.parallelogram[0]
    assert lights.area[0] == pytest.approx(p.area[em].sum(), rel=1e-12)


def test_final_gather_keeps_the_books_and_its_estimate_is_honest(uniform_furnace):
    """Accuracy mode with the direct light gathered: the reflected light is shot coarsely and
    gathered again (final.py; at 0.05 the shooting alone meets the target per input triangle).  The
    estimate is within 1.5 of the exact error, the target is met, the ledger closes, and the same
    seed gives the same B."""
    patches, tracer = uniform_furnace
    runs = []
    for _ in range(2):
        patches.reset()
        s = solve_to_accuracy(patches, SolverConfig(seed=13, accuracy=0.03), tracer)
        runs.append(patches.radiosity.copy())
    assert any(c.text.startswith("final gather") for c in s.choices.of("final_gather")), s.choices
    assert s.stats.stopped_by == "accuracy"
    est = s.estimate()
    assert assert_honest(est, patches) < 1.5 * 0.03
    assert s.ledger.closure() < 1e-9
    np.testing.assert_array_equal(runs[0], runs[1])


def test_a_final_gather_round_moves_reflected_light_but_not_its_total(uniform_furnace):
    """A round of the final gather changes B patch by patch; sum A (B - E) per channel and every
    ledger account stay as the shooting left them."""
    patches, tracer = uniform_furnace
    patches.reset()
    s = Solver(patches, SolverConfig(seed=3, tol=1e-3, rays_per_power=2e4, direct=True), tracer=tracer)
    s.run()
    assert s.direct.light is not None
    before = patches.radiosity.copy()
    books = s.ledger.copy().as_arrays()
    total = ((before - patches.emission) * patches.area[:, None]).sum(axis=0)
    assert s.final.round(32) == 32 * len(patches)
    after = ((patches.radiosity - patches.emission) * patches.area[:, None]).sum(axis=0)
    np.testing.assert_allclose(after, total, rtol=1e-12)
    assert np.abs(patches.radiosity - before).max() > 0
    for name, value in s.ledger.as_arrays().items():
        np.testing.assert_array_equal(value, books[name])


@pytest.fixture(scope="module")
def office_lights(tmp_path_factory):
    """The 2x2 office (lamps of four rooms, doorways), its lights and receivers."""
    from dcrad.pipeline import resolve_scene

    _, p, _ = prepare(resolve_scene("office:rows=2,cols=2", tmp_path_factory.mktemp("office")))
    em = np.flatnonzero(p.emission.any(axis=1))
    lights = light_polygons(p, em, p.emission[em] * p.area[em, None])
    assert lights is not None
    return p, lights, np.flatnonzero(p.rho.any(axis=1))


def test_light_lists_bound_the_exact_form_factor(office_lights):
    """Every receiver's exact unoccluded form factor (Lambert) to every light, at its centroid and
    near its corners, is within its cell's bound: 0 where the light is not listed, at most
    q FAR_BOUND where the light is far (q < 1); the lists never drop a light a receiver sees."""
    from dcrad.transport.direct import FAR_BOUND, light_lists

    p, lights, rec = office_lights
    lists = light_lists(p, lights, rec)
    cell_of = np.empty(len(rec), np.int64)
    cell_of[lists.order] = np.repeat(np.arange(len(lists.count)), lists.count)
    q = np.zeros((len(lists.count), len(lights)))
    q[lists.cell, lists.light] = lists.q
    assert (q < 1).any() and (q == 1).any() and (q == 0).any()
    corners = p.vertices[p.faces[rec]]
    for w in (None, 0, 1, 2):
        x = p.centroid[rec] if w is None else 0.999 * corners[:, w] + 0.001 * p.centroid[rec]
        for light in range(len(lights)):
            loops = np.flatnonzero(lights.loop_light == light)
            f = sum(polygon_form_factor(x, p.normal[rec], np.repeat(lights.loops[j][None], len(rec), axis=0),
                                        np.repeat(lights.normal[light][None], len(rec), axis=0)) for j in loops)
            qi = q[cell_of, light]
            assert np.all(f[qi == 0] <= 1e-12)
            assert np.all(f[qi < 1] <= qi[qi < 1] * FAR_BOUND * (1 + 1e-6))  # q is stored float32


def test_far_pairs_are_drawn_without_bias(office_lights, monkeypatch):
    """light_pairs draws a far light's pairs per half with chance q, weighted 1/q: over many
    draws each pair's weight averages 1, and no pair outside the full set (every listed light
    near) is drawn."""
    from dcrad.transport import direct

    p, lights, rec = office_lights
    monkeypatch.setattr(direct, "FAR_BOUND", 1e-300)
    s, lt, present, w = direct.light_pairs(p, lights, rec, np.random.default_rng(0))
    assert present.all() and np.all(w == 1)
    n_l = len(lights)
    full = s * n_l + lt
    monkeypatch.undo()
    lists = direct.light_lists(p, lights, rec)
    draws = 60
    total = np.zeros((len(full), 2))
    for seed in range(draws):
        s, lt, present, w = direct.light_pairs(p, lights, rec, np.random.default_rng(seed), lists)
        code = s * n_l + lt
        at = np.searchsorted(full, code)
        assert np.all(full[np.minimum(at, len(full) - 1)] == code)
        for h in range(2):
            total[:, h] += np.bincount(at, weights=w * present[:, h], minlength=len(full))
    mean = total / draws
    cell_of = np.empty(len(rec), np.int64)
    cell_of[lists.order] = np.repeat(np.arange(len(lists.count)), lists.count)
    q = np.zeros((len(lists.count), n_l))
    q[lists.cell, lists.light] = lists.q
    far = q[cell_of[full // n_l], full % n_l] < 1.0
    assert far.sum() > 100
    # a far pair's weight per draw: 1/q with chance q (binomial picks, with replacement)
    assert abs(float(mean[far].mean()) - 1.0) < 0.02
    assert np.all(mean[~far] == 1.0)


@pytest.fixture(scope="module")
def bright_box(uniform_furnace):
    """The furnace cube reading B - E = 1 everywhere but 8 on a 0.4 m square of its floor (4% of its
    area): the bright set of final.Bright."""
    patches, tracer = uniform_furnace
    c = patches.centroid
    spot = (c[:, 2] < 1e-9) & (np.abs(c[:, 0] - 0.5) < 0.2) & (np.abs(c[:, 1] - 0.5) < 0.2)
    refl = np.ones((len(patches), 3))
    refl[spot] = 8.0
    return patches, tracer, refl, spot


def _gathers(patches, tracer, refl, share, rays, seeds, spot=None):
    """(seeds, n, 3) indirect irradiance G = what the final gather's rays read, per receiver, and the
    half difference G_A - G_B (final.FinalGather's sums)."""
    from dcrad.transport.final import FinalGather

    patches.reset()
    patches.radiosity = patches.emission + refl
    zero = np.zeros((len(patches), 3))
    g, d = [], []
    for seed in seeds:
        fg = FinalGather(patches, tracer, zero, zero, zero, bright=share)
        if share > 0:
            assert fg.bright is not None and np.array_equal(fg.bright.rows, np.flatnonzero(spot))
        fg.add(rays, np.random.default_rng(seed))
        g.append(0.5 * (fg.sum_a + fg.sum_b) / fg.per_half)
        d.append((fg.sum_a - fg.sum_b) / fg.per_half)
    patches.reset()
    return np.array(g), np.array(d)


def test_bright_area_samples_are_unbiased_against_the_cosine_gather(bright_box):
    """The gather with the bright patches also drawn by area (balance heuristic, final.Bright)
    against the plain cosine gather, 12 seeds each: per patch the means agree within their
    standard errors (mean z^2 about 1), the area-weighted total within 0.5%, and the noise
    of the patches that see the bright square is lower."""
    patches, tracer, refl, spot = bright_box
    mis, _ = _gathers(patches, tracer, refl, 0.25, 48, range(12), spot)
    plain, _ = _gathers(patches, tracer, refl, 0.0, 60, range(100, 112))
    se = np.sqrt(mis.var(axis=0, ddof=1) / len(mis) + plain.var(axis=0, ddof=1) / len(plain))
    z = (mis.mean(axis=0) - plain.mean(axis=0))[:, 0] / np.maximum(se[:, 0], 1e-12)
    assert 0.6 < float(np.mean(z * z)) < 1.5, float(np.mean(z * z))
    area = patches.area
    assert float(np.dot(mis.mean(axis=0)[:, 0], area) / np.dot(plain.mean(axis=0)[:, 0], area)) == pytest.approx(
        1.0, abs=5e-3)
    # the ceiling (z = 1) sees the square best: its noise per ray falls
    top = patches.centroid[:, 2] > 1 - 1e-9
    assert mis[:, top, 0].std(axis=0).mean() < 0.8 * plain[:, top, 0].std(axis=0).mean()


def test_bright_area_samples_keep_the_half_difference_honest(bright_box):
    """Half A and half B of the gather with area samples are independent: the noise the half
    difference estimates, |G_A - G_B| / 2 in RMS over patches and seeds, is the spread of G
    over seeds within 15%."""
    patches, tracer, refl, spot = bright_box
    g, d = _gathers(patches, tracer, refl, 0.25, 48, range(20, 32), spot)
    measured = float(np.sqrt(g.var(axis=0, ddof=1).mean()))
    estimated = float(np.sqrt((0.25 * d * d).mean()))
    assert 1 / 1.15 < estimated / measured < 1.15, (estimated, measured)


def test_korobov_lattice_is_the_fibonacci_lattice_and_integrates_a_disk_without_bias():
    """sampling.rank1_lattice: at Fibonacci m the generator is the Fibonacci lattice's; each
    coordinate takes every one of the m strata once; over random shifts it integrates a disk's
    indicator (a discontinuous integrand like the gather's, area pi r^2 known) without bias and
    with a smaller spread than the R2 sequence's first m points (what the final gather used)."""
    from dcrad.transport.sampling import korobov_generator, lattice, rank1_lattice

    assert [korobov_generator(m) for m in (21, 34, 55, 89, 144)] == [8, 13, 21, 34, 55]
    rng = np.random.default_rng(5)
    m, sets, r = 89, 4000, 0.3
    index = np.tile(np.arange(m), sets)
    shift = np.repeat(rng.random((sets, 2)), m, axis=0)
    u = rank1_lattice(index, m, shift)
    assert u.min() >= 0.0 and u.max() < 1.0
    for c in range(2):
        strata = np.floor((u[:, c] - shift[:, c]) % 1.0 * m).astype(int).reshape(sets, m)
        assert (np.sort(strata, axis=1) == np.arange(m)).all()

    def disk(p):
        return (((p - 0.5) ** 2).sum(axis=1) < r * r).reshape(sets, m).mean(axis=1)

    truth = math.pi * r * r
    kor = disk(u)
    r2 = disk(lattice(index, shift, 2))
    assert abs(kor.mean() - truth) < 4 * kor.std() / math.sqrt(sets)
    assert abs(r2.mean() - truth) < 4 * r2.std() / math.sqrt(sets)
    assert kor.std() < 0.95 * r2.std()  # 0.90 measured (variance 0.81)


def test_the_held_reading_is_the_triangles_unless_the_elements_would_carry_more_than_the_slack():
    """held_factors: B per input triangle, its noise raised to the elements' over SHOWN_SLACK^2 where
    that is more (in the triangles' RMS(B - E)); the bias and the reference magnitudes are the
    triangles'."""
    # a wall of two triangles in many elements: the triangles average the noise 100x, the elements bind
    assert held_factors((0.01, 0.99, 0.98), (1.0, 1.0, 1.0)) == pytest.approx((0.98 / SHOWN_SLACK ** 2, 0.99, 0.98))
    # a triangle a element: the reading is the triangles' own
    assert held_factors((0.7, 1.0, 1.0), (0.7, 1.0, 1.0)) == (0.7, 1.0, 1.0)
    # the estimate combines them: noise_refl^2 = d2 fd / (4 r2 fr)
    sums = NoiseSums(d2=4e-4, b2=1.0, r2=1.0, area=1.0)
    fd, _, fr = held_factors((0.01, 1.0, 1.0), (1.0, 1.0, 1.0))
    held = combine(NoiseSums(d2=sums.d2 * fd, b2=1.0, r2=sums.r2 * fr, area=1.0), np.zeros(3))
    element = combine(sums, np.zeros(3))
    assert held.noise_refl == pytest.approx(element.noise_refl / SHOWN_SLACK)
