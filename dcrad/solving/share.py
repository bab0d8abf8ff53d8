"""Shared runs: k workers share one solve of the whole scene, split by receivers and by rays.

Where a run gathers its light (accuracy mode with exact form factors: the
``accuracy.FinalPlan`` of direct gather, coarse shooting and final gather), most
of its work is per receiver, and the final plan is a single-subscene plan: it
reads the whole scene's light.  Dividing space would throw it away (the 8x8
office at 2%: 307M rays on two workers against 48.7M in one process,
bench/RESULTS.md).  A shared run keeps it and divides the work instead:

1. **direct**: the receivers are split into runs along a Morton curve
   (``work_shares``: DIRECT_SHARES_PER_WORKER a worker, in sizes that halve from each
   round of k runs to the next, taken by the workers big ones first as they come
   free); each share gathers the exact direct light of its run
   (``DirectPhase.pilot``: the cost is per receiver-light pair, not per ray, so
   splitting receivers is what divides it), its pilot first; the shadow rays left
   after the pilots go to every share's penumbrae at one rate (``direct.shared_rate``),
   as in one gather of every receiver.  The tallies are merged
   (``direct.merge``): the direct light of every receiver, gathered once.
2. **shoot**: every worker runs an independent replica ``Solver`` over the whole
   scene from that direct light (``run_replica``), with its own random streams:
   its own emitter rays book where the power goes, and it shoots the reflected
   light at 1/k of the final plan's density, up to where the final gather would
   start.  The replicas are averaged (``blend``): B, dB, the half-solution
   differences, the ledger and the return tallies are linear in the rays'
   outcomes, so the books close and the average's noise is the replicas' over k
   in the mean square, less the direct light's, which all share
   (``shared_noise``, ``Solver.target_error``).
3. **gather**: the final gather of the average, split by receivers as in 1 but one share a
   worker (``SHARES_PER_WORKER``: its cost is even per receiver): each share traces the full
   number of gather rays for its receivers (``gather_share``; splitting the rays instead, k
   gathers of 1/k of them each, lost the stratification's gain: on the office 3x3, 62 rays a
   patch gave 2.40% where 124 gave 1.57%), and the shared run combines the sums
   (``final.FinalGather.solution``), topping the gather up while the estimate is
   above the target as a single run does (``rounds.gather_rounds``).

Every share is a pure function of the scene, the settings, its index and its
inputs: a share lost with its worker is run again elsewhere with the same
result.  The same functions run in process (``LocalShares``) and on workers
(coordinator.shared), bit-identically.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dcrad.choices import Choice, Choices
from dcrad.config import SolverConfig
from dcrad.estimate.noise import Estimate, NoiseTally, bias_ambient, finite
from dcrad.meshing.patches import Patches
from dcrad.outputs.report import RunBooks
from dcrad.solving.accuracy import final_plan, resolve
from dcrad.solving.direct_phase import GATHER_STOPPED
from dcrad.solving.energy import ACCOUNTS, MAGNITUDES, Ledger
from dcrad.solving.rounds import budget_cut_note, fit_round, gather_rounds
from dcrad.solving.solver import ReplicaRole, Snapshot, Solver, Stats
from dcrad.solving.stiffness import Stiffness
from dcrad.transport.direct import AnalyticGather, DirectTally, GatherStopped, merge, shared_rate
from dcrad.transport.final import FinalGather
from dcrad.transport.rays import Tracer
from dcrad.transport.shooters import spatial_order

__all__ = ["receiver_shares", "replica_config", "direct_share", "direct_pilot", "run_replica",
           "Replica", "blend", "Shot", "gather_share", "SharedRun", "run_shared", "LocalShares", "shared_books",
           "tally_to_arrays", "tally_from_arrays", "shared_noise", "work_shares", "SHARES_PER_WORKER",
           "DIRECT_SHARES_PER_WORKER",
           "REPLICA_SEED"]

#: replica i seeds its random streams this much after replica i - 1 (passes.PASS_SEED's role)
REPLICA_SEED = 104729
#: the direct shares' random streams: (seed, DIRECT_STREAM, share index); the gather's: (seed,
#: GATHER_STREAM, round, share index)
DIRECT_STREAM, GATHER_STREAM = 7, 11


def _morton_runs(patches: Patches, weight: np.ndarray) -> list[np.ndarray]:
    """The receivers (patches with a reflectance) in runs along a Morton curve, sized in proportion
    to ``weight`` (sorted rows each): neighbouring receivers share a run, so a run's penumbra pilot
    sees its neighbours' probes."""
    rec = np.flatnonzero(patches.rho.any(axis=1))
    order = rec[spatial_order(patches, rec)]
    cuts = np.round(np.cumsum(weight)[:-1] / weight.sum() * len(order)).astype(np.int64)
    return [np.sort(part) for part in np.split(order, cuts)]


