"""Progressive refinement for one (sub)scene: select shooters, shoot, repeat.

``Solver`` owns the patch table, its Embree scene, the random stream and the
ledger.  ``step()`` shoots the top-K unshot patches in one Embree call;
``run()`` steps until the residual tolerance, the time limit, the ray budget
or an external stop request, recording snapshots of B at geometric intervals
of rays for the error-against-time report.

Ambient overshooting (after Feda and Purgathofer's overshooting, with Cohen et
al.'s ambient term).  In a stiff scene (rho near 1) plain shooting needs
ln(tol)/ln(rho) bounces.  Most of that tail is spatially smooth: the
irradiance still to come is close to uniform.  We estimate it,

    g = q * U / ((1 - lambda) * A_total)      (W/m^2, per channel)

from the signed unshot power U, the share q of shot power that lands on a
surface, and the return ratio lambda = q * (mean rho where light lands),
measured so far.  A
shooter i then shoots dB_i + rho_i * g, the light it will reflect once that
irradiance arrives, and keeps dB_i = -rho_i * g (negative).  When the light
does arrive it cancels the negative unshot; what the estimate got wrong is
still unshot (either sign) and is shot like anything else.  Everything stays
a shot of real rays, so the ledger closes exactly and the limit is the same;
only the number of bounces drops.  ``overshoot`` scales g (0: plain).  It
acts only in stiff scenes (return ratio >= ``overshoot_min_return``): in
ordinary ones the tail is short, and negative shots would only add noise
(dim patches could dip below zero before the light they wait for arrives).

The return ratio is measured with magnitudes (``Tally.landed/kept/lost``):
once rays of both signs fly, signed sums cancel and would make a stiff scene
look tame.  Stiff scenes also shoot far more power than they emit, E/(1-lambda)
in all (1000x at rho 0.999), so at a fixed power per ray they spend 1/(1-lambda)
times the rays of a scene with no reflection, and their noise relative to B
is far below an ordinary scene's.  With ``stiff_rays`` the power per ray grows
by sqrt((1-min_return)/(1-lambda)) and the 32-ray floor per shot shrinks by
the same factor.  The square root is measured, not derived: on the furnace it
brings the noise relative to B back to that of rho 0.5-0.8 rooms of the same
mesh (linear scaling left it 1.5-1.8x higher; bench/RESULTS.md).

A divided job overshoots as one scene: light crosses the boundaries, so
``divide.run_divided`` sums every subscene's tallies at each barrier and
hands each subscene the job's scale F and the unshot power the others hold
(``subscene.BarrierPlan``).  Twin buffers then carry signed power.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from dcrad.arrays import colsum, put_rows, rowsum, take_rows
from dcrad.choices import Choice, Choices
from dcrad.config import SolverConfig
from dcrad.estimate.noise import Estimate, NoiseTally, bias_ambient, combine, finite
from dcrad.meshing.patches import Patches
from dcrad.solving.accuracy import FINAL_BIAS_SHARE, by_accuracy, noise_floor, resolve
from dcrad.solving.budget import Budget
from dcrad.solving.direct_phase import DirectPhase
from dcrad.solving.energy import Ledger, escaped_light, flipped_normals
from dcrad.solving.final_phase import FinalPhase
from dcrad.solving.snapshots import SnapshotStore
from dcrad.solving.stiffness import Stiffness, stiff_choice, stiffness
from dcrad.transport.direct import (
    DirectTally,
)
from dcrad.transport.emitters import sources_power
from dcrad.transport.rays import Tracer
from dcrad.transport.shoot import deposit, landing, patch_rays, trace
from dcrad.transport.shooters import ShooterPool, pool_size, spatial_order

__all__ = ["Solver", "ReplicaRole", "Snapshot", "solve"]

#: batches between exact recounts of the ledger's unshot sums; in between they are
#: kept incrementally from the rows each batch touched (shooters and rows hit)
RECOUNT_EVERY = 256


#: the report's line for a scene whose rho and E are grey
GREY_CHOICE = ("grey scene (every rho and E has equal channels): "
               "one colour channel is tallied and copied to the other two")


@dataclass
class Snapshot:
    """State of a run at one moment (B is kept separately in ``Solver.snapshot_B``)."""

    time: float  #: s of wall time since the run started
    shots: int  #: patches shot so far (the paper's iterations)
    rays: int  #: rays traced so far
    residual: float  #: (unshot + in flight) / emitted
    closure: float  #: ledger imbalance, relative
    error_rms: float | None = None  #: W/m^2, the estimated RMS error (noise.Estimate.rms)
    error_refl: float | None = None  #: the same over RMS(B - E) (noise.Estimate.rms_refl)

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class Stats:
    shots: int = 0  #: patches shot
    rays: int = 0  #: rays traced
    batches: int = 0  #: Embree calls (divided: summed over subscenes)
    barriers: int = 0  #: barriers of a divided run (0: one subscene, no barriers)
    trace_seconds: float = 0.0  #: s spent inside trace (Embree + tally; divided: summed over subscenes)
    wall_seconds: float = 0.0  #: s of the whole run
    stopped_by: str = ""  #: tolerance | time_limit | ray_budget | stopped | no_emitters

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class ReplicaRole:
    """How a shared run's replica (share.py) differs from a run of its own; the defaults are a run of
    its own.  Kept apart from the solver's state so that only share.run_replica sets it."""

    #: the direct gather of every receiver, done by the shared run's workers (None: gather here)
    preset_direct: DirectTally | None = None
    #: ``replicas`` k of them will be averaged, and ``shared_noise`` (W^2/m^4) is the noise mean
    #: square they share (their direct light, gathered once): the run stops by the error the
    #: average will have (``Solver.target_error``)
    replicas: int = 1
    shared_noise: float = 0.0
    #: share of the final plan's shooting density this run shoots at: k replicas shoot 1/k each (the
    #: final gathers read their average's noise), 1 otherwise
    shoot_share: float = 1.0
    #: stop where the final gather would start (``stopped_by: final_gather``): the replicas leave it
    #: to the shared run, which gathers their average split by receivers
    defer_final: bool = False
    #: the job's final gather rays per receiver (its own plan is at 1/k of the density; the replicas
    #: plan, and a budget coarsens, the job's gather: share.run_replica); 0: its own plan's
    planned_final_rays: int = 0


