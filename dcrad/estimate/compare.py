"""Error against run time: the sequential solver versus k subscenes (the paper, section 1.4).

``compare`` solves one scene sequentially (k=1: the plain Solver) and divided for
each k>1, keeping B at every snapshot (every barrier, for divided runs), and
measures each snapshot's area-weighted RMS error against a reference B*: a
``radiosity.npz`` the user supplies, or a converged sequential run with ten times
the rays per unit power and a ten times smaller tolerance.  It then checks the
paper's three statements about the sequential curve S(n) and the divided curve
P(n), n being the sum of the iterations (shots) in all subscenes, on the data:

1. small n: S(n) < P(n);  2. large n: S(n) = P(n);  3. small n, k>1: S(n) > P(kn).

``write_compare`` writes compare.json, compare.csv and one chart (PNG and SVG)
in the manner of the paper's Figure 3.
"""

from __future__ import annotations

import csv
import math
import time
from pathlib import Path

import numpy as np

from dcrad.config import SolverConfig
from dcrad.division.divide import DivideConfig, solve_divided
from dcrad.errors import ConfigError, DcradError
from dcrad.outputs.report import write_json
from dcrad.pipeline import prepare
from dcrad.solving.accuracy import residual_goal, resolve
from dcrad.solving.energy import rms_error
from dcrad.solving.solver import Solver

__all__ = ["compare", "write_compare", "loglog_interp", "CLAIM2_FACTOR"]

#: claim 2 holds when the largest final RMS error is within this factor of the smallest
CLAIM2_FACTOR = 1.5
#: seed offset of the reference run, so its noise is independent of the runs'
REF_SEED_OFFSET = 7919

FIELDS = ("run", "k", "time_s", "shots", "rays", "residual", "rms", "rms_norm")


# == curves ========================================================================
def loglog_interp(xs, ys, x: float):
    """y at x on the piecewise-linear curve log y(log x); None outside the measured range."""
    pts = {}
    for a, b in zip(xs, ys):
        if a > 0 and b > 0:
            pts[float(a)] = float(b)  # repeated x (no shot between snapshots): keep the last
    if not pts or x <= 0:
        return None
    lx = np.log(sorted(pts))
    ly = np.log([pts[a] for a in sorted(pts)])
    if math.log(x) < lx[0] - 1e-12 or math.log(x) > lx[-1] + 1e-12:
        return None
    return float(np.exp(np.interp(math.log(x), lx, ly)))


def first_reach(xs, ys, target: float):
    """First x at which y falls to ``target`` (log y interpolated linearly in x); None if never."""
    for i, (x, y) in enumerate(zip(xs, ys)):
        if y <= target:
            if i == 0 or ys[i - 1] <= 0 or y <= 0:
                return float(x)
            x0, y0 = xs[i - 1], ys[i - 1]
            f = (math.log(y0) - math.log(target)) / max(math.log(y0) - math.log(y), 1e-300)
            return float(x0 + (x - x0) * f)
    return None