def receiver_shares(patches: Patches, k: int) -> list[np.ndarray]:
    """The receivers in k Morton runs of equal count (``_morton_runs``)."""
    return _morton_runs(patches, np.ones(k))


#: a shared run over k > 1 workers splits its receivers into this many direct shares per worker,
#: in sizes that halve from one round of k shares to the next (``work_shares``): the workers take
#: them big ones first as they come free (coordinator/shared.py).  The direct light's cost per
#: receiver varies with the lamps it sees and its penumbrae: on the office 8x8 the two Morton
#: halves' pilot and gather took 4.77 and 3.25 CPU s.  Replaying measured share costs through
#: the queue (2 workers; pilot then direct): 1 a worker 4.80 s, 2 4.18 s, 4 4.24 s, 8 4.51 s (a
#: share's set-up is small, 8.05-8.69 CPU s in all) (bench/RESULTS.md, fifth session).
DIRECT_SHARES_PER_WORKER = 2
#: the final gather's cost is per receiver and even (8x8 office: two halves 5.85 / 5.85 CPU s,
#: 8 shares 1.53-1.59 s), and each gather share pays a FinalGather's set-up (12.5 CPU s for 8
#: shares, 13.7 s for 32, against 11.7 s for 2): one a worker.
SHARES_PER_WORKER = 1


def work_shares(patches: Patches, k: int, per_worker: int | None = None) -> list[np.ndarray]:
    """The receivers of a shared run over k workers in ``per_worker`` (default
    ``SHARES_PER_WORKER``) x k Morton runs (sorted rows each; one run when k is 1): round r of k
    runs takes 2^-r as many receivers as the first."""
    if k <= 1:
        return [np.flatnonzero(patches.rho.any(axis=1))]
    per = SHARES_PER_WORKER if per_worker is None else per_worker
    return _morton_runs(patches, np.repeat(0.5 ** np.arange(per), k))


def replica_config(config: SolverConfig, k: int, index: int, patches: int) -> SolverConfig:
    """Replica ``index`` of k over ``patches`` patches: the job's target, 1/k of its ray density
    and of its ray budget, k x its shooters a batch, its own seed."""
    cfg = resolve(config, patches)
    if k <= 1:
        return cfg
    # k x the shooters a batch: a replica's shots carry 1/k of the rays, so its batches keep the
    # job's rays a batch (office 8x8: 157 batches of 36k rays each at the job's cap)
    return cfg.replace(rays_per_power=cfg.rays_per_power / k, seed=cfg.seed + REPLICA_SEED * (index + 1),
                       max_rays=int(math.ceil(cfg.max_rays / k)) if cfg.max_rays else 0,
                       max_shooters=cfg.max_shooters * k)


def shared_noise(patches: Patches, direct: DirectTally) -> float:
    """W^2/m^4: the noise mean square of the direct light ``direct`` (noise.combine's d2 / area / 4
    over its half difference D = rho 2 (2 P_A - P) / A), which every replica shares (each rescales
    it to its own emitter rays' landed power, by about 1)."""
    hit = direct.hit
    d = patches.rho[hit] * (2.0 * (2.0 * direct.received_a - direct.received)) / patches.area[hit, None]
    return float((patches.area[hit] * (d * d).mean(axis=1)).sum()) / max(float(patches.total_area), 1e-300) / 4.0


def direct_pilot(patches: Patches, config: SolverConfig, tracer: Tracer, rows: np.ndarray,
                 index: int, should_stop=None) -> AnalyticGather | None:
    """Share ``index``'s exact direct gather over ``rows``, after its pilot (its ``need`` and
    ``weight`` set the shared rate, ``direct.shared_rate``); None: the lights make no exact
    polygons, or there is no final plan (``DirectPhase.pilot``).  Its random stream is
    (seed, DIRECT_STREAM, index), so a share piloted again gathers the same light.  ``should_stop()``
    True between two runs of cells raises direct.GatherStopped (a worker's share of a cancelled job)."""
    solver = Solver(patches, config, tracer=tracer)
    rng = np.random.default_rng([solver.config.seed, DIRECT_STREAM, index])
    return solver.direct.pilot(np.asarray(rows, np.int64), rng, should_stop)