class Solver:
    """Progressive-refinement radiosity over one patch table.

    patches : the table (its radiosity/unshot arrays are updated in place)
    config  : SolverConfig
    tracer  : optional prebuilt Tracer over ``patches.triangles`` (plus boundary
              primitives after the patches, for subscenes)
    """

    def __init__(self, patches: Patches, config: SolverConfig | None = None, tracer: Tracer | None = None):
        self.patches = patches
        #: settings with the automatic ones filled in (accuracy.resolve: ray density, stop rule)
        self.config = resolve(config or SolverConfig(), patches.read_units)
        self.tracer = tracer if tracer is not None else Tracer.mesh(patches)
        self.rng = np.random.default_rng(self.config.seed)
        self.ledger = Ledger(emitted=patches.emitted_power + sources_power(patches.sources))
        self.ledger.unshot = patches.unshot_power.copy()
        self.ledger.unshot_abs = (np.abs(patches.unshot) * patches.area[:, None]).sum(axis=0)
        #: W (magnitudes) shot by patches, lost (escaped, back faces), landed, kept as unshot:
        #: the return-ratio tallies (rows; see ``stiffness``)
        self.tallies = np.zeros((4, 3))
        self.stats = Stats()
        self.back_by_obj = np.zeros(max(len(patches.names), 1))
        emitted = float(self.ledger.emitted.sum())
        #: W carried by one ray (fixed power per ray)
        self.power_per_ray = emitted / self.config.rays_per_power if emitted > 0 else 1.0
        #: W below which a shooter is not worth a ray (round-off of the overshoot arithmetic)
        self._negligible = 1e-12 * max(emitted, 1e-300)
        #: what this run leaves out because the scene does not need it (for the report)
        self.choices = Choices()  #: what the run chose and why (choices.py)
        self.channels = 1 if patches.is_grey and len(patches) else 3
        if self.channels == 1:
            self.choices.add("grey", GREY_CHOICE)
        #: the stiffness estimate of the last batch that overshot or stretched rays (None: never)
        self.stiff: Stiffness | None = None
        self.snapshots: list[Snapshot] = []
        #: B at each snapshot, float16, at most ``config.snapshot_mb`` MB (snapshots.py)
        self.snapshot_B: SnapshotStore | list = SnapshotStore()
        self._next_snapshot = 0
        self._snapshot_factor = self.config.snapshot_factor  #: squared each time the store is thinned
        #: the candidates for the top-K shooters (shooters.py); ``full_selection``: sort everything
        self.pool = ShooterPool(patches, pool_size(len(patches), self.config.max_shooters))
        self.full_selection = False
        #: batches between exact recounts of the ledger's unshot sums (0: never)
        self.recount_every = RECOUNT_EVERY
        self._since_recount = 0
        #: the two half-solutions' difference, for the error estimate (noise.py)
        self.noise = NoiseTally(patches)
        #: the phases this run is composed of besides the shooting: the direct light at the start
        #: (it plans the final gather), the ray plan under a budget, the final gather at the end
        self.direct = DirectPhase(self)
        self.budget = Budget(self)
        self.final = FinalPhase(self)
        #: what a shared run's replica does differently (``ReplicaRole``; the default: a run of its own)
        self.role = ReplicaRole()
        #: the clusters have settled (``settle``: once a run; a later pass of a blend sets it so that they
        #: settle on the blend, passes.py)
        self.settled = False
        #: a later pass of a blend stops by accuracy only once its unshot light's bias (over RMS(B - E))
        #: is below this (passes.py): the passes' noise averages down in the blend, their bias does not
        self.bias_cap = math.inf
        self._fresh_at = -FRESH_EVERY  #: the batch of the last resync ``stop_reason`` asked for
        self._t0 = clock()

    # == one Embree call ===========================================================
    def stiffness(self) -> "Stiffness":
        """This scene's stiffness estimate, from its own return tallies (see ``stiffness``)."""
        p = self.patches
        if len(p) == 0:
            return Stiffness.none()
        return stiffness(self.tallies, p.total_area, self.config, p.mean_rho)

    def note_stiffness(self, st: "Stiffness") -> "Stiffness":
        if st.active:
            self.stiff = st
        return st

    def stiffness_choice(self) -> list[Choice]:
        """The report's line on stiffness, when it changed how this run shot."""
        return [Choice("stiff", stiff_choice(self.stiff, self.config))] if self.stiff is not None else []

    def ambient(self, st: "Stiffness") -> np.ndarray:
        """(3,) W/m^2: the irradiance still to arrive, as if spread uniformly (see module doc)."""
        if not st.scale.any():
            return st.scale
        return st.scale * (self.ledger.unshot + self.ledger.in_flight)

    def shoot_amounts(self, st: "Stiffness") -> np.ndarray:
        """(n,3) W/m^2 each patch would shoot now: dB plus its overshoot rho * g."""
        g = self.ambient(st)
        if not g.any():
            return self.patches.unshot
        return self.patches.unshot + self.patches.rho * g

    def rank(self, power: np.ndarray, min_rays=None, max_shooters=None, ray_factor: float = 1.0):
        """Top-K shooters by |power| (m,3) W and their ray counts (fixed power per ray).

        min_rays: fewest rays per shooter, scalar or (m,) (default config.min_rays);
        max_shooters: K (default config.max_shooters); the batch's ray budget caps it too;
        ray_factor: the power per ray is ``power_per_ray * ray_factor`` (stiff scenes).
        """
        cfg = self.config
        floor = cfg.min_rays if min_rays is None else min_rays
        scalar = rowsum(np.abs(power))
        n = len(scalar)
        if n == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        k = min(max_shooters or cfg.max_shooters, n)
        # Top-K by power, largest first
        idx = np.argpartition(-scalar, k - 1)[:k] if k < n else np.arange(n)
        idx = idx[np.argsort(-scalar[idx], kind="stable")]
        idx = idx[scalar[idx] > self._negligible]
        # Rays in proportion to power, clamped; fill the batch's ray budget
        floor = floor if np.isscalar(floor) else np.asarray(floor)[idx]
        counts = np.clip(np.ceil(scalar[idx] / (self.power_per_ray * ray_factor)), floor, cfg.max_rays_per_shot)
        counts = counts.astype(np.int64)
        # the batch, and what the run's ray budget leaves of it (one shot at least)
        fits = np.cumsum(counts) <= self.batch_limit()
        fits[:1] = True
        return idx[fits], counts[fits]

    def batch_limit(self) -> int:
        """Rays the next batch may trace: ``batch_rays``, or what the run's ray budget leaves of it."""
        cfg = self.config
        return min(cfg.batch_rays, cfg.max_rays - self.stats.rays) if cfg.max_rays else cfg.batch_rays

    def select(self):
        """Choose this batch's shooters: (indices (k,), ray counts (k,), power (k,3) W, amounts (k,3) W/m^2,
        share (k,): the part of each one's amount it shoots now, 1 unless capped by max_rays_per_shot).

        The top K come from the shooter pool (shooters.py: the same shooters as a
        full sort, at O(pool + touched rows) per batch).  While overshooting, every
        patch's amount moves with the ambient term g, so stiff scenes rank the whole
        table (one O(patches) pass per batch), as ``full_selection`` does.
        """
        p = self.patches
        st = self.note_stiffness(self.stiffness())
        floor = st.min_rays(self.config)
        if self.full_selection or self.ambient(st).any():
            amounts = self.shoot_amounts(st)
            power = amounts * p.area[:, None]
            idx, counts = self.rank(power, floor, ray_factor=st.ray_factor)
            power, amounts = power[idx], amounts[idx]
        else:
            rows = self.candidates(self.config.max_shooters)
            amounts = p.unshot[rows]
            power = amounts * p.area[rows, None]
            sel, counts = self.rank(power, floor, ray_factor=st.ray_factor)
            idx, power, amounts = rows[sel], power[sel], amounts[sel]
        # a shooter whose power needs more rays than one shot may have (max_rays_per_shot) shoots
        # that many at the run's power per ray and keeps the rest unshot for later batches: shot
        # whole, its rays would carry more power than the density planned, and a lamp of two
        # triangles would light a room with 2 x 65,536 rays whatever the target
        full = rowsum(np.abs(power)) / (self.power_per_ray * st.ray_factor)
        share = np.where(full > counts, counts / np.maximum(full, 1e-300), 1.0)
        power, amounts = power * share[:, None], amounts * share[:, None]
        # shoot neighbours after each other: coherent rays for Embree (shooters.spatial_order)
        order = spatial_order(p, idx)
        return idx[order], counts[order], power[order], amounts[order], share[order]

    def candidates(self, k: int) -> np.ndarray:
        """Rows of the shooter pool's top ``k`` (shooters.py; the pool's priorities are rank's,
        so its top k is rank's top k), in the pool's order."""
        rows, pr = self.pool.candidates(k, self._negligible)
        if len(rows) > k:
            rows = rows[np.sort(np.argpartition(-pr, k - 1)[:k])]
        return rows

    # -- the ledger's unshot sums, kept incrementally -------------------------------
    def book_unshot(self, rows: np.ndarray, before: np.ndarray, after: np.ndarray | None = None,
                    area: np.ndarray | None = None) -> None:
        """The unshot radiosity of ``rows`` (distinct) changed from ``before`` to ``after`` (k,3)
        (None: read it): update the sums.  ``area``: the rows' areas (k,) when the caller has them.

        O(k).  ``recount`` redoes them exactly every ``recount_every`` batches.
        """
        after = take_rows(self.patches.unshot, rows) if after is None else after
        area = (take_rows(self.patches.area, rows) if area is None else area)[:, None]
        led = self.ledger
        led.unshot = led.unshot + colsum((after - before) * area)
        led.unshot_abs = led.unshot_abs + colsum((np.abs(after) - np.abs(before)) * area)

    def release(self, rows: np.ndarray, amounts: np.ndarray) -> None:
        """Shooters ``rows`` (distinct) give up ``amounts`` (k,3) W/m^2 of unshot radiosity."""
        before = take_rows(self.patches.unshot, rows)
        after = before - amounts
        put_rows(self.patches.unshot, rows, after)
        area = take_rows(self.patches.area, rows)
        self.book_unshot(rows, before, after, area)
        self.pool.update(rows, after, area)

    def recount(self) -> None:
        """The unshot sums and the noise tallies' sums from the whole table (one O(patches) pass
        each; drops the increments' round-off).

        Called at the start and end of ``run`` and every ``recount_every`` batches.  The
        noise sums were resynced at every snapshot before (0.3 s each at 1.27M patches,
        ~40 snapshots in a 15M-ray run); their increments are exact sums of the changes
        (noise.NoiseTally.commit), so, like the ledger's, they only need the round-off
        dropped now and then, and whoever changes B outside ``commit`` resyncs
        (passes.blend).
        """
        p = self.patches
        unshot = p.unshot * p.area[:, None]  # W per patch, signed
        self.ledger.unshot = colsum(unshot)
        self.ledger.unshot_abs = colsum(np.abs(unshot))
        self.noise.resync(p)
        self._since_recount = 0

    def account(self, shot: np.ndarray, tally, absorbed: np.ndarray, extra_lost=0.0) -> None:
        """Book one batch: ledger accounts and the return-ratio tallies used by ``ambient``.

        shot: (m,3) W per ray of the rays patches shot (rays that continue light
        shot elsewhere, like twins', are not counted again).
        """
        led = self.ledger
        led.absorbed = led.absorbed + absorbed
        led.escaped = led.escaped + tally.escaped
        led.back_faces = led.back_faces + tally.back_faces + extra_lost
        self._since_recount += 1
        if self.recount_every and self._since_recount >= self.recount_every:
            self.recount()
        self.tallies += np.stack([colsum(np.abs(shot)), tally.lost + np.abs(extra_lost), tally.landed, tally.kept])
        self.back_by_obj[: len(tally.back_by_obj)] += tally.back_by_obj[: len(self.back_by_obj)]

    # -- the three phases every kind of step shares -----------------------------------
    def fire(self, batch, t0: float):
        """Trace a batch whose sampling began at ``t0``; the time counts as trace time."""
        tally = trace(self.tracer, batch, self.patches, self.channels)
        self.stats.trace_seconds += time.perf_counter() - t0
        return tally

    def crossings(self, batch, tally) -> np.ndarray:
        """Power (3,) W of hits that leave the books another way (subscenes: boundaries)."""
        return np.zeros(3)

    def commit(self, batch, tally, shot=None) -> None:
        """Receivers keep rho of what arrived; book the batch (``shot``: see ``account``).

        The rows hit are gathered once (``shoot.landing``) for the noise tallies, the
        deposit, the ledger and the pool.
        """
        p, hit = self.patches, tally.hit
        land = landing(p, hit, tally.received)
        self.noise.commit(p, land, tally.received_a)  # reads the old B of the rows hit
        absorbed = deposit(p, hit, tally.received, land=land)
        after = land.unshot_after
        self.book_unshot(hit, land.unshot, after, land.area)
        self.pool.update(hit, after, land.area)
        self.account(batch.power if shot is None else shot, tally, absorbed, self.crossings(batch, tally))

    def counted(self, shots: int, rays: int) -> int:
        self.stats.shots += shots
        self.stats.rays += rays
        self.stats.batches += 1
        return rays

    def step(self) -> int:
        """Shoot one batch; return the number of rays traced (0 when nothing is unshot)."""
        idx, counts, power, amounts, share = self.select()
        if len(idx) == 0:
            return 0
        t0 = time.perf_counter()
        diff = self.noise.shot_diff(idx, self.patches.area) * share[:, None]
        batch = patch_rays(self.patches, idx, counts, power, self.rng, diff)
        tally = self.fire(batch, t0)
        # Shooters give up what they shot (dB - amount: 0, or -rho*g when overshooting)
        self.release(idx, amounts)
        self.noise.shot(idx, 1.0 - share)
        self.commit(batch, tally)
        return self.counted(len(idx), len(batch))

    # == the loop ==================================================================
    def elapsed(self) -> float:
        return clock() - self._t0

    def residual(self) -> float:
        return self.ledger.residual()

    def estimate(self) -> Estimate:
        """The estimated RMS error of B now, as the target holds it (per input triangle, the elements
        within ``noise.SHOWN_SLACK`` of it), with ``triangles_refl`` and ``elements_refl`` beside it:
        noise and unshot bias (noise.py); O(1)."""
        p = self.patches
        return self.noise.estimate(bias_ambient(self.tallies, self.ledger.held(), p.total_area, p.mean_rho))

    def unshot_bias(self) -> float:
        """The estimate's bias from the light still unshot alone (the clusters' spread left out), over
        RMS(B - E); 0 while ``bias_cap`` is not set (not needed)."""
        if not math.isfinite(self.bias_cap):
            return 0.0
        p = self.patches
        return combine(self.noise.sums(), bias_ambient(self.tallies, self.ledger.held(), p.total_area, p.mean_rho),
                       0.0).bias_refl

    def target_error(self, est: Estimate | None = None) -> float:
        """The error the accuracy target is held to, over RMS(B - E): the estimate's, or for a shared
        run's replica the estimate of the average of ``replicas`` such runs (the shared noise stays,
        the rest falls by 1/k in the mean square, the bias stays)."""
        est = est if est is not None else self.estimate()
        if self.role.replicas <= 1:
            return est.rms_refl
        sums = self.noise.sums()
        refl_ms = max(sums.r2, 0.0) / max(sums.area, 1e-300)  # RMS(B - E)^2, the estimate's reference
        if refl_ms <= 0:
            return est.rms_refl
        noise = est.noise_refl ** 2
        # shared_noise is per patch: read it as the target does, like the rest of the noise
        shared = min(self.role.shared_noise * self.noise.factors[0] / refl_ms, noise)
        return math.sqrt(shared + (noise - shared) / self.role.replicas + est.bias_refl ** 2)

    def settled_target_error(self) -> float:
        """``target_error`` once a clustered table's clusters have settled (NoiseTally.settle: those
        whose patches' light differs beyond their noise are undone, the kept ones' spread is bias):
        the estimate the report gives, which a stop by accuracy must meet (office3 and the ice-cream
        store stopped at 1.99% and reported 2.08% and 2.02%).  O(patches) when clustered."""
        self.settle()
        return self.target_error()

    def settle(self) -> tuple[int, int]:
        """Settle a clustered table's clusters once a run (NoiseTally.settle; each settling undoes some
        uniform clusters by chance, 5% at its margin, so not at every stop check): (clusters kept,
        undone in all)."""
        if self.noise.pooled and not self.settled:
            self.settled = True
            return self.noise.settle(self.patches)
        kept = len(np.unique(self.patches.cluster[self.patches.cluster >= 0]))
        return kept, self.noise.undone

    def snapshot(self, force: bool = False) -> None:
        """Record a snapshot when the ray count passed the next geometric mark."""
        if not force and self.stats.rays < self._next_snapshot:
            return
        if self.snapshots and self.snapshots[-1].rays == self.stats.rays:
            return
        est = self.estimate()
        self.snapshots.append(
            Snapshot(self.elapsed(), self.stats.shots, self.stats.rays, self.residual(), self.ledger.closure(),
                     finite(est.rms), finite(est.rms_refl))
        )
        self.snapshot_B.append(self.patches.radiosity)
        cap = self.config.snapshot_mb * 2**20
        if isinstance(self.snapshot_B, SnapshotStore) and self.snapshot_B.nbytes > cap and len(self.snapshots) > 2:
            keep = self.snapshot_B.thin()
            self.snapshots = [self.snapshots[i] for i in keep]
            self._snapshot_factor *= self._snapshot_factor
        first = max(self.config.min_rays, 1024)
        self._next_snapshot = max(first, int(math.ceil(self.stats.rays * self._snapshot_factor)))

    def stop_reason(self) -> str:
        cfg = self.config
        if float(self.ledger.emitted.sum()) <= 0.0:
            return "no_emitters"
        if self.residual() <= cfg.tol:
            return "tolerance"
        if by_accuracy(cfg):
            est = self.estimate()
            # the estimate's bias layout and a clustered table's factors come from the last resync
            # (noise.py): near a stop, read them fresh, at most every FRESH_EVERY batches (O(n) each):
            # on the first batch's factors a closed cube ran on past its target and then ended on its
            # noise floor at 1.1% of a 2% target
            near = self.target_error(est) <= NEAR_STOP * cfg.accuracy or noise_floor(est, cfg.accuracy)
            if near and self.stats.batches - self._fresh_at >= FRESH_EVERY:
                self._fresh_at = self.stats.batches
                self.noise.resync(self.patches)
                est = self.estimate()
            shot = self.residual() <= UNSHOT_SHARE * cfg.accuracy or self.final.pending()
            if (shot and self.target_error(est) <= cfg.accuracy and self.unshot_bias() <= self.bias_cap
                    and self.settled_target_error() <= cfg.accuracy):
                return "accuracy"
            if self.final.pending():
                if est.bias_refl <= FINAL_BIAS_SHARE * cfg.accuracy:
                    return "final_gather"  # the light is nearly all shot: gather it (``run``)
            elif shot and noise_floor(est, cfg.accuracy):
                return "noise_floor"
        if cfg.time_limit and self.elapsed() >= cfg.time_limit:
            return "time_limit"
        if self.budget.gather_reserve and self.final.pending():
            left = self.budget.left()
            if left is not None and left <= self.budget.gather_reserve:
                return "final_gather"  # what is left of the budget is the gather's (``Budget.fit``)
        if cfg.max_rays and self.stats.rays >= cfg.max_rays:
            return "ray_budget"
        return ""

    def run(self, on_progress=None, should_stop=None) -> Stats:
        """Step until a stop criterion; ``should_stop()`` True ends the run cleanly.

        on_progress(solver) is called after every batch.
        """
        self._t0 = clock() - self.stats.wall_seconds
        self.pool.invalidate()  # the table may have changed since the last run
        self.recount()
        self.direct.shoot_sources()
        self.snapshot(force=True)
        # a preset gather (a shared run's) is booked even when stopping: it is done, and cheap to book
        if self.config.direct and not self.direct.tried and (self.role.preset_direct is not None
                                                         or not (should_stop is not None and should_stop())):
            self.direct.gather(should_stop)
            self.snapshot()
            if on_progress is not None:
                on_progress(self)
        if not self.budget.fitted:
            self.budget.calibrate()
            self.budget.fit()
        while True:
            reason = self.stop_reason()
            if not reason and should_stop is not None and should_stop():
                reason = "stopped"
            if reason:
                break
            if self.step() == 0:
                reason = "tolerance"
                break
            self.snapshot()
            if on_progress is not None:
                on_progress(self)
        if (reason == "final_gather" or (self.final.pending() and reason == "tolerance")) and not self.role.defer_final:
            self.final.finish(should_stop)
            if self.final.gather is not None and self.final.gather.stopped:
                reason = "stopped"
            elif by_accuracy(self.config):
                met = self.settled_target_error() <= self.config.accuracy
                reason = "accuracy" if met else self.final.cut or "noise_floor"
        self.recount()
        self.snapshot(force=True)
        self.stats.stopped_by = reason
        self.choices.drop("stiff")
        self.choices.extend(self.stiffness_choice())
        self.stats.wall_seconds = self.elapsed()
        return self.stats

    # == reporting =================================================================
    def eta(self) -> float:
        """Seconds to the tolerance, from the log-residual slope of recent snapshots (nan if unknown)."""
        snaps = [s for s in self.snapshots[-6:] if s.residual > 0]
        now = self.residual()
        if len(snaps) < 2 or now <= 0:
            return float("nan")
        a, b = snaps[0], snaps[-1]
        if b.time <= a.time or b.residual >= a.residual:
            return float("nan")
        rate = math.log(a.residual / b.residual) / (b.time - a.time)
        goal = self.config.tol
        if by_accuracy(self.config):
            # the bias falls with the residual; the estimate meets the target once
            # sqrt(noise^2 + bias^2) <= accuracy (nan when the noise alone is above it)
            est = self.estimate()
            room = self.config.accuracy ** 2 - est.noise_refl ** 2
            if room <= 0 or not math.isfinite(est.bias_refl):
                return float("nan")
            goal = now * min(1.0, math.sqrt(room) / max(est.bias_refl, 1e-300))
        return max(0.0, math.log(now / max(goal, 1e-300)) / rate)

    def warnings(self) -> list[str]:
        """Warnings about the run: flipped normals (back-face share of shot power), escaped light."""
        return flipped_normals(self.ledger, self.back_by_obj, self.patches.names) + escaped_light(self.ledger,
                                                                                                  self.patches)


#: the solver's clock (``time.perf_counter``; a test may run it on a clock of its own)
clock = time.perf_counter

#: batches between the resyncs ``stop_reason`` asks for near a stop (clustered tables), and how near:
#: the estimate on the last factors within this many times the target (a cluster of 16 patches
#: divides their noise's square by up to 16)
FRESH_EVERY = 16
NEAR_STOP = 4.0
#: a run that shoots its light stops (by accuracy, or on its noise floor) only once its unshot share
#: of the emitted power (the residual) is under this share of the target, whatever the estimate's
#: bias reads: the bias is laid out like the irradiance smoothed over a free path, which cannot see
#: light still bouncing inside a lamp's housing (office3 stopped with 1.8% unshot, its lamp
#: interiors 2% dark, 87% of its error, the estimate at 0.6x the error measured)
UNSHOT_SHARE = 0.25


def solve(patches: Patches, config: SolverConfig | None = None, **run_kwargs) -> Solver:
    """Convenience: build a Solver, run it, return it."""
    solver = Solver(patches, config)
    solver.run(**run_kwargs)
    return solver