def _load_reference(file, n: int, area: np.ndarray, size: float) -> np.ndarray:
    try:
        z = np.load(file, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise DcradError(f"reference {file}: cannot read it as .npz ({exc})") from None
    if not isinstance(z, np.lib.npyio.NpzFile) or "patch_B" not in z.files:
        raise DcradError(f"reference {file}: not an .npz with a 'patch_B' array (write one with 'dcrad solve')")
    with z:
        ref = np.asarray(z["patch_B"], np.float64)
        ref_area = z["patch_area"] if "patch_area" in z.files else None
    if ref.ndim != 2 or ref.shape[1] != 3 or len(ref) != n:
        raise DcradError(f"reference {file}: it has {len(ref)} patches (shape {ref.shape}) but the scene "
                         f"has {n} patches at patch size {size:.4g} m; solve it with the same "
                         f"scene and --patch-size")
    if not np.isfinite(ref).all():
        raise DcradError(f"reference {file}: patch_B holds non-finite values")
    if ref_area is not None and (np.shape(ref_area) != area.shape or not np.allclose(ref_area, area, rtol=1e-6)):
        raise DcradError(f"reference {file}: {n} patches, but their areas differ from this scene's meshing")
    return ref


def _curve(snaps, snap_B, ref, area, ref_rms, k: int) -> list[dict]:
    label = "sequential" if k == 1 else f"divided-{k}"
    out = []
    for s, b in zip(snaps, snap_B):
        rms = rms_error(b, ref, area)
        out.append({"run": label, "k": k, "time_s": s.time, "shots": int(s.shots), "rays": int(s.rays),
                    "residual": s.residual, "rms": rms, "rms_norm": rms / ref_rms if ref_rms > 0 else 0.0})
    return out


# == claims ========================================================================
def _claims(runs: list[dict]) -> dict:
    seq = next(r for r in runs if r["k"] == 1)
    divided = [r for r in runs if r["k"] > 1]
    S = seq["points"]
    sx, sy = [p["shots"] for p in S], [p["rms_norm"] for p in S]
    c1, c3 = [], []
    for r in divided:
        k, P = r["k"], r["points"]
        first = next((p for p in P if p["shots"] > 0), None)
        if first is None:
            continue
        n, p_n = first["shots"], first["rms_norm"]  # the earliest P measured: the first barrier
        s_n = loglog_interp(sx, sy, n)
        c1.append({"k": k, "n": n, "S(n)": s_n, "P(n)": p_n, "P/S": None if not s_n else p_n / s_n,
                   "holds": None if s_n is None else bool(s_n < p_n)})
        s_small = loglog_interp(sx, sy, n / k)  # P(k m) with m = n/k is the measured P(n)
        c3.append({"k": k, "n": n / k, "kn": n, "S(n)": s_small, "P(kn)": p_n,
                   "S/P": None if s_small is None or p_n <= 0 else s_small / p_n,
                   "holds": None if s_small is None else bool(s_small > p_n)})
    finals = [{"k": r["k"], "shots": r["points"][-1]["shots"], "rms_norm": r["points"][-1]["rms_norm"],
               "residual": r["points"][-1]["residual"]} for r in runs]
    for f in finals[1:]:
        f["ratio_to_sequential"] = f["rms_norm"] / finals[0]["rms_norm"] if finals[0]["rms_norm"] > 0 else None
    vals = [f["rms_norm"] for f in finals]
    spread = max(vals) / min(vals) if min(vals) > 0 else math.inf

    def overall(items):
        if not items:
            return None
        return all(i["holds"] is True for i in items)

    return {
        "claim1": {"statement": "small n: S(n) < P(n)", "holds": overall(c1), "per_k": c1,
                   "method": "n = total shots at the first divided barrier (the earliest P measured); "
                             "S(n) interpolated log-log on the sequential curve; holds = S(n) < P(n) "
                             "for every k (undetermined when n lies outside the sequential curve)"},
        "claim2": {"statement": "large n: S(n) = P(n)", "holds": None if not divided else bool(spread <= CLAIM2_FACTOR),
                   "finals": finals, "spread": spread, "tolerance_factor": CLAIM2_FACTOR,
                   "method": f"final normalised RMS of every run (each stopped at its residual tolerance); "
                             f"holds = largest / smallest <= {CLAIM2_FACTOR}"},
        "claim3": {"statement": "small n, k>1: S(n) > P(kn)", "holds": overall(c3), "per_k": c3,
                   "method": "kn = total shots at the first divided barrier, P(kn) measured there; "
                             "S(n) at n = kn/k interpolated log-log; holds = S(n) > P(kn) for every k"},
    }


# == the comparison ================================================================
def compare(path, subscenes=(1, 2, 4, 8), config: SolverConfig = SolverConfig(), mode: str = "binned",
            reference=None, patch_size: float | None = None, ref_rays_factor: float = 10.0,
            ref_tol: float | None = None, iterations: int = 0) -> dict:
    """Solve ``path`` sequentially and divided into each k, measure RMS error curves; return a dict.

    subscenes : values of k; 1 (the sequential baseline S) is always included
    reference : optional radiosity.npz (from ``dcrad solve``) whose patch_B is B*
    iterations: batches per subscene between barriers, 0: adaptive (a divided run is measured at barriers)
    """
    ks = sorted({int(k) for k in subscenes} | {1})
    if ks[0] < 1:
        raise ConfigError(f"subscenes must be >= 1, not {ks[0]}")
    if ref_rays_factor <= 0:
        raise ConfigError(f"ref_rays_factor={ref_rays_factor} must be > 0")
    scene, patches, size = prepare(path, patch_size)
    area, n = patches.area.copy(), len(patches)
    config = resolve(config, n)  # the ray density and stop rule of the runs (accuracy.py)
    ref_info: dict[str, object] = {"patches": n}
    if reference is not None:
        ref = _load_reference(reference, n, area, size)
        ref_info |= {"source": "file", "file": str(reference)}
    else:
        tol = ref_tol if ref_tol is not None else min(residual_goal(config) / 10.0, 1e-3)
        rcfg = config.replace(tol=tol, rays_per_power=config.rays_per_power * ref_rays_factor,
                              seed=config.seed + REF_SEED_OFFSET, time_limit=0.0, max_rays=0)
        solver = Solver(patches, rcfg)
        solver.run()
        ref = patches.radiosity.copy()
        ref_info |= {"source": "sequential run", "tol": tol, "rays_per_power": rcfg.rays_per_power,
                     "seed": rcfg.seed, "rays": solver.stats.rays, "residual": solver.residual(),
                     "wall_s": solver.stats.wall_seconds}
    ref_rms = rms_error(np.zeros_like(ref), ref, area)
    ref_info["rms_W_m2"] = ref_rms

    runs = []
    for k in ks:
        _, p, _ = prepare(path, size, adapt=not patch_size)  # the mesh of the reference
        t0 = time.perf_counter()
        if k == 1:
            s = Solver(p, config)
            setup = time.perf_counter() - t0
            s.run()
            snaps, snap_B, wall, stop, extra = s.snapshots, s.snapshot_B, s.stats.wall_seconds, s.stats.stopped_by, {}
        else:
            run, subs, bounds, _ = solve_divided(p, config, DivideConfig(subscenes=k, mode=mode, iterations=iterations),
                                                 record=True)
            setup = time.perf_counter() - t0 - run.wall_seconds
            snaps, snap_B, wall, stop = run.snapshots, run.snapshot_B, run.wall_seconds, run.stopped_by
            extra = {"subscenes": len(subs), "boundaries": len(bounds), "barriers": run.barriers}
        pts = _curve(snaps, snap_B, ref, area, ref_rms, k)
        runs.append({"k": k, "label": pts[0]["run"], "setup_s": setup, "wall_s": wall, "stopped_by": stop,
                     **extra, "points": pts})

    seq_final = runs[0]["points"][-1]["rms"]
    for r in runs:
        P = r["points"]
        r["final_rms"], r["final_rms_norm"] = P[-1]["rms"], P[-1]["rms_norm"]
        r["time_to_2x_seq_final_s"] = first_reach([p["time_s"] for p in P], [p["rms"] for p in P], 2 * seq_final)
        r["shots_to_2x_seq_final"] = first_reach([p["shots"] for p in P], [p["rms"] for p in P], 2 * seq_final)
    return {
        "dcrad_compare": 1,
        "scene": {"path": str(scene.path), "name": Path(scene.path).stem, "patches": n, "patch_size_m": size},
        "settings": {"subscenes": ks, "mode": mode, "iterations": iterations, "solver": config.as_dict(),
                     "ref_rays_factor": ref_rays_factor},
        "reference": ref_info,
        "notes": ("rms: area-weighted RMS error (W/m^2) against B*; rms_norm = rms / RMS(B*); "
                  "shots: iterations summed over all subscenes (the paper's n); time_s: wall time since "
                  "the solve loop started (meshing, Embree build and partitioning are in setup_s); "
                  "divided runs are measured at barriers only, and run their subscenes one after another in "
                  "this process, so their wall time is the sum over subscenes, not a parallel time"),
        "runs": runs,
        "claims": _claims(runs),
    }


# == output ========================================================================
def _chart(result: dict, out_dir: Path) -> None:
    # matplotlib (an optional heavy import, ~0.5 s) only when a chart is drawn, headless
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4), constrained_layout=True)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, r in enumerate(result["runs"]):
        pts = [p for p in r["points"] if p["rms_norm"] > 0]
        seq = r["k"] == 1
        style = dict(color="black" if seq else colors[i % len(colors)], lw=2.8 if seq else 1.6,
                     ls="-" if seq else "--", marker=None if seq else "o", ms=3.5,
                     label="sequential (k=1)" if seq else f"{r['k']} subscenes")
        axes[0].plot([p["time_s"] for p in pts], [p["rms_norm"] for p in pts], **style)
        xy = [(p["shots"], p["rms_norm"]) for p in pts if p["shots"] > 0]
        if xy:
            axes[1].plot(*zip(*xy), **style)
    axes[1].set_xscale("log")  # wall time stays linear: it starts at 0 and is what a user waits
    for ax, xl in zip(axes, ("wall time of the solve loop (s)", "iterations n (shots, summed over subscenes)")):
        ax.set_yscale("log")
        ax.set_xlabel(xl)
        ax.set_ylabel("normalised RMS error  RMS(B* - B) / RMS(B*)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    sc = result["scene"]
    fig.suptitle(f"{sc['name']}: RMS error, sequential vs divided ({sc['patches']} patches, "
                 f"{result['settings']['mode']} boundaries, B*: {result['reference']['source']})")
    fig.savefig(out_dir / "compare.png", dpi=110)
    fig.savefig(out_dir / "compare.svg")
    plt.close(fig)


def write_compare(result: dict, out_dir) -> dict:
    """Write compare.json, compare.csv, compare.png and compare.svg; return {kind: path}."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "compare.json", result)
    with open(out / "compare.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=FIELDS)
        w.writeheader()
        for r in result["runs"]:
            for p in r["points"]:
                w.writerow({f: p[f] for f in FIELDS})
    _chart(result, out)
    return {k: out / f"compare.{k}" for k in ("json", "csv", "png", "svg")}


def summary_lines(result: dict) -> list[str]:
    """A short table for the terminal: k, final RMS, time to 2x the sequential final, claims."""
    fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
    lines = [f"{'k':>3} {'final RMS W/m2':>15} {'normalised':>11} {'residual':>9} {'wall s':>8} "
             f"{'t(2x seq final) s':>18} {'shots':>9}"]
    for r in result["runs"]:
        last = r["points"][-1]
        lines.append(f"{r['k']:>3} {r['final_rms']:>15.4g} {r['final_rms_norm']:>11.4f} {last['residual']:>9.2e} "
                     f"{r['wall_s']:>8.2f} {fmt(r['time_to_2x_seq_final_s'], '18.3f')} {last['shots']:>9}")
    for name, c in result["claims"].items():
        verdict = {True: "TRUE", False: "FALSE", None: "n/a"}[c["holds"]]
        detail = ""
        if "per_k" in c:
            a, b, r = ("S(n)", "P(n)", "P/S") if name == "claim1" else ("S(n)", "P(kn)", "S/P")
            detail = "; ".join(f"k={i['k']}: n={i['n']:.0f} {a}={fmt(i[a], '.4f')} {b}={fmt(i[b], '.4f')} "
                               f"{r}={fmt(i[r], '.3f')}" for i in c["per_k"])
        else:
            detail = f"finals spread {c['spread']:.3f}x (tolerance {c['tolerance_factor']}x)"
        lines.append(f"{name} ({c['statement']}): {verdict}  [{detail}]")
    return lines
