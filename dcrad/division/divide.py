"""Divide and conquer: subscenes that iterate alone and trade light at barriers.

The paper's main loop (van Liere, section 1.3.2)::

    subDivideScene()                     # partition.partition + partition.clip
    while notConverged:
        foreach subScene: doIterations(n, subScene)   # Subscene.iterate, in parallel
        foreach boundary: transferEnergy(boundary)    # boundary.transfer
        displayScene()                                # on_barrier callback

``Subscene`` is a Solver whose Embree scene also holds its boundary rectangles:
a ray that hits one is recorded in that portal cell's bin for its direction
(``sent``) and goes no further.  At the barrier the coordinator collects every
subscene's ``sent`` buffer, ``transfer`` turns A->B power into outgoing power
on side B, and each subscene shoots its outgoing twins like patches, competing
by power.  ``run_divided`` drives any objects with the handle interface
(``SubsceneHandle``: ``iterate``, ``collect``, ``deliver``, ``state``), so remote
workers (``coordinator.remote.RemoteSubscene``) replace the local ones without
touching the numerics.  What differs between the boundary modes (binned twins,
exact rays) lives in one place, ``boundary.MODES``.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from dcrad.arrays import colsum, take_rows
from dcrad.config import DivideConfig, SolverConfig
from dcrad.division.boundary import (
    Boundary,
    RayParcel,
    TwinBuffer,
    boundary_mode,
    coarsen_directions,
    direction_levels,
    make_boundary,
)
from dcrad.division.partition import clip, partition
from dcrad.errors import ConfigError
from dcrad.estimate.noise import Estimate, NoiseSums, NoiseTally, bias_ambient, combine, finite
from dcrad.meshing.patches import Patches
from dcrad.solving.accuracy import by_accuracy, noise_floor, residual_goal, resolve
from dcrad.solving.energy import Ledger
from dcrad.solving.snapshots import SnapshotStore
from dcrad.solving.solver import Snapshot, Solver, Stiffness, stiffness
from dcrad.transport.emitters import check_single
from dcrad.transport.optics import check_single as check_glass
from dcrad.transport.rays import Tracer
from dcrad.transport.shoot import RayBatch, patch_rays, per_ray_power, ray_lattice, ray_offset
from dcrad.transport.shooters import spatial_order

__all__ = [
    "Subscene", "SubsceneHandle", "SubsceneState", "run_divided", "assemble", "DividedRun", "SequentialExecutor",
    "DivideConfig", "build_subscenes", "subscene_specs", "SubsceneSpec", "SUBSCENES_PER_WORKER",
    "expected_work", "placement",
    "solve_divided", "subscene_arrays", "checkpoint_arrays", "build_subscene", "boundaries_to_array",
    "boundaries_from_array", "run_subscenes",
]


#: exact mode: a subscene's barrier comes once this many batches' worth of rays crossed its boundaries
FORWARD_CAP = 4


class SequentialExecutor(Executor):
    """Runs submitted work at once in the caller's thread (deterministic, for tests)."""

    def submit(self, fn, *args, **kwargs):
        fut: Future = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # handed back through the future
            fut.set_exception(exc)
        return fut


@dataclass
class SubsceneState:
    """What a subscene reports at a barrier (small: no per-patch arrays)."""

    cell: int
    ledger: Ledger
    shots: int
    rays: int
    twin_entries: int  #: non-empty (boundary, crossing, cell, bin) entries held
    twin_bytes: int  #: bytes held by twin buffers
    area: float = 0.0  #: m^2 of the subscene's patches
    #: (4,3) W shot by patches, lost, landed, kept (``Solver.tallies``), for the job's stiffness
    tallies: np.ndarray = field(default_factory=lambda: np.zeros((4, 3)))
    twins_delivered: int = 0  #: twin entries received from neighbours so far
    twin_blocks: int = 0  #: what they were stored as (``Subscene.deliver``)
    batches: int = 0  #: Embree calls so far
    trace_seconds: float = 0.0  #: s spent inside trace so far
    #: (n_objects,) W that hit back faces, by object index (the flipped-normals warning)
    back_by_obj: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: the half-solution sums of the error estimate (noise.py); None: not reported
    noise: NoiseSums | None = None


@runtime_checkable
class SubsceneHandle(Protocol):
    """What ``run_divided`` drives: one subscene, here (``Subscene``) or on a worker
    (``coordinator.remote.RemoteSubscene``).

    cell : the subscene's cell id; mode : its boundary mode (``boundary.MODES``)
    """

    cell: int
    mode: str

    def iterate(self, n: int, plan: "BarrierPlan | None" = None) -> int:
        """doIterations: up to n batches with this barrier's plan; the rays traced."""
        ...

    def collect(self) -> TwinBuffer | RayParcel:
        """What crossed its boundaries since the last barrier (the mode's buffer)."""
        ...

    def deliver(self, buffer: TwinBuffer | RayParcel) -> None:
        """Accept what crossed into it from its neighbours at the barrier."""
        ...

    def state(self) -> SubsceneState:
        """Its books now (small: no per-patch arrays)."""
        ...

    def radiosity(self) -> np.ndarray:
        """(n,3) B of its clipped patches, as of the last barrier."""
        ...

    def interrupt(self) -> None:
        """End the doIterations in flight after its current batch, and shoot no more (the job
        was cancelled); safe to call from another thread, at any time."""
        ...


