"""The ``dcrad`` command.

Exit codes:

====  =======================================================
0     success
1     internal error (a bug: please report it with the traceback)
2     bad input: scene, settings or partition (one readable line)
130   interrupted twice (the first Ctrl-C stops cleanly and writes results)
====  =======================================================
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path
from types import SimpleNamespace

from dcrad.choices import Choice
from dcrad.config import BOUNDARY_MODES, DivideConfig, SolverConfig
from dcrad.division.placement import SUBSCENES_PER_WORKER
from dcrad.errors import DcradError
from dcrad.outputs.progress import error_text
from dcrad.settings import (
    add_divide_flags,
    add_flags,
    add_scene_flags,
    daylight_from_args,
    divide_from_args,
    from_args,
    scene_values,
)
from dcrad.solving.accuracy import resolve

__all__ = ["main"]

log = logging.getLogger("dcrad")


def _solver_args(p: argparse.ArgumentParser) -> None:
    add_flags(p, SolverConfig)
    add_scene_flags(p)
    p.add_argument("--workers", type=int, default=None,
                   help="local worker processes with an embedded coordinator (0: solve in this process; "
                        "default: 2 for scenes of 150k patches or more on 2+ CPUs, else 0)")
    add_divide_flags(p, "split into k subscenes (default: the coordinator chooses: a shared run of the whole "
                        "scene where the light is gathered, else two per worker; 1: no partition, no twins)")
    p.add_argument("--planes", default="", help="explicit partition planes, e.g. x=4.06,z=4.06 (each splits "
                                                "every cell it crosses; overrides --subscenes)")


def parse_planes(text: str) -> list[tuple[int, float]]:
    """``"x=4.06,z=3"`` -> [(0, 4.06), (2, 3.0)]; a bad item raises ConfigError naming it."""
    from dcrad.errors import ConfigError

    planes = []
    for item in filter(None, (t.strip() for t in text.split(","))):
        axis, _, value = item.partition("=")
        try:
            planes.append(("xyz".index(axis.strip().lower()), float(value)))
        except ValueError:
            raise ConfigError(f"--planes: '{item}' is not axis=offset with axis x, y or z") from None
    return planes


def _config(args) -> SolverConfig:
    return from_args(SolverConfig, args)


class Stopped(KeyboardInterrupt):
    """A stop before the solve started: there is nothing to write (``main``: exit 130)."""


class _Interrupt:
    """First Ctrl-C asks the solver to stop cleanly; the second one aborts.  ``before``: until
    ``running()`` is called (the scene is loaded and meshed, the solve starts), the first one ends
    the command at once with that phase named: there are no results to write yet."""

    def __init__(self, before: str = ""):
        self.requested = False
        self.before = before

    def running(self) -> None:
        self.before = ""

    def __call__(self, signum, frame):
        if self.before:
            self.requested = True
            raise Stopped(f"stopped {self.before}: nothing solved, no results written")
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        try:  # after SIGHUP the terminal may be gone
            print("\ndcrad: stopping after this batch and writing results (Ctrl-C again to abort)", file=sys.stderr)
        except OSError:
            pass

    def should_stop(self) -> bool:
        return self.requested


#: seconds between two looks at a stop request by the thread that tells the coordinator
STOP_POLL = 0.1

#: signals that stop a solve like Ctrl-C: `timeout`, `kill` and a closed terminal send the others
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def _catch(handler) -> dict:
    """Install ``handler`` for every STOP_SIGNALS; returns the previous handlers for ``_restore``."""
    return {sig: signal.signal(sig, handler) for sig in STOP_SIGNALS}


def _restore(previous: dict) -> None:
    for sig, old in previous.items():
        signal.signal(sig, old)


def cmd_solve(args) -> int:
    from coordinator.embedded import check_workers
    from dcrad.errors import ConfigError
    from dcrad.outputs.progress import ProgressBar
    from dcrad.outputs.render import check_image_size
    from dcrad.pipeline import resolve_scene, solve_to

    check_image_size(args.width, args.height)
    daylight = daylight_from_args(args)  # read (and refused) before the scene loads
    choice, loaded = None, None
    # caught from the start: a stop while the scene loads and meshes ends the command at once
    stop = _Interrupt(before="while the scene loaded and meshed")
    previous = _catch(stop)
    try:
        if args.workers is None:  # the default: divide only where it pays
            args.workers, choice, loaded = _auto_workers(args, Path(args.out), daylight)
    finally:
        _restore(previous)
    check_workers(args.workers)
    if args.subscenes < 0:
        raise ConfigError(f"--subscenes must be >= 1 (or 0: one per worker), not {args.subscenes}")
    config = _config(args)
    out = Path(args.out)
    if args.workers > 0:
        code = _solve_embedded(args, config, out, daylight)
        _note_choice(out, choice)
        return code
    rules = resolve(config)
    bar = ProgressBar(rules.tol, force=args.progress, accuracy=rules.accuracy)
    previous = _catch(stop)

    def on_progress(solver):
        bar.update(solver.residual(), solver.stats.rays, solver.elapsed(), solver.eta(), estimate=solver.estimate())

    try:
        with tempfile.TemporaryDirectory(prefix="dcrad-scene-") as tmp:
            # the scene the default's choice loaded (a built-in one written where it is written here)
            path = loaded[2] if loaded is not None else resolve_scene(
                args.scene, out / "scene" if not Path(args.scene).exists() else Path(tmp))
            planes = parse_planes(args.planes)
            k = max(args.subscenes, 2) if planes else max(args.subscenes, 1)
            divide = divide_from_args(args, k)
            report = solve_to(path, out, config, patch_size=args.patch_size, scale=args.scale,
                              on_progress=on_progress, should_stop=stop.should_stop,
                              width=args.width, height=args.height, divide=divide, planes=planes or None,
                              up=args.up, two_sided=args.two_sided, workplane=args.workplane,
                              loaded=(loaded[0], loaded[1], loaded[3]) if loaded is not None else None,
                              # a mesh handed on is lit by the luminaires already (``_auto_workers``)
                              luminaires_path=args.luminaires if loaded is None or loaded[3] is None else None,
                              daylight=daylight if loaded is None or loaded[3] is None else None,
                              on_meshed=stop.running)
    finally:
        _restore(previous)
    final = SimpleNamespace(**report["error"]) if report.get("error") else None
    bar.update(report["residual"], report["stats"]["rays"], report["stats"]["wall_seconds"], 0.0, final=True,
               estimate=final)
    _note_choice(out, choice)
    _summary(report, out)
    return 0


def _auto_workers(args, out: Path, daylight=None) -> tuple[int, Choice, tuple | None]:
    """--workers by default: from the scene's unknowns (meshed here, or estimated when too large to
    mesh) and the CPUs; and, when it chooses this process, (scene, load seconds, path, patches or
    None) for the solve to reuse (a
    built-in scene is written into ``out``/scene, where the solve writes it: the 3x3 office was
    written and loaded twice, 0.5-1.2 s more than ``--workers 0``)."""
    from dcrad.io.scene import load_scene
    from dcrad.meshing.mesh import estimate_elements
    from dcrad.pipeline import default_patch_size, light_sources, patch_limit, resolve_scene
    from dcrad.solving.strategy import gathers, local

    if args.planes or args.subscenes > 1:
        return 0, Choice("workers", "solved in this process (--workers 0 by default with --planes or "
                                    "--subscenes)"), None
    builtin = not Path(args.scene).exists()
    fresh = builtin and not (out / "scene").exists()
    with tempfile.TemporaryDirectory(prefix="dcrad-scene-") as tmp:
        path = resolve_scene(args.scene, out / "scene" if builtin else Path(tmp))
        t0 = time.perf_counter()
        scene = load_scene(path, scale=args.scale, up=args.up, two_sided=args.two_sided)
        seconds = time.perf_counter() - t0
    size = args.patch_size if args.patch_size and args.patch_size > 0 else default_patch_size(scene)
    tri = scene.vertices[scene.faces[scene.valid]]
    config = _config(args)
    n = estimate_elements(tri, size)
    patches = None
    if n <= patch_limit():
        # the unknowns, not the patches: a run's rays follow them (clusters share one B), and
        # only a run in this process settles its clusters (passes.settle); the mesh is handed on
        # the luminaires light it before meshing, so that the refinement follows their light too
        lit = light_sources(args.luminaires, daylight, args.scale)
        extra = tuple(lit(scene)) if lit is not None else ()
        patches = scene.patches(size, adapt=not (args.patch_size and args.patch_size > 0), sources=extra)
        n = patches.units
    strategy = local(n, os.cpu_count() or 1, gathers(config, n))
    workers, choice = strategy.workers, strategy.why
    if daylight is not None and workers > 0:
        # a daylit run shares its workers only when asked to (--workers N): it was measured in one process
        workers, choice = 0, Choice("workers", "solved in this process: daylight (--sky) runs here by default "
                                               "(--workers N shares it)")
    elif scene.tau is not None and workers > 0:
        # glass by default in one process, where it was measured (--workers N shares or divides it)
        workers, choice = 0, Choice("workers", "solved in this process: a scene with glass (ideal specular "
                                               "transmitters, optics.py) runs here by default (--workers N "
                                               "shares or divides it)")
    if workers > 0 and fresh:  # the workers' run writes its own copy; out/ keeps only what it wrote
        shutil.rmtree(out / "scene", ignore_errors=True)
    return workers, choice, (scene, seconds, path, patches) if workers == 0 else None


def _note_choice(out: Path, choice: Choice | None) -> None:
    """Add the default's choice of workers to report.json's ``choices``."""
    import json

    path = out / "report.json"
    if choice is None or not path.exists():
        return
    report = json.loads(path.read_text())
    report["choices"] = [choice.as_dict()] + list(report.get("choices", []))
    path.write_text(json.dumps(report, indent=1))


def ranged(kind, low: float, high: float | None = None, above: bool = False):
    """An argparse type: ``kind`` (int or float) of ``text``, finite and >= ``low`` (> with ``above``)
    and <= ``high``; else the flag's one-line error naming the range."""
    bound = f"{'>' if above else '>='} {low:g}" + (f" and <= {high:g}" if high is not None else "")

    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not {'an integer' if kind is int else 'a number'}") from None
        if not (math.isfinite(v) and (v > low if above else v >= low) and (high is None or v <= high)):
            raise argparse.ArgumentTypeError(f"{text}: must be {bound}")
        return v

    return parse