def direct_share(patches: Patches, config: SolverConfig, tracer: Tracer, rows: np.ndarray, index: int,
                 rate: float, held: AnalyticGather | None = None, should_stop=None) -> DirectTally | None:
    """Share ``index``'s exact direct gather over ``rows`` at the shared ``rate``; ``held``: its pilot
    (None: piloted here first).  ``should_stop``: as ``direct_pilot``."""
    pilot = held if held is not None else direct_pilot(patches, config, tracer, rows, index, should_stop)
    return None if pilot is None else pilot.finish(rate, should_stop)


@dataclass
class Replica:
    """What one replica's shooting leaves: its state arrays, books and stats (averaged by ``blend``)."""

    radiosity: np.ndarray
    unshot: np.ndarray
    diff: np.ndarray  #: half-solution difference D (noise.py)
    diff_unshot: np.ndarray
    direct: np.ndarray  #: (n,3) W of direct light each patch got (``DirectPhase.light``)
    direct_a: np.ndarray  #: half A's part of it
    tallies: np.ndarray  #: (4,3) return tallies
    ledger: Ledger
    back_by_obj: np.ndarray
    shots: int
    rays: int
    batches: int
    trace_seconds: float
    wall_seconds: float
    stopped_by: str
    final_rays: int = 0  #: the final plan's gather rays per receiver (0: no final gather pending)
    choices: Choices = field(default_factory=Choices)
    stiff: Stiffness | None = None
    estimate: dict = field(default_factory=dict)  #: its own estimate (noise.Estimate.as_dict)

    _STATE = ("radiosity", "unshot", "diff", "diff_unshot", "direct", "direct_a")

    def to_arrays(self) -> dict:
        meta = {"shots": self.shots, "rays": self.rays, "batches": self.batches,
                "trace_seconds": self.trace_seconds, "wall_seconds": self.wall_seconds,
                "stopped_by": self.stopped_by, "final_rays": self.final_rays, "choices": self.choices.as_json(),
                "estimate": self.estimate,
                "stiff": None if self.stiff is None else {"scale": [float(x) for x in self.stiff.scale],
                                                          "ray_factor": self.stiff.ray_factor,
                                                          "ret": self.stiff.ret}}
        return {name: getattr(self, name) for name in self._STATE} | {
            "tallies": self.tallies, "ledger": self.ledger.to_array(),
            "back_by_obj": self.back_by_obj, "meta": np.frombuffer(json.dumps(meta).encode(), np.uint8)}

    @classmethod
    def from_arrays(cls, arrays: dict, n: int) -> "Replica":
        """The inverse of ``to_arrays``; ValueError when a state array is not (n, 3)."""
        for name in cls._STATE:
            if np.shape(arrays[name]) != (n, 3):
                raise ValueError(f"replica array {name} has shape {np.shape(arrays[name])}, not ({n}, 3)")
        meta = json.loads(bytes(np.asarray(arrays["meta"], np.uint8)).decode())
        led = Ledger.from_array(arrays["ledger"])
        st = meta.get("stiff")
        stiff = None if st is None else Stiffness(np.array(st["scale"], np.float64), st["ray_factor"], st["ret"])
        state = {name: np.asarray(arrays[name], np.float64) for name in cls._STATE}
        return cls(**state, tallies=np.asarray(arrays["tallies"], np.float64).reshape(4, 3), ledger=led,
                   back_by_obj=np.asarray(arrays["back_by_obj"], np.float64), shots=int(meta["shots"]),
                   rays=int(meta["rays"]), batches=int(meta["batches"]), trace_seconds=float(meta["trace_seconds"]),
                   wall_seconds=float(meta["wall_seconds"]), stopped_by=str(meta["stopped_by"]),
                   final_rays=int(meta["final_rays"]), choices=Choices.from_json(meta["choices"]), stiff=stiff,
                   estimate=dict(meta["estimate"]))


