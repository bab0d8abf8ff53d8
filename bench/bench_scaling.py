"""Past one machine: the barrier loop with k subscenes, timed per subscene, and what k machines would take.

For each k the subscenes run in this process, one after another (``SequentialExecutor``),
and every subscene's ``iterate`` is timed on its own, in CPU seconds of this process
(``time.process_time``: the machine is shared, and wall time would count the others' load).
A barrier on k machines takes the slowest subscene's iterate (the critical path) plus the exchange; the exchange is
modelled for a stated link: the coordinator relays every subscene's crossing rays (in
and out over its one link), with 4 round trips per barrier (iterate, collect, deliver,
checkpoint).  Predicted time on k machines = sum over barriers of (critical path +
exchange); speed-up = the one-process solve's time / that; efficiency = speed-up / k.
Partition, clipping and loading are left out of the prediction (printed separately).
A second table puts k subscenes on m machines (``--machines``): kept where ``placement.placement``
puts them by expected work (as the coordinator does), or assigned afresh at each barrier by the
power each holds, paying for the moves; the critical path is then the busiest machine's.

Prints figures; asserts nothing.  Run, e.g. (the issue-14 figures in bench/RESULTS.md)::

    .venv/bin/python bench/bench_scaling.py --rows 20 --cols 20 --patch-size 0.4 --ks 1,2,4,8,16,32,64

``--service`` also runs ``dcrad solve --workers 0`` and ``--workers 2`` with the same
settings, whole process, and prints the measured 2-worker speed-up beside the prediction.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import dcrad.division.divide
import scenes
from dcrad.config import DivideConfig, SolverConfig
from dcrad.division.divide import SequentialExecutor, run_divided, subscene_specs
from dcrad.division.placement import expected_work, placement
from dcrad.division.subscene import checkpoint_arrays, subscene_arrays
from dcrad.pipeline import prepare
from dcrad.solving.solver import Solver


def on_machines(per: np.ndarray, m: int, pending: np.ndarray, moving: np.ndarray, static: np.ndarray,
                bw: float) -> tuple[np.ndarray, np.ndarray]:
    """Dynamic subscene reconfiguration: k subscenes on m machines, assigned afresh at each
    barrier by the work each has pending (longest first to the least loaded machine: LPT).

    per (k, barriers) CPU s; pending (k, barriers) W each held when the barrier's iterates began
    (its unshot and in-flight power: what the coordinator knows from the states); moving (k,)
    bytes of a subscene's changing state (its checkpoint), static (k,) bytes of its patches and
    boundaries.  A subscene that changes machine sends its state over the coordinator's link,
    and its patches too the first time it lands on a machine.
    Returns ((barriers,) critical path s, (barriers,) s of moves).
    """
    k, n = per.shape
    crit, moves = np.zeros(n), np.zeros(n)
    where = np.full(k, -1)
    held = np.zeros((k, m), bool)
    for b in range(n):
        load, est = np.zeros(m), np.zeros(m)
        slot = np.empty(k, np.int64)
        for i in np.argsort(-pending[:, b], kind="stable"):
            j = int(np.argmin(est))
            est[j] += pending[i, b]
            load[j] += per[i, b]
            slot[i] = j
        moved = (where >= 0) & (slot != where)
        fresh = moved & ~held[np.arange(k), slot]
        moves[b] = (moving[moved].sum() + static[fresh].sum()) / bw
        held[np.arange(k), slot] = True
        where = slot
        crit[b] = load.max()
    return crit, moves


def placed(per: np.ndarray, slots: list[int], m: int) -> np.ndarray:
    """(barriers,) s: k subscenes on m machines, each kept on its slot (``placement.placement``)."""
    load = np.zeros((m, per.shape[1]))
    for i, j in enumerate(slots):
        load[j] += per[i]
    return load.max(axis=0)


class Timed:
    """A subscene handle that times its own iterate and counts the bytes it hands over."""

    def __init__(self, sub):
        self.sub, self.cell, self.mode = sub, sub.cell, sub.mode
        self.seconds: list[float] = []  # per barrier
        self.rays: list[int] = []  # per barrier
        self.sent: list[int] = []  # bytes collected per barrier
        self.received: list[int] = []  # bytes delivered per barrier
        self.pending: list[float] = []  # W held (unshot + in flight) as each barrier's iterates began

    def iterate(self, n, plan=None):
        self.pending.append(float(self.sub.ledger.held().sum()))  # what the coordinator knows
        t0 = time.process_time()
        rays = self.sub.iterate(n, plan)
        self.seconds.append(time.process_time() - t0)
        self.rays.append(rays)
        return rays

    def collect(self):
        out = self.sub.collect()
        self.sent.append(out.nbytes())
        return out

    def deliver(self, buffer):
        self.received.append(buffer.nbytes())
        self.sub.deliver(buffer)

    def state(self):
        return self.sub.state()

    def radiosity(self):
        return self.sub.radiosity()

    def interrupt(self):
        self.sub.interrupt()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rows", type=int, default=20)
    ap.add_argument("--cols", type=int, default=20)
    ap.add_argument("--patch-size", type=float, default=0.4)
    ap.add_argument("--ks", default="1,2,4,8,16,32,64")
    ap.add_argument("--tol", type=float, default=0.05, help="residual to stop at (the same for every k)")
    ap.add_argument("--rays-per-power", type=float, default=2e5)
    ap.add_argument("--max-rays", type=int, default=0, help="ray budget per run (0: none)")
    ap.add_argument("--min-rays", type=int, default=SolverConfig().min_rays, help="fewest rays per patch shot")
    ap.add_argument("--direct", action="store_true",
                    help="k=1 gathers the direct light (divided runs shoot it; off by default: like for like)")
    ap.add_argument("--max-iterations", type=int, default=DivideConfig().max_iterations,
                    help="most batches per subscene between barriers (adaptive doIterations)")
    ap.add_argument("--gbps", type=float, default=1.0, help="link bandwidth, Gbit/s")
    ap.add_argument("--latency-ms", type=float, default=0.5, help="one round trip, ms")
    ap.add_argument("--machines", default="2,16", help="also put k subscenes on m machines, for each m < k")
    ap.add_argument("--cut", choices=("light", "area"), default=dcrad.division.divide.CUT_WORK,
                    help="what the automatic cut balances (divide.CUT_WORK; area: as before issue 14's fifth session)")
    ap.add_argument("--service", action="store_true", help="also measure dcrad solve --workers 0 / 2")
    args = ap.parse_args(argv)
    machines = [int(x) for x in args.machines.split(",") if x]
    dcrad.division.divide.CUT_WORK = args.cut

    folder = Path(tempfile.mkdtemp())
    path = scenes.write_builtin("office", folder, rows=args.rows, cols=args.cols)
    cfg = SolverConfig(tol=args.tol, rays_per_power=args.rays_per_power, max_rays=args.max_rays, seed=1,
                       min_rays=args.min_rays, direct=args.direct)
    bw = args.gbps * 1e9 / 8  # bytes/s
    rtt = args.latency_ms * 1e-3
    print(f"office {args.rows}x{args.cols}, patch size {args.patch_size} m; tol {args.tol}, "
          f"{args.rays_per_power:.3g} rays per emitted power, ray budget {args.max_rays or 'none'}, "
          f"min rays {args.min_rays}, direct light {'gathered at k=1' if args.direct else 'shot'}; "
          f"link {args.gbps:g} Gbit/s, {args.latency_ms:g} ms round trip, coordinator relays; cut by {args.cut}")
    _, p, _ = prepare(path, args.patch_size)
    print(f"{len(p)} patches", flush=True)
    t0 = time.process_time()
    one = Solver(p, cfg)
    one.run()
    t1 = time.process_time() - t0
    rays1 = one.stats.rays
    print(f"k=1 (one process): {t1:.1f} CPU s, {rays1:,d} rays, residual {one.residual():.3g}", flush=True)
    head = (f"{'k':>3} {'setup s':>7} {'barriers':>8} {'rays/k1':>7} {'crit s':>7} {'sum s':>7} {'balance':>7} "
            f"{'rays bal':>8} {'MB/barrier':>10} {'xchg s':>7} {'pred s':>7} {'speed-up':>8} {'eff':>5}")
    print(head)
    rows = []  # (k, m, ...) for the table of k subscenes on m machines
    for k in [int(x) for x in args.ks.split(",") if int(x) > 1]:
        _, q, _ = prepare(path, args.patch_size)
        t0 = time.perf_counter()
        specs, boundaries, _, _ = subscene_specs(q, cfg, DivideConfig(subscenes=k))
        handles = [Timed(s.build()) for s in specs]
        setup = time.perf_counter() - t0
        per_barrier = DivideConfig(max_iterations=args.max_iterations).batches_per_barrier
        run = run_divided(handles, boundaries, cfg, per_barrier, SequentialExecutor())
        per = np.array([h.seconds for h in handles])  # (k, barriers)
        rays = np.array([h.rays for h in handles], np.float64)
        moved = np.array([h.sent for h in handles]).sum(axis=0) if run.barriers else np.zeros(1)
        crit = per.max(axis=0)
        xchg = 4 * rtt + 2 * moved / bw
        pred = float((crit + xchg).sum())
        total = per.sum(axis=1)
        balance = float(total.max() / total.mean())  # slowest subscene / mean
        speed = t1 / pred
        print(f"{k:3d} {setup:7.1f} {run.barriers:8d} {run.snapshots[-1].rays / rays1:7.2f} "
              f"{crit.mean():7.3f} {per.sum():7.1f} {balance:7.2f} {rays.sum(1).max() / rays.sum(1).mean():8.2f} "
              f"{moved.mean() / 1e6:10.2f} {xchg.sum():7.2f} {pred:7.2f} {speed:8.2f} {speed / k:5.0%}", flush=True)
        # why the slowest is slow: its lamps, its patches, its rays against the mean
        lamps = np.array([float(sp.patches.emitted_power.sum()) for sp in specs])
        size = np.array([len(sp.patches) for sp in specs], np.float64)
        i = int(np.argmax(total))
        print(f"    slowest: cell {handles[i].cell}, lamps {lamps[i] / lamps.mean():.2f}x the mean, patches "
              f"{size[i] / size.mean():.2f}x, rays {rays[i].sum() / rays.sum(1).mean():.2f}x; lamps per cell "
              f"{lamps.min():.0f}-{lamps.max():.0f} W; correlation of CPU s with lamps "
              f"{np.corrcoef(total, lamps)[0, 1]:.2f}, with patches {np.corrcoef(total, size)[0, 1]:.2f}")
        moving = np.array([sum(v.nbytes for v in checkpoint_arrays(h.sub).values()) for h in handles], np.float64)
        static = np.array([sum(np.asarray(v).nbytes for v in subscene_arrays(h.sub).values()) for h in handles],
                          np.float64)
        pending = np.array([h.pending for h in handles])
        work = [expected_work(sp.patches) for sp in specs]
        for m in machines:
            if m >= k:
                continue
            slots = placement(work, m)
            crit_p = placed(per, slots, m)
            rays_p = placed(rays, slots, m)
            crit_d, moves = on_machines(per, m, pending, moving, static, bw)
            pred_p = float((crit_p + xchg).sum())
            pred_d = float((crit_d + xchg + moves).sum())
            ideal = float((per.sum(axis=0) / m + xchg).sum())
            rows.append((k, m, pred_p, crit_p.sum(), rays_p.sum() / 1e6, pred_d, moves.sum(), ideal))
        del handles, specs
    print("crit s: mean per-barrier critical path (slowest subscene); sum s: all subscenes' iterate time; "
          "balance: slowest subscene's total / the mean (rays bal: the same in rays, free of the machine's "
          "drift); MB/barrier: crossing rays handed over")
    if rows:
        print(f"\nk subscenes on m machines (over-decomposed): {'k':>3} {'m':>3} {'placed s':>8} {'speed-up':>8} "
              f"{'eff':>5} {'crit s':>7} {'Mrays':>6} {'dynamic s':>9} {'speed-up':>8} {'eff':>5} {'moves s':>7} "
              f"{'ideal s':>7} {'eff':>5}")
        for k, m, pred_p, crit_p, mrays, pred_d, moves, ideal in rows:
            print(f"{'':45}{k:3d} {m:3d} {pred_p:8.2f} {t1 / pred_p:8.2f} {t1 / pred_p / m:5.0%} {crit_p:7.2f} "
                  f"{mrays:6.1f} {pred_d:9.2f} {t1 / pred_d:8.2f} {t1 / pred_d / m:5.0%} {moves:7.2f} {ideal:7.2f} "
                  f"{t1 / ideal / m:5.0%}")
        print("placed: each subscene kept on the machine placement.placement gives it by expected work (its lamps and "
              "patches; what the coordinator does), plus the exchange; crit s / Mrays: its critical path summed "
              "over barriers, in CPU s and rays; dynamic: assigned afresh at each barrier by the W each subscene "
              "holds (unshot and in flight), plus the exchange and the moves (a moved subscene's checkpoint over "
              "the link, and its patches the first time on a machine); ideal: all iterates' CPU s / m plus the "
              "exchange (perfect balance)")
    if args.service:
        common = [f"office:rows={args.rows},cols={args.cols}", "--patch-size", str(args.patch_size),
                  "--tol", str(args.tol), "--rays-per-power", str(args.rays_per_power), "--width", "64",
                  "--height", "48", "--min-rays", str(args.min_rays)]
        if not args.direct:
            common += ["--no-direct"]
        if args.max_rays:
            common += ["--max-rays", str(args.max_rays)]
        times = {}
        for w in (0, 2):
            t0 = time.perf_counter()
            r = subprocess.run([sys.executable, "-m", "dcrad.cli", "solve", *common, "--workers", str(w),
                                "--out", str(folder / f"w{w}")], capture_output=True, text=True)
            times[w] = time.perf_counter() - t0
            if r.returncode:
                print(f"--workers {w} failed: {r.stderr.strip().splitlines()[-1:]}")
        print(f"measured, whole process: --workers 0 {times[0]:.1f} s, --workers 2 {times[2]:.1f} s: "
              f"2-worker speed-up {times[0] / times[2]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
