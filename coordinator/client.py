"""Client side of the Coordinator service: the API and the ``dcrad`` job commands.

``submit`` uploads a scene with the files it references, ``watch`` follows a job
barrier by barrier, ``fetch`` downloads its results, ``cancel`` and ``jobs``
manage the queue.  The address comes from ``--coordinator``, else the
``DCRAD_COORDINATOR`` environment variable, else :data:`DEFAULT_ADDRESS`.
"""

from __future__ import annotations

import functools
import json
import math
import os
import signal
import sys
import tempfile
import threading
from pathlib import Path

import grpc

from dcrad.config import SolverConfig
from dcrad.errors import ConfigError, DcradError, SceneFormatError
from dcrad.io.gltf import gltf_files, gltf_header
from dcrad.io.objfile import inside_folder, mtllib_files, mtllib_name, read_mtl
from dcrad.outputs.progress import error_text, progress_fraction
from dcrad.pipeline import resolve_scene
from dcrad.settings import (
    add_divide_flags,
    add_flags,
    add_scene_flags,
    daylight_from_args,
    divide_from_args,
    from_args,
    scene_values,
)
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.v1 import dcrad_pb2_grpc as pb_grpc
from dcrad.wire import FileSink, path_chunks, safe_relpath

from .rpc import MAX_MESSAGE

__all__ = ["DEFAULT_ADDRESS", "channel", "scene_files", "scene_paths", "submit", "watch", "fetch", "cancel",
           "list_jobs", "rpc_message", "add_client_commands"]

DEFAULT_ADDRESS = "127.0.0.1:50051"
#: attempts per call on UNAVAILABLE (gRPC caps it at 5; < 2 disables retries)
RETRY_ATTEMPTS = 4
#: deadline of the short unary calls (Cancel, ListJobs), seconds
UNARY_TIMEOUT = 30.0
TERMINAL = ("done", "failed", "cancelled")


def resolve_address(address: str | None = None) -> str:
    return address or os.environ.get("DCRAD_COORDINATOR") or DEFAULT_ADDRESS


def channel(address: str, attempts: int | None = None) -> grpc.Channel:
    """An insecure channel retrying UNAVAILABLE with exponential backoff, 8 MB messages."""
    attempts = RETRY_ATTEMPTS if attempts is None else attempts
    method: dict[str, object] = {"name": [{"service": "dcrad.v1.Coordinator"}]}
    if attempts >= 2:
        method["retryPolicy"] = {"maxAttempts": int(attempts), "initialBackoff": "0.2s", "maxBackoff": "2s",
                                 "backoffMultiplier": 2, "retryableStatusCodes": ["UNAVAILABLE"]}
    options = [("grpc.service_config", json.dumps({"methodConfig": [method]})),
               ("grpc.enable_retries", 1 if attempts >= 2 else 0),
               ("grpc.max_send_message_length", MAX_MESSAGE),
               ("grpc.max_receive_message_length", MAX_MESSAGE)]
    return grpc.insecure_channel(address, options=options)


# -- scene files ---------------------------------------------------------------------------
def _obj_refs(lines, label: str, folder: str) -> list[str]:
    """The material files of an OBJ's mtllib lines (an iterable of lines, or the whole text),
    read as the loader reads them."""
    refs = []
    for no, raw in enumerate(lines.splitlines() if isinstance(lines, str) else lines, 1):
        name = mtllib_name(raw)
        if name:
            refs += mtllib_files(name, f"{label} line {no}", folder)
    return refs


def _texture_refs(mtllibs: list[str], folder: str) -> list[str]:
    """The map_Kd images of the material files that exist (a missing one is the loader's warning)."""
    refs = []
    for one in mtllibs:
        full = inside_folder(folder, one, one, "mtllib")
        if not os.path.isfile(full):
            continue
        for mat in read_mtl(full, one, folder, exact=False).values():
            refs += [name for key, name in mat.textures if key.lower() == "map_kd"
                     and os.path.isfile(inside_folder(folder, name, one, "texture"))]
    return refs