PORT = ranged(int, 0, 65535)


def _k_list(text: str) -> tuple[int, ...]:
    try:
        ks = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a comma-separated list of integers") from None
    if not ks or min(ks) < 1:
        raise argparse.ArgumentTypeError(f"'{text}': subscene counts must be integers >= 1")
    return ks


def cmd_compare(args) -> int:
    from dcrad.estimate.compare import compare, summary_lines, write_compare
    from dcrad.pipeline import resolve_scene

    out = Path(args.out)
    config = from_args(SolverConfig, args)
    path = resolve_scene(args.scene, out / "scene")
    result = compare(path, args.subscenes, config, mode=args.mode, reference=args.reference,
                     patch_size=args.patch_size or None, iterations=args.iterations)
    files = write_compare(result, out)
    ref = result["reference"]
    print(f"dcrad: {result['scene']['name']}, {result['scene']['patches']} patches; B*: {ref['source']}"
          f" (RMS {ref['rms_W_m2']:.4g} W/m^2)")
    for line in summary_lines(result):
        print(line)
    print(f"dcrad: wrote {', '.join(f.name for f in files.values())} in {out}")
    return 0


def _summary(report: dict, out: Path) -> None:
    st = report["stats"]
    print(
        f"dcrad: {report['scene']['patches']} patches, {st['rays']:,} rays, {st['shots']:,} shots in "
        f"{st['wall_seconds']:.2f} s ({report['rays_per_second'] / 1e6:.2f} Mrays/s); residual "
        f"{report['residual']:.2e}, stopped by {st['stopped_by']}; ledger closure {report['ledger']['closure']:.1e}"
    )
    err = report.get("error")
    if err:
        text = error_text(err["rms_refl"], err["noise_refl"], err["bias_refl"], report["settings"].get("accuracy", 0.0))
        reads = [f"{100 * err[key]:.2f}% {what}" for key, what in (("triangles_refl", "per input triangle"),
                                                                   ("elements_refl", "per element (pictures)"))
                 if err.get(key) is not None]
        per = f" ({', '.join(reads)})" if reads else ""
        print(f"dcrad: {text}{per}, {100 * (err['rms_norm'] or 0.0):.2f}% of RMS(B) "
              f"(estimated, {err['rms']:.3g} W/m^2)")
    from dcrad.transport.luminaires import summary_lines
    from dcrad.transport.punctual import summary_lines as light_lines

    for line in [*summary_lines(report.get("luminaires")), *light_lines(report.get("gltf_lights"))]:
        print(f"dcrad: {line}")
    print(f"dcrad: wrote {', '.join(report['outputs'].values())}, report.json in {out}")


