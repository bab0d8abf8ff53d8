"""The three ways a run goes, as objects with one shape: ``strategy.run(patches, config, hooks,
timings)`` returns the run's books (``report.RunBooks``), whatever runs it.

* ``Single``: one subscene in this process (``passes.solve_to_accuracy``);
* ``Divided``: k subscenes trading light at barriers (``division.divide.run_divided``), on a
  *backend* that opens the subscenes' handles: ``InProcess`` builds them here, the coordinator's
  backend places them on workers (``coordinator.jobs``);
* ``Shared``: k workers share one run of the whole scene (``solving.share.run_shared``) through
  its *shares*: ``LocalShares`` here, the coordinator's ``RemoteShares`` on workers.

What a caller watches and steers is the same ``RunHooks`` for each (a stop request, a callback
after each step); which strategy runs a job is chosen in one place, ``solving.strategy``, and
every path ends in ``pipeline.finish_run``.  The strategies hold no service code: the
coordinator adds its checkpoints, previews and metrics through the hooks and its backend.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from dcrad.config import DivideConfig, SolverConfig, unused_divide_note
from dcrad.division.books import divided_books
from dcrad.division.divide import DividedRun, SequentialExecutor, SubsceneSpec, assemble, run_divided, subscene_specs
from dcrad.division.outside import gather_outside
from dcrad.division.subscene import SubsceneHandle
from dcrad.meshing.patches import Patches
from dcrad.outputs.report import RunBooks
from dcrad.solving.accuracy import describe, noise_floor_note
from dcrad.solving.passes import solve_to_accuracy
from dcrad.solving.share import run_shared, shared_books
from dcrad.transport.rays import Tracer

log = logging.getLogger("dcrad")

__all__ = ["RunHooks", "Single", "Divided", "Shared", "InProcess", "SubsceneBackend", "PieceArea"]


@dataclass
class RunHooks:
    """What the caller of a run watches and steers; every strategy takes the same.

    should_stop : () -> True ends the run cleanly at its next batch, its results kept
    on_batch    : (Solver) after every batch of a single run (the progress bar)
    on_barrier  : (DividedRun) after every barrier of a divided run
    on_phase    : (name, elapsed s, rays, estimate or None) after each phase of a shared run
    """

    should_stop: Callable[[], bool] | None = None
    on_batch: Callable[[Any], None] | None = None
    on_barrier: Callable[[DividedRun], None] | None = None
    on_phase: Callable[..., None] | None = None


class Single:
    """One subscene in this process: no partition, no boundaries, no twins.  ``divide``: the
    DivideConfig the caller was given, whose divided-run flags the report says were not used.
    ``tracer`` (after ``run``): the Embree scene it traced, for the outputs to reuse."""

    kind = "single"

    def __init__(self, divide: DivideConfig | None = None):
        self.divide = divide
        self.tracer: Tracer | None = None

    def run(self, patches: Patches, config: SolverConfig, hooks: RunHooks | None = None,
            timings: dict | None = None) -> RunBooks:
        hooks = hooks or RunHooks()
        t0 = time.perf_counter()
        self.tracer = Tracer.mesh(patches)
        t_setup = time.perf_counter() - t0
        solver = solve_to_accuracy(patches, config, self.tracer, on_progress=hooks.on_batch,
                                   should_stop=hooks.should_stop)
        solver.choices.add("subscenes", "one subscene: no partition, no boundaries, no twin buffers")
        unused = unused_divide_note(self.divide, "was one subscene in this process")
        if unused:
            solver.choices.add("unused_flags", unused)
            log.warning(unused)
        solver.choices.add("accuracy", describe(solver.config))
        if solver.stats.stopped_by == "noise_floor":
            solver.choices.add("noise_floor", noise_floor_note(solver.estimate(), solver.config.accuracy))
        # the solver's tallies (noise, pool) go with it, before the outputs; the Embree scene is reused
        return RunBooks.of_solver(solver, {**(timings or {}), "setup_s": t_setup,
                                           "solve_s": solver.stats.wall_seconds})


class PieceArea:
    """A clipped piece kept by its areas only (what ``assemble`` reads once B is given): a backend
    whose subscenes live elsewhere lets their patch tables go."""

    def __init__(self, area: np.ndarray):
        self.area = area

    def __len__(self) -> int:
        return len(self.area)


class SubsceneBackend(Protocol):
    """Where a divided run's subscenes live: ``open`` turns the specs into handles (built here, or
    placed on workers), ``resumed`` says where the opened handles start (barrier, crossing share,
    seconds already run: a job resumed from checkpoints), ``unshot`` reads one handle's unshot
    radiosity at the end, ``close`` frees them (once, even when ``open`` failed); ``executor`` runs
    their iterates (in parallel where they are elsewhere)."""

    def open(self, specs: list[SubsceneSpec]) -> list[SubsceneHandle]: ...

    def resumed(self) -> tuple[int, float, float]: ...

    def executor(self, n: int) -> Executor: ...

    def unshot(self, handle: SubsceneHandle) -> np.ndarray: ...

    def close(self, handles: list[SubsceneHandle]) -> None: ...


class InProcess:
    """The subscenes built in this process (each a Solver with its own Embree scene), iterated one
    after another; ``record``: each barrier's assembled B is kept for the report's snapshots."""

    record = True

    def open(self, specs: list[SubsceneSpec]) -> list[SubsceneHandle]:
        return [s.build() for s in specs]

    def resumed(self) -> tuple[int, float, float]:
        return 0, -1.0, 0.0

    def executor(self, n: int) -> Executor:
        return SequentialExecutor()

    def unshot(self, handle) -> np.ndarray:
        return handle.patches.unshot

    def close(self, handles: list[SubsceneHandle]) -> None:
        pass


@dataclass
class Divided:
    """k subscenes trading light at barriers (the paper's loop) on ``backend``.  ``planes``: the
    cut asked for (internal frame; None: automatic).  After ``run``: ``run_state`` (the
    ``DividedRun``), ``subscenes``; during it, ``assemble(values)`` gives the whole scene's
    (n,3) from the subscenes' values concatenated (a live display's)."""

    divide: DivideConfig
    backend: Any = field(default_factory=InProcess)
    planes: Any = None
    kind = "divided"

    def run(self, patches: Patches, config: SolverConfig, hooks: RunHooks | None = None,
            timings: dict | None = None) -> RunBooks:
        hooks = hooks or RunHooks()
        timings = dict(timings or {})
        t0 = time.perf_counter()
        # the sky and the sun: gathered on the whole scene before it is cut (division/outside.py)
        outside = gather_outside(patches, config)
        specs, boundaries, parents, part = subscene_specs(patches, config, self.divide, planes=self.planes,
                                                          outside=outside)
        self.subscenes = len(specs)
        try:
            handles = self.backend.open(specs)
        except BaseException:
            self.backend.close([])
            raise
        # the pieces' patches are in their handles (or on workers): keep their areas only
        pieces: list[Any] = [PieceArea(s.patches.area) for s in specs]
        del specs
        timings["setup_s"] = time.perf_counter() - t0
        splits = np.cumsum([len(p) for p in pieces])[:-1]

        def whole(values: list[np.ndarray]) -> np.ndarray:
            return assemble(len(patches), patches.area, parents, pieces, values)

        self.assemble = lambda values: whole(np.split(values, splits))
        record = getattr(self.backend, "record", False)
        barrier, crossing, ran = self.backend.resumed()
        # a resumed run's time limit counts the time it ran before (its report keeps the job's)
        run_config = config.replace(time_limit=max(1e-3, config.time_limit - ran)) if ran and config.time_limit \
            else config
        try:
            executor = self.backend.executor(len(handles))
            try:
                run = run_divided(handles, boundaries, run_config, self.divide.batches_per_barrier,
                                  executor, (lambda: whole([h.radiosity() for h in handles])) if record else None,
                                  on_barrier=hooks.on_barrier, should_stop=hooks.should_stop,
                                  first_barrier=barrier, crossing=crossing)
            finally:
                executor.shutdown()
            self.run_state = run
            patches.radiosity = whole([h.radiosity() for h in handles])
            patches.unshot = whole([self.backend.unshot(h) for h in handles])
        finally:
            self.backend.close(handles)
        parents.clear()  # assembled: the outputs need the patch table only
        timings["solve_s"] = run.wall_seconds
        books = divided_books(run, patches, config, boundaries, part, self.divide, timings)
        if outside is not None:  # what the outside's gather chose, on the whole scene
            books.choices.extend(c for c in outside.choices if c.code != "grey")
        return books


class Shared:
    """k workers share one run of the whole scene through ``shares`` (``LocalShares`` or the
    coordinator's ``RemoteShares``).  ``where``: the report's words for who ran it.  ``run`` returns
    None when the lights make no exact form factors (the caller divides instead); ``section``
    (after ``run``): the report's ``shared`` section, and ``run_state`` the ``SharedRun``."""

    kind = "shared"

    def __init__(self, k: int, shares, where: str | Callable[[], str] = "in this process"):
        self.k, self.shares, self.where = k, shares, where
        self.section: dict = {}

    def run(self, patches: Patches, config: SolverConfig, hooks: RunHooks | None = None,
            timings: dict | None = None) -> RunBooks | None:
        hooks = hooks or RunHooks()
        run = run_shared(patches, config, self.k, self.shares, on_phase=hooks.on_phase,
                         should_stop=hooks.should_stop)
        if run is None:
            return None
        self.run_state = run
        timings = dict(timings or {})
        timings["solve_s"] = run.stats.wall_seconds
        where = self.where() if callable(self.where) else self.where
        books, self.section = shared_books(run, patches, config, timings, where=where)
        return books