def run_replica(patches: Patches, config: SolverConfig, tracer: Tracer, direct: DirectTally, index: int, k: int,
                should_stop=None) -> Replica:
    """Replica ``index`` of k from the merged direct light, up to where the final gather would start
    (module doc, step 2).  ``patches`` is reset first (its B and dB are the replica's afterwards)."""
    patches.reset()
    solver = Solver(patches, replica_config(config, k, index, patches.read_units), tracer=tracer)
    job_plan = final_plan(resolve(config, patches.read_units), len(patches))
    solver.role = ReplicaRole(preset_direct=direct, replicas=k, shared_noise=shared_noise(patches, direct),
                              shoot_share=1.0 / max(k, 1), defer_final=True,
                              planned_final_rays=job_plan.final_rays if job_plan is not None else 0)
    solver.run(should_stop=should_stop)
    st, est = solver.stats, solver.estimate()
    n = len(patches)
    full, half_a = solver.direct.light if solver.direct.light is not None else (np.zeros((n, 3)), np.zeros((n, 3)))
    return Replica(patches.radiosity.copy(), patches.unshot.copy(), solver.noise.diff.copy(),
                   solver.noise.unshot.copy(), full, half_a, solver.tallies.copy(), solver.ledger.copy(),
                   solver.back_by_obj.copy(), st.shots, st.rays, st.batches, st.trace_seconds, st.wall_seconds,
                   st.stopped_by, solver.final.rays if solver.final.pending() else 0, Choices(solver.choices),
                   solver.stiff, {k: (v if not isinstance(v, float) or math.isfinite(v) else None)
                                  for k, v in est.as_dict().items()})


@dataclass
class Shot:
    """The replicas' average: what the final gather reads (B, D, the direct light) and the books."""

    radiosity: np.ndarray
    diff: np.ndarray
    direct: np.ndarray
    direct_a: np.ndarray
    ledger: Ledger
    tallies: np.ndarray

    def to_arrays(self) -> dict:
        """What a gather share reads (the books stay with the shared run)."""
        return {"radiosity": self.radiosity, "diff": self.diff, "direct": self.direct, "direct_a": self.direct_a}

    @staticmethod
    def from_arrays(arrays: dict, n: int) -> "Shot":
        """``to_arrays``' inverse (a gather share's input; no books); ValueError for a wrong shape."""
        got = {}
        for name in ("radiosity", "diff", "direct", "direct_a"):
            a = np.asarray(arrays[name], np.float64)
            if a.shape != (n, 3):
                raise ValueError(f"shot array {name} has shape {a.shape}, not ({n}, 3)")
            got[name] = a
        return Shot(**got, ledger=Ledger(), tallies=np.zeros((4, 3)))


def blend(patches: Patches, replicas: list[Replica]) -> tuple[Shot, NoiseTally]:
    """Average the replicas into ``patches`` (B, dB); return the average and its noise tally.

    Equal weights: the replicas are alike (same density, independent streams), and fixed
    weights keep the average unbiased (inverse-variance weights read from the same noise
    would not be, quite)."""
    w = 1.0 / len(replicas)

    def mean(name):
        return sum(getattr(r, name) for r in replicas) * w

    patches.radiosity, patches.unshot = mean("radiosity"), mean("unshot")
    # the job's table as meshed: in this process the replicas ran on it and settled its clusters, on
    # a worker each on its own copy (the service's blend reads the mesh's)
    patches.restore_clusters()
    ledger = Ledger(**{a: sum(getattr(r.ledger, a) for r in replicas) * w for a in ACCOUNTS + MAGNITUDES})
    noise = NoiseTally(patches)
    noise.diff, noise.unshot = mean("diff"), mean("diff_unshot")
    noise.resync(patches)
    return Shot(patches.radiosity.copy(), noise.diff.copy(), mean("direct"), mean("direct_a"), ledger,
                mean("tallies")), noise


def estimate_of(patches: Patches, noise: NoiseTally, shot: Shot) -> Estimate:
    """The shared run's estimate as the target holds it, with B per input triangle and per element
    beside it (``NoiseTally.estimate``, as ``Solver.estimate``)."""
    return noise.estimate(bias_ambient(shot.tallies, shot.ledger.held(), patches.total_area, patches.mean_rho))