def scene_paths(path) -> dict[str, Path]:
    """{relative path: file}: the scene file first, then the files it references.

    The OBJ is scanned line by line for its mtllib lines: memory does not grow with the file.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in (".obj", ".gltf", ".glb"):
        raise SceneFormatError(f"unsupported scene format '{ext}' for {path}; use .obj, .gltf or .glb")
    folder = str(path.parent.resolve())
    try:
        if ext == ".obj":
            with open(path, encoding="utf-8", errors="replace", newline=None) as f:
                refs = _obj_refs(f, str(path), folder)
            refs += _texture_refs(refs, folder)
        elif ext == ".gltf":
            refs = gltf_files(gltf_header(str(path)), str(path))
        else:
            path.stat()
            refs = []  # a .glb carries its buffers
    except OSError as exc:
        raise SceneFormatError(f"cannot read scene file {path}: {exc.strerror or exc}") from None
    files = {path.name: path}
    for ref in refs:
        rel = safe_relpath(os.path.relpath(inside_folder(folder, ref, str(path), "file"), folder).replace(os.sep, "/"))
        if rel in files:
            continue
        if not (path.parent / rel).is_file():
            raise SceneFormatError(f"{path}: referenced file '{ref}' cannot be read: no such file")
        files[rel] = path.parent / rel
    return files


def scene_files(path) -> dict[str, bytes]:
    """{relative path: bytes} of ``scene_paths`` (reads every file: for small scenes and tests)."""
    try:
        return {rel: p.read_bytes() for rel, p in scene_paths(path).items()}
    except OSError as exc:
        raise SceneFormatError(f"{path}: a scene file cannot be read: {exc.strerror or exc}") from None


def luminaire_paths(schedule, folder: Path) -> tuple[str, dict[str, Path]]:
    """(the schedule's path in the upload, {relative path: file}): a luminaire schedule and the
    photometric files it names, uploaded under ``luminaires/``.  The files keep their own names
    (numbered when two differ) and the schedule is rewritten into ``folder`` to name them there;
    the coordinator checks the rest as ``dcrad solve`` does (luminaires.load_schedule).
    ConfigError naming the schedule for one that cannot be read or a file it names that is missing."""
    schedule = Path(schedule)
    try:
        data = json.loads(schedule.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{schedule}: no such luminaire schedule") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ConfigError(f"{schedule}: cannot be read as a JSON luminaire schedule ({exc})") from None
    entries = [data] if isinstance(data, dict) else data if isinstance(data, list) else []
    rel = f"luminaires/{safe_relpath(schedule.name)}"
    files: dict[str, Path] = {}
    names: dict[Path, str] = {}
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict) or not isinstance(entry.get("file"), str) or not entry["file"]:
            continue  # the coordinator names what is wrong with it
        src = (schedule.parent / entry["file"]).resolve()
        if not src.is_file():
            raise ConfigError(f"{schedule}: luminaire {i + 1}: no such photometric file '{entry['file']}'")
        if src not in names:
            taken = f"luminaires/{src.name}" in files or f"luminaires/{src.name}" == rel
            name = safe_relpath(f"{len(names)}_{src.name}" if taken else src.name)
            names[src] = name
            files[f"luminaires/{name}"] = src
        entry["file"] = names[src]
    rewritten = Path(folder) / "schedule.json"
    rewritten.write_text(json.dumps(data))
    return rel, {rel: rewritten, **files}


# -- calls ---------------------------------------------------------------------------------
def _requests(scene: str, files: dict, solver: dict, divide: dict, preview: tuple[int, int] = (0, 0),
              luminaires: str = "", daylight: str = ""):
    yield pb.SubmitRequest(spec=pb.JobSpec(scene=scene, solver=pb.SolverSettings(**solver),
                                           divide=pb.DivideSettings(**divide),
                                           preview_width=preview[0], preview_height=preview[1],
                                           luminaires=luminaires, daylight=daylight))
    for rel, file in files.items():  # streamed from disk, one chunk at a time
        for chunk in path_chunks(file, rel):
            yield pb.SubmitRequest(file=chunk)


def submit(address: str, path, solver: dict | None = None, divide: dict | None = None,
           preview: tuple[int, int] = (0, 0), luminaires=None, daylight=None) -> pb.JobSummary:
    """Upload the scene at ``path`` and its files with the settings; the new job's summary.

    preview: (width, height) of the preview images in pixels; 0 means the default.
    luminaires: a luminaire schedule (JSON) lighting the scene too, uploaded with its files.
    daylight: a sky.DaylightSpec (``--sky``) lighting it from outside.
    """
    files = scene_paths(path)
    solver = {k: v for k, v in (solver or {}).items() if v is not None}
    divide = {k: v for k, v in (divide or {}).items() if v is not None}
    with tempfile.TemporaryDirectory(prefix="dcrad-submit-") as tmp:
        schedule = ""
        if luminaires is not None:
            schedule, extra = luminaire_paths(luminaires, Path(tmp))
            clash = sorted(set(extra) & set(files))
            if clash:
                raise ConfigError(f"{path}: the scene's own files include {clash[0]}, where the luminaires go")
            files |= extra
        with channel(address) as ch:
            return pb_grpc.CoordinatorStub(ch).Submit(_requests(next(iter(files)), files, solver, divide, preview,
                                                                schedule, "" if daylight is None else
                                                                daylight.to_json()))


def watch(address: str, job_id: str, on_progress=None) -> pb.Progress | None:
    """Follow the job until its Watch stream ends; the last Progress (None if none came)."""
    last = None
    with channel(address) as ch:
        stream = pb_grpc.CoordinatorStub(ch).Watch(pb.JobRef(job_id=job_id))
        try:
            for last in stream:
                if on_progress is not None:
                    on_progress(last)
        except BaseException:
            stream.cancel()
            raise
    return last


def fetch(address: str, job_id: str, out_dir) -> list[Path]:
    """Download the job's result files under ``out_dir`` (written as they arrive); the paths written."""
    out, totals = Path(out_dir), {}
    sink = FileSink(out, max_bytes=1 << 40)
    try:
        with channel(address) as ch:
            for chunk in pb_grpc.CoordinatorStub(ch).Fetch(pb.JobRef(job_id=job_id)):
                sink.add(chunk)
                totals[safe_relpath(chunk.path)] = chunk.total_bytes
    finally:
        sink.close()
    for rel, size in sink.files.items():
        if size != totals[rel]:
            raise DcradError(f"fetch of job '{job_id}': {rel} arrived with {size} of {totals[rel]} bytes")
    return [out.joinpath(*rel.split("/")) for rel in sink.files]


def cancel(address: str, job_id: str) -> pb.JobSummary:
    with channel(address) as ch:
        return pb_grpc.CoordinatorStub(ch).Cancel(pb.JobRef(job_id=job_id), timeout=UNARY_TIMEOUT)


def list_jobs(address: str) -> list[pb.JobSummary]:
    with channel(address) as ch:
        return list(pb_grpc.CoordinatorStub(ch).ListJobs(pb.ListJobsRequest(), timeout=UNARY_TIMEOUT).jobs)


def rpc_message(exc: grpc.RpcError, address: str, job_id: str | None = None) -> str:
    """One readable line for a failed call."""
    code = exc.code() if hasattr(exc, "code") else None
    details = ((exc.details() if hasattr(exc, "details") else "") or "").strip().splitlines()
    details = details[0] if details else ""
    if code == grpc.StatusCode.UNAVAILABLE:
        return f"cannot reach coordinator at {address}"
    if code == grpc.StatusCode.DEADLINE_EXCEEDED:
        return f"coordinator at {address} did not answer in time"
    if code == grpc.StatusCode.NOT_FOUND:
        if job_id and job_id not in details:
            return f"job '{job_id}' not found" + (f" ({details})" if details else "")
        return details or "not found"
    if code == grpc.StatusCode.UNIMPLEMENTED:
        return f"{address} does not serve the dcrad coordinator API"
    name = code.name.lower().replace("_", " ") if code is not None else "call failed"
    return details or name


# -- command line --------------------------------------------------------------------------
def _handled(fn):
    """Turn gRPC and dcrad errors into one line on stderr and exit code 2."""

    @functools.wraps(fn)
    def run(args) -> int:
        try:
            return fn(args)
        except grpc.RpcError as exc:
            msg = rpc_message(exc, resolve_address(args.coordinator), getattr(args, "job", None))
        except DcradError as exc:
            msg = str(exc)
        print(f"dcrad: error: {msg}", file=sys.stderr)
        return 2

    return run


class WatchBar:
    """``[####----] 40% barrier 3 | residual 3.1e-02 -> 1.0e-02 | 2.30 Mrays/s | 00:12 | ETA 00:18``."""

    def __init__(self, tol: float, stream=None, force: bool = False, width: int = 24):
        self.tol, self.width = max(tol, 1e-300), width
        self.stream = stream or sys.stderr
        self.enabled = force or getattr(self.stream, "isatty", lambda: False)()
        self.prev: tuple[float, int, float] | None = None  # (elapsed, rays, residual) of the previous Progress
        self.first_error: float | None = None  # the first estimated error seen (the bar's start)
        self.drawn = False

    def line(self, p: pb.Progress) -> str:
        r, t = p.ledger.residual if p.HasField("ledger") else p.job.residual, p.job.elapsed_s
        rate, eta = 0.0, math.inf
        if self.prev is not None and t > self.prev[0]:
            dt = t - self.prev[0]
            rate = max(0, p.rays - self.prev[1]) / dt
            if 0 < r < self.prev[2]:
                eta = max(0.0, math.log(r / self.tol) / (math.log(self.prev[2] / r) / dt))
        self.prev = (t, p.rays, r)
        if p.HasField("error") and p.error.rms_refl > 0:
            # the job's estimated error (noise + bias) towards its accuracy target
            e = p.error
            if self.first_error is None:
                self.first_error = e.rms_refl
            frac = progress_fraction(r, self.tol, e.rms_refl, p.accuracy, self.first_error)
            what = f"{error_text(e.rms_refl, e.noise_refl, e.bias_refl, p.accuracy)} | residual {r:.2e}"
            if p.accuracy > 0:
                eta = math.inf
        else:
            frac = progress_fraction(r, self.tol)
            what = f"residual {r:.2e} -> {self.tol:.1e}"
        done = int(round(frac * self.width))
        return (f"[{'#' * done}{'-' * (self.width - done)}] {100 * frac:3.0f}% barrier {p.barrier} | "
                f"{what} | {rate / 1e6:.2f} Mrays/s | {_hms(t)} | ETA {_hms(eta)}")

    def __call__(self, p: pb.Progress) -> None:
        text = self.line(p)
        if self.enabled:
            self.stream.write("\r" + text)
            self.stream.flush()
            self.drawn = True

    def close(self) -> None:
        if self.drawn:
            self.stream.write("\n")
            self.stream.flush()
            self.drawn = False


def _hms(s: float) -> str:
    if not math.isfinite(s):
        return "--:--"
    s = int(round(s))
    return f"{s // 60:02d}:{s % 60:02d}" if s < 3600 else f"{s // 3600}h{(s % 3600) // 60:02d}"


def _follow(address: str, job_id: str, tol: float, force: bool) -> int:
    """Watch with a bar; print the final line; 0 when done, 1 otherwise, 130 on Ctrl-C."""
    bar = WatchBar(tol, force=force)
    # Ctrl-C stops watching, as in `dcrad solve`, even when started with SIGINT ignored
    main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, signal.default_int_handler) if main else None
    try:
        last = watch(address, job_id, bar)
    except KeyboardInterrupt:
        bar.close()
        print(f"dcrad: stopped watching job {job_id}; it keeps running on the coordinator", file=sys.stderr)
        return 130
    finally:
        if main:
            signal.signal(signal.SIGINT, previous)
        bar.close()
    if last is None:
        print(f"dcrad: error: the coordinator sent no progress for job {job_id}", file=sys.stderr)
        return 1
    job = last.job
    print(f"dcrad: job {job.job_id or job_id} {job.state}: residual {last.ledger.residual:.2e}, ledger closure "
          f"{last.ledger.closure:.1e}, {last.barrier} barriers, {last.rays:,} rays in {job.elapsed_s:.1f} s")
    if job.state == "done":
        return 0
    reason = job.error or ("cancelled" if job.state == "cancelled" else f"watch ended while it is {job.state}")
    print(f"dcrad: job {job.job_id or job_id} {job.state}: {reason}", file=sys.stderr)
    return 1


