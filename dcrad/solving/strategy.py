"""Which way a run goes, and why: the one place the choice is made.

Three strategies run a job (``dcrad.runs``, one object each): **single** (one subscene in one
process), **divided** (k subscenes trading light at barriers: divide.py, in process or on
workers) and **shared** (k workers share one run of the whole scene, the work split, not space:
share.py).
Two callers choose:

* ``dcrad solve`` without ``--workers`` asks ``local``: this process (single), or two local worker
  processes, which then run the job as the coordinator chooses;
* the coordinator asks ``on_workers``: shared where the run takes the final plan (accuracy mode
  with the direct light gathered exactly), divided otherwise or when subscenes were asked for.

Each answer carries its reason as a ``Choice`` for the report.
"""

from __future__ import annotations

from dataclasses import dataclass

from dcrad.choices import Choice
from dcrad.config import SolverConfig
from dcrad.division.placement import SUBSCENES_PER_WORKER, subscene_limit
from dcrad.solving.accuracy import by_accuracy
from dcrad.transport.direct import MAX_ANALYTIC_RECEIVERS

__all__ = ["Strategy", "local", "on_workers", "gathers", "shares_possible", "AUTO_DIVIDE_PATCHES",
           "SHARE_PATCHES", "SUBSCENES_PER_WORKER"]

#: unknowns below which `dcrad solve` runs in one process by default: two local workers pay for
#: their start-up (processes, upload, partition, loading: a few seconds) only on bigger scenes
AUTO_DIVIDE_PATCHES = 150_000
#: the same for a shared run (the runs that gather their light)
SHARE_PATCHES = 100_000


@dataclass(frozen=True)
class Strategy:
    kind: str  #: "single", "divided" or "shared"
    workers: int  #: worker processes (0: this process)
    subscenes: int  #: cells of a divided run (1 otherwise)
    why: Choice  #: the report's entry


def gathers(config: SolverConfig, units: int) -> bool:
    """The run takes the final plan (exact direct gather, shot reflected light, final gather):
    accuracy mode, the direct light gathered, few enough receivers for exact form factors."""
    return by_accuracy(config) and config.direct and units <= MAX_ANALYTIC_RECEIVERS


def shares_possible(config: SolverConfig, receivers: int) -> bool:
    """A shared run can take this job: accuracy mode with the direct light gathered, and at most
    MAX_ANALYTIC_RECEIVERS receivers (where the exact gather, and so the final plan, is used).
    The lights must also make exact-form-factor polygons: the direct shares find out (the
    job divides space instead)."""
    return by_accuracy(config) and config.direct and 0 < receivers <= MAX_ANALYTIC_RECEIVERS


def local(units: int, cpus: int, gathered: bool = False) -> Strategy:
    """`dcrad solve` without --workers: this process or two local workers, from the run's unknowns
    (Patches.units: a cluster of small triangles counts once) and the CPUs.

    ``gathered`` (``gathers``): two workers would share the run (share.py), which pays for its
    start-up from SHARE_PATCHES unknowns; dividing space would lose the plan (on the 8x8 office at
    2%: 307M rays on two workers against 48.7M in one process, bench/RESULTS.md)."""
    def single(text: str) -> Strategy:
        return Strategy("single", 0, 1, Choice("workers", text))

    if cpus < 2:
        return single("solved in this process (--workers 0 by default): one CPU, local workers would only compete")
    if gathered:
        if units < SHARE_PATCHES:
            return single(f"solved in this process (--workers 0 by default): about {units} unknowns, below the "
                          f"{SHARE_PATCHES} at which two local workers sharing the run pay for their start-up "
                          f"(--workers 2 shares it anyway)")
        return Strategy("shared", 2, 1, Choice("workers", (
            f"two local worker processes by default, sharing one run of the whole scene: about {units} unknowns "
            f"(at least {SHARE_PATCHES}); its light is gathered (the final plan), which a divided run would lose "
            f"(share.py)")))
    if units < AUTO_DIVIDE_PATCHES:
        return single(f"solved in this process (--workers 0 by default): about {units} unknowns, below the "
                      f"{AUTO_DIVIDE_PATCHES} at which two local workers pay for their start-up "
                      f"(--workers 2 divides anyway)")
    k = SUBSCENES_PER_WORKER * 2
    return Strategy("divided", 2, k, Choice("workers", (
        f"two local worker processes by default: about {units} unknowns (at least {AUTO_DIVIDE_PATCHES}: dividing "
        f"pays for the start-up)")))


def on_workers(config: SolverConfig, receivers: int, patches: int, live: int, subscenes: int = 0,
               resumed: bool = False, exact_lights: bool = True) -> Strategy:
    """The coordinator's choice for a job on ``live`` workers: shared when the run takes the final
    plan and no subscenes were asked for (``subscenes`` 0) and it is not resumed from a divided
    run's checkpoints; divided otherwise, into the subscenes asked for or SUBSCENES_PER_WORKER a
    worker (at most ``placement.subscene_limit`` of ``patches``).  ``exact_lights`` False: a shared
    run's direct shares found the lights make no exact-form-factor polygons, and the job divides."""
    if not subscenes and not resumed and exact_lights and shares_possible(config, receivers):
        return Strategy("shared", live, 1, Choice("strategy", (
            f"shared by the {live} worker(s), each holding the whole scene: accuracy mode with the direct light "
            f"gathered exactly ({receivers} receiving patches, at most {MAX_ANALYTIC_RECEIVERS}) takes the final "
            f"plan, which reads the whole scene's light; dividing space would lose it")))
    k = subscenes or min(SUBSCENES_PER_WORKER * live, subscene_limit(patches))
    if resumed:
        why = "divided: resumed from its checkpoints"
    elif not exact_lights:
        why = (f"divided into {k} subscenes: the lights make no exact-form-factor polygons, which a shared "
               f"run's direct shares need")
    elif subscenes:
        why = f"divided into the {subscenes} subscenes asked for"
    elif not by_accuracy(config) or not config.direct:
        why = (f"divided into {k} subscenes ({SUBSCENES_PER_WORKER} a worker): the run does not gather its direct "
               f"light (a tolerance run, or --no-direct), so nothing is lost by dividing space")
    else:
        why = (f"divided into {k} subscenes ({SUBSCENES_PER_WORKER} a worker): {receivers} receiving patches, "
               f"above the {MAX_ANALYTIC_RECEIVERS} an exact direct gather (and so a shared run) takes")
    return Strategy("divided", live, k, Choice("strategy", why))