class Subscene(Solver):
    """Progressive refinement over one cell's patches plus its boundary rectangles.

    cell          : cell id
    patches       : the cell's clipped patches
    boundaries    : every Boundary this cell touches (side A or B)
    power_per_ray : W per ray, the same in every subscene of a job
    """

    def __init__(self, cell: int, patches: Patches, boundaries: list[Boundary], config: SolverConfig,
                 power_per_ray: float, mode: str = "binned", local_target: float = 0.0):
        # the patches from their shared vertices, then each boundary's rectangles (Tracer.mesh:
        # the same hits as the triangles, built in half the time)
        rects = np.concatenate([b.triangles() for b in boundaries]).reshape(-1, 3) if boundaries else np.zeros((0, 3))
        faces = np.concatenate([patches.faces, len(patches.vertices) + np.arange(len(rects)).reshape(-1, 3)])
        super().__init__(patches, config, tracer=Tracer(None, vertices=np.concatenate([patches.vertices, rects]),
                                                        faces=faces))
        self.cell = cell
        #: adaptive doIterations: W of local residual below which a barrier's iterations stop
        self.local_target = local_target
        self.boundaries = list(boundaries)
        self.power_per_ray = power_per_ray
        self.rng = np.random.default_rng([config.seed, cell])
        mc = max((b.n_cells for b in boundaries), default=1)
        mb = max((b.n_bins for b in boundaries), default=1)
        self.mode = mode  #: "binned" (the paper's twins) or "exact" (forward whole rays)
        self.boundary_mode = boundary_mode(mode)  #: what crosses and how (boundary.MODES)
        #: recorded crossings, handed over at the barrier (TwinBuffer; exact mode: RayParcel)
        self.sent: TwinBuffer | RayParcel = self.boundary_mode.sent(mc, mb)
        #: power received from neighbours, still to shoot here; its bin is level * n_bins + bin,
        #: a block of 2**level x 2**level bins (``coarsen_directions``)
        self.pending = TwinBuffer(mc, mb * direction_levels(max((b.solid for b in boundaries), default=1)))
        self.forward = RayParcel()  #: rays from neighbours, continued here unchanged (exact mode)
        self._offset = ray_offset(patches) if len(patches) else 1e-6
        self.twins_delivered = 0  #: twin entries received from neighbours
        self.twin_blocks = 0  #: what they became after coarsening (see ``deliver``)
        #: this barrier's plan from ``run_divided``: the job's Stiffness and U_rest (see ``ambient``)
        self.plan: BarrierPlan | None = None
        self.interrupted = False  #: set from another thread by ``interrupt``: iterate shoots no more
        self._solid_of = np.ones(max((b.id for b in self.boundaries), default=0) + 1, np.int64)  #: by boundary id
        for b in self.boundaries:
            self._solid_of[b.id] = b.solid
        #: (3 held buffers: sent, pending, forward; 3) W, signed and magnitude sums of what each holds:
        #: counted exactly at barriers (``_book_in_flight``), kept from each batch's moves in between
        self._held_sum = np.zeros((3, 3))
        self._held_abs = np.zeros((3, 3))

    def stiffness(self) -> Stiffness:
        """The job's stiffness, estimated by ``run_divided`` at the barrier (none before)."""
        return self.plan.stiffness if self.plan is not None else Stiffness.none()

    def ambient(self, st: Stiffness) -> np.ndarray:
        """(3,) W/m^2: the job's ambient irradiance g = F * U (solver.py module doc).

        The estimate needs the whole job: F comes from the summed return tallies,
        and U = U_rest (the signed unshot and twin power the other subscenes held
        at the barrier) + this subscene's own, as it is now.
        """
        if not st.scale.any() or self.plan is None:
            return st.scale
        return st.scale * (self.plan.rest + self.ledger.unshot + self.ledger.in_flight)

    # == sources: patches and outgoing twins, one ranking ========================
    def select_all(self):
        """Patches and outgoing twins ranked together by power.

        Returns (rows, counts, power (k,3) W, amounts (k,3) W/m^2) of the patch shooters,
        in spatial order (``shooters.spatial_order``: coherent rays, as ``Solver.select``),
        and (positions, counts, power) of the twin entries shot, with the pending entries.

        The patch candidates come from the shooter pool (``Solver.select``: the top K
        without a pass over all patches); while overshooting every amount moves with
        the ambient term, so the whole table is ranked, as a single solver does.
        """
        p = self.patches
        cfg = self.config
        st = self.stiffness()
        entries = self.pending.entries() if len(self.pending) else None
        t_power = entries[4].reshape(-1, 3) if entries is not None else np.zeros((0, 3))
        n_twins = len(t_power)
        floor_p = st.min_rays(cfg)
        if self.full_selection or self.ambient(st).any():
            rows = np.arange(len(p))
            amounts = self.shoot_amounts(st)
        else:
            # at most batch_rays // floor patches fit in a batch, and at most K + twins are ranked
            k = max(1, min(cfg.max_shooters + n_twins, cfg.batch_rays // floor_p))
            rows = self.candidates(k)
            amounts = take_rows(p.unshot, rows)
        p_power = amounts * take_rows(p.area, rows)[:, None]
        power = np.concatenate([p_power, t_power]) if n_twins else p_power
        # A twin entry is already narrow in direction and position: rays in proportion to
        # its power, at least one (the 32-ray floor is for a patch's whole hemisphere;
        # on an open boundary with 1e5 small entries it multiplied the rays 32-fold)
        floor = np.concatenate([np.full(len(rows), floor_p), np.ones(n_twins, np.int64)]) if n_twins else floor_p
        # twin entries are many and cheap: only the batch's ray budget limits them
        idx, counts = self.rank(power, floor, cfg.max_shooters + n_twins, st.ray_factor)
        patch = idx < len(rows)
        sel = idx[patch]
        order = spatial_order(p, rows[sel])
        sel = sel[order]
        shooters = (rows[sel], counts[patch][order], p_power[sel], amounts[sel])
        twins = (idx[~patch] - len(rows), counts[~patch], power[idx[~patch]])
        return shooters, twins, entries

    def twin_rays(self, pending, entries: np.ndarray, counts: np.ndarray, power: np.ndarray) -> RayBatch:
        """Rays from outgoing twins: points in the portal cell, directions inside the bin
        (or the block of bins, for entries coarsened on delivery: see ``deliver``).

        pending: ``self.pending.entries()``; entries (k,) the positions shot.
        """
        bid, crossing, cell, code, _ = pending
        total = int(counts.sum())
        owner, u = ray_lattice(counts, self.rng)
        e = entries[owner]
        origins = np.empty((total, 3))
        dirs = np.empty((total, 3))
        for b in self.boundaries:  # a handful per subscene
            sel = np.flatnonzero(bid[e] == b.id)
            if len(sel) == 0:
                continue
            es = e[sel]
            level, corner = np.divmod(code[es], b.n_bins)
            o, d = b.sample(cell[es], corner, crossing[es], u[sel], level)
            side = np.where(crossing[es] == 0, 1.0, -1.0)
            origins[sel] = o + (self._offset * side)[:, None] * b.normal[None, :]
            dirs[sel] = d
        # halves at random (noise.py): the twin rays' sampling noise is counted, V = 0 for twin power
        return RayBatch(origins=origins, dirs=dirs, power=per_ray_power(power, counts), shooter=owner,
                        half=self.rng.random(total) < 0.5)

    def _held(self) -> list:
        return [self.sent, self.pending, self.forward]

    def _book_in_flight(self) -> None:
        """The in-flight accounts counted from the held buffers (O(held): at barriers)."""
        for i, h in enumerate(self._held()):
            self._held_sum[i] = h.total()
            self._held_abs[i] = h.total_abs()
        self._in_flight_to_ledger()

    def _in_flight_to_ledger(self) -> None:
        self.ledger.in_flight = self._held_sum.sum(axis=0)
        self.ledger.in_flight_abs = self._held_abs.sum(axis=0)

    def _moved(self, i: int, signed: np.ndarray, magnitude: np.ndarray) -> None:
        """Held buffer i (0 sent, 1 pending, 2 forward) gained ``signed`` W (negative: gave up)."""
        self._held_sum[i] += signed
        self._held_abs[i] += magnitude
        self._in_flight_to_ledger()

    def step_forwarded(self) -> int:
        """Exact mode: continue up to batch_rays rays handed over by neighbours."""
        part = self.forward.take_front(self.config.batch_rays)
        self._moved(2, -part.total(), -part.total_abs())
        side = np.ones(len(part))
        for b in self.boundaries:
            sel = part.boundary == b.id
            side[sel] = np.where(part.dirs[sel] @ b.normal > 0, 1.0, -1.0)
            part.origins[sel] += (self._offset * side[sel])[:, None] * b.normal[None, :]
        batch = RayBatch(part.origins, part.dirs, part.power, np.zeros(len(part), np.int64),
                         self.rng.random(len(part)) < 0.5)  # halves at random (noise.py)
        tally = self.fire(batch, time.perf_counter())
        self.commit(batch, tally, shot=np.zeros((0, 3)))  # continued light, shot elsewhere
        return self.counted(0, len(batch))

    def crossings(self, batch: RayBatch, tally) -> np.ndarray:
        return self.record_crossings(batch, tally)

    def step(self) -> int:
        if len(self.forward):
            return self.step_forwarded()
        (rows, counts, power, amounts), (twin_idx, t_counts, t_power), pending = self.select_all()
        if len(rows) + len(twin_idx) == 0:
            return 0
        p = self.patches
        t0 = time.perf_counter()
        batches = []
        if len(rows):
            batches.append(patch_rays(p, rows, counts, power, self.rng, self.noise.shot_diff(rows, p.area)))
        if len(twin_idx):
            batches.append(self.twin_rays(pending, twin_idx, t_counts, t_power))
        batch = batches[0] if len(batches) == 1 else RayBatch(
            *(np.concatenate([getattr(b, f) for b in batches])
              for f in ("origins", "dirs", "power", "shooter", "half")))
        tally = self.fire(batch, t0)

        # Shooters give up their power (twins leave the pending buffer)
        self.release(rows, amounts)  # keeps the ledger's unshot sums and the shooter pool
        self.noise.shot(rows)
        if len(twin_idx):
            gone = self.pending.take(twin_idx)
            self._moved(1, -gone.total(), -gone.total_abs())
        n_patch = len(batches[0]) if len(rows) else 0
        self.commit(batch, tally, shot=batch.power[:n_patch])
        return self.counted(len(rows) + len(twin_idx), len(batch))

    def record_crossings(self, batch: RayBatch, tally) -> np.ndarray:
        """Store rays that hit a boundary in ``sent``; return power of mis-sided hits (3,) W.

        A ray can only leave this cell through a boundary in the direction away from
        it; a hit the other way (an origin a hair beyond the plane) is not light that
        crosses, and goes to the back-face account instead of vanishing.
        """
        lost = np.zeros(3)
        if len(tally.portal) == 0:
            return lost
        rays = tally.portal
        local = tally.portal_prim // 2
        points = batch.origins[rays] + tally.portal_t[:, None] * batch.dirs[rays]
        for i, b in enumerate(self.boundaries):
            sel = np.flatnonzero(local == i)
            if len(sel) == 0:
                continue
            r = rays[sel]
            d = batch.dirs[r]
            crossing = b.crossing(d)
            ok = crossing == (0 if b.side_a == self.cell else 1)
            lost += batch.power[r[~ok]].sum(axis=0)
            r, d, pts = r[ok], d[ok], points[sel][ok]
            if len(r):
                pw = take_rows(batch.power, r)
                self.boundary_mode.record(self.sent, b, pts, d, crossing[ok], pw)
                if isinstance(self.sent, RayParcel):  # rays are kept whole: the sums just add
                    self._moved(0, colsum(pw), colsum(np.abs(pw)))
        if not isinstance(self.sent, RayParcel):  # twins merge by entry: count the buffer
            self._held_sum[0], self._held_abs[0] = self.sent.total(), self.sent.total_abs()
            self._in_flight_to_ledger()
        return lost

    # == the handle interface used by run_divided ================================
    def local_residual(self) -> float:
        """W this subscene would still shoot now: |shoot amounts| + |pending twins| (absolute).

        Without overshooting the amounts are the unshot power, whose magnitude the
        ledger keeps (O(1)).  With it, a patch that has shot keeps -rho*g parked until
        the light it anticipated arrives, much of it from the other subscenes at later
        barriers: that is not work this subscene can do now, so it does not count here
        (and the amounts are summed over the table, as stiff scenes rank it whole).
        """
        p = self.patches
        pending = float(self._held_abs[1:].sum())
        st = self.stiffness()
        if self.ambient(st).any():
            amounts = self.shoot_amounts(st)
            return float((np.abs(amounts) * p.area[:, None]).sum() + pending)
        return float(self.ledger.unshot_abs.sum()) + pending

    def iterate(self, n: int, plan: "BarrierPlan | None" = None) -> int:
        """doIterations: up to n batches; returns rays traced.

        plan: how to shoot until the next barrier (``barrier_plan``); None: plainly.

        Adaptive (``local_target`` > 0, in W): stop once the local residual has
        fallen to a quarter of what it was when this barrier's iterations began,
        or below ``local_target``, whichever is larger.  The target is tol/2 of the
        job's emitted power shared over the subscenes, so when every subscene
        meets it the job's residual is below tol.  A subscene then does a fixed share
        of its own work per barrier however much light it was handed.

        Exact mode: the barrier also comes once ``sent`` holds ``FORWARD_CAP``
        batches' worth of crossing rays, so forwarded rays (80 bytes each) stay
        bounded in memory and on the wire.
        """
        self.plan = plan
        # Exact sums and a fresh shooter pool at every barrier (O(patches) once a barrier):
        # a subscene resumed from this barrier's checkpoint then continues bit-identically
        self.pool.invalidate()
        self.recount()
        self._book_in_flight()
        rays = 0
        share = plan.goal if plan is not None and plan.goal > 0 else BARRIER_GOAL
        goal = max(self.local_target, share * self.local_residual()) if self.local_target > 0 else 0.0
        cap = FORWARD_CAP * self.config.batch_rays
        deadline = time.perf_counter() + plan.time_left if plan is not None and plan.time_left > 0 else None
        for i in range(n):
            if deadline is not None and i > 0 and time.perf_counter() >= deadline:
                break  # the job's time limit, inside the barrier
            if self.interrupted:
                break  # the job was cancelled
            if plan is not None and plan.rays_left and rays >= plan.rays_left:
                break  # its share of the job's ray budget
            if goal > 0 and self.local_residual() <= goal:
                break
            if isinstance(self.sent, RayParcel) and len(self.sent) >= cap:
                break
            r = self.step()
            if r == 0:
                break
            rays += r
        return rays

    def collect(self) -> TwinBuffer | RayParcel:
        """Hand over what crossed the boundaries since the last barrier."""
        out = self.sent.drain()
        self.ledger.exported = self.ledger.exported + out.total()
        self._book_in_flight()
        return out

    def deliver(self, buffer) -> None:
        """Accept outgoing power (TwinBuffer) or rays (RayParcel) from neighbours.

        Directional resolution where the energy is (``adaptive_bins``): twin entries
        weaker than one ray's power are summed into coarser blocks of direction
        bins before they are stored, so weak light costs one ray per block, not
        one per bin.  Power is kept exactly; only its direction gets coarser.
        """
        self.ledger.imported = self.ledger.imported + buffer.total()
        if isinstance(buffer, RayParcel):
            self.forward.merge(buffer)
        elif len(buffer):
            bid, crossing, cell, bins, power = buffer.entries()
            self.twins_delivered += len(bins)
            if self.config.adaptive_bins:
                factor = self.plan.stiffness.ray_factor if self.plan is not None else 1.0
                _, g = coarsen_directions(bid, crossing, cell, bins, power, self._solid_of[bid],
                                          self.power_per_ray * factor)
                n_bins = self._solid_of[g["bid"]] ** 2
                bid, crossing, cell, bins, power = g["bid"], g["crossing"], g["cell"], \
                    g["level"] * n_bins + g["bin"], g["power"]
            self.twin_blocks += len(bins)
            self.pending.add(bid, crossing, cell, bins, power)
        self._book_in_flight()

    def state(self) -> SubsceneState:
        held = self._held()
        return SubsceneState(self.cell, self.ledger.copy(), self.stats.shots, self.stats.rays,
                             sum(len(h) for h in held), sum(h.nbytes() for h in held),
                             self.patches.total_area, self.tallies.copy(),
                             self.twins_delivered, self.twin_blocks, self.stats.batches,
                             self.stats.trace_seconds, self.back_by_obj.copy(), self.noise.sums())

    def radiosity(self) -> np.ndarray:
        return self.patches.radiosity

    def interrupt(self) -> None:
        self.interrupted = True


def assemble(n_patches: int, area: np.ndarray, parents: list[np.ndarray], pieces: list[Patches],
             values: list[np.ndarray] | None = None) -> np.ndarray:
    """Radiosity per original patch (n,3): area-weighted mean of its clipped pieces."""
    num = np.zeros((n_patches, 3))
    den = np.zeros(n_patches)
    for k, (par, sub) in enumerate(zip(parents, pieces)):
        b = sub.radiosity if values is None else values[k]
        for c in range(3):
            num[:, c] += np.bincount(par, weights=b[:, c] * sub.area, minlength=n_patches)
        den += np.bincount(par, weights=sub.area, minlength=n_patches)
    out = np.zeros((n_patches, 3))
    ok = den > 0
    out[ok] = num[ok] / den[ok, None]
    return out


@dataclass
class DividedRun:
    """Result of run_divided: per-barrier snapshots and the job ledger."""

    ledger: Ledger
    snapshots: list[Snapshot] = field(default_factory=list)
    #: B at each snapshot, float16 under the ``snapshot_mb`` cap (snapshots.py)
    snapshot_B: SnapshotStore = field(default_factory=SnapshotStore)
    barrier_closures: list[float] = field(default_factory=list)
    states: list[SubsceneState] = field(default_factory=list)
    barriers: int = 0
    stopped_by: str = ""
    wall_seconds: float = 0.0
    max_twin_bytes: int = 0
    stiff: Stiffness | None = None  #: the last barrier plan's stiffness that changed shooting
    estimate: Estimate | None = None  #: the job's error estimate at the last barrier (``job_estimate``)
    #: the share of the power shot at the last barrier that came back as another subscene's residual
    #: (``crossing_share``, for ``landing_goal``; -1: not measured yet, as after a resume)
    crossing: float = -1.0
    goals: list[float] = field(default_factory=list)  #: each barrier's ``landing_goal`` (0: the plain one)


def job_ledger(states: list[SubsceneState]) -> Ledger:
    total = Ledger()
    for s in states:
        total += s.ledger
    return total


def job_estimate(states: list[SubsceneState], led: Ledger) -> Estimate | None:
    """The job's error estimate (noise.py) from every subscene's half-solution sums, return
    tallies and the job ledger's unshot and in-flight power; None if a subscene sent no sums."""
    if not states or any(s.noise is None for s in states):
        return None
    sums = sum((s.noise for s in states if s.noise is not None), NoiseSums())
    tallies = sum((s.tallies for s in states), np.zeros((4, 3)))
    mean_rho = sums.rho1 / max(sums.area, 1e-300)  # stands in for lambda before the first shot
    return combine(sums, bias_ambient(tallies, led.held(), sums.area, mean_rho))


@dataclass(frozen=True)
class BarrierPlan:
    """How one subscene shoots until the next barrier (set by ``run_divided``).

    stiffness : the job's Stiffness (ambient scale and ray factor)
    rest      : (3,) W, signed unshot + twin power held by the *other* subscenes
    time_left : s until the job's time limit (0: none); doIterations stops after the
                batch that passes it, so the limit holds inside a barrier, on any worker
    rays_left : rays this subscene may trace before the next barrier, its share of what is left of
                the job's --max-rays (0: no budget); doIterations stops after the batch that
                reaches it, so the budget holds inside a barrier (the 20x20 office at --max-rays
                3e7 traced 153M rays when only the barriers checked it)
    """

    stiffness: Stiffness
    rest: np.ndarray
    time_left: float = 0.0
    goal: float = 0.0  #: the share of its residual a subscene leaves this barrier (0: ``BARRIER_GOAL``)
    rays_left: int = 0


#: an adaptive barrier ends once a subscene's residual has fallen to this share of what it held
#: at the barrier's start (``Subscene.iterate``), unless ``landing_goal`` says otherwise
BARRIER_GOAL = 0.25
#: the shares a landing barrier may ask for: below MIN_GOAL a barrier shoots long past where the
#: estimate was measured; above MAX_GOAL it is hardly worth its sync
MIN_GOAL, MAX_GOAL = 0.1, 0.8
#: the last barrier aims at this share of the accuracy target: its noise estimate moves a little.
#: Rays to the target in process (office, landed against plain quarters): 3x3 at 5%, k = 2, 4, 8:
#: -4.6%, -8.5%, -1.4%; 3x3 at 2% k=4 -0.5%, at 3% k=16 -0.3%; 4x4 at 5% k=4 +1.6% (the plain
#: run happened to land at 4.95%); at 0.95 the savings were about half, and no run took an extra barrier
LANDING = 0.98


def landing_goal(estimate: Estimate | None, accuracy: float, crossing: float) -> float:
    """The share of its residual each subscene should leave this barrier for the job's estimate to
    land just below ``accuracy`` at the barrier's end, or 0 (the plain ``BARRIER_GOAL``).

    The estimate's bias part is in proportion to the job's unshot and in-flight power (noise.py
    ``bias_ambient``), so the job's residual must fall by want = sqrt((LANDING a)^2 - noise^2) / bias.
    The subscenes cannot see each other's light while they shoot: a share ``crossing`` of what
    they shoot away comes back as another's residual at the barrier (measured at the last one:
    ``DividedRun.crossing``, ``crossing_share``), so a share f left gives f + crossing (1 - f) of the
    job's residual.
    The noise is taken as it is now (it falls as the barrier adds rays: the barrier lands lower).
    Out of reach of one barrier: 0, plain barriers.
    """
    if estimate is None or accuracy <= 0 or not (estimate.bias_refl > 0 and math.isfinite(estimate.noise_refl)):
        return 0.0
    room = (LANDING * accuracy) ** 2 - estimate.noise_refl ** 2
    if room <= 0:
        return 0.0  # the noise alone is above the target: plain barriers (their rays lower it)
    want = math.sqrt(room) / estimate.bias_refl
    f = (want - crossing) / (1.0 - crossing) if crossing < 1.0 else 0.0
    return float(min(f, MAX_GOAL)) if f >= MIN_GOAL else 0.0


def crossing_share(previous: Ledger, led: Ledger, f: float) -> float:
    """``DividedRun.crossing`` after a barrier that asked each subscene to leave a share ``f`` of its
    residual: ``previous`` the job's ledger as it began, ``led`` at its end.

    Two readings, the lower kept.  From how far the residual fell, (after / before - f) / (1 - f):
    right when the subscenes leave f or a little less (a batch shoots past the goal: the 3x3 office,
    which lands that way again).  From the power exported, crossed / (crossed + before - after):
    right when a barrier ends above its goal, at the forward cap or its batch count, which the first
    reading counts as crossing (the 20x20 office's last barrier then took 0.47 for 0.62 of the
    residual, and landed at 4.63% for a 5% target; with the second, 0.62 and 4.86%)."""
    before, after = previous.residual(), led.residual()  # before > 0 (the caller's check)
    fell = (after / before - f) / (1.0 - f)
    emitted = float(led.emitted.sum())
    crossed = float((led.exported - previous.exported).sum()) / emitted if emitted > 0 else 0.0
    left = before - after + crossed  # shot away, or handed over
    share = min(fell, crossed / left) if left > 0 else fell
    return min(max(share, 0.0), 0.99)


def barrier_plan(states: list[SubsceneState], config: SolverConfig, time_left: float = 0.0,
                 goal: float = 0.0, rays_left: int = 0) -> dict:
    """{cell: BarrierPlan} for the next doIterations (empty: plain shooting everywhere).

    Stiffness is a property of the whole job (light crosses the boundaries), so
    it is estimated from every subscene's return tallies and area at the
    barrier, exactly as a single solver estimates its own.  ``goal``: ``landing_goal``'s share.
    ``rays_left``: what is left of the job's ray budget (0: none), shared out in proportion to the
    power each subscene holds (its rays follow its power), at least one ray each.
    """
    area = sum(s.area for s in states)
    tallies = sum((s.tallies for s in states), np.zeros((4, 3)))
    st = stiffness(tallies, area, config)
    budget = ray_shares(states, rays_left)
    if not st.active:
        if time_left <= 0 and goal <= 0 and rays_left <= 0:
            return {}
        return {s.cell: BarrierPlan(st, np.zeros(3), time_left, goal, budget[s.cell]) for s in states}
    held = {s.cell: s.ledger.unshot + s.ledger.in_flight for s in states}
    total = sum(held.values(), np.zeros(3))
    return {cell: BarrierPlan(st, total - u, time_left, goal, budget[cell]) for cell, u in held.items()}


def ray_shares(states: list[SubsceneState], rays_left: int) -> dict:
    """{cell: rays} of ``rays_left`` (0: no budget, every share 0) by the power each subscene holds."""
    if rays_left <= 0:
        return {s.cell: 0 for s in states}
    held = np.array([float(s.ledger.held().sum()) for s in states])
    weight = held / held.sum() if held.sum() > 0 else np.full(len(states), 1.0 / max(len(states), 1))
    return {s.cell: max(int(rays_left * w), 1) for s, w in zip(states, weight)}


def run_divided(handles: Sequence[SubsceneHandle], boundaries: list[Boundary], config: SolverConfig,
                iterations: int = 4,
                executor: Executor | None = None, assemble_B=None, on_barrier=None,
                should_stop=None, first_barrier: int = 0, crossing: float = -1.0) -> DividedRun:
    """The paper's main loop over subscene handles.

    handles    : SubsceneHandle objects (Subscene, or coordinator.remote.RemoteSubscene), one mode
    iterations : batches per subscene between two barriers (doIterations' n)
    assemble_B : optional callable () -> (n,3) radiosity of the whole scene, for snapshots
    on_barrier : optional callable (DividedRun) after every barrier
    first_barrier : barriers already done (handles resumed from that barrier's checkpoints)
    crossing   : ``DividedRun.crossing`` at that barrier (a resumed job lands as the undisturbed one)
    """
    executor = executor or SequentialExecutor()
    config = resolve(config)  # the stop rule: by the error estimate, or at the residual tol
    modes = {h.mode for h in handles}
    if len(modes) != 1:
        raise ConfigError(f"the subscenes of one job disagree on the boundary mode: {sorted(modes)}")
    mode = boundary_mode(modes.pop())
    run = DividedRun(ledger=Ledger(), barriers=first_barrier, crossing=crossing)
    t0 = time.perf_counter()

    def barrier_snapshot(states):
        led = job_ledger(states)
        run.ledger = led
        run.states = states
        shots = sum(s.shots for s in states)
        rays = sum(s.rays for s in states)
        run.estimate = est = job_estimate(states, led)
        run.snapshots.append(Snapshot(time.perf_counter() - t0, shots, rays, led.residual(), led.closure(),
                                      finite(est.rms) if est else None, finite(est.rms_refl) if est else None))
        run.barrier_closures.append(led.closure())
        run.max_twin_bytes = max(run.max_twin_bytes, sum(s.twin_bytes for s in states))
        if assemble_B is not None:
            run.snapshot_B.append(assemble_B())
            if run.snapshot_B.nbytes > config.snapshot_mb * 2**20 and len(run.snapshot_B) > 2:
                keep = run.snapshot_B.thin()  # every other barrier's B goes: the cap holds
                run.snapshots = [run.snapshots[i] for i in keep]
        return led

    led = barrier_snapshot([h.state() for h in handles])
    reason = ""
    while True:
        if float(led.emitted.sum()) <= 0:
            reason = "no_emitters"
        elif led.residual() <= config.tol:
            reason = "tolerance"
        elif by_accuracy(config) and run.estimate is not None and run.estimate.rms_refl <= config.accuracy:
            reason = "accuracy"
        elif by_accuracy(config) and run.estimate is not None and noise_floor(run.estimate, config.accuracy):
            reason = "noise_floor"
        elif config.time_limit and time.perf_counter() - t0 >= config.time_limit:
            reason = "time_limit"
        elif config.max_rays and run.snapshots[-1].rays >= config.max_rays:
            reason = "ray_budget"
        elif should_stop is not None and should_stop():
            reason = "stopped"
        if reason:
            break
        # doIterations in every subscene (in parallel when the executor allows)
        left = config.time_limit - (time.perf_counter() - t0) if config.time_limit else 0.0
        landing = by_accuracy(config) and run.crossing >= 0
        goal = landing_goal(run.estimate, config.accuracy, run.crossing) if landing else 0.0
        budget = max(config.max_rays - run.snapshots[-1].rays, 1) if config.max_rays else 0
        plan = barrier_plan(run.states, config, max(left, 1e-9) if config.time_limit else 0.0, goal, budget)
        run.goals.append(goal)
        previous = led
        if plan and next(iter(plan.values())).stiffness.active:
            run.stiff = next(iter(plan.values())).stiffness
        list(executor.map(lambda h, plan=plan: h.iterate(iterations, plan.get(h.cell)), handles))
        # transferEnergy at the barrier
        incoming = {h.cell: h.collect() for h in handles}
        outgoing = mode.transfer(incoming, boundaries)
        del incoming  # routed; each buffer is let go once delivered (a coordinator's memory)
        for h in handles:
            h.deliver(outgoing.pop(h.cell) if h.cell in outgoing else mode.empty())
        run.barriers += 1
        led = barrier_snapshot([h.state() for h in handles])
        if previous.residual() > 0:
            run.crossing = crossing_share(previous, led, goal or BARRIER_GOAL)
        if on_barrier is not None:
            on_barrier(run)
        stopping = should_stop is not None and should_stop()  # an interrupted barrier may shoot nothing
        if run.snapshots[-1].rays == run.snapshots[-2].rays and led.residual() > config.tol and not stopping:
            # nothing left to shoot anywhere: every subscene is at its local target.  In accuracy mode
            # with the noise above the target that is the run's noise floor (Cornell, k=4, 3%: its
            # shot direct light's noise 3.8%, the bias 0.8%, above noise_floor's bias share)
            floor = by_accuracy(config) and run.estimate is not None and run.estimate.noise_refl > config.accuracy
            reason = "noise_floor" if floor else "stalled"
            break
    run.stopped_by = reason
    run.wall_seconds = time.perf_counter() - t0
    return run


#: the most subscenes of one job, and the fewest patches a subscene must have on average
#: (64 subscenes of a 4-triangle scene, 4,352 patches: 47 s against 4.4 s unsplit; 256: 120 s)
MAX_SUBSCENES, MIN_PATCHES_PER_SUBSCENE = 64, 16


def subscene_limit(n_patches: int) -> int:
    """The most subscenes a scene of ``n_patches`` patches may be cut into."""
    return max(1, min(MAX_SUBSCENES, n_patches // MIN_PATCHES_PER_SUBSCENE))


def check_subscenes(k: int, n_patches: int) -> None:
    """ConfigError when k subscenes are more than the scene can use (``subscene_limit``)."""
    limit = subscene_limit(n_patches)
    if k > limit:
        raise ConfigError(f"{k} subscenes for {n_patches} patches: at most {limit} (each subscene needs "
                          f"{MIN_PATCHES_PER_SUBSCENE} patches on average, and a job at most {MAX_SUBSCENES}); "
                          f"use fewer subscenes or a smaller --patch-size")


#: subscenes per worker when --subscenes is not given: over-decomposed, so one worker's two
#: subscenes even out (office 8x8 on 2 workers: 238 s with 2 subscenes, 192 s with 4;
#: bench_scaling's model on the 3x3 office: 1.27x and 2.05x on 2 machines).  Four per worker
#: (office 8x8, 2 workers) pays only when placed by expected work (``placement``: 2-worker
#: critical path 165M rays, round-robin 183M) and then ties two per worker (163M) with more rays
SUBSCENES_PER_WORKER = 2

#: expected_work: W of emitted power a patch counts as (a cell with no lamp still shoots
#: the light its neighbours hand it; office 8x8, k=8: the unlit cell's iterates took 0.34 s
#: for its 25k patches, the lit ones 0.030 s per W of their lamps, so a patch ~ 4.5e-4 W)
WORK_PER_PATCH_W = 4.5e-4

#: what the automatic cut balances (partition's ``work``): "light", a patch share plus twice the
#: emitted share (partition.LIGHT_WEIGHT).  By area, the 20x20 office's 16 cells held 7 to 16 lit
#: rooms and the slowest cell's iterates took 1.24-1.39x the mean (their CPU s follow their lamps'
#: W, correlation 0.99); by light 12 or 13, and 1.10-1.12x (bench/RESULTS.md).  Not by lamps
#: alone (W emitted + WORK_PER_PATCH_W a patch, tried): where one room
#: holds all the lamps (the 1x2 office of tests/test_divide.py) that cut the lit room in half
#: rather than follow the wall; the patch share keeps the wall (score 0.83 against 1.0 across)
CUT_WORK = "light"


def expected_work(patches: Patches) -> float:
    """A subscene's expected iterate work before it runs, in W of emitted power equivalents.

    Progressive refinement at a fixed power per ray traces rays in proportion to the power
    it shoots, and a cell shoots its lamps' light and what that light reflects there: on
    the 8x8 office at the default accuracy each cell's iterate CPU seconds were 0.028-0.033 s
    per W of its own lamps at k = 4 and k = 8 (bench/RESULTS.md).  Light that crosses
    in from neighbours is about what crosses out, so the cell's own lamps predict its work.
    """
    return float(patches.emitted_power.sum()) + WORK_PER_PATCH_W * len(patches)


def placement(work: Sequence[float], workers: int) -> list[int]:
    """Worker slot (0..workers-1) for each subscene so that the slots' expected work evens out.

    Largest first to the least loaded slot (LPT), then single moves and pairwise swaps
    between the most and the least loaded slot while they lower the maximum.  Deterministic
    (ties: the lower index).  Placement does not change the numerics (each subscene's
    iterates are the same on any worker), only which worker waits at each barrier.
    """
    w = np.asarray(work, np.float64)
    if workers < 1:
        raise ConfigError(f"placement needs at least one worker, not {workers}")
    slot = np.zeros(len(w), np.int64)
    load = np.zeros(workers)
    for i in np.argsort(-w, kind="stable"):
        j = int(np.argmin(load))
        slot[i] = j
        load[j] += w[i]
    for _ in range(4 * len(w)):  # each step strictly lowers the pair's maximum
        hi, lo = int(np.argmax(load)), int(np.argmin(load))
        gap = load[hi] - load[lo]
        a = np.flatnonzero(slot == hi)
        b = np.flatnonzero(slot == lo)
        # moving a (d = w_a) or swapping a <-> b (d = w_a - w_b) lowers the maximum when 0 < d < gap;
        # the best d is the one nearest gap / 2
        cand = [(abs(gap / 2 - w[i]), int(i), -1) for i in a if 0 < w[i] < gap]
        cand += [(abs(gap / 2 - (w[i] - w[j])), int(i), int(j)) for i in a for j in b if 0 < w[i] - w[j] < gap]
        if not cand:
            break
        _, i, j = min(cand)
        d = w[i] - (w[j] if j >= 0 else 0.0)
        slot[i] = lo
        if j >= 0:
            slot[j] = hi
        load[hi] -= d
        load[lo] += d
    return slot.tolist()


@dataclass
class SubsceneSpec:
    """What a subscene is made of, as arrays: its clipped patches, boundaries and settings.

    ``build()`` makes the Subscene (a Solver with its own Embree scene) where it
    will iterate; ``state()`` is the state it reports before its first iterate.
    """

    cell: int
    patches: Patches
    boundaries: list[Boundary]
    config: SolverConfig
    power_per_ray: float
    mode: str
    local_target: float = 0.0

    def build(self) -> "Subscene":
        return Subscene(self.cell, self.patches, self.boundaries, self.config, self.power_per_ray, self.mode,
                        local_target=self.local_target)

    def state(self) -> SubsceneState:
        p = self.patches
        led = Ledger(emitted=p.emitted_power.copy())
        led.unshot = p.unshot_power.copy()
        led.unshot_abs = (np.abs(p.unshot) * p.area[:, None]).sum(axis=0)
        return SubsceneState(self.cell, led, 0, 0, 0, 0, p.total_area, back_by_obj=np.zeros(max(len(p.names), 1)),
                             noise=NoiseTally(p).sums())


def subscene_specs(patches: Patches, config: SolverConfig, divide: DivideConfig, planes=None, boxes=None):
    """subDivideScene as arrays: partition, clip, make boundaries and one SubsceneSpec per cell.

    No Solver and no Embree scene is built (the coordinator, which traces nothing,
    sends these to workers).  Returns (specs, boundaries, parents, partition).
    """
    check_single(patches.sources, "divided")
    check_glass(patches.glazing, "divided")
    if planes is None and boxes is None:
        check_subscenes(divide.subscenes, len(patches))
    config = resolve(config, patches.read_units)  # the job's ray density: from its patch count
    # balanced by light (CUT_WORK): a subscene's iterates cost in proportion to its lamps, and
    # cells of equal area differ in lamps.  Binned twins keep the area cut: by light, the cut
    # moves toward the lamps, and binned twins blur the light that crosses open space there
    # (furnace box, k=2: a vertical plane under the light, RMS error 1.54x the unsplit noise
    # against below 1.5x with the area's horizontal one); exact boundaries forward it unchanged
    work = CUT_WORK if divide.mode == "exact" else "area"
    part = partition(patches, divide.subscenes, planes=planes, boxes=boxes,
                     **({"work": work} if planes is None and boxes is None else {}))
    pieces = clip(patches, part)
    # Portal cells must be small next to walls and doorways: re-emitted twin light
    # starts anywhere in its cell, and the part of a cell inside a wall loses it
    # to back faces (0.6 m cells: 24% too dark behind a doorway; 0.05 m: 3%).
    cell_size = divide.cell_size or patches.scale / 128.0
    # Boundary rectangles stop at the scene's box: no ray can leave the box and come
    # back, and portal cells reaching past the outer walls would re-emit light outside
    boundaries: list[Boundary] = []
    lo_box, hi_box = patches.bounds
    for f in part.faces:
        u, v = (f.axis + 1) % 3, (f.axis + 2) % 3
        lo = (max(f.lo[0], lo_box[u]), max(f.lo[1], lo_box[v]))
        hi = (min(f.hi[0], hi_box[u]), min(f.hi[1], hi_box[v]))
        if hi[0] <= lo[0] or hi[1] <= lo[1]:
            continue
        boundaries.append(make_boundary(len(boundaries), f.axis, f.offset, lo, hi, f.side_a, f.side_b,
                                        cell_size, divide.solid))
    emitted = float(patches.emitted_power.sum())
    per_ray = emitted / config.rays_per_power if emitted > 0 else 1.0
    specs = []
    for cell, (sub, _) in zip(part.cells, pieces):
        touching = [b for b in boundaries if cell.id in (b.side_a, b.side_b)]
        target = 0.5 * residual_goal(config) * emitted / len(part.cells) if divide.adaptive else 0.0
        # The job shoots about max_shooters patches per round, as one solver would: each subscene
        # its share by patch count.  With the whole K each, every subscene shot all its patches
        # every batch, at the 32-ray floor (office 2x3, k=16: 10.7M rays -> 6.3M, same error)
        share = max(64, math.ceil(config.max_shooters * len(sub) / max(len(patches), 1)))
        specs.append(SubsceneSpec(cell.id, sub, touching, config.replace(max_shooters=min(share, config.max_shooters)),
                                  per_ray, divide.mode, target))
    return specs, boundaries, [par for _, par in pieces], part


def build_subscenes(patches: Patches, config: SolverConfig, divide: DivideConfig, planes=None, boxes=None):
    """subDivideScene: partition, clip, make boundaries and one Subscene per cell.

    Returns (subscenes, boundaries, parents, partition).
    """
    specs, boundaries, parents, part = subscene_specs(patches, config, divide, planes, boxes)
    return [s.build() for s in specs], boundaries, parents, part


def solve_divided(patches: Patches, config: SolverConfig | None = None, divide: DivideConfig | None = None,
                  executor: Executor | None = None, planes=None, boxes=None, record=True, **run_kwargs):
    """Divide, iterate with barriers until the tolerance, and write B back into ``patches``.

    Returns (DividedRun, subscenes, boundaries, partition).
    """
    config = config or SolverConfig()
    divide = divide or DivideConfig()
    subs, boundaries, parents, part = build_subscenes(patches, config, divide, planes, boxes)
    run = run_subscenes(patches, subs, boundaries, parents, config, divide, executor, record, **run_kwargs)
    return run, subs, boundaries, part


def run_subscenes(patches: Patches, subs: list[Subscene], boundaries: list[Boundary], parents: list[np.ndarray],
                  config: SolverConfig, divide: DivideConfig, executor: Executor | None = None, record=True,
                  **run_kwargs) -> DividedRun:
    """Iterate in-process subscenes (``build_subscenes``) with barriers until a stop criterion;
    write the assembled B and unshot back into ``patches``."""
    pieces = [s.patches for s in subs]

    def assemble_B():
        return assemble(len(patches), patches.area, parents, pieces)

    run = run_divided(subs, boundaries, config, divide.batches_per_barrier, executor,
                      assemble_B if record else None, **run_kwargs)
    patches.radiosity = assemble_B()
    patches.unshot = assemble(len(patches), patches.area, parents, pieces, [s.patches.unshot for s in subs])
    return run


# == moving subscenes between processes (no networking here: plain arrays) ==========

_BOUNDARY_COLUMNS = 12  # id, axis, offset, lo(2), hi(2), side_a, side_b, cells(2), solid


def boundaries_to_array(boundaries: list[Boundary]) -> np.ndarray:
    """(m, 12) float64 table of boundaries (integers are exact in float64)."""
    rows = [[b.id, b.axis, b.offset, *b.lo, *b.hi, b.side_a, b.side_b, *b.cells, b.solid] for b in boundaries]
    return np.array(rows, np.float64).reshape(-1, _BOUNDARY_COLUMNS)


def boundaries_from_array(table: np.ndarray) -> list[Boundary]:
    out = []
    for r in np.asarray(table, np.float64).reshape(-1, _BOUNDARY_COLUMNS):
        out.append(Boundary(id=int(r[0]), axis=int(r[1]), offset=float(r[2]), lo=(float(r[3]), float(r[4])),
                            hi=(float(r[5]), float(r[6])), side_a=int(r[7]), side_b=int(r[8]),
                            cells=(int(r[9]), int(r[10])), solid=int(r[11])))
    return out


def subscene_arrays(sub: Subscene) -> dict:
    """What a worker needs to rebuild a subscene: its patches and boundaries."""
    p = sub.patches
    return p.table_arrays() | {"radiosity": p.radiosity, "unshot": p.unshot,
                               "boundaries": boundaries_to_array(sub.boundaries)}


#: the buffers a subscene holds between barriers, saved in checkpoints as NAME_array
_HELD = ("sent", "pending", "forward")


def checkpoint_arrays(sub: Subscene) -> dict:
    """The state that changes while iterating, taken at a barrier (after deliver).

    With the RNG state included, a subscene restored from this continues exactly
    as the original would have.
    """
    led = sub.ledger
    held = {f"{name}_{k}": np.asarray(v) for name in _HELD for k, v in getattr(sub, name).to_arrays().items()}
    rng = json.dumps(sub.rng.bit_generator.state).encode()
    return {
        "radiosity": sub.patches.radiosity, "unshot": sub.patches.unshot,
        "ledger": led.to_array(),
        "return_tallies": sub.tallies,
        "stats": np.array([sub.stats.shots, sub.stats.rays, sub.stats.batches, sub.twins_delivered,
                           sub.twin_blocks], np.int64),
        "trace_seconds": np.array([sub.stats.trace_seconds]),
        "back_by_obj": sub.back_by_obj,
        "rng_state": np.frombuffer(rng, np.uint8),
        # the error estimate's half-solution difference: it also splits each shot's power
        "noise_diff": sub.noise.diff, "noise_unshot": sub.noise.unshot,
        "noise_sums": np.array([sub.noise._sums.d2, sub.noise._sums.b2, sub.noise._sums.r2]),
        **held,
    }


def build_subscene(cell: int, config: SolverConfig, power_per_ray: float, mode: str, names: list[str],
                   arrays: dict, local_target: float = 0.0) -> Subscene:
    """Rebuild a subscene from ``subscene_arrays`` (plus ``checkpoint_arrays`` to resume)."""
    p = Patches.from_table(arrays, names, radiosity=arrays["radiosity"].copy(), unshot=arrays["unshot"].copy())
    sub = Subscene(cell, p, boundaries_from_array(arrays["boundaries"]), config, power_per_ray, mode, local_target)
    if "ledger" in arrays:  # resume from a checkpoint
        sub.ledger = Ledger.from_array(arrays["ledger"])
        if "return_tallies" in arrays:
            sub.tallies = np.array(arrays["return_tallies"], np.float64).reshape(4, 3)
        stats = [int(x) for x in arrays["stats"]] + [0, 0]
        sub.stats.shots, sub.stats.rays, sub.stats.batches, sub.twins_delivered, sub.twin_blocks = stats[:5]
        sub.stats.trace_seconds = float(arrays["trace_seconds"][0])
        sub.back_by_obj = np.array(arrays["back_by_obj"], np.float64)
        sub.rng.bit_generator.state = json.loads(bytes(arrays["rng_state"]).decode())
        if "noise_diff" in arrays:
            sub.noise.diff = np.array(arrays["noise_diff"], np.float64)
            sub.noise.unshot = np.array(arrays["noise_unshot"], np.float64)
            sub.noise._sums.d2, sub.noise._sums.b2, sub.noise._sums.r2 = (float(x) for x in arrays["noise_sums"])
        kinds = {"sent": sub.boundary_mode.buffer, "pending": TwinBuffer, "forward": RayParcel}
        for name in _HELD:
            part = {k[len(name) + 1:]: v for k, v in arrays.items() if k.startswith(name + "_")}
            if part:
                setattr(sub, name, kinds[name].from_arrays(part))
        sub._book_in_flight()
    return sub
