"""Light sources that are not surfaces (emitters.py), against closed forms.

The layouts are the CIE 171:2006 ones for point sources: an isotropic source in a closed black
room (case 5.4: every lumen lands), a source above a black floor (case 5.2: E = I cos / d^2), and
the source at the centre of a closed cube of uniform reflectance (case 5.8: the mean indirect
irradiance is rho Phi / (S (1 - rho))).  A new kind of emitter is checked the same way with a
class defined here, to show that adding one touches nothing but its own class.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import dcrad
from dcrad.errors import ConfigError
from dcrad.outputs.photometry import workplane
from dcrad.transport.emitters import Emitter, PointSource
from dcrad.transport.rays import Tracer
from scenes.objwriter import ObjWriter

SIDE, HEIGHT = 4.0, 3.0


def box(folder, rho: float, size=(SIDE, HEIGHT, SIDE), stem="box", floor_only=False):
    """A closed box (or only its floor) of one reflectance, its faces facing in; Y up."""
    x, y, z = size
    w = ObjWriter()
    w.material("surface", rho)
    faces = [("floor", 1, 0.0, 1)]
    if not floor_only:
        faces += [("ceiling", 1, y, -1), ("wall_x0", 0, 0.0, 1), ("wall_x1", 0, x, -1), ("wall_z0", 2, 0.0, 1),
                  ("wall_z1", 2, z, -1)]
    for name, axis, value, facing in faces:
        w.begin(name, "surface")
        lo, hi = {0: ((0.0, 0.0), (y, z)), 1: ((0.0, 0.0), (x, z)), 2: ((0.0, 0.0), (x, y))}[axis]
        w.add_rect(axis, value, lo, hi, facing)
    return w.write(folder, stem)


def test_an_isotropic_source_in_a_closed_black_room_puts_every_watt_on_its_surfaces(tmp_path):
    """CIE 171:2006 case 5.4: Phi = 4 pi I emitted, all of it absorbed by the black surfaces, none
    escaping; the ledger closes to round-off and the run is exact (nothing reflects)."""
    intensity = 10_000.0 / 179.0 / (4 * math.pi)  # a 10,000 lm source, W/sr at 179 lm/W
    src = PointSource([2.0, 1.5, 2.0], np.full(3, intensity), name="lamp")
    result = dcrad.solve(box(tmp_path, 0.0), accuracy=0.05, patch_size=0.5, sources=[src], seed=1)
    led = result.report["ledger"]
    phi = 4 * math.pi * intensity
    assert sum(led["emitted"]) == pytest.approx(3 * phi, rel=1e-12)
    assert sum(led["absorbed"]) == pytest.approx(3 * phi, rel=1e-9)
    assert sum(led["escaped"]) == 0.0 and led["closure"] < 1e-9
    assert not any("no emitters" in w for w in result.report["warnings"])


def test_a_point_above_a_black_floor_lights_it_by_the_inverse_square_law(tmp_path):
    """CIE 171:2006 case 5.2: I(theta) = I0 cos(theta) (a downlight) 3 m above a black floor; every
    work-plane point reads E = I cos / d^2 = I0 h^2 / d^4 (exact: one shadow ray a point), and the
    floor's patches their mean of it, from the solve's outputs."""
    i0 = 1000.0 / 179.0

    def downlight(dirs):
        return np.repeat(np.maximum(-dirs[:, 1:2], 0.0) * i0, 3, axis=1)

    pos = np.array([2.0, HEIGHT, 2.0])
    src = PointSource(pos, downlight, name="downlight")
    assert src.power() == pytest.approx(np.full(3, math.pi * i0), rel=1e-3)  # integral of I0 cos over a hemisphere
    path = box(tmp_path, 0.0, floor_only=True)
    result = dcrad.solve(path, tmp_path / "out", accuracy=0.05, patch_size=0.25, sources=[src], seed=1,
                         width=32, height=24)
    wp = workplane(result.patches, 0.0001, spacing=0.37, tracer=Tracer.mesh(result.patches), border=0.0)
    d = pos - wp["points"]
    r2 = (d * d).sum(axis=1)
    expected = 179.0 * i0 * (HEIGHT - 0.0001) ** 2 / r2 ** 2  # lux: Y of a grey W/m^2 is itself
    assert len(expected) > 80
    np.testing.assert_allclose(wp["lux"], expected, rtol=1e-9)


def test_a_point_source_s_direct_light_on_reflecting_patches_is_gathered_exactly(tmp_path):
    """A downlight I0 cos(theta) 3 m above a grey floor plate (nothing else: no light comes back): each
    floor patch's reflected light B - E is rho times the mean of I cos / d^2 over it (the degree-2
    rule, computed here from the geometry alone) times one factor common to all patches, the share
    of the power its rays landed over the gathered total (within their noise of 1).  Shot instead
    (--no-direct), every patch carries its own noise."""
    from dcrad.transport.sampling import DEGREE2_RULE

    i0, rho = 1000.0 / 179.0, 0.5

    def downlight(dirs):
        return np.repeat(np.maximum(-dirs[:, 1:2], 0.0) * i0, 3, axis=1)

    pos = np.array([2.0, HEIGHT, 2.0])
    path = box(tmp_path, rho, floor_only=True)
    ratios = {}
    for direct in (True, False):
        result = dcrad.solve(path, accuracy=0.05, patch_size=0.25, sources=[PointSource(pos, downlight)], seed=4,
                             direct=direct)
        p = result.patches
        points = np.einsum("rc,kcx->krx", DEGREE2_RULE, p.corners())
        d = pos - points
        r2 = (d * d).sum(axis=2)
        h = (i0 * d[..., 1] ** 2 / r2 ** 2).mean(axis=1)  # I0 cos(theta) cos(theta) / d^2, theta at the floor
        ratios[direct] = (p.radiosity - p.emission)[:, 0] / (rho * h)
        assert result.report["ledger"]["closure"] < 1e-9
    gathered, shot = ratios[True], ratios[False]
    assert np.ptp(gathered) < 1e-9 * gathered.mean()  # one factor for every patch: no noise of its own
    assert gathered.mean() == pytest.approx(1.0, rel=0.02)
    assert np.std(shot) > 100 * np.std(gathered)


def test_the_mean_indirect_light_in_a_closed_cube_is_the_integrating_sphere_s(tmp_path):
    """CIE 171:2006 case 5.8: an isotropic source at the centre of a closed 4 m cube of reflectance
    rho: the area-weighted mean of B - E over the walls is the reflected exitance, and B = rho H, so
    mean H_indirect = mean H - mean H_direct = rho Phi / (S (1 - rho)).  Within the run's own
    estimate, at rho 0.5 and 0.9."""
    for rho in (0.5, 0.9):
        intensity = 1.0 / (4 * math.pi)  # 1 W
        src = PointSource([2.0, 2.0, 2.0], np.full(3, intensity))
        result = dcrad.solve(box(tmp_path / f"r{rho}", rho, (4.0, 4.0, 4.0)), accuracy=0.01, patch_size=0.5,
                             sources=[src], seed=2)
        p = result.patches
        area = float(p.area.sum())
        reflected = float((p.area[:, None] * (p.radiosity - p.emission)).sum()) / 3
        # all reflected light: rho times everything that arrives, Phi (direct) + the indirect
        expected = rho * 1.0 / (1 - rho)
        est = result.estimate
        assert est is not None and result.report["ledger"]["closure"] < 1e-9
        assert reflected == pytest.approx(expected, rel=max(3 * est.rms_refl, 0.01)), (rho, est)
        assert area == pytest.approx(96.0)


def test_a_room_lit_only_by_a_source_follows_the_final_plan(tmp_path):
    """A grey room lit by a downlight alone: its direct light is gathered exactly (a point has no
    area), so the run follows the final plan as a room lit by emitting patches does (the reflected
    light shot coarsely, then gathered again), says so, and closes its books; its error against a
    converged run of the same mesh (tol mode, another seed) is within its target and its estimate
    reads that error within 1.5x."""
    from dcrad.solving.energy import read_error

    i0 = 2000.0 / 179.0

    def downlight(dirs):
        return np.repeat(np.maximum(-dirs[:, 1:2], 0.0) * i0, 3, axis=1)

    path = box(tmp_path, 0.6)
    src = PointSource([2.0, HEIGHT - 0.1, 2.0], downlight)
    run = dcrad.solve(path, accuracy=0.03, patch_size=0.25, sources=[src], seed=4)
    codes = [c["code"] for c in run.report["choices"]]
    assert "plan" in codes and "final_gather" in codes, run.report["choices"]
    assert run.report["stats"]["stopped_by"] == "accuracy" and run.report["ledger"]["closure"] < 1e-9
    ref = dcrad.solve(path, tol=1e-4, rays_per_power=2e7, patch_size=0.25, sources=[src], seed=9)
    assert "plan" not in [c["code"] for c in ref.report["choices"]]  # tol mode: shot to the end
    est = run.estimate
    err = read_error(run.patches, run.patches.radiosity, ref.patches.radiosity)
    assert err < 2 * 0.03 and est.elements_refl is not None
    assert err / 1.5 < est.elements_refl < 1.5 * err, (err, est)


class HalfSphere:
    """A new kind of emitter, here only: isotropic below the horizontal, dark above.  It implements
    the protocol and nothing else is touched (the solver shoots it, the photometry reads it)."""

    name = "half sphere"

    def __init__(self, position, intensity: float):
        self.point = PointSource(position, lambda d: np.repeat((d[:, 1:2] < 0) * intensity, 3, axis=1))
        self.i = intensity

    def power(self):
        return np.full(3, 2 * math.pi * self.i)

    def rays(self, n, rng):
        batch = self.point.rays(n, rng)
        batch.power = batch.power * (self.power()[0] / max(float(batch.power[:, 0].sum()), 1e-300))
        return batch

    def irradiance(self, points, normals, tracer, offset):
        return self.point.irradiance(points, normals, tracer, offset)


def test_a_new_kind_of_emitter_touches_only_its_class(tmp_path):
    """The half-sphere source in a closed black room: its 2 pi I all land (the ledger), and the
    floor under it reads I / h^2 straight below (the photometry), with no change outside this file."""
    src = HalfSphere([2.0, 2.0, 2.0], 1.0)
    assert isinstance(src, Emitter)
    result = dcrad.solve(box(tmp_path, 0.0), tmp_path / "out", accuracy=0.05, patch_size=0.5, sources=[src],
                         seed=3, width=32, height=24)
    led = result.report["ledger"]
    assert sum(led["absorbed"]) == pytest.approx(3 * 2 * math.pi, rel=1e-9) and led["closure"] < 1e-9
    wp = workplane(result.patches, 0.0001, spacing=4.0 / 3, tracer=Tracer.mesh(result.patches), border=0.0)
    centre = np.argmin(np.linalg.norm(wp["points"][:, [0, 2]] - 2.0, axis=1))
    assert wp["lux"][centre] == pytest.approx(179.0 * 1.0 / (2.0 - 0.0001) ** 2, rel=1e-6)


def test_a_divided_run_gives_each_source_to_the_subscene_holding_it_and_bad_ones_are_named(tmp_path):
    """Each source belongs to the one subscene whose cell holds it (one a little outside every cell
    to the nearest), which books it as emitted and held until its first iterate shoots it; a bad
    position or intensity is named."""
    from dcrad.config import DivideConfig, SolverConfig
    from dcrad.division.divide import build_subscenes
    from dcrad.pipeline import prepare

    _, p, _ = prepare(box(tmp_path, 0.5), 0.5)
    p.sources = (PointSource([0.5, 1.5, 0.5], np.ones(3), name="lamp 7"),
                 PointSource([3.5, 1.5, 3.5], np.ones(3), name="lamp 8"),
                 PointSource([4.2, 1.5, 3.9], np.ones(3), name="outside"))
    subs, _, _, part = build_subscenes(p, SolverConfig(), DivideConfig(subscenes=2))
    held = {s.cell: [src.name for src in s.patches.sources] for s in subs}
    assert sorted(n for names in held.values() for n in names) == ["lamp 7", "lamp 8", "outside"]
    assert any(names == ["lamp 7"] for names in held.values())  # opposite corners: different cells
    for s in subs:
        state = s.state()
        own = 4 * np.pi * len(s.patches.sources)
        assert state.ledger.emitted[0] == pytest.approx(float(s.patches.emitted_power[0]) + own)
        assert state.ledger.closure() < 1e-12
    with pytest.raises(ConfigError, match="position"):
        PointSource([np.nan, 0.0, 0.0])
    with pytest.raises(ConfigError, match="intensity"):
        PointSource([0.0, 0.0, 0.0], [-1.0, 0.0, 0.0])
