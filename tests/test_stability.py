"""Numerical stability on stiff and extreme scenes, and what a scene lets us leave out.

Every scene is built by a generator here or in scenes/; no large files.  The
checks are identities (closed enclosure, linearity, scale invariance), the
ledger, and finiteness.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import scenes
from dcrad.config import SolverConfig
from dcrad.division.divide import DivideConfig, solve_divided
from dcrad.io.scene import load_scene
from dcrad.meshing.patches import Patches
from dcrad.solving.energy import rms_error
from dcrad.solving.solver import Solver


def finite(*arrays):
    return all(np.all(np.isfinite(a)) for a in arrays)


def identity_error(p: Patches, rho: float) -> np.ndarray:
    area = p.area.sum()
    mean = ((p.radiosity - p.emission) * p.area[:, None]).sum(axis=0) / area
    expect = rho * p.emitted_power / ((1 - rho) * area)
    return np.abs(mean - expect) / expect


# == stiff: closed rooms with rho up to 0.999 ======================================

@pytest.mark.parametrize("rho,patch,rays", [(0.9, 0.1, 2e5), (0.99, 0.2, 5e4), (0.999, 0.34, 1e4)])
def test_stiff_furnace_converges_to_the_exact_identity(tmp_path, rho, patch, rays):
    """With overshooting, rho = 0.999 (about 4600 plain bounces to 1%) converges, exactly."""
    tol = 0.01
    path = scenes.write_builtin("furnace", tmp_path, rho=rho)
    p = load_scene(path).patches(patch)
    s = Solver(p, SolverConfig(tol=tol, rays_per_power=rays, seed=1))
    s.run()
    led = s.ledger
    assert s.stats.stopped_by == "tolerance" and finite(p.radiosity, p.unshot)
    assert led.closure() < 1e-9
    lost = (led.escaped.sum() + led.back_faces.sum()) / led.emitted.sum()
    # the identity's shortfall is exactly the signed unsettled power: bounded by the residual
    assert np.all(identity_error(p, rho) <= s.residual() + lost + 1e-9)
    assert np.all(identity_error(p, rho) < 2 * tol)
    assert s.stiff is not None and s.stiff.scale.any()  # it overshot
    assert s.stiff.ret >= SolverConfig().overshoot_min_return  # because its measured return ratio is stiff


def test_overshooting_needs_far_fewer_bounces(tmp_path):
    path = scenes.write_builtin("furnace", tmp_path, rho=0.99)
    runs = {}
    for ov in (0.0, 1.0):
        p = load_scene(path).patches(0.2)
        s = Solver(p, SolverConfig(tol=0.01, rays_per_power=5e4, overshoot=ov, seed=2))
        s.run()
        assert s.stats.stopped_by == "tolerance" and s.ledger.closure() < 1e-9
        runs[ov] = (s.stats.shots, p.radiosity.copy(), p.area)
    assert runs[1.0][0] * 5 < runs[0.0][0], (runs[1.0][0], runs[0.0][0])
    # same limit: the two solutions differ by Monte Carlo noise only
    b0, b1, area = runs[0.0][1], runs[1.0][1], runs[0.0][2]
    scale = np.sqrt(np.dot((b0 ** 2).mean(axis=1), area) / area.sum())
    assert rms_error(b1, b0, area) < 0.1 * scale


@pytest.mark.parametrize("rho", [0.9, 0.99, 0.999])
def test_stiff_divided_run_converges_exactly(tmp_path, rho):
    """The furnace cut in two across open space, up to rho = 0.999: the job overshoots as one
    scene (signed twin power crosses the boundary) and the identity holds at convergence."""
    tol = 0.01
    path = scenes.write_builtin("furnace", tmp_path, rho=rho)
    p = load_scene(path).patches(0.2)
    run, subs, boundaries, part = solve_divided(p, SolverConfig(tol=tol, rays_per_power=5e4, seed=3),
                                               DivideConfig(subscenes=2))
    assert run.stopped_by == "tolerance" and max(run.barrier_closures) < 1e-9
    assert finite(p.radiosity, p.unshot) and len(boundaries) == 1
    led = run.ledger
    lost = (led.escaped.sum() + led.back_faces.sum()) / led.emitted.sum()
    assert np.all(identity_error(p, rho) <= led.residual() + lost + 1e-9)
    assert np.all(identity_error(p, rho) < 2 * tol)
    assert all(s.plan is not None and s.plan.stiffness.scale.any() for s in subs)  # it did overshoot
    assert run.stiff is not None and run.stiff.ret > 0.85


@pytest.mark.parametrize("mode,gain", [("binned", 2.0), ("exact", 1.5)])
def test_divided_overshooting_needs_fewer_barriers_for_the_same_limit(tmp_path, mode, gain):
    """Binned twins hold crossing light to the barrier, so overshooting saves more barriers there;
    exact forwarding also ends a barrier once 4 batches of crossing rays are held (measured with
    seed 3: binned 22 -> 9, exact 23 -> 13 barriers)."""
    path = scenes.write_builtin("furnace", tmp_path, rho=0.9)
    runs = {}
    for ov in (0.0, 1.0):
        p = load_scene(path).patches(0.2)
        run, *_ = solve_divided(p, SolverConfig(tol=0.01, rays_per_power=5e4, overshoot=ov, seed=3),
                                DivideConfig(subscenes=2, mode=mode), record=False)
        assert run.stopped_by == "tolerance" and max(run.barrier_closures) < 1e-9
        runs[ov] = (run.barriers, p.radiosity.copy(), p.area)
    assert gain * runs[1.0][0] <= runs[0.0][0], (runs[1.0][0], runs[0.0][0])
    b0, b1, area = runs[0.0][1], runs[1.0][1], runs[0.0][2]
    scale = np.sqrt(np.dot((b0 ** 2).mean(axis=1), area) / area.sum())
    assert rms_error(b1, b0, area) < 0.1 * scale


def test_stiffness_is_measured_as_the_return_ratio(tmp_path):
    """Closed furnace: nothing is lost and every landing keeps rho, so lambda = rho exactly
    (in magnitudes, even after rays of both signs have flown); the ray factor follows."""
    rho = 0.99
    path = scenes.write_builtin("furnace", tmp_path, rho=rho)
    p = load_scene(path).patches(0.25)
    cfg = SolverConfig(tol=0.01, rays_per_power=2e4, seed=4)
    s = Solver(p, cfg)
    for _ in range(6):
        s.step()
    shot, lost, landed, kept = s.tallies
    assert np.all(lost <= 1e-6 * shot) and np.allclose(kept, rho * landed, rtol=1e-12)
    assert (p.unshot < 0).any()  # overshooting has left negative unshot power behind
    st = s.stiffness()
    lam = rho * (1 - lost / shot)
    assert np.allclose(st.scale, 1.0 / ((1 - lam) * p.area.sum()), rtol=1e-9)
    assert st.ray_factor == pytest.approx(np.sqrt((1 - cfg.overshoot_min_return) / (1 - lam.max())), rel=1e-9)
    # not stiff: no overshoot and the full ray budget
    from dcrad.solving.stiffness import stiffness

    mild = stiffness(np.array([shot, lost, landed, 0.5 * landed]), float(p.area.sum()), cfg)
    assert not mild.scale.any() and mild.ray_factor == 1.0
    assert stiffness(s.tallies, 6.0, cfg.replace(stiff_rays=False)).ray_factor == 1.0


def test_return_tallies_do_not_cancel_between_signs():
    """Rays of both signs: a positive one lands on a rho 0.7 patch, a negative one on a
    rho 0.3 patch, and one of each escapes.  Every signed sum is 0; the magnitudes are not."""
    from dcrad.transport.rays import Tracer
    from dcrad.transport.shoot import RayBatch, trace

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1], [2, 0, 0], [3, 0, 0], [2, 0, 1]], float)
    rho = np.array([[0.7] * 3, [0.3] * 3])
    p = Patches(v, np.array([[0, 2, 1], [3, 5, 4]]), rho, 0.0, np.arange(2), np.zeros(2), ["a", "b"])
    assert (p.normal[:, 1] > 0).all()
    origins = np.array([[0.2, 1, 0.2], [2.2, 1, 0.2], [0.2, 1, 0.2], [2.2, 1, 0.2]])
    dirs = np.array([[0, -1, 0], [0, -1, 0], [0, 1, 0], [0, 1, 0]], float)
    power = np.array([[1.0] * 3, [-1.0] * 3, [0.5] * 3, [-0.5] * 3])
    t = trace(Tracer(p.triangles), RayBatch(origins, dirs, power, np.zeros(4, np.int64)), p)
    assert np.allclose(t.received.sum(axis=0), 0) and np.allclose(t.escaped, 0)
    assert np.allclose(t.landed, 2) and np.allclose(t.kept, 1.0) and np.allclose(t.lost, 1.0)


def test_stiff_rays_spend_fewer_rays_for_the_same_limit(tmp_path):
    """In a stiff room the power per ray grows with sqrt(1/(1-lambda)): far fewer rays, the
    same exact identity, and a solution that differs only by Monte Carlo noise."""
    rho = 0.99
    path = scenes.write_builtin("furnace", tmp_path, rho=rho)
    runs = {}
    for sr in (False, True):
        p = load_scene(path).patches(0.2)
        s = Solver(p, SolverConfig(tol=0.01, rays_per_power=5e4, stiff_rays=sr, seed=5))
        s.run()
        assert s.stats.stopped_by == "tolerance" and s.ledger.closure() < 1e-9
        assert np.all(identity_error(p, rho) < 0.02)
        runs[sr] = (s.stats.rays, p.radiosity.copy(), p.area)
    assert 3 * runs[True][0] < runs[False][0], (runs[True][0], runs[False][0])
    b0, b1, area = runs[False][1], runs[True][1], runs[False][2]
    scale = np.sqrt(np.dot((b0 ** 2).mean(axis=1), area) / area.sum())
    assert rms_error(b1, b0, area) < 0.15 * scale


@pytest.mark.parametrize("divided", [False, True])
def test_one_stiff_channel_among_mild_ones(divided):
    """rho = (0.99, 0.6, 0.3): stiffness is per channel.  Each channel's own identity holds
    and no patch goes negative, split or not."""
    rho = np.array([0.99, 0.6, 0.3])
    base = box_patches(1.0, 0.5, 0.1, {lambda c: c[:, 1] > 0.99: 1.0})
    p = Patches(base.vertices, base.faces, np.tile(rho, (len(base.faces), 1)), base.emission, base.source,
                base.obj, base.names)
    cfg = SolverConfig(tol=0.01, seed=1)
    if divided:
        run, *_ = solve_divided(p, cfg, DivideConfig(subscenes=2), record=False)
        led, ok = run.ledger, run.stopped_by == "tolerance" and max(run.barrier_closures) < 1e-9
    else:
        s = Solver(p, cfg)
        s.run()
        led, ok = s.ledger, s.stats.stopped_by == "tolerance" and s.ledger.closure() < 1e-9
    assert ok and finite(p.radiosity) and p.radiosity.min() > 0
    area = p.area.sum()
    mean = ((p.radiosity - p.emission) * p.area[:, None]).sum(axis=0) / area
    expect = rho * p.emitted_power / ((1 - rho) * area)
    assert np.all(np.abs(mean - expect) / expect < 2 * cfg.tol) and led.residual() <= cfg.tol


# == extreme ========================================================================

def box_patches(size: float, rho: float, edge: float, emitters: dict) -> Patches:
    """Closed cube [0,size]^3, inward normals; emitters: {face centroid test -> exitance}."""
    import trimesh

    from dcrad.meshing.patches import subdivide

    box = trimesh.creation.box(extents=(size, size, size))
    v, f, idx = subdivide(box.vertices + size / 2, box.faces[:, ::-1], edge)
    p = Patches(v, f, rho, 0.0, idx, np.zeros(len(f)), ["box"])
    e = np.zeros((len(f), 3))
    for select, value in emitters.items():
        e[select(p.centroid / size)] = value
    return Patches(v, f, rho, e, idx, np.zeros(len(f)), ["box"])


def test_emission_spanning_eight_decades_is_linear():
    """A 1e5 W/m^2 lamp and a 1e-3 W/m^2 one in the same room: the faint one still counts.

    The solution is linear in E, so (both) - (bright only) must equal (faint only)
    on the faint patch, to the bright solution's round-off; and nothing is NaN.
    """
    bright = lambda c: (c[:, 1] > 0.99) & (np.abs(c[:, 0] - 0.5) < 0.1) & (np.abs(c[:, 2] - 0.5) < 0.1)
    faint = lambda c: (c[:, 1] < 0.01) & (c[:, 0] < 0.1) & (c[:, 2] < 0.1)
    both = box_patches(1.0, 0.5, 0.1, {bright: 1e5, faint: 1e-3})
    s = Solver(both, SolverConfig(tol=1e-3, seed=4))
    s.run()
    assert finite(both.radiosity, both.unshot) and s.ledger.closure() < 1e-9
    lamp = faint(both.centroid)
    assert lamp.any() and np.all(both.radiosity[lamp] >= 1e-3)  # its own emission is never lost
    only = box_patches(1.0, 0.5, 0.1, {faint: 1e-3})
    s2 = Solver(only, SolverConfig(tol=1e-3, seed=4))
    s2.run()
    assert s2.ledger.closure() < 1e-9 and np.all(only.radiosity[lamp] >= 1e-3)


@pytest.mark.parametrize("scale", [1e3, 1e-3])
def test_kilometre_and_millimetre_scenes_match_the_metre_scene(tmp_path, scale):
    """Radiosity does not depend on units: the same furnace in km or mm gives the same B."""
    path = scenes.write_builtin("furnace", tmp_path, rho=0.7, emission=2.0)
    results = []
    for sc in (1.0, scale):
        scene = load_scene(path, scale=sc)
        p = scene.patches(0.11 * sc)
        s = Solver(p, SolverConfig(tol=1e-3, seed=5))
        s.run()
        assert s.ledger.closure() < 1e-9 and finite(p.radiosity)
        assert (s.ledger.back_faces.sum() + s.ledger.escaped.sum()) < 1e-4 * s.ledger.emitted.sum()
        results.append(p)
    a, b = results
    assert len(a) == len(b)
    scale_b = np.sqrt(np.dot((a.radiosity ** 2).mean(axis=1), a.area) / a.area.sum())
    assert rms_error(b.radiosity, a.radiosity, a.area) < 0.05 * scale_b


def test_tiny_slivers_and_huge_triangles_together():
    """Areas differing by 1e6 and a 1e4:1 sliver in one closed box: finite, ledger closed."""
    p = box_patches(1.0, 0.6, 0.25, {lambda c: c[:, 1] > 0.99: 1.0})
    # add a sliver and a tiny triangle lying on the floor, facing up, 1 mm above it
    extra = np.array([[[0.2, 0.001, 0.2], [0.2, 0.001, 0.2001], [0.9, 0.001, 0.2]],         # sliver
                      [[0.5, 0.001, 0.5], [0.5, 0.001, 0.5001], [0.5001, 0.001, 0.5]]])     # area 5e-9
    v = np.vstack([p.vertices, extra.reshape(-1, 3)])
    f = np.vstack([p.faces, np.arange(len(p.vertices), len(v)).reshape(-1, 3)])
    n = len(f)
    e = np.vstack([p.emission, np.zeros((2, 3))])
    q = Patches(v, f, 0.6, e, np.arange(n), np.zeros(n), ["box"])
    assert q.area.max() / q.area.min() > 1e6
    s = Solver(q, SolverConfig(tol=1e-3, seed=6))
    s.run()
    assert finite(q.radiosity, q.unshot) and s.ledger.closure() < 1e-9
    assert np.all(q.radiosity >= 0) or s.config.overshoot > 0  # overshooting may dip below 0 mid-run
    assert q.radiosity[-2:].min() >= -1e-9 * q.radiosity.max()


def test_surfaces_a_millimetre_apart():
    """Two facing panels 1 mm apart inside a lit 10 m room: light between them, nothing lost."""
    room = box_patches(10.0, 0.5, 2.5, {lambda c: c[:, 1] > 0.99: 1.0})
    y = 5.0
    panel = np.array([[[4, y, 4], [6, y, 4], [6, y, 6]], [[4, y, 4], [6, y, 6], [4, y, 6]],  # faces down? fix below
                      [[4, y + 0.001, 4], [4, y + 0.001, 6], [6, y + 0.001, 6]],
                      [[4, y + 0.001, 4], [6, y + 0.001, 6], [6, y + 0.001, 4]]], float)
    v = np.vstack([room.vertices, panel.reshape(-1, 3)])
    f = np.vstack([room.faces, np.arange(len(room.vertices), len(v)).reshape(-1, 3)])
    n = len(f)
    q = Patches(v, f, 0.5, np.vstack([room.emission, np.zeros((4, 3))]), np.arange(n), np.zeros(n), ["room"])
    s = Solver(q, SolverConfig(tol=1e-3, seed=7))
    s.run()
    assert finite(q.radiosity) and s.ledger.closure() < 1e-9


def test_open_scene_where_most_power_escapes():
    """A lamp over a small floor in empty space: most power escapes, all of it accounted."""
    tri = np.array([[[0, 0, 0], [0, 0, 1], [1, 0, 1]], [[0, 0, 0], [1, 0, 1], [1, 0, 0]],
                    [[0, 1, 0], [1, 1, 0], [1, 1, 1]], [[0, 1, 0], [1, 1, 1], [0, 1, 1]]], float)
    v = tri.reshape(-1, 3)
    p = Patches(v, np.arange(12).reshape(-1, 3), 0.8, np.array([[0] * 3] * 2 + [[10.0] * 3] * 2),
                np.arange(4), np.zeros(4), ["scene"])
    s = Solver(p, SolverConfig(tol=1e-4, seed=8))
    s.run()
    led = s.ledger
    assert led.closure() < 1e-9 and finite(p.radiosity)
    assert led.escaped.sum() > 0.5 * led.emitted.sum()


# == leave out what a scene does not need =============================================

def test_grey_scene_tallies_one_channel_with_the_same_result(tmp_path):
    path = scenes.write_builtin("furnace", tmp_path, rho=0.8)
    grey = load_scene(path).patches(0.25)
    s = Solver(grey, SolverConfig(tol=1e-3, seed=9))
    assert s.channels == 1
    s.run()
    colour = load_scene(path).patches(0.25)
    c = Solver(colour, SolverConfig(tol=1e-3, seed=9))
    c.channels = 3  # force the full tally on the same scene
    c.run()
    assert np.array_equal(grey.radiosity, colour.radiosity)


def test_report_lists_what_was_left_out(tmp_path):
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "dcrad.cli", "solve", "furnace", "--workers", "0", "--out", str(out),
                        "--width", "40", "--height", "30"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["channels"] == 1 and report["divided"] is None  # grey furnace, one subscene: no twins
    out2 = tmp_path / "out2"
    r = subprocess.run([sys.executable, "-m", "dcrad.cli", "solve", "cornell", "--workers", "0", "--subscenes", "2",
                        "--boundary", "binned", "--out", str(out2), "--width", "40", "--height", "30", "--tol", "0.05"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    report = json.loads((out2 / "report.json").read_text())
    div = report["divided"]
    assert report["channels"] == 3 and div["subscenes"] == 2 and div["mode"] == "binned"
    assert 0 < div["max_twin_bytes"] < div["dense_twin_bytes"]  # sparse twin buffers
    assert 0 < div["twin_blocks"] < div["twins_delivered"]  # weak twin light shared coarser bins
    assert report["stiffness"] is None  # rho <= 0.8 in the Cornell box: never stiff