def gather_share(patches: Patches, config: SolverConfig, tracer: Tracer, shot: Shot, rows: np.ndarray, index: int,
                 rounds: list[int], held: FinalGather | None = None, should_stop=None) -> tuple[FinalGather, int]:
    """Share ``index``'s final gather over ``rows`` reading ``shot``: ``rounds`` rays per receiver in
    each round so far (round r draws from its own stream: seed, GATHER_STREAM, r, index).  ``held``:
    this share's gather of the rounds before (a worker keeps it), continued when it matches, else
    the rounds are traced again.  Returns (the gather, rays traced now); its sums are the share's.
    ``should_stop()`` True between two batches raises direct.GatherStopped: a share cut short has
    no sums a shared run could use (a worker's share of a cancelled job)."""
    if held is not None and held.per_half * 2 == sum(rounds[:-1]) and np.array_equal(held.rec, rows):
        fg, todo = held, [len(rounds) - 1]
    else:
        patches.radiosity = shot.radiosity
        fg = FinalGather(patches, tracer, shot.diff, shot.direct, shot.direct_a, config.batch_rays, rows=rows)
        todo = list(range(len(rounds)))
    seed = resolve(config).seed
    traced = 0
    for r in todo:
        traced += fg.add(rounds[r], np.random.default_rng([seed, GATHER_STREAM, r, index]), should_stop)
        if fg.stopped:
            raise GatherStopped
    return fg, traced


@dataclass
class SharedRun:
    """A finished shared run: the result is in the patch table; these are its books."""

    k: int
    ledger: Ledger
    tallies: np.ndarray
    estimate: Estimate
    stats: Stats
    replicas: list[Replica]
    direct_rays: int
    gather_rays: int
    rounds: list[int]
    seconds: dict
    snapshots: list[Snapshot]
    snapshot_B: list[np.ndarray]
    choices: Choices


class LocalShares:
    """The shares run one after another in this process (tests, and the reference the workers
    must match bit for bit)."""

    def __init__(self, patches: Patches, config: SolverConfig, tracer: Tracer | None = None):
        self.patches, self.config = patches, config
        self.tracer = tracer if tracer is not None else Tracer.mesh(patches)
        self.held: dict[int, FinalGather] = {}  #: each share's final gather so far

    def direct(self, shares: list[np.ndarray], should_stop=None) -> list[DirectTally | None]:
        """Each share's exact direct gather (None each: no exact-form-factor lights); ``should_stop()``
        True between two runs of cells raises direct.GatherStopped."""
        pilots = [direct_pilot(self.patches, self.config, self.tracer, rows, i, should_stop)
                  for i, rows in enumerate(shares)]
        if any(g is None for g in pilots):
            return [None] * len(shares)
        rate = shared_rate([(g.need, g.weight) for g in pilots if g is not None])
        return [g.finish(rate, should_stop) if g is not None else None for g in pilots]

    def replicas(self, direct: DirectTally, k: int, should_stop=None, time_left: float = 0.0) -> list[Replica]:
        """The k replicas (one after another here); ``time_left`` s (0: no limit) for each."""
        cfg = self.config.replace(time_limit=time_left) if time_left else self.config
        return [run_replica(self.patches, cfg, self.tracer, direct, i, k, should_stop) for i in range(k)]

    def gather(self, shot: Shot, shares: list[np.ndarray], rounds: list[int], should_stop=None):
        """[(sum_a, sum_b, rays traced)] of each share; a stop (``should_stop``) raises
        direct.GatherStopped (the round is lost: a share cut short has no usable sums)."""
        out = []
        for i, rows in enumerate(shares):
            fg, traced = gather_share(self.patches, self.config, self.tracer, shot, rows, i, rounds,
                                      self.held.get(i), should_stop)
            self.held[i] = fg
            out.append((fg.sum_a, fg.sum_b, traced))
        self.patches.radiosity = shot.radiosity
        return out


def empty_tally(patches: Patches) -> DirectTally:
    """A direct gather that gathered nothing (a scene with no emitting patch)."""
    z3, none = np.zeros(3), np.zeros(0, np.int64)
    return DirectTally(np.zeros((0, 3)), none, z3, z3.copy(), np.zeros(max(len(patches.names), 1)), none.copy(),
                       none.copy(), np.zeros(0), z3.copy(), z3.copy(), z3.copy(), np.zeros((0, 3)), 0)