def _solve_embedded(args, config: SolverConfig, out: Path, daylight=None) -> int:
    """`dcrad solve --workers N`: a coordinator and N workers on loopback, then submit/watch/fetch."""
    if args.planes:
        raise DcradError("--planes works in process only (--workers 0)")
    # caught from the start: a stop before the job runs ends the command at once (``_Interrupt``)
    stop = _Interrupt(before="while the workers started and the coordinator loaded and meshed the scene")
    previous = _catch(stop)
    try:
        return _run_embedded(args, config, out, stop, daylight)
    finally:
        _restore(previous)


def _run_embedded(args, config: SolverConfig, out: Path, stop: "_Interrupt", daylight=None) -> int:
    import json

    from coordinator import client
    from coordinator.embedded import LocalCluster
    from dcrad.errors import SolveError
    from dcrad.pipeline import resolve_scene

    with tempfile.TemporaryDirectory(prefix="dcrad-scene-") as tmp:
        from dcrad.io.scene import load_scene

        # the processes start (imports: about a second) while the scene is written (a built-in
        # one) and validated here; a bad scene fails naming the user's own file, and the
        # processes are stopped
        with LocalCluster(workers=args.workers, wait=False) as cluster:
            path = resolve_scene(args.scene, Path(tmp))
            if not path.is_relative_to(tmp):  # a built-in scene is checked by the coordinator alone
                load_scene(path, scale=args.scale, up=args.up, two_sided=args.two_sided)
            client.scene_paths(path)
            cluster.wait()
            print(f"dcrad: coordinator {cluster.address} with {args.workers} local workers", file=sys.stderr)
            solver = config.as_dict() | scene_values(args)
            divide = divide_from_args(args, args.subscenes or SUBSCENES_PER_WORKER * args.workers).as_dict()
            if not args.subscenes:  # unset: the coordinator chooses (a shared run where the light is gathered)
                divide["subscenes"] = None
            try:
                job = client.submit(cluster.address, path, solver, divide, (args.width, args.height),
                                    luminaires=args.luminaires, daylight=daylight)
            except client.grpc.RpcError as exc:
                raise DcradError(client.rpc_message(exc, cluster.address)) from None
            if cluster.web_url:
                print(f"dcrad: status page {cluster.web_url}/jobs/{job.job_id} (while this runs)", file=sys.stderr)
            bar = client.WatchBar(config.tol, force=args.progress)
            stop.running()
            watching = threading.Event()

            def send_cancel() -> None:
                # at once, not at the next progress message: a phase may send none for many seconds
                while not watching.wait(STOP_POLL):
                    if stop.requested:
                        client.cancel(cluster.address, job.job_id)
                        return

            threading.Thread(target=send_cancel, name="dcrad-stop", daemon=True).start()
            try:
                last = client.watch(cluster.address, job.job_id, bar)
            finally:
                watching.set()
                bar.close()
            if last is None or last.job.state not in ("done", "cancelled"):
                raise SolveError(f"job {job.job_id} {last.job.state if last else 'vanished'}: "
                                 f"{last.job.error if last else ''}")
            client.fetch(cluster.address, job.job_id, out)
    report = json.loads((out / "report.json").read_text())
    for w in report.get("warnings", []):
        log.warning(w)
    _summary(report, out)
    return 0


