"""Divide and conquer: subscenes that iterate alone and trade light at barriers.

The paper's main loop (van Liere, section 1.3.2)::

    subDivideScene()                     # partition.partition + partition.clip
    while notConverged:
        foreach subScene: doIterations(n, subScene)   # Subscene.iterate, in parallel
        foreach boundary: transferEnergy(boundary)    # boundary.transfer
        displayScene()                                # on_barrier callback

``Subscene`` (subscene.py) is a Solver whose Embree scene also holds its boundary rectangles:
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

import math
import time
from collections.abc import Sequence
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field

import numpy as np

from dcrad.config import DivideConfig, SolverConfig
from dcrad.division.boundary import (
    Boundary,
    boundary_mode,
    make_boundary,
)
from dcrad.division.outside import OutsideLight, gather_outside, split_outside
from dcrad.division.partition import clip, partition
from dcrad.division.placement import check_subscenes
from dcrad.division.subscene import (
    BARRIER_GOAL,
    BarrierPlan,
    Subscene,
    SubsceneHandle,
    SubsceneState,
    gathered_rays,
)
from dcrad.errors import ConfigError
from dcrad.estimate.noise import Estimate, NoiseSums, NoiseTally, bias_ambient, combine, finite
from dcrad.meshing.patches import Patches
from dcrad.solving.accuracy import by_accuracy, noise_floor, residual_goal, resolve
from dcrad.solving.energy import Ledger
from dcrad.solving.snapshots import SnapshotStore
from dcrad.solving.solver import Snapshot
from dcrad.solving.stiffness import Stiffness, stiffness
from dcrad.transport.emitters import sources_power

__all__ = [
    "run_divided", "assemble", "DividedRun", "SequentialExecutor", "DivideConfig", "build_subscenes",
    "subscene_specs", "SubsceneSpec", "solve_divided", "run_subscenes"
]


class SequentialExecutor(Executor):
    """Runs submitted work at once in the caller's thread (deterministic, for tests)."""

    def submit(self, fn, *args, **kwargs):
        fut: Future = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # handed back through the future
            fut.set_exception(exc)
        return fut


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
    # rounded up: the shares hold inside a barrier (Subscene.batch_limit), and rounded down they left a
    # few rays of the budget to a barrier of its own
    return {s.cell: max(math.ceil(rays_left * w), 1) for s, w in zip(states, weight)}


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


#: what the automatic cut balances (partition's ``work``): "light", a patch share plus twice the
#: emitted share (partition.LIGHT_WEIGHT).  By area, the 20x20 office's 16 cells held 7 to 16 lit
#: rooms and the slowest cell's iterates took 1.24-1.39x the mean (their CPU s follow their lamps'
#: W, correlation 0.99); by light 12 or 13, and 1.10-1.12x (bench/RESULTS.md).  Not by lamps
#: alone (W emitted + WORK_PER_PATCH_W a patch, tried): where one room
#: holds all the lamps (the 1x2 office of tests/test_divide.py) that cut the lit room in half
#: rather than follow the wall; the patch share keeps the wall (score 0.83 against 1.0 across)
CUT_WORK = "light"


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
        own = sources_power(p.sources)  # its light sources, not shot yet: held as unshot
        led = Ledger(emitted=p.emitted_power + own)
        led.unshot = p.unshot_power + own
        led.unshot_abs = (np.abs(p.unshot) * p.area[:, None]).sum(axis=0) + np.abs(own)
        return SubsceneState(self.cell, led, 0, gathered_rays(p.sources), 0, 0, p.total_area,
                             back_by_obj=np.zeros(max(len(p.names), 1)),
                             noise=NoiseTally(p).sums())


def subscene_specs(patches: Patches, config: SolverConfig, divide: DivideConfig, planes=None, boxes=None,
                   outside: OutsideLight | None = None):
    """subDivideScene as arrays: partition, clip, make boundaries and one SubsceneSpec per cell.

    No Solver and no Embree scene is built (the coordinator, which traces nothing,
    sends these to workers), except for light from outside the model (the sky, the sun): it is
    gathered on the whole scene first (outside.py; ``outside``: gathered already by the caller)
    and each cell is handed what landed on it.  Returns (specs, boundaries, parents, partition).
    """
    if planes is None and boxes is None:
        check_subscenes(divide.subscenes, len(patches))
    config = resolve(config, patches.read_units)  # the job's ray density: from its patch count
    if outside is None:
        outside = gather_outside(patches, config)
    _, others = split_outside(patches.sources)
    # balanced by light (CUT_WORK): a subscene's iterates cost in proportion to its lamps, and
    # cells of equal area differ in lamps.  Binned twins keep the area cut: by light, the cut
    # moves toward the lamps, and binned twins blur the light that crosses open space there
    # (furnace box, k=2: a vertical plane under the light, RMS error 1.54x the unsplit noise
    # against below 1.5x with the area's horizontal one); exact boundaries forward it unchanged
    work = CUT_WORK if divide.mode == "exact" else "area"
    part = partition(patches, divide.subscenes, planes=planes, boxes=boxes,
                     **({"work": work} if planes is None and boxes is None else {}))
    pieces = clip(patches, part)
    owners = source_cells(others, part)
    for i, (cell, (sub, parent)) in enumerate(zip(part.cells, pieces)):
        lit = outside.for_cell(sub, parent, first=i == 0) if outside is not None else None
        # the outside's light first: it is laid down before the cell's own sources are shot
        sub.sources = ((lit,) if lit is not None else ()) + tuple(
            src for src, owner in zip(others, owners) if owner == cell.id)
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
    # the sources' power too (the outside's: what its gather spent, not its flux into the scene's box)
    emitted = float(patches.emitted_power.sum() + sum(sources_power(sub.sources).sum() for sub, _ in pieces))
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


def source_cells(sources, part) -> np.ndarray:
    """(s,) the cell each light source that is not a patch belongs to: the cell holding its position
    (its light leaves through the cell's boundaries like any other), or the nearest cell for one
    just outside every cell (a schedule may place a luminaire a little outside the patches' box)."""
    if not sources:
        return np.zeros(0, np.int64)
    pos = np.array([s.position for s in sources], np.float64)
    owner = part.locate(pos)
    for i in np.flatnonzero(owner < 0):
        gap = [float(np.linalg.norm(np.maximum(np.maximum(np.subtract(c.lo, pos[i]), np.subtract(pos[i], c.hi)), 0.0)))
               for c in part.cells]
        owner[i] = part.cells[int(np.argmin(gap))].id
    return owner


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
