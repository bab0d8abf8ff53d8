"""The direct light at the start of a run, composed by the ``Solver`` (``solver.direct``).

The emitting patches' light is gathered per receiver with shadow rays (``gather``: exact form
factors or next-event estimation, direct.py) or shot, whichever is quieter, and light sources that
are not patches (emitters.py) are gathered exactly or shot (``shoot_sources``).  The phase decides
the run's plan: in accuracy mode with exact form factors it sets the final plan (shoot the reflected
light coarsely, gather it again at the end: ``final_phase``).  It books through the solver's
``commit`` and ``counted``: the ledger, the noise tallies and the stats stay the solver's.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING

import numpy as np

from dcrad.solving.accuracy import final_plan
from dcrad.transport.direct import (
    GATHER_MARGIN,
    MAX_ANALYTIC_RECEIVERS,
    PILOT_SHARE,
    AnalyticGather,
    DirectTally,
    GatherStopped,
    analytic_lights,
    gather_analytic,
    gather_direct,
    landing_rays,
    merge,
    noise_against_shooting,
    rescale_to_landed,
    shadow_rays_for,
)
from dcrad.transport.emitters import patch_irradiance
from dcrad.transport.shoot import patch_rays, ray_offset

if TYPE_CHECKING:
    from dcrad.solving.solver import Solver

__all__ = ["DirectPhase", "GATHER_STOPPED", "SOURCE_LANDING_RAYS", "MIN_BUDGET_SHADOW", "DIRECT_BUDGET_SHARE"]

#: the report's line for a direct gather a stop request ended
GATHER_STOPPED = ("direct gather stopped before it finished (a stop request): nothing of it is booked, the "
                  "emitters' light is left unshot")
#: most rays a light source that is not a patch shoots to book where its gathered light lands in all
#: (``gather_source``): they set the total's noise (under 0.2% of the power at this count when
#: a tenth of it escapes), not where it lands
SOURCE_LANDING_RAYS = 1 << 18
#: rays a half a receiver gathers a sampled source's light with (``gather_sampled``), at least and at most
SAMPLED_MIN_RAYS, SAMPLED_MAX_RAYS = 8, 1 << 16
#: share of --max-rays a sampled source's gather may take (the shooting of what it lands needs the rest)
SAMPLED_BUDGET_SHARE = 0.5
#: fewest shadow rays per receiver of a direct gather coarsened to fit --max-rays: below about 16
#: the exact gather's own floor (its pilot, a ray a half per receiver-light pair) dominates (the
#: office: 271k rays at 4, 276k at 8, 304k at 16, 611k at 32; Cornell 97k, 199k, 405k, 816k)
MIN_BUDGET_SHADOW = 16
#: the direct gather takes at most this share of a --max-rays budget; else the emitters are shot
DIRECT_BUDGET_SHARE = 0.5


class DirectPhase:
    """The run's direct light: ``tried`` once ``gather`` ran; ``light``: (n,3) W of direct light each
    patch received by the gather and half A's part (None: shot, or not gathered yet);
    ``sources_left``: the light sources that are not patches still to spend (once, at the start)."""

    def __init__(self, solver: "Solver"):
        self.solver = solver
        self.tried = False
        self.light: tuple[np.ndarray, np.ndarray] | None = None
        self.sources_left = list(solver.patches.sources)
        #: (n,3) W the sources' exact gathers put on each patch, and half A's part (None: none gathered):
        #: direct light the final gather must not re-estimate, like the emitting patches'
        self.source_light: tuple[np.ndarray, np.ndarray] | None = None
        #: a source's light was shot, not gathered: the final gather could not tell it from reflected light
        self.sources_shot = False
        #: the tallies the sources' light was booked with, kept when a list (division/outside.py reads
        #: the sky's and the sun's, gathered on the whole scene, to hand to the subscenes)
        self.kept: list | None = None

    def shoot_sources(self) -> int:
        """Spend each light source that is not a patch (emitters.py) once, at the start of the run: its
        direct light gathered exactly onto the patches (``gather_source``) while the direct gather is on
        (the default), else shot with rays at the run's power per ray.  What lands is deposited,
        reflected and shot on like any light, and the ledger books it as emitted (``__init__``) and
        shot here.  Returns the rays traced."""
        s = self.solver
        rays = 0
        while self.sources_left:
            source = self.sources_left.pop(0)
            if float(np.abs(source.power()).sum()) <= 0:
                continue
            attune = getattr(source, "attune", None)  # the outputs read a sampled source's light as this run
            if attune is not None:
                attune(s.config.seed, s.config.accuracy)
            if getattr(source, "gathered", False):  # gathered already (emitters.Gathered): laid down
                rays += self.deposit(source)
            elif not s.config.direct:
                rays += self.shoot_source(source)
            elif getattr(source, "exact", True):
                rays += self.gather_source(source)
            else:  # its direct light has no exact gather (the sky: an integral over the openings a point sees)
                rays += self.gather_sampled(source)
        return rays

    def deposit(self, source) -> int:
        """Lay down a light gathered elsewhere (emitters.Gathered: a divided run's sky and sun, gathered on
        the whole scene): what landed on each receiver and its half A, booked as this run's emitted
        light (``__init__``) and shot; its gather's rays counted here.  No final plan: its light may be
        a sampled estimate, as the sky's.  Returns the rays counted."""
        s = self.solver
        tally = self._gathered(source.received, source.rows, np.zeros(3), source.received_a, source.rays)
        s.commit(None, tally, shot=np.asarray(source.power(), np.float64)[None, :])
        self.sources_shot = True
        return s.counted(1, source.rays)

    def _book(self, batch, tally, shot=None) -> None:
        """``Solver.commit`` of a source's light, its tally kept when ``kept`` is a list."""
        self.solver.commit(batch, tally, shot=shot)
        if self.kept is not None:
            self.kept.append(tally)

    def gather_sampled(self, source) -> int:
        """The direct light of a source without an exact gather (the sky, ``patch_gather``), gathered
        onto every receiver by rays from all over it, in two independent halves whose difference
        is its noise (noise.py): a receiver of area A takes A E / (power per ray) rays, E the mean
        irradiance of the receivers (the portal map's pilot), the rays the light landing on it would
        take shot at the run's density, none spent on the outside of the model (a small roof
        opening: 98% of the sky's rays into the bounding box met the roof's outside).
        The books take as emitted what lands (its power into the bounding box is set aside, and the
        run's power per ray scaled to it from the portal map's pilot); the final plan is not taken (its
        direct light is a sampled estimate, which the final gather's books do not carry).  Returns the
        rays traced."""
        s = self.solver
        p = s.patches
        power = np.asarray(source.power(), np.float64)
        rows = np.flatnonzero((p.area > 0) & p.rho.any(axis=1))
        if p.glazing is not None:  # a pane's own share of the sky (1 - tau) is not gathered: its Kd is small
            rows = rows[~p.glazing.mask[rows]]
        # the books hold what lands, not all the light into the bounding box (30x more for a side-lit
        # room): the run's density and its unshot share (the stop rule's "all shot") are of that
        corners = p.corners(rows)
        gather_ray = s.power_per_ray
        if len(rows):
            guess = source.pilot(corners.mean(axis=1), p.normal[rows], s.tracer, ray_offset(p))
            landed_guess = guess * float(p.area[rows].sum())
            # the run's power per ray follows the books' emitted light, the sky's share of it now what
            # lands (scaled by landed / flux alone, the other sources' shrank with it: the sun's, 80x)
            total = float(s.ledger.emitted.mean())
            if 0.0 < landed_guess < float(power.mean()) and total > 0:
                now = total - float(power.mean()) + landed_guess
                s.power_per_ray *= now / total
                # ... and its gather takes the rays the run's density gives the sky's light alone: a
                # sampled gather is noisier per ray than shooting, and at the sky's share of the
                # density (office3, lamps on) its first pass ended on its noise floor: 3 passes,
                # 22.7M rays against 9.9M
                gather_ray = s.power_per_ray * landed_guess / now
        # a receiver takes the rays the light landing on it would at the run's density, its mean
        # irradiance read as the pilot's: half the rays aim at the openings, so most of them count
        # (a plane that saw the whole sky in the count cost office3 451M rays for its 41,710 receivers)
        per_half = np.ceil(0.5 * source.pilot_mean * p.area[rows] / gather_ray)
        counts = np.clip(per_half, SAMPLED_MIN_RAYS, SAMPLED_MAX_RAYS).astype(np.int64)
        left = s.budget.left()
        cap = SAMPLED_BUDGET_SHARE * left if left is not None else math.inf
        if 2 * counts.sum() > cap:  # under --max-rays: coarser, every receiver still gathered
            counts = np.maximum((counts * (cap / (2 * counts.sum()))).astype(np.int64), 1)
            s.choices.add("budget", f"{source.name}: its gather coarsened to {int(2 * counts.sum()):,} rays to fit "
                                    f"--max-rays ({SAMPLED_BUDGET_SHARE:g} of what the budget left)")
        if len(rows):
            h_a, h_b = source.patch_gather(corners, p.normal[rows], counts, s.tracer, ray_offset(p), s.rng)
        else:  # nothing reflects (a black room): all of it is booked escaped
            h_a = h_b = np.zeros((0, 3))
        area = p.area[rows, None]
        received, received_a = 0.5 * (h_a + h_b) * area, 0.5 * h_a * area
        keep = np.flatnonzero(received.any(axis=1))
        got = received[keep]
        landed = got.sum(axis=0)
        if np.all(landed > 0):  # it emitted, in the books, what it landed: nothing escapes
            s.ledger.emitted = s.ledger.emitted + landed - power
            power = landed
        elif not np.any(landed > 0):  # a closed model, or one whose openings only black surfaces see
            s.choices.add("direct", f"{source.name}: none of its light lands on a surface that reflects: no "
                                    f"opening or pane lets it in where anything reflects")
        tally = self._gathered(got, rows[keep], power - landed, received_a[keep], int(2 * counts.sum()))
        self._book(None, tally, shot=power[None, :])
        self.sources_shot = True
        if len(rows):
            s.choices.add("direct", f"{source.name}: its direct light gathered onto {len(rows):,} receivers with "
                                    f"{int(2 * counts.sum()):,} rays ({int(counts.min())} to {int(counts.max())} a "
                                    f"half a receiver), two independent halves: its noise is in the estimate")
        return s.counted(1, int(2 * counts.sum()))

    def _landed_only(self, tally, power: np.ndarray):
        """A source outside the model (the sun) booked as emitting what it landed, as the sky is
        (``gather_sampled``): its light that met the envelope's outside or passed the model by never
        entered it.  Booked as lost, it made the model look leaky to the return tallies, whose
        estimate then took the light left unshot for a fifth of what it was (a sunlit roof opening
        stopped 4% dark with a bias of 0.2% estimated), and set the run's density by light no ray
        needs.  Returns (the tally, the power it emitted); the run's power per ray follows."""
        s = self.solver
        landed = tally.received.sum(axis=0)
        before = float(s.ledger.emitted.sum())
        s.ledger.emitted = s.ledger.emitted + landed - power
        after = float(s.ledger.emitted.sum())
        if before > 0 and after > 0:
            s.power_per_ray *= after / before
        tally.escaped, tally.back_faces, tally.lost = np.zeros(3), np.zeros(3), np.zeros(3)
        tally.back_by_obj = np.zeros_like(tally.back_by_obj)
        return tally, landed

    def _gathered(self, got: np.ndarray, hit: np.ndarray, escaped: np.ndarray, got_a: np.ndarray,
                  rays: int) -> DirectTally:
        """The tally of a source's gather: ``got`` (k,3) W on the receivers ``hit``, ``escaped`` (3,)
        W booked as leaving (its magnitude is the return tallies' loss), half A's part ``got_a``."""
        s = self.solver
        magnitude = np.abs(got)
        return DirectTally(got, hit, escaped, np.zeros(3), np.zeros(len(s.back_by_obj)), np.zeros(0, np.int64),
                           np.zeros(0, np.int64), np.zeros(0), magnitude.sum(axis=0),
                           (magnitude * s.patches.rho[hit]).sum(axis=0), np.abs(escaped), got_a, rays)

    def source_rays(self, source) -> int:
        """Rays ``source`` takes shot at the run's power per ray (at least the shots' floor)."""
        s = self.solver
        return max(int(math.ceil(float(np.abs(source.power()).sum()) / s.power_per_ray)), s.config.min_rays, 2)

    def shoot_source(self, source, n: int | None = None) -> int:
        """Shoot ``source``'s whole power with ``n`` rays (None: at the run's power per ray), in
        batches of at most ``batch_rays``; returns the rays traced."""
        self.sources_shot = True
        s = self.solver
        if n is None:
            n = self.source_rays(source)
        rays = 0
        for lo in range(0, n, s.config.batch_rays):
            m = min(s.config.batch_rays, n - lo)
            t0 = time.perf_counter()
            batch = source.rays(m, s.rng)
            batch.power = batch.power * (m / n)  # each batch an unbiased estimate of its share
            tally = s.fire(batch, t0)
            self._book(batch, tally)
            rays += s.counted(1 if lo == 0 else 0, m)
        return rays

    def gather_source(self, source) -> int:
        """``source``'s direct light on every patch, exactly: the mean of I cos / d^2 over the patch
        with shadow rays (emitters.patch_irradiance; a point source has no area, so nothing is
        sampled but the visibility at three points a patch).  How much of its power lands in all, and
        what escapes or meets back faces, comes from SOURCE_LANDING_RAYS of its own rays at most
        (the books close to round-off, as for the emitting patches' gather, direct.rescale_to_landed);
        the half-solutions differ only by those rays' landed total.  Returns the rays traced."""
        s = self.solver
        p = s.patches
        power = np.asarray(source.power(), np.float64)
        t0 = time.perf_counter()
        # the receivers (what reflects); the rays' own hits book the rest (rescale_to_landed)
        rows = np.flatnonzero((p.area > 0) & p.rho.any(axis=1))
        glazing = None if p.glazing is None else p.glazing.take(rows)
        received = patch_irradiance(source, p.corners(rows), p.normal[rows], s.tracer, ray_offset(p), glazing)
        received *= p.area[rows, None]
        keep = np.flatnonzero(received.any(axis=1))
        shadow = len(rows) * 3
        n = int(min(max(float(np.abs(power).sum()) / s.power_per_ray, 1024.0), SOURCE_LANDING_RAYS))
        batch = source.rays(n, s.rng)
        shot = s.fire(batch, t0)
        landed = shot.received.sum(axis=0)
        landed_a = shot.received_a.sum(axis=0) if shot.received_a is not None else 0.5 * landed
        share_a = np.where(landed != 0, landed_a / np.where(landed != 0, landed, 1.0), 0.5)
        got = received[keep]
        gathered = self._gathered(got, rows[keep], np.zeros(3), got * share_a, shadow)
        tally = rescale_to_landed(gathered, shot, p)
        if tally is None:  # its rays landed light where no patch faces it: keep the rays' own result
            self._book(batch, shot)
            self.sources_shot = True
            s.choices.add("direct", f"{source.name}: its light shot, not gathered: its rays landed light where "
                                       f"the exact gather found none")
            return s.counted(1, shadow + n)
        if getattr(source, "outside", False):  # the sun: its books hold what lands, as the sky's
            tally, power = self._landed_only(tally, power)
        self._book(None, tally, shot=power[None, :])
        if self.source_light is None:
            self.source_light = (np.zeros((len(p), 3)), np.zeros((len(p), 3)))
        np.add.at(self.source_light[0], tally.hit, tally.received)
        np.add.at(self.source_light[1], tally.hit, tally.received_a)
        return s.counted(1, shadow + n)

    def inputs(self, rows: np.ndarray | None = None):
        """What the direct gather works from: (emitters, their unshot radiosity, their power (W),
        shadow rays per receiver, the light polygons or None, the FinalPlan or None); None when
        nothing emits.  Appends the report's line when the scene is too large for exact form factors.
        ``rows``: the receivers whose light lists decide between exact and sampled gathers (None:
        all; a shared run's share decides on its own, and its gather reuses the lists)."""
        s = self.solver
        p = s.patches
        cfg = s.config
        emitters = np.flatnonzero(p.emission.any(axis=1) & p.unshot.any(axis=1))
        if len(emitters) == 0:
            return None
        amounts = p.unshot[emitters].copy()
        power = amounts * p.area[emitters, None]
        shadow = cfg.shadow_rays or shadow_rays_for(cfg.rays_per_power, len(p))
        if s.role.preset_direct is not None:  # gathered by a shared run's workers: exact, with a final plan
            plan = final_plan(cfg, len(p))
            if plan is None:
                raise ValueError("a preset direct gather needs accuracy mode with the direct light gathered")
            return emitters, amounts, power, plan.shadow_rays, None, plan
        n_receivers = len(np.flatnonzero(p.rho.any(axis=1)))
        lights = analytic_lights(p, emitters, power, n_receivers, rows)
        if lights is None and n_receivers > MAX_ANALYTIC_RECEIVERS:
            s.choices.add(
                "direct", f"no exact direct gather (nor final plan): {n_receivers} receiving patches, above "
                                f"{MAX_ANALYTIC_RECEIVERS} (its memory and CPU stop paying there: direct.py)")
        plan = final_plan(cfg, len(p)) if lights is not None else None
        if plan is not None and self.sources_shot:
            # the final gather re-estimates all but the gathered direct light, and a source's shot
            # direct light is not in it: it would be laid out as if it were reflected light
            plan = None
            s.choices.add("direct", "no final plan: a light source that is not a patch (emitters.py) was shot, "
                                       "not gathered, and the final gather cannot tell its direct light apart")
        if plan is not None and self.glass_refuses_plan():
            plan = None
        if plan is not None:
            shadow = plan.shadow_rays
            if cfg.max_rays:
                # the whole plan (direct, shooting, gather) coarsened alike to fit the budget (the
                # shooting and gather are fitted again once the direct light is in: ``Budget.fit``)
                f = s.budget.scale(cfg.max_rays - s.stats.rays,
                                      shadow * n_receivers + s.budget.plan_rays(plan, n_receivers))
                shadow = max(int(shadow * f), MIN_BUDGET_SHADOW) if f < 1.0 else shadow  # f = 0: none fit
        return emitters, amounts, power, shadow, lights, plan

    def pilot(self, rows: np.ndarray, rng: np.random.Generator, should_stop=None) -> AnalyticGather | None:
        """The exact direct gather of the receivers ``rows`` only, after its pilot pass
        (``AnalyticGather``: ``finish(rate)`` gathers): one worker's share of a shared run
        (share.py); None when the scene has no exact-form-factor lights or no final plan (a
        shared run needs both)."""
        s = self.solver
        got = self.inputs(rows)
        if got is None:
            return None
        emitters, _, power, shadow, lights, plan = got
        if lights is None or plan is None:
            return None
        return AnalyticGather(s.patches, s.tracer, emitters, power, lights, shadow, rng,
                              ray_offset(s.patches), s.config.batch_rays, rows, should_stop)

    def gather(self, should_stop=None) -> int:
        """Gather the emitters' direct light with shadow rays (direct.py); return the rays traced.
        ``should_stop()`` True between two of the gather's batches abandons it: nothing is booked,
        the emitters keep their light unshot (``run`` then stops).

        The emitters' power is spent: a modest number of their ordinary rays books
        how much lands, escapes or meets back faces (exactly, as shooting would),
        and the gather distributes the landed power over the receivers' fronts.
        Receivers keep rho of it; shooting goes on with the reflected light.  Exact
        form factors (``gather_analytic``) when the emitters make few light polygons,
        else next-event estimation (``gather_direct``).  Kept only when it is quieter
        than shooting the emitters (``noise_against_shooting``), except in accuracy
        mode with exact form factors: there the run follows an ``accuracy.FinalPlan``
        (shoot the reflected light coarsely, gather it again at the end, final.py),
        which needs the direct light gathered.

        ``preset_direct`` (set by a shared run, share.py): the gather of every receiver, done
        by the workers' shares; this run books it with its own emitter rays and does not
        count its shadow rays (the shared run counts them once).
        """
        s = self.solver
        p = s.patches
        cfg = s.config
        self.tried = True
        got = self.inputs()
        if got is None:
            self.sources_only()
            return 0
        emitters, amounts, power, shadow, lights, plan = got
        preset = s.role.preset_direct
        # a pilot on a random share of the receivers decides whether gathering beats shooting
        receivers = np.flatnonzero(p.rho.any(axis=1))
        budget = cfg.max_rays - s.stats.rays if cfg.max_rays else 0
        if preset is None and cfg.max_rays and shadow * len(receivers) > DIRECT_BUDGET_SHARE * budget:
            # the gather's shadow rays would take most of the ray budget (the office at --max-rays
            # 1e5: 611k rays, all of them the gather's; at 16 shadow rays, its least under a budget,
            # still 304k): the emitters are shot, within it (``Budget.fit`` sets their density)
            s.choices.add("direct", f"direct light shot, not gathered: {shadow} shadow rays for each of "
                                f"{len(receivers)} receiving patches are more than {DIRECT_BUDGET_SHARE:.0%} of "
                                f"the ray budget ({max(budget, 0)} of --max-rays {cfg.max_rays})")
            return 0
        size = min(len(receivers), max(64, int(PILOT_SHARE * len(receivers))))
        pilot = np.sort(s.rng.choice(receivers, size, replace=False))
        t0 = time.perf_counter()
        off = ray_offset(p)

        def gather_for(rows: np.ndarray):
            if lights is not None:
                return gather_analytic(p, s.tracer, emitters, power, lights, shadow, s.rng, off,
                                       cfg.batch_rays, rows, should_stop)
            return gather_direct(p, s.tracer, emitters, power, shadow, s.rng, off, cfg.batch_rays, rows,
                                 should_stop)

        how = (f"exact form factors to {len(lights)} light polygon(s), visibility from" if lights is not None
               else "exact form factors (the shared run's direct shares), visibility from" if preset is not None
               else "next-event estimation,")
        # the exact form factors gather every receiver at once (their pilot finds penumbrae by
        # neighbourhood: on a sparse share of the receivers it would find few), then compare
        def abandoned(rays: int) -> int:  # a stop request ended the gather: nothing of it is booked
            s.stats.trace_seconds += time.perf_counter() - t0
            s.choices.add("direct", GATHER_STOPPED)
            return s.counted(0, rays) if rays else 0

        try:
            gathered = preset if preset is not None else gather_for(pilot if lights is None else receivers)
        except GatherStopped:
            return abandoned(0)
        shadow_counted = 0 if preset is not None else gathered.rays
        s.stats.trace_seconds += time.perf_counter() - t0
        quiet, loud = noise_against_shooting(p, gathered, power, s.power_per_ray)
        ratio = math.sqrt(quiet / loud) if loud > 0 else math.inf
        # a run with a final plan keeps its gather: the cheap path (shoot coarsely, gather again)
        # needs the direct light gathered, and the noise of shooting it is the noise of a far
        # denser run (the office: 1.2x the noise of shooting at 1.2e7 rays per power, which
        # took 30.5M rays to 2%; gathered and finished: 4.3M rays for 1.6%)
        # ... unless the pilot measured the gather so noisy that matching shooting's noise would take
        # more shadow rays than shooting the emitted power at the run's density takes rays: a lamp
        # in a fixture (louvres, a trough) is seen partly by most receivers, and its gather can be
        # 13x noisier than shooting: the light is shot instead
        equal = shadow * ratio * ratio * len(receivers)
        if plan is not None and preset is None and equal > cfg.rays_per_power:
            s.choices.add(
                "direct", f"direct light shot, not gathered, and no final gather: the gather's {shadow} shadow "
                                f"rays per receiving patch gave {ratio:.2f}x the noise of shooting; matching it would "
                                f"take about {equal:.3g} shadow rays, more than the {cfg.rays_per_power:.3g} rays "
                                f"shooting the emitted power once takes (its {gathered.rays} shadow rays are counted)")
            s.final.rays = 0
            return s.counted(0, gathered.rays)
        if plan is None and not ratio < GATHER_MARGIN:
            on = f"on a pilot of {len(pilot)} patches" if lights is None else "on every patch"
            s.choices.add("direct", f"direct light shot, not gathered: {how} {shadow} shadow rays per patch gave "
                                f"{ratio:.2f}x the noise shooting the emitters would, {on} (its "
                                f"{gathered.rays} shadow rays are counted)")
            return s.counted(0, gathered.rays)
        if lights is None and preset is None:
            t0 = time.perf_counter()
            rest = np.setdiff1d(receivers, pilot, assume_unique=True)
            try:
                gathered = merge(gathered, gather_for(rest), p)
            except GatherStopped:
                return abandoned(gathered.rays)
            s.stats.trace_seconds += time.perf_counter() - t0
        # the emitters' own rays: how much of their power lands (the books), not where
        total = power.sum(axis=1)
        n_land = landing_rays(shadow, len(gathered.hit), len(emitters), cfg.batch_rays)
        counts = np.maximum(np.ceil(n_land * total / total.sum()), 2).astype(np.int64)
        t0 = time.perf_counter()
        shot = s.fire(patch_rays(p, emitters, counts, power, s.rng), t0)
        tally = rescale_to_landed(gathered, shot, p)
        s.release(emitters, amounts)
        s.noise.shot(emitters)
        if tally is None:  # the gather missed light the rays found: keep the rays' own result
            s.commit(None, shot, shot=power)
            s.choices.add(
                "direct", "direct light shot: the gather found no light where the emitters' rays landed some")
            return s.counted(len(emitters), shadow_counted + int(counts.sum()))
        s.commit(None, tally, shot=power)
        full, half_a = np.zeros((len(p), 3)), np.zeros((len(p), 3))
        full[tally.hit], half_a[tally.hit] = tally.received, tally.received_a
        if self.source_light is not None:  # the sources' exact direct light is direct light too
            full += self.source_light[0]
            half_a += self.source_light[1]
        self.light = (full, half_a)
        s.choices.add("direct", f"direct light gathered ({how} {shadow} shadow rays per receiving patch, "
                            f"{ratio:.2f}x the noise of shooting it); {int(counts.sum())} rays from "
                            f"the emitters book how much of it lands, escapes or meets back faces")
        if plan is not None:
            self.adopt(plan)
        return s.counted(len(emitters), shadow_counted + int(counts.sum()))

    def adopt(self, plan) -> None:
        """Follow ``plan`` (accuracy.FinalPlan): shoot the reflected light coarsely, gather it again at
        the end (final.py)."""
        s = self.solver
        s.final.rays = s.role.planned_final_rays or plan.final_rays
        s.power_per_ray = float(s.ledger.emitted.sum()) / (plan.shoot_rays_per_power * s.role.shoot_share)
        # a replica of a shared run shoots 1/k of the rays of every shot, the floor's too
        s.config = s.config.replace(min_rays=max(2, int(round(plan.min_rays * s.role.shoot_share))))
        density = plan.shoot_rays_per_power * s.role.shoot_share
        s.choices.add("plan", f"reflected light shot at {density:.3g} rays "
                            f"per emitted power "
                            f"(at least {plan.min_rays} rays a shot), then gathered again with "
                            f"{plan.final_rays} rays per receiving patch (accuracy.FinalPlan)")

    def sources_only(self) -> None:
        """No patch emits: when every light source's direct light was gathered exactly, it is the
        run's direct light, and in accuracy mode the run follows the final plan as one lit by
        emitting patches does (the sources' gather has no sampling noise: a point has no area)."""
        s = self.solver
        p = s.patches
        if self.source_light is None or self.sources_shot:
            return
        self.light = (self.source_light[0].copy(), self.source_light[1].copy())
        receivers = int(p.rho.any(axis=1).sum())
        plan = final_plan(s.config, len(p))
        if plan is None:
            return
        if receivers > MAX_ANALYTIC_RECEIVERS:
            s.choices.add("direct", f"no final plan: {receivers} receiving patches, above the "
                                    f"{MAX_ANALYTIC_RECEIVERS} a final gather takes (direct.py)")
            return
        if self.glass_refuses_plan():
            return
        self.adopt(plan)

    def glass_refuses_plan(self) -> bool:
        """True (and the report's line) when the scene has glass: final.read_hits reads the first
        surface a ray meets, a pane too, so the final gather cannot follow the light through it."""
        s = self.solver
        glazing = s.patches.glazing
        if glazing is None or not glazing.mask.any():
            return False
        s.choices.add("direct", "no final plan: the scene has glass, which the final gather's rays do not "
                                "see through yet (the shooting and the direct gather do)")
        return True