def cmd_scenes(args) -> int:
    import scenes

    if args.name:  # the same names as `dcrad solve`, parameters included (office:rows=3,cols=4)
        from dcrad.errors import ConfigError
        from dcrad.pipeline import resolve_scene

        name = args.name.partition(":")[0]
        if name not in scenes.names():
            raise ConfigError(f"unknown built-in scene '{name}'; known scenes: {', '.join(scenes.names())}")
        print(resolve_scene(args.name, Path(args.out)))
        return 0
    for name in scenes.names():
        print(f"{name:10s} {scenes.describe(name)}")
    return 0


def _announce(role: str, host: str):
    def ready(port: int) -> None:
        # one machine-readable line: tests and `dcrad solve` read the bound port from it
        print(f"dcrad {role} listening on {host}:{port}", flush=True)

    return ready


def cmd_coordinator(args) -> int:
    import asyncio

    from coordinator.embedded import die_with_parent
    from coordinator.server import serve

    die_with_parent()  # a child of `dcrad solve` ends with it

    def web_ready(url: str) -> None:
        # machine-readable too: LocalCluster reads the status page's address from it
        print(f"dcrad coordinator web on {url}", flush=True)

    web_port = args.web_port if args.web_port >= 0 else None
    asyncio.run(serve(port=args.port, host=args.host, root=args.data, max_upload=args.max_upload,
                      worker_wait=args.worker_wait, ready=_announce("coordinator", args.host),
                      web_port=web_port, web_host=args.web_host or args.host, web_ready=web_ready,
                      preview_interval=args.preview_interval))
    return 0