@_handled
def cmd_submit(args) -> int:
    address = resolve_address(args.coordinator)
    daylight = daylight_from_args(args)  # read first: a bad daylight flag is named as such
    solver = from_args(SolverConfig, args).as_dict() | scene_values(args)
    # subscenes 0 travels as 0: the coordinator makes one per registered worker
    divide = divide_from_args(args, max(args.subscenes, 1)).as_dict() | {"subscenes": args.subscenes}
    with tempfile.TemporaryDirectory(prefix="dcrad-scene-") as tmp:
        job = submit(address, resolve_scene(args.scene, Path(tmp)), solver, divide, luminaires=args.luminaires,
                     daylight=daylight)
    print(job.job_id, flush=True)
    if not args.wait:
        return 0
    code = _follow(address, job.job_id, args.tol, args.progress)
    if code != 0:
        return code
    out = Path(args.out) if args.out else Path("out") / job.job_id
    files = fetch(address, job.job_id, out)
    print(f"dcrad: wrote {', '.join(f.name for f in files)} in {out}")
    return 0


@_handled
def cmd_watch(args) -> int:
    return _follow(resolve_address(args.coordinator), args.job, args.tol, args.progress)


@_handled
def cmd_fetch(args) -> int:
    out = Path(args.out) if args.out else Path("out") / args.job
    files = fetch(resolve_address(args.coordinator), args.job, out)
    print(f"dcrad: wrote {', '.join(f.name for f in files) or 'no files'} in {out}")
    return 0


