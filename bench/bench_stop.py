"""How soon a stop request (Ctrl-C, SIGTERM, a cancelled job) is answered, phase by phase.

One in-process run per phase of a scene (the direct gather, the shooting, the final gather): the
run's ``should_stop`` turns True a moment after the phase has begun, and the bench prints the
seconds from then until ``run`` returned (the outputs are written after that), beside the phase's
own length in an undisturbed run.  No assertions.

Run: .venv/bin/python bench/bench_stop.py [scene] [--accuracy A] [--after S]
     (default: ../shared/models/office3/scene.obj at 0.005, the request 0.3 s into the phase)
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dcrad.config import SolverConfig  # noqa: E402
from dcrad.pipeline import prepare, resolve_scene  # noqa: E402
from dcrad.solving.solver import Solver  # noqa: E402
from dcrad.transport.rays import Tracer  # noqa: E402


def one(patches, tracer, config: SolverConfig, phase: str | None, after: float) -> tuple[float, float, str]:
    """(seconds from when the request was due to run's return, seconds in the final gather undisturbed,
    stop reason).  The request is due ``after`` s into ``phase``; a phase is timed from its start
    (the solver's ``direct.gather`` and ``final.round`` wrapped; the shooting from the first batch after the
    gather), so a phase that never polls ``should_stop`` shows its whole remaining length."""
    patches.reset()
    solver = Solver(patches, config, tracer=tracer)
    seen: dict[str, float] = {}

    def timed(name, method):
        def call(*args, **kwargs):
            seen.setdefault(name, time.perf_counter())
            return method(*args, **kwargs)
        return call

    solver.direct.gather = timed("direct gather", solver.direct.gather)  # type: ignore[method-assign]
    solver.final.round = timed("final gather", solver.final.round)  # type: ignore[method-assign]

    def should_stop() -> bool:
        if solver.direct.tried and not solver.final.done and solver.stats.batches > 0:
            seen.setdefault("shooting", time.perf_counter())
        return phase is not None and phase in seen and time.perf_counter() >= seen[phase] + after

    solver.run(should_stop=should_stop)
    end = time.perf_counter()
    if phase is None:
        return 0.0, end - seen.get("final gather", end), solver.stats.stopped_by
    if phase not in seen:
        return float("nan"), 0.0, solver.stats.stopped_by
    return end - (seen[phase] + after), 0.0, solver.stats.stopped_by


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", default=str(ROOT.parent / "shared" / "models" / "office3" / "scene.obj"))
    ap.add_argument("--accuracy", type=float, default=0.005)
    ap.add_argument("--after", type=float, default=0.3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        _, p, _ = prepare(resolve_scene(args.scene, Path(tmp)))
    tracer = Tracer.mesh(p)
    cfg = SolverConfig(accuracy=args.accuracy, seed=1)
    t0 = time.perf_counter()
    _, final_s, reason = one(p, tracer, cfg, None, args.after)
    print(f"bench_stop: {args.scene} at --accuracy {args.accuracy}, {len(p)} elements; undisturbed "
          f"{time.perf_counter() - t0:.1f} s (final gather {final_s:.1f} s), stopped by {reason}")
    for phase in ("direct gather", "shooting", "final gather"):
        latency, _, reason = one(p, tracer, cfg, phase, args.after)
        print(f"  stop asked {args.after:g} s into the {phase}: run returned {latency:.2f} s later ({reason})",
              flush=True)


if __name__ == "__main__":
    main()