def cmd_worker(args) -> int:
    import asyncio

    from coordinator.embedded import die_with_parent
    from worker.server import serve

    die_with_parent()  # a child of `dcrad solve` ends with it
    asyncio.run(serve(port=args.port, host=args.host, coordinator=args.coordinator, advertise=args.advertise,
                      capacity=args.capacity, name=args.name, ready=_announce("worker", args.host)))
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="dcrad", description="Divide-and-conquer radiosity.")
    ap.add_argument("-v", "--verbose", action="store_true", help="log more")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("solve", help="solve a scene and write radiosity, meshes, previews and a report")
    p.add_argument("scene", help="an .obj/.gltf/.glb file, or a built-in scene: office, cornell, furnace, cie_room "
                                 "(parameters as office:rows=3,cols=4,seed=2)")
    p.add_argument("--out", default="out", help="output folder (default ./out)")
    p.add_argument("--width", type=int, default=640, help="preview width in pixels")
    p.add_argument("--height", type=int, default=480, help="preview height in pixels")
    p.add_argument("--progress", action="store_true", help="draw the progress bar even when stderr is not a terminal")
    _solver_args(p)
    p.set_defaults(func=cmd_solve)

    env = os.environ
    p = sub.add_parser("coordinator", help="run the gRPC coordinator service")
    p.add_argument("--host", default=env.get("DCRAD_HOST", "127.0.0.1"), help="address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=PORT, default=env.get("DCRAD_PORT", "50051"), help="gRPC port (0: any free)")
    p.add_argument("--data", default=env.get("DCRAD_DATA", "dcrad-coordinator"), help="folder for uploads and results")
    p.add_argument("--max-upload", type=ranged(int, 1), default=env.get("DCRAD_MAX_UPLOAD", str(512 * 1024 * 1024)),
                   help="largest scene upload in bytes, all files of a job together (default 536870912 = "
                        "512 MiB, or $DCRAD_MAX_UPLOAD); uploads are streamed to disk as they arrive")
    p.add_argument("--worker-wait", type=ranged(float, 0, above=True), default=60.0,
                   help="seconds a job waits for a first worker")
    p.add_argument("--web-port", type=ranged(int, -1, 65535), default=env.get("DCRAD_WEB_PORT", "8080"),
                   help="port of the web status pages (default 8080; 0: any free port; -1: off)")
    p.add_argument("--web-host", default=env.get("DCRAD_WEB_HOST"),
                   help="address the status pages bind (default: the same as --host)")
    p.add_argument("--preview-interval", type=ranged(float, 0), default=2.0,
                   help="seconds between preview images of a running job (at most one per barrier)")
    p.set_defaults(func=cmd_coordinator)

    p = sub.add_parser("worker", help="run a gRPC worker that registers with a coordinator")
    p.add_argument("--host", default=env.get("DCRAD_HOST", "127.0.0.1"), help="address to bind")
    p.add_argument("--port", type=PORT, default=env.get("DCRAD_WORKER_PORT", "0"), help="gRPC port (0: any free)")
    p.add_argument("--coordinator", default=env.get("DCRAD_COORDINATOR", "127.0.0.1:50051"),
                   help="coordinator address host:port")
    p.add_argument("--advertise", default=env.get("DCRAD_ADVERTISE"),
                   help="address the coordinator should use for this worker (default host:port)")
    p.add_argument("--capacity", type=ranged(int, 1), default=4, help="subscenes this worker takes at once")
    p.add_argument("--name", default="", help="a readable name")
    p.set_defaults(func=cmd_worker)

    from coordinator.client import add_client_commands

    add_client_commands(sub)

    p = sub.add_parser("scenes", help="list built-in scenes, or write one as OBJ/MTL")
    p.add_argument("name", nargs="?", help="built-in scene to write")
    p.add_argument("--out", default=".", help="folder to write it into")
    p.set_defaults(func=cmd_scenes)

    p = sub.add_parser("compare", help="RMS error against time and iterations: sequential vs k subscenes "
                                       "(the paper's Figure 3), as JSON, CSV, PNG and SVG")
    p.add_argument("scene", help="a scene file or a built-in scene (e.g. office:rows=1,cols=2)")
    p.add_argument("--subscenes", type=_k_list, default=(1, 2, 4, 8),
                   help="comma-separated subscene counts k (default 1,2,4,8; 1 is always included)")
    p.add_argument("--boundary", dest="mode", choices=BOUNDARY_MODES, default=DivideConfig().mode,
                   help="boundary mode of divided runs")
    add_flags(p, DivideConfig, only=("iterations",))
    p.add_argument("--out", default="compare", help="output folder (default ./compare)")
    p.add_argument("--reference", default=None,
                   help="radiosity.npz from 'dcrad solve' to use as B* (default: a converged sequential run "
                        "with 10x the rays per power)")
    add_flags(p, SolverConfig)
    p.add_argument("--patch-size", type=float, default=0.0,
                   help="element size in metres (default 0: automatic, mesh.py)")
    p.set_defaults(func=cmd_compare)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="dcrad: %(levelname)s: %(message)s")
    try:
        return args.func(args)
    except DcradError as exc:
        print(f"dcrad: error: {exc}", file=sys.stderr)
        return 2
    except Stopped as exc:
        print(f"dcrad: {exc}", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print("dcrad: aborted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