def merged_direct(tallies: list[DirectTally], patches: Patches) -> DirectTally:
    """One tally of the shares' gathers over disjoint receivers."""
    out = tallies[0]
    for t in tallies[1:]:
        out = merge(out, t, patches)
    return out


def run_shared(patches: Patches, config: SolverConfig, k: int, shares, on_phase=None,
               should_stop=None) -> SharedRun | None:
    """A shared run over k shares (module doc); ``shares``: a ``LocalShares`` or anything with its
    ``direct``, ``replicas`` and ``gather`` methods (the coordinator's, on workers).  Returns None
    when the lights make no exact form factors (the caller solves another way).  ``on_phase(name,
    elapsed s, rays so far, estimate or None)`` after each phase.  The result is left in ``patches``."""
    cfg = resolve(config, patches.read_units)
    t0 = time.perf_counter()
    emission = patches.emission.copy()
    parts = work_shares(patches, k)  # the final gather's
    try:
        if should_stop is not None and should_stop():  # asked before it began (while it loaded)
            raise GatherStopped
        if patches.sources and not patches.emission.any():
            # lit by light sources alone: no patch emits, so there is no patch light to gather; each
            # replica gathers the sources' light exactly (DirectPhase.shoot_sources)
            tallies = [empty_tally(patches)]
        else:
            tallies = shares.direct(work_shares(patches, k, DIRECT_SHARES_PER_WORKER), should_stop)
    except GatherStopped:  # as a run in one process stopped in its gather: B = E, nothing booked
        return stopped_in_direct(patches, cfg, k, time.perf_counter() - t0)
    if any(t is None for t in tallies):
        return None
    direct = merged_direct(tallies, patches)
    seconds = {"direct_s": time.perf_counter() - t0}
    direct_rays = int(direct.rays)
    b_direct = emission.copy()
    b_direct[direct.hit] += patches.rho[direct.hit] * direct.received / patches.area[direct.hit, None]
    if on_phase is not None:
        on_phase("direct", seconds["direct_s"], direct_rays, None)
    # the replicas run at once: each gets what is left of the job's time limit
    left = max(cfg.time_limit - (time.perf_counter() - t0), 1e-3) if cfg.time_limit else 0.0
    replicas = shares.replicas(direct, k, should_stop, left)
    shot, noise = blend(patches, replicas)
    est = estimate_of(patches, noise, shot)
    seconds["shoot_s"] = time.perf_counter() - t0 - seconds["direct_s"]
    shot_rays = direct_rays + sum(r.rays for r in replicas)
    if on_phase is not None:
        on_phase("shoot", time.perf_counter() - t0, shot_rays, est)
    snapshots = [Snapshot(0.0, 0, 0, 1.0, 0.0, None, None), Snapshot(seconds["direct_s"], 0, direct_rays, 1.0, 0.0,
                                                                     None, None),
                 Snapshot(time.perf_counter() - t0, sum(r.shots for r in replicas), shot_rays, shot.ledger.residual(),
                          shot.ledger.closure(), finite(est.rms), finite(est.rms_refl))]
    snapshot_B = [emission, b_direct, patches.radiosity.copy()]
    # the final gather of the average, split by receivers, topped up as FinalPhase.finish does:
    # the job's plan (the replicas' is at 1/k of the density): the gather is not split by rays
    plan = final_plan(cfg, len(patches))
    # the replicas' plan: a budget coarsens it alike in each (Budget.fit)
    first = min(r.final_rays for r in replicas) if plan is not None and all(r.final_rays for r in replicas) else 0
    rounds: list[int] = []
    gather_rays = 0
    stopped = _stopped_by(replicas)
    if not stopped and should_stop is not None and should_stop():
        stopped = "stopped"
    t1 = time.perf_counter()
    receivers = int(patches.rho.any(axis=1).sum())

    cut: list[Choice] = []
    budget_cut = ""

    def first_cut(more: int, by: str) -> None:
        if by and not stopped:
            cut.append(Choice("budget", budget_cut_note(more, first, by, cfg, shot_rays)))

    # as in one process, no final gather where its books cannot carry the light: a sampled source's
    # direct light (the sky's: the gather would read it as reflected light and lose it, 4.6% of a
    # side-lit floor) or glass (DirectPhase.glass_refuses_plan)
    no_plan = any(not getattr(s, "exact", True) for s in patches.sources) or (
        patches.glazing is not None and bool(patches.glazing.mask.any()))
    if stopped == "" and receivers and not no_plan:
        fg = FinalGather(patches, None, shot.diff, shot.direct, shot.direct_a, cfg.batch_rays)
        pos = [np.searchsorted(fg.rec, rows) for rows in parts]
        est_now: list = []

        def trace(more: int) -> None:
            nonlocal gather_rays, stopped
            rounds.append(more)
            try:
                got = shares.gather(shot, parts, rounds, should_stop)
            except GatherStopped:  # the round is lost; B stays what the rounds before left
                rounds.pop()
                stopped = "stopped"
                return
            for (sum_a, sum_b, traced), at in zip(got, pos):
                fg.sum_a[at], fg.sum_b[at] = sum_a, sum_b
                gather_rays += traced
            fg.per_half = sum(rounds) // 2
            b, d, _ = fg.solution()
            patches.radiosity, noise.diff = b, d
            noise.resync(patches)
            est_now[:] = [estimate_of(patches, noise, shot)]
            if on_phase is not None:
                on_phase("gather", time.perf_counter() - t0, shot_rays + gather_rays, est_now[0])

        # the rounds are FinalPhase.finish's (rounds.gather_rounds), each split by receivers over the shares
        budget_cut = gather_rounds(first, cfg, receivers,
                                   spent=lambda: (shot_rays + gather_rays, time.perf_counter() - t0), trace=trace,
                                   error=lambda: est_now[0].rms_refl,
                                   halted=lambda: stopped == "stopped" or (should_stop is not None and should_stop()),
                                   on_first=first_cut).by
        if est_now:
            est = est_now[0]
    elif not no_plan:
        more, budget_cut = fit_round(first + first % 2, cfg, shot_rays, time.perf_counter() - t0, receivers)
        first_cut(more, budget_cut)
    seconds["gather_s"] = time.perf_counter() - t1
    wall = time.perf_counter() - t0
    rays = shot_rays + gather_rays
    if not stopped and should_stop is not None and should_stop():
        stopped = "stopped"
    if not stopped:
        stopped = "accuracy" if est.rms_refl <= cfg.accuracy else budget_cut or "noise_floor"
    stats = Stats(shots=sum(r.shots for r in replicas), rays=rays, batches=sum(r.batches for r in replicas),
                  trace_seconds=float(sum(r.trace_seconds for r in replicas)), wall_seconds=wall, stopped_by=stopped)
    if rounds:
        snapshots.append(Snapshot(wall, stats.shots, rays, shot.ledger.residual(), shot.ledger.closure(),
                                  finite(est.rms), finite(est.rms_refl)))
        snapshot_B.append(patches.radiosity.copy())
    # the job's gather and plan are told by shared_books, not by a replica's own
    choices = Choices([c for c in replicas[0].choices if c.code not in ("direct", "plan", "final_gather")] + cut)
    return SharedRun(k, shot.ledger, shot.tallies, est, stats, replicas, direct_rays, gather_rays, rounds, seconds,
                     snapshots, snapshot_B, choices)