@_handled
def cmd_cancel(args) -> int:
    job = cancel(resolve_address(args.coordinator), args.job)
    if job.state in TERMINAL:
        print(f"dcrad: job {job.job_id or args.job} had already ended ({job.state}); nothing to cancel")
    else:
        print(f"dcrad: job {job.job_id or args.job}: cancel requested; its workers stop after the batch in flight "
              f"and it keeps its results so far (`dcrad watch` follows it to the end)")
    return 0


@_handled
def cmd_jobs(args) -> int:
    jobs = list_jobs(resolve_address(args.coordinator))
    rows = [("ID", "STATE", "SCENE", "SUBSCENES", "WORKERS", "ELAPSED", "RESIDUAL")]
    # "-": no worker holds it yet (queued, or being prepared), rather than a misleading 0
    rows += [(j.job_id, j.state, j.scene, str(j.subscenes or "-"), str(len(j.workers) or "-"), f"{j.elapsed_s:.1f}s",
              f"{j.residual:.2e}") for j in jobs]
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for r in rows:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip())
    return 0


def add_client_commands(subparsers) -> None:
    """Add submit, watch, fetch, cancel and jobs to the ``dcrad`` subcommands."""
    d = SolverConfig()

    def command(name, func, help):
        p = subparsers.add_parser(name, help=help)
        p.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                       help=f"coordinator address (default $DCRAD_COORDINATOR or {DEFAULT_ADDRESS})")
        p.set_defaults(func=func)
        return p

    def progress_flag(p):
        p.add_argument("--progress", action="store_true",
                       help="draw the progress bar even when stderr is not a terminal")

    p = command("submit", cmd_submit, "upload a scene to the coordinator as a job; prints the job id")
    p.add_argument("scene", help="an .obj/.gltf/.glb file (with its .mtl, buffers, images) or a built-in scene")
    add_divide_flags(p, "k subscenes (default 0: one per registered worker)")
    add_flags(p, SolverConfig)
    add_scene_flags(p)
    p.add_argument("--wait", action="store_true", help="watch the job and fetch its results when done")
    p.add_argument("--out", default=None, help="with --wait: results folder (default ./out/<job id>)")
    progress_flag(p)

    p = command("watch", cmd_watch, "follow a job's progress until it ends")
    p.description = ("Follow a job's progress until it ends. Exit code: 0 when the job is done; 1 when it "
                     "failed or was cancelled (a cancelled job keeps its results: `dcrad fetch` them); 2 for "
                     "an unknown job or an unreachable coordinator; 130 on Ctrl-C (the job keeps running).")
    p.add_argument("job", help="job id")
    p.add_argument("--tol", type=float, default=d.tol, help=f"tolerance the bar counts towards (default {d.tol})")
    progress_flag(p)

    p = command("fetch", cmd_fetch, "download a finished job's result files")
    p.add_argument("job", help="job id")
    p.add_argument("--out", default=None, help="output folder (default ./out/<job id>)")

    p = command("cancel", cmd_cancel, "cancel a job")
    p.add_argument("job", help="job id")

    command("jobs", cmd_jobs, "list the coordinator's jobs")
