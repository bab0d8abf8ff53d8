"""A subscene: a Solver whose scene also holds its boundary rectangles, and how it moves.

``Subscene`` shoots like any Solver; a ray that hits one of its boundaries is recorded in that
portal cell's bin for its direction (``sent``) and goes no further, and at each barrier it shoots
the outgoing twins delivered to it like patches, competing by power.  ``SubsceneHandle`` is what
the barrier loop (divide.py) drives, here or on a worker; ``BarrierPlan`` is what it hands each
subscene for one barrier.  ``subscene_arrays``, ``checkpoint_arrays`` and ``build_subscene`` move
a subscene between processes as plain arrays (no networking here).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from dcrad.arrays import colsum, take_rows
from dcrad.config import SolverConfig
from dcrad.division.boundary import (
    Boundary,
    RayParcel,
    TwinBuffer,
    boundary_mode,
    coarsen_directions,
    direction_levels,
)
from dcrad.estimate.noise import NoiseSums
from dcrad.meshing.patches import Patches
from dcrad.solving.energy import Ledger
from dcrad.solving.solver import Solver
from dcrad.solving.stiffness import Stiffness
from dcrad.transport.emitters import sources_power
from dcrad.transport.rays import Tracer
from dcrad.transport.shoot import RayBatch, patch_rays, per_ray_power, ray_lattice, ray_offset
from dcrad.transport.shooters import spatial_order
from dcrad.transport.source_wire import sources_from_table, sources_table

__all__ = [
    "BARRIER_GOAL", "BarrierPlan", "FORWARD_CAP", "Subscene", "SubsceneHandle", "SubsceneState",
    "boundaries_from_array", "boundaries_to_array", "build_subscene", "checkpoint_arrays", "subscene_arrays"
]


#: an adaptive barrier ends once a subscene's residual has fallen to this share of what it held
#: at the barrier's start (``Subscene.iterate``), unless ``landing_goal`` says otherwise
BARRIER_GOAL = 0.25
#: the share of a barrier's --max-rays share a subscene's light sources may take at its first iterate
SOURCE_BUDGET_SHARE = 0.5


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

#: exact mode: a subscene's barrier comes once this many batches' worth of rays crossed its boundaries
FORWARD_CAP = 4


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
        # glass: a ray meets a pane and goes on with tau(theta) of its power (shoot.through_panes), to a
        # surface or a boundary, which forwards what is left of it (the boundaries' primitives follow the
        # patches': Glazing.panes takes them as opaque)
        self.tracer.glazing = patches.glazing
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
        #: rays left of this barrier's share of the job's ray budget (None: no budget; ``iterate``)
        self._share_left: int | None = None

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

    def batch_limit(self) -> int:
        """The batch's rays, within what this barrier's share of the job's ray budget leaves (a
        barrier's check after each batch let a lamp room's two subscenes trace 142,504 rays for
        --max-rays 100,000: a batch each past their shares)."""
        limit = super().batch_limit()
        return min(limit, max(self._share_left, 1)) if self._share_left is not None else limit

    def rank(self, power: np.ndarray, min_rays=None, max_shooters=None, ray_factor: float = 1.0):
        """``Solver.rank``, its one shot at least cut to what the barrier's share leaves (its rays carry
        more power each: the share holds, unbiased, noisier)."""
        idx, counts = super().rank(power, min_rays, max_shooters, ray_factor)
        if self._share_left is not None and len(counts) and counts.sum() > self._share_left:
            counts = counts.copy()
            counts[0] = max(min(int(counts[0]), self._share_left), 1)
        return idx, counts

    def step_forwarded(self) -> int:
        """Exact mode: continue up to a batch's rays handed over by neighbours."""
        part = self.forward.take_front(self.batch_limit())
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
        batch = tally.ends if tally.ends is not None else batch  # through glass: the powers that end
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
        while self.direct.sources_left and getattr(self.direct.sources_left[0], "gathered", False):
            # the sky's and the sun's light, gathered on the whole scene (outside.py): laid down first
            rays += self.direct.deposit(self.direct.sources_left.pop(0))
        if self.direct.sources_left and not self.interrupted:
            # its light sources that are not patches, shot once, first (a subscene shoots its direct
            # light: the exact gather reads only this cell's patches, and its light crosses boundaries);
            # under --max-rays at most SOURCE_BUDGET_SHARE of this barrier's share, coarser if need be
            # (all their power is still shot): at the run's density the 2x3 office's 12 luminaires
            # took 2.5M rays of a 1M budget in one go
            counts = [self.direct.source_rays(s) for s in self.direct.sources_left]
            allowed = SOURCE_BUDGET_SHARE * plan.rays_left if plan is not None and plan.rays_left else math.inf
            f = min(1.0, allowed / max(sum(counts), 1))
            for count in counts:
                rays += self.direct.shoot_source(self.direct.sources_left.pop(0), max(int(count * f), 2))
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
            self._share_left = plan.rays_left - rays if plan is not None and plan.rays_left else None
            r = self.step()
            if r == 0:
                break
            rays += r
        self._share_left = None
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
        led = self.ledger.copy()
        waiting = sources_power(self.direct.sources_left)  # booked as emitted, not shot yet: held as unshot
        led.unshot, led.unshot_abs = led.unshot + waiting, led.unshot_abs + np.abs(waiting)
        rays = self.stats.rays + gathered_rays(self.direct.sources_left)
        return SubsceneState(self.cell, led, self.stats.shots, rays,
                             sum(len(h) for h in held), sum(h.nbytes() for h in held),
                             self.patches.total_area, self.tallies.copy(),
                             self.twins_delivered, self.twin_blocks, self.stats.batches,
                             self.stats.trace_seconds, self.back_by_obj.copy(), self.noise.sums())

    def radiosity(self) -> np.ndarray:
        return self.patches.radiosity

    def interrupt(self) -> None:
        self.interrupted = True

def gathered_rays(sources) -> int:
    """Rays the light gathered before the cut (emitters.Gathered, not laid down yet) took: traced
    already, so counted from the start (a --max-rays budget's first barrier shares out the rest)."""
    return sum(int(s.rays) for s in sources if getattr(s, "gathered", False))

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
    """What a worker needs to rebuild a subscene: its patches, their light sources that are not
    patches (source_wire.py) and its boundaries."""
    p = sub.patches
    return p.table_arrays() | sources_table(p.sources) | {"radiosity": p.radiosity, "unshot": p.unshot,
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
        # its light sources still to shoot (the last ones of its list: they are shot in order)
        "sources_left": np.array([len(sub.direct.sources_left)], np.int64),
        **held,
    }


def build_subscene(cell: int, config: SolverConfig, power_per_ray: float, mode: str, names: list[str],
                   arrays: dict, local_target: float = 0.0) -> Subscene:
    """Rebuild a subscene from ``subscene_arrays`` (plus ``checkpoint_arrays`` to resume)."""
    p = Patches.from_table(arrays, names, radiosity=arrays["radiosity"].copy(), unshot=arrays["unshot"].copy())
    p.sources = sources_from_table(arrays)
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
        left = int(np.asarray(arrays.get("sources_left", [0])).ravel()[0])
        sub.direct.sources_left = list(p.sources[len(p.sources) - left:]) if left else []
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