def stopped_in_direct(patches: Patches, config: SolverConfig, k: int, seconds: float) -> SharedRun:
    """A shared run stopped during its direct shares: nothing of the gather is booked and nothing
    was shot, so B = E and all the emitted light is unshot (as ``DirectPhase.gather`` leaves a run in one
    process stopped there, ``GATHER_STOPPED``); its estimate is the unshot light's bias alone."""
    patches.radiosity = patches.emission.copy()
    patches.unshot = patches.emission.copy()
    power = patches.unshot_power.copy()
    ledger = Ledger(emitted=power.copy())
    ledger.unshot = power
    ledger.unshot_abs = power.copy()
    noise = NoiseTally(patches)
    est = noise.estimate(bias_ambient(np.zeros((4, 3)), ledger.held(), patches.total_area, patches.mean_rho))
    stats = Stats(wall_seconds=seconds, stopped_by="stopped")
    snapshots = [Snapshot(0.0, 0, 0, ledger.residual(), ledger.closure(), finite(est.rms), finite(est.rms_refl))]
    return SharedRun(k, ledger, np.zeros((4, 3)), est, stats, [], 0, 0, [], {"direct_s": seconds},
                     snapshots, [patches.radiosity.copy()], Choices([Choice("direct", GATHER_STOPPED)]))


def _stopped_by(replicas: list[Replica]) -> str:
    """A replica's limit (time, rays, a stop request) if one was hit, else ''."""
    for reason in ("stopped", "time_limit", "ray_budget", "no_emitters"):
        if any(r.stopped_by == reason for r in replicas):
            return reason
    return ""


def shared_books(run: SharedRun, patches: Patches, config: SolverConfig, timings: dict | None = None,
                 where: str = "in this process") -> tuple[RunBooks, dict]:
    """The books of a shared run for its report (``pipeline.finish_run``) and the report's
    ``shared`` section."""
    cfg = resolve(config, patches.read_units)
    rep = run.replicas
    back = (np.sum([r.back_by_obj for r in rep], axis=0) / len(rep) if rep
            else np.zeros(max(len(patches.names), 1)))
    stiff = next((r.stiff for r in rep if r.stiff is not None), None)
    choices = Choices(run.choices)
    s = run.seconds
    if not rep:
        choices.add("shared", f"shared run on {run.k} workers ({where}), stopped in its direct shares "
                              f"({s['direct_s']:.1f} s): nothing was shot")
    else:
        choices.add("shared",
            f"shared run on {run.k} workers ({where}), no subscenes: the final plan (exact direct gather, coarse "
            f"shooting, final gather) reads the whole scene's light, so the work is split, not space (share.py): "
            f"each worker gathered the exact direct light of 1/{run.k} of the receivers ({run.direct_rays} shadow "
            f"rays, "
            f"{s['direct_s']:.1f} s), shot an independent replica of the reflected light at 1/{run.k} of the density "
            f"({s['shoot_s']:.1f} s; the replicas were averaged), and gathered the average again for its receivers "
            f"({'+'.join(str(r) for r in run.rounds) or 0} rays a receiver, {run.gather_rays} rays, "
            f"{s.get('gather_s', 0.0):.1f} s)")
    from dcrad.solving.accuracy import describe, noise_floor_note  # noqa: PLC0415

    choices.add("accuracy", describe(cfg))
    if run.stats.stopped_by == "noise_floor":
        choices.add("noise_floor", noise_floor_note(run.estimate, cfg.accuracy))
    shared = {"workers": run.k, **{k: round(v, 3) for k, v in s.items()}, "direct_rays": run.direct_rays,
              "replica_rays": [r.rays for r in rep], "gather_rays": run.gather_rays, "gather_rounds": run.rounds,
              "replica_estimates_refl": [r.estimate.get("rms_refl") for r in rep],
              "replica_stopped_by": [r.stopped_by for r in rep]}
    books = RunBooks(patches, cfg, run.ledger, run.stats, list(run.snapshots), list(run.snapshot_B), back,
                     choices, dict(timings or {}), None, estimate=run.estimate,
                     channels=1 if patches.is_grey and len(patches) else 3, stiff=stiff)
    return books, shared


# == the wire form of shares (coordinator.shared and worker.server) ==============================
_TALLY = ("received", "hit", "escaped", "back_faces", "back_by_obj", "portal", "portal_prim", "portal_t",
          "landed", "kept", "lost", "received_a")


def tally_to_arrays(t: DirectTally) -> dict:
    out = {name: np.asarray(getattr(t, name)) for name in _TALLY}
    out["rays"] = np.array([t.rays], np.int64)
    return out


def tally_from_arrays(arrays: dict, n: int) -> DirectTally:
    """The inverse of ``tally_to_arrays``; ValueError for rows outside 0..n-1 or mismatched shapes."""
    hit = np.asarray(arrays["hit"], np.int64)
    received = np.asarray(arrays["received"], np.float64)
    if received.shape != (len(hit), 3) or np.shape(arrays["received_a"]) != (len(hit), 3):
        raise ValueError("a direct tally's received rows do not match its hit rows")
    if len(hit) and (hit.min() < 0 or hit.max() >= n):
        raise ValueError(f"a direct tally names patches outside 0..{n - 1}")
    vals: dict[str, Any] = {name: np.asarray(arrays[name]) for name in _TALLY}
    vals["hit"], vals["received"] = hit, received
    return DirectTally(**vals, rays=int(np.asarray(arrays["rays"]).ravel()[0]))

