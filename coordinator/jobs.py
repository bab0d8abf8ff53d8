"""Jobs: validate a scene, choose its strategy, run it on workers, write results.

Each job runs in a thread the strategy objects ``dcrad solve`` runs in process
(``dcrad.runs``): ``Shared`` through ``RemoteShares``, or ``Divided`` on
``WorkersBackend`` (``RemoteSubscene`` handles); this module wires them to the
service.  Progress after every barrier or phase is kept on the job and pushed to
watchers on the event loop.

For the web status page (``coordinator.web``) the job thread also keeps, at
barriers, a small preview image and the assembled radiosity at geometrically
spaced times, from which the RMS error against the final solution is measured
when the run ends (``coordinator.display``).
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import shutil
import threading
import time
import traceback
import uuid
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dcrad.choices import Choice
from dcrad.config import SolverConfig, unused_divide_note
from dcrad.division.divide import DivideConfig
from dcrad.division.placement import check_subscenes
from dcrad.errors import DcradError
from dcrad.outputs import render
from dcrad.outputs.report import residual_estimate
from dcrad.pipeline import finish_run, light_sources, output_views, prepare, scene_settings
from dcrad.runs import Divided, RunHooks, Shared
from dcrad.settings import from_pb
from dcrad.solving.accuracy import resolve
from dcrad.solving.strategy import Strategy, on_workers
from dcrad.transport.sky import DaylightSpec
from dcrad.transport.source_wire import sources_table
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.wire import estimate_to_pb, ledger_to_pb

from .ahead import ViewsAhead
from .display import BarrierDisplay, ErrorCurve, LivePreview, MemoryLog, background
from .divided import WorkersBackend
from .remote import NoWorkers, WorkerPool
from .shared import Cancelled, RemoteShares
from .store import JobRecord, JobStore, Resume, StoredPreview

log = logging.getLogger("dcrad.coordinator")

TERMINAL = {"done", "failed", "cancelled"}
#: s a job resumed after a coordinator restart waits for a first worker
RESUME_WAIT = 3600.0
STATES = ("queued", "running", "done", "failed", "cancelled")


@dataclass
class Job:
    id: str
    spec: pb.JobSpec
    root: Path  #: job folder: scene/ (upload) and out/ (results)
    state: str = "queued"
    error: str = ""
    created: float = field(default_factory=time.time)
    started: float = 0.0
    finished: float = 0.0
    subscenes: int = 0
    residual: float = 1.0
    workers: list = field(default_factory=list)
    updates: list = field(default_factory=list)  #: pb.Progress per barrier
    cancel: threading.Event = field(default_factory=threading.Event)
    report: dict | None = None
    preview: LivePreview | StoredPreview | None = None  #: StoredPreview: an ended job, after a restart
    curve: ErrorCurve = field(default_factory=ErrorCurve)
    divide: dict | None = None  #: the DivideConfig it runs with (kept in the record, for a resume)
    resume: Resume | None = None  #: checkpoints to resume from, after a coordinator restart
    #: (scene, patches, patch size, timings) from the upload's validation, for the job's first run
    prepared: tuple | None = field(default=None, repr=False)
    ahead: ViewsAhead | None = field(default=None, repr=False)  #: the outputs' views' process (ahead.py)
    _waiters: list = field(default_factory=list)  #: (loop, asyncio.Event) of watchers
    #: callables run (in a thread of their own) when the job is cancelled: the running solve's
    #: interrupts, so a cancel does not wait for the barrier in flight
    on_cancel: list = field(default_factory=list, repr=False)

    def request_cancel(self) -> None:
        """Cancel the job: it stops within a batch per subscene, keeping what it has."""
        self.cancel.set()
        hooks = list(self.on_cancel)
        if hooks:
            threading.Thread(target=lambda: [f() for f in hooks], name=f"cancel-{self.id}", daemon=True).start()

    def summary(self) -> pb.JobSummary:
        end = self.finished or (time.time() if self.started else 0.0)
        return pb.JobSummary(job_id=self.id, state=self.state, scene=self.spec.scene, subscenes=self.subscenes,
                             elapsed_s=(end - self.started) if self.started else 0.0, residual=self.residual,
                             workers=list(self.workers), error=self.error)

    def notify(self) -> None:
        for loop, ev in list(self._waiters):
            loop.call_soon_threadsafe(ev.set)

    async def changes(self):
        """Yield every progress message, old and new, until the job ends."""
        loop = asyncio.get_running_loop()
        seen = 0
        while True:
            ev = asyncio.Event()
            self._waiters.append((loop, ev))
            try:
                while seen < len(self.updates):
                    seen += 1
                    yield self.updates[seen - 1]
                if self.state in TERMINAL:
                    return
                await ev.wait()
            finally:
                self._waiters.remove((loop, ev))


def _record_fields(obj: Job | JobRecord) -> dict:
    """The ``JobRecord`` fields of a job or a record (a Job holds every one of them)."""
    return {f.name: getattr(obj, f.name) for f in dataclasses.fields(JobRecord)}


def solver_config(s: pb.SolverSettings) -> SolverConfig:
    """The job's SolverConfig: every field the client set, defaults for the rest (``dcrad.settings``)."""
    return from_pb(SolverConfig, s)


class JobManager:
    """All jobs of a coordinator; jobs run in threads."""

    def __init__(self, root: Path, pool: WorkerPool, worker_wait: float = 60.0, rpc_timeout: float = 300.0,
                 preview_interval: float = 2.0, preview_size: tuple[int, int] = (320, 240)):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.pool = pool
        self.jobs: dict[str, Job] = {}
        self.worker_wait = worker_wait
        self.rpc_timeout = rpc_timeout
        self.preview_interval, self.preview_size = preview_interval, preview_size
        #: counters over all jobs, updated at every barrier (for /metrics)
        self.metrics = {"barriers": 0, "rays": 0, "bytes_relayed": 0, "previews": 0}
        self._metrics_lock = threading.Lock()
        self.store = JobStore(self.root / "jobs")
        shutil.rmtree(self.root / "incoming", ignore_errors=True)  # uploads a crash cut short
        self._reload()

    def count(self, **deltas) -> None:
        with self._metrics_lock:
            for k, v in deltas.items():
                self.metrics[k] += v

    def counters(self) -> dict:
        """A consistent copy of the metrics counters."""
        with self._metrics_lock:
            return dict(self.metrics)

    def get(self, job_id: str) -> Job | None:
        return self.jobs.get(job_id)

    # == durability (coordinator.store) ============================================
    def _save(self, job: Job) -> None:
        """Write the job's record (atomically); a failing disk is logged, never fatal."""
        rec = JobRecord(**_record_fields(job))
        try:
            self.store.save(rec)
        except OSError as exc:
            log.warning("job %s: cannot write its record (%s); it will not survive a restart", job.id, exc)

    @staticmethod
    def _resume_handles(job: Job, handles: list) -> Resume | None:
        """Give each handle its checkpoint from disk; None (start over) if they do not match."""
        resume, job.resume = job.resume, None
        if resume is None:
            return None
        if sorted(resume.cells) != sorted(h.cell for h in handles):
            log.warning("job %s: checkpoints on disk are for cells %s, the job has %s; it starts over",
                        job.id, sorted(resume.cells), sorted(h.cell for h in handles))
            return None
        for h in handles:
            h.resume_from(resume.cells[h.cell], resume.barrier)
        log.warning("job %s resumes from barrier %d (%.1f s in) after a coordinator restart",
                 job.id, resume.barrier, resume.elapsed)
        return resume

    def _reload(self) -> None:
        """Every job under the data folder: ended ones are listed and fetchable; the others
        resume from their last checkpointed barrier (or start over) once workers register."""
        for rec in self.store.load_all():
            job = Job(root=self.store.folder(rec.id), **_record_fields(rec))
            self.jobs[job.id] = job
            if rec.state in TERMINAL:
                report = job.root / "out" / "report.json"
                try:
                    job.report = json.loads(report.read_text()) if report.exists() else None
                except (OSError, ValueError) as exc:
                    log.warning("job %s: its report %s is unreadable (%s)", job.id, report, exc)
                measured = ((job.report or {}).get("error_curve") or {}).get("measured")
                if measured:
                    job.curve.measured = [tuple(m) for m in measured["points"]]
                    job.curve.label = measured.get("label", "")
                barriers = int(((job.report or {}).get("divided") or {}).get("barriers", 0) or 0)
                job.preview = StoredPreview.load(job.root / "live" / "preview-live.png", barriers)
                closure = float(((job.report or {}).get("ledger") or {}).get("closure", 0.0))
                job.updates.append(pb.Progress(job=job.summary(),
                                               ledger=pb.Ledger(residual=job.residual, closure=closure)))
                continue
            job.state, job.resume = "queued", self.store.resume(job.id)
            if job.resume is None:
                job.divide = None  # nothing to resume: cut afresh, for the workers there are now
            log.info("job %s (%s) was %s when the coordinator stopped: %s", job.id, rec.spec.scene, rec.state,
                     f"it resumes from barrier {job.resume.barrier}" if job.resume else "it starts over")
            self.start(job)

    # == submit ===================================================================
    def create(self, spec: pb.JobSpec, files: dict[str, bytes] | Path) -> Job:
        """Store the upload and validate the scene; raises DcradError for a bad scene.

        files: {relative path: bytes}, or a folder the upload was streamed into (moved, not copied).
        """
        job = Job(id=uuid.uuid4().hex[:12], spec=spec, root=self.root / "jobs")
        job.root = self.root / "jobs" / job.id
        scene_dir = job.root / "scene"
        if isinstance(files, Path):
            scene_dir.parent.mkdir(parents=True, exist_ok=True)
            shutil.move(str(files), str(scene_dir))
            files = {p.relative_to(scene_dir).as_posix(): b"" for p in scene_dir.rglob("*") if p.is_file()}
        else:
            for rel, data in files.items():
                dest = scene_dir / rel
                dest.parent.mkdir(parents=True, exist_ok=True)
                dest.write_bytes(bytes(data))
        if spec.scene not in files:
            shutil.rmtree(job.root, ignore_errors=True)
            raise DcradError(f"the upload has no file '{spec.scene}' (the scene named in the job)")
        try:
            render.check_image_size(spec.preview_width or 640, spec.preview_height or 480)
            t0 = time.perf_counter()
            phases: dict[str, float] = {}
            if spec.luminaires and spec.luminaires not in files:
                raise DcradError(f"the upload has no file '{spec.luminaires}' (the luminaire schedule named in "
                                 f"the job)")
            scene, patches, size = self._prepare(spec, scene_dir, phases)
            sources_table(patches.sources)  # every light source can travel to the workers
            resolve(solver_config(spec.solver), len(patches))  # an accuracy beyond reach is refused now
            check_subscenes(self._divide(spec, 1).subscenes, len(patches))
            # kept for the job's run (meshing a scene twice cost 0.4 s at 201k patches)
            job.prepared = (scene, patches, size, {"load_and_mesh_s": time.perf_counter() - t0, **phases})
        except DcradError as exc:
            shutil.rmtree(job.root, ignore_errors=True)
            # name the file as the user uploaded it, not by the coordinator's folder
            raise type(exc)(str(exc).replace(f"{scene_dir}/", "").replace(str(scene_dir), ".")) from None
        self.jobs[job.id] = job
        self._save(job)
        return job

    @staticmethod
    def _prepare(spec: pb.JobSpec, scene_dir: Path, phases: dict):
        """(scene, patches, element size) of the job's upload: loaded, validated and meshed, lit by
        its luminaire schedule and its sky too when it has them (pipeline.light_sources, as `dcrad solve`)."""
        scale = spec.solver.scale or 1.0
        sources = light_sources(scene_dir / spec.luminaires if spec.luminaires else None,
                                DaylightSpec.from_json(spec.daylight) if spec.daylight else None, scale)
        return prepare(scene_dir / spec.scene, spec.solver.patch_size or None, scale, spec.solver.up or None,
                       spec.solver.two_sided, timings=phases, workplane=spec.solver.workplane, sources=sources)

    def start(self, job: Job) -> None:
        threading.Thread(target=self._run, args=(job,), name=f"job-{job.id}", daemon=True).start()

    @staticmethod
    def _divide(spec: pb.JobSpec, workers: int) -> DivideConfig:
        """The job's DivideConfig; subscenes unset or 0: ``workers`` (the caller's count)."""
        return from_pb(DivideConfig, spec.divide, subscenes=spec.divide.subscenes or max(1, workers))

    # == run ======================================================================
    def _run(self, job: Job) -> None:
        try:
            self._solve(job)
        except DcradError as exc:
            job.state, job.error = "failed", str(exc)
            log.warning("job %s failed: %s", job.id, exc)
        except Exception as exc:  # a bug: keep the coordinator alive, report it
            job.state, job.error = "failed", f"internal error: {exc}"
            log.error("job %s crashed:\n%s", job.id, traceback.format_exc())
        finally:
            job.finished = time.time()
            self._save(job)
            self.store.drop_checkpoints(job.id)  # ended: the results are in out/
            job.curve.clear()  # a failed job frees its snapshots too
            if job.preview is not None:
                job.preview.close()
            if job.ahead is not None:  # done by now, unless the job failed or was cancelled
                job.ahead.close()
                job.ahead = None
            # one last message carrying the final state, so every watcher sees the end
            final = pb.Progress()
            if job.updates:
                final.CopyFrom(job.updates[-1])
            final.job.CopyFrom(job.summary())
            job.updates.append(final)
            job.notify()

    def _solve(self, job: Job) -> None:
        spec = job.spec
        config = solver_config(spec.solver)
        if job.prepared is not None:  # validated at the upload, moments ago
            scene, patches, size, timings = job.prepared
            job.prepared = None
        else:
            t0 = time.perf_counter()
            phases: dict[str, float] = {}
            scene, patches, size = self._prepare(spec, job.root / "scene", phases)
            timings = {"load_and_mesh_s": time.perf_counter() - t0, **phases}
        mem = MemoryLog(job.id)
        mem("load and mesh")
        # a job resumed after a restart waits longer: its workers may come back after the coordinator
        wait = self.worker_wait if job.resume is None else max(self.worker_wait, RESUME_WAIT)
        live = self.pool.wait_for(1, wait)
        if live == 0:
            raise NoWorkers(f"no worker registered within {wait:.0f} s")
        receivers = int(np.count_nonzero(patches.rho.any(axis=1)))
        strategy = on_workers(config, receivers, len(patches), live, spec.divide.subscenes,
                              resumed=job.resume is not None)
        if strategy.kind == "shared":
            if self._solve_shared(job, scene, patches, size, config, timings, mem, strategy.why):
                return
            strategy = on_workers(config, receivers, len(patches), live, spec.divide.subscenes, exact_lights=False)
        self._solve_divided(job, scene, patches, size, config, timings, mem, strategy)

    def _solve_divided(self, job: Job, scene, patches, size: float, config: SolverConfig, timings: dict,
                       mem: MemoryLog, strategy: Strategy) -> None:
        """The job divided into subscenes on the workers (``runs.Divided`` on ``WorkersBackend``)."""
        spec = job.spec
        divide = self._divide(spec, strategy.subscenes)
        divide = DivideConfig(**job.divide) if job.resume is not None and job.divide else divide
        job.divide = dataclasses.asdict(divide)  # a resumed job cuts the same
        # at nice 19 it takes the core the partition leaves idle, and little from the workers: started
        # after the loading on the workers it had to finish after the solve (the 20x20 office's
        # outputs waited 2.1 s for it)
        views = self._views_ahead(job, scene, patches)
        backend = WorkersBackend(self, job, scene, patches, views, mem, config)
        divided = Divided(divide, backend)
        backend.assemble = lambda values: divided.assemble(values)
        books = divided.run(patches, config, RunHooks(should_stop=job.cancel.is_set, on_barrier=backend.on_barrier),
                            timings)
        run = divided.run_state
        mem("assembly")
        shown = job.preview
        assert isinstance(shown, LivePreview)  # WorkersBackend.open made it
        shown.close()  # its view goes before the outputs; the final state's preview is theirs
        job.curve.measure(patches.radiosity, patches.area, self._measured_label(run, config), run.barriers)
        books.divided = (books.divided or {}) | backend.service_figures()
        books.choices.insert(0, strategy.why)
        if backend.resume is not None:
            books.choices.add("resumed", f"resumed from barrier {backend.resume.barrier} after a coordinator "
                                         f"restart (checkpoints on disk)")
        books.divided["coordinator_rss_mb"] = dict(mem.phases)
        self._write_results(job, scene, size, books, views, {}, shown, run.barriers, mem)
        job.residual = run.ledger.residual()
        job.state = "cancelled" if run.stopped_by == "stopped" else "done"

    def _solve_shared(self, job: Job, scene, patches, size: float, config: SolverConfig, timings: dict,
                      mem: MemoryLog, why: Choice) -> bool:
        """The job as a shared run (dcrad.solving.share): every live worker holds the whole scene, the
        direct gather is split by receivers, each worker runs a replica, the replicas are averaged.
        False (nothing done) when the lights make no exact form factors: the job divides instead."""
        spec = job.spec
        t0 = time.perf_counter()
        k = len(self.pool.live())
        shares = RemoteShares(job.id, patches, config, self.pool, self.rpc_timeout)
        accuracy = resolve(config).accuracy
        job.subscenes = 1
        job.state, job.started = "running", time.time()
        self._save(job)
        timings["setup_s"] = time.perf_counter() - t0
        views = self._views_ahead(job, scene, patches)

        phases: list[str] = []
        # previews and the error curve beside the workers, as a divided job's (BarrierDisplay)
        job.preview = LivePreview(scene, patches, job.root / "live", self.preview_size, self.preview_interval,
                                  views)
        job.curve.folder = job.root / "curve"
        display = BarrierDisplay(lambda b: b, job.curve, job.preview, self.count, shares.quiet)

        def on_phase(name: str, elapsed: float, rays: int, est=None) -> None:
            """Progress after each phase (direct, shoot, each gather round): the status page's barriers."""
            phases.append(name)
            if name != "direct":  # the table holds the phase's B (the direct phase leaves it at E)
                display.offer(elapsed, len(phases), patches.radiosity.copy())
            job.workers = sorted(shares.used)
            job.updates.append(pb.Progress(job=job.summary(), barrier=len(phases), rays=rays,
                                           rms_estimate=float(est.rms) if est is not None else 0.0,
                                           error=estimate_to_pb(est) if est is not None else None,
                                           accuracy=accuracy, bytes_relayed=shares.bytes_sent))
            self.count(barriers=1)
            job.notify()
            mem(f"shared {name}")

        strategy = Shared(k, shares, where=lambda: (f"{len(shares.used)} worker process(es): "
                                                    f"{', '.join(sorted(shares.used))}"))
        try:
            books = strategy.run(patches, config, RunHooks(should_stop=job.cancel.is_set, on_phase=on_phase), timings)
        except Cancelled:
            job.state, job.error = "cancelled", "cancelled while its shares ran: no results"
            return True
        finally:
            shares.drop()
            display.close()
        if books is None:
            log.info("job %s: its lights make no exact form factors; it divides the scene instead", job.id)
            job.state = "queued"
            return False
        run = strategy.run_state
        shared = strategy.section
        self.count(rays=run.stats.rays)
        job.residual = run.ledger.residual()
        if not job.updates:  # stopped before its first phase ended: no progress was sent
            job.updates.append(pb.Progress(job=job.summary(), accuracy=accuracy))
        last = job.updates[-1]
        last.ledger.CopyFrom(ledger_to_pb(run.ledger))
        last.shots = run.stats.shots
        books.choices.insert(0, why)
        unused = unused_divide_note(from_pb(DivideConfig, spec.divide, subscenes=1),
                                    f"was shared by {len(shares.used)} worker(s), each holding the whole scene")
        if unused:
            books.choices.add("unused_flags", unused)
        shared |= {"workers_used": sorted(shares.used), "reassigned": shares.reassigned,
                   "bytes_sent": shares.bytes_sent, "display_seconds": display.seconds,
                   "display_cpu_seconds": display.cpu_seconds}
        live = job.preview
        live.close()  # its Embree scene goes before the outputs; the final state's preview is theirs
        job.curve.measure(patches.radiosity, patches.area, self._measured_label(run, config), len(phases))
        shared["coordinator_rss_mb"] = dict(mem.phases)
        self._write_results(job, scene, size, books, views, {"shared": shared}, live, len(phases), mem)
        job.state = "cancelled" if run.stats.stopped_by == "stopped" else "done"
        return True

    def _write_results(self, job: Job, scene, size: float, books, views: Future, extra: dict, shown, barrier: int,
                       mem: MemoryLog) -> None:
        """The job's outputs and report (``finish_run``, as `dcrad solve` writes them) with its error
        curve and ``extra`` sections; the status page then shows the result's own preview, rendered
        only when the live one (``shown``) is of an earlier ``barrier``."""
        spec = job.spec
        settings = scene_settings(scene, size, spec.solver.scale or 1.0, spec.solver.two_sided,
                                  spec.solver.workplane)
        made = self._views(views)
        job.report = finish_run(job.root / "out", scene, books, settings, spec.preview_width or 640,
                                spec.preview_height or 480, extra={"error_curve": self.curve_dict(job), **extra},
                                views=made, painter=self._painter(job, made))
        mem("outputs")
        if shown.barrier != barrier:
            self._final_preview(job, barrier)

    def _views_ahead(self, job: Job, scene, patches) -> Future:
        """The outputs' views (``pipeline.output_views(ahead=True)``: cameras, both views' primary hits,
        the corner pairs, the live preview's view: what does not depend on B), made while the workers
        solve, in a process at nice 19 (ahead.py; a background thread if it cannot start).  At 1.27M
        patches 7.6 s of the outputs' 18.7 s came off the job's critical path, at 201k 3.0 s of 5.4 s."""
        w, h = job.spec.preview_width or 640, job.spec.preview_height or 480
        try:
            job.ahead = ViewsAhead(patches, scene.camera, w, h, self.preview_size)
            return job.ahead.future
        except (OSError, RuntimeError) as exc:  # no process to be had: a background thread instead
            log.warning("job %s: the outputs' views are made in a thread (%s)", job.id, exc)

        def build():
            background()
            return output_views(scene, patches, w, h, ahead=True)

        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"views-{job.id}")
        future = pool.submit(build)
        pool.shutdown(wait=False)
        return future

    @staticmethod
    def _views(future: Future):
        """The views built ahead, or None (they are built with the outputs) if that failed."""
        t0 = time.perf_counter()
        ready = future.done()
        try:
            views = future.result()
            if not ready:
                log.info("the outputs waited %.1f s for the views made ahead", time.perf_counter() - t0)
            return views
        except Exception:  # the outputs build their own; never fail a solved job over it
            log.warning("building the outputs' views ahead failed; the outputs build them\n%s",
                        traceback.format_exc())
            return None

    @staticmethod
    def _painter(job: Job, views):
        """Who writes the pictures (``write_outputs``' ``painter``): the views process, which holds the
        views and the corner pairs at any size, while the coordinator writes the npz and PLY, when the
        coordinator's views hold no pairs (more than render.KEEP_PAIRS: 20x20 office, outputs 8.2-10.2
        -> 5.1-7.0 s); None (the outputs write them here) when they do, where the npz's thread already
        runs beside them and a second process only adds its cold start (8x8 office: 1.45 -> 1.58 s,
        mean of 8 runs each), or when the views were not made there."""
        if views is None or job.ahead is None or (views.smoother is not None and views.smoother.kept):
            return None
        return job.ahead.paint

    @staticmethod
    def _final_preview(job: Job, barrier: int) -> None:
        """The job page's preview from the result's (the top-down one of a floor plan), kept where a
        restarted coordinator looks for it."""
        out = job.root / "out"
        src = out / "preview_top.png" if (out / "preview_top.png").is_file() else out / "preview.png"
        try:
            (job.root / "live").mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, job.root / "live" / "preview-live.png")
        except OSError as exc:
            log.warning("job %s: cannot keep its preview (%s)", job.id, exc)
        previous = job.preview.current[0] if job.preview is not None else 0
        stored = StoredPreview.load(src, barrier)
        if stored is not None:
            stored.current = (previous + 1, barrier, stored.current[2])
            job.preview = stored

    @staticmethod
    def _measured_label(run, config: SolverConfig) -> str:
        stopped_by = getattr(run, "stopped_by", None) or run.stats.stopped_by
        if stopped_by == "tolerance":
            return f"measured against the final solution (converged to the residual tol {config.tol:g})"
        why = {"stopped": "when cancelled", "time_limit": "at the time limit",
               "ray_budget": "at the ray budget"}.get(stopped_by, f"at the end ({stopped_by})")
        return (f"measured against the state {why} (residual {run.ledger.residual():.1e}; "
                f"not the converged solution)")

    @staticmethod
    def curve_dict(job: Job) -> dict:
        """RMS error against wall time: the live estimate per barrier; the measured curve after the run.

        Points are [elapsed s, rms W/m^2, barrier] in both series.
        """
        est, seen = [], set()
        for p in list(job.updates):
            # the closing message repeats the last barrier; a shared run's first phase has no estimate yet
            if p.barrier > 0 and p.barrier not in seen and (p.HasField("error") or p.rms_estimate > 0):
                seen.add(p.barrier)
                est.append([p.job.elapsed_s, p.rms_estimate, p.barrier])
        measured = job.curve.measured
        return {"unit": "W/m^2", "time": "s since the job started running",
                "estimate": {"label": "estimated error: noise from two half-solutions + unshot bias "
                                      "(converged solution unknown)",
                             "points": est},
                "measured": None if measured is None else {"label": job.curve.label,
                                                           "points": [list(m) for m in measured]}}

    def _progress(self, job: Job, run, handles, b: np.ndarray, area: np.ndarray, accuracy: float) -> pb.Progress:
        snap = run.snapshots[-1]
        subs = []
        for h, st in zip(handles, run.states):
            led = st.ledger
            total = float((led.emitted + led.imported).sum())
            res = float((led.unshot + led.in_flight).sum() / total) if total > 0 else 0.0
            subs.append(pb.SubsceneProgress(cell=h.cell, worker=h.worker.address if h.worker else "",
                                            shots=st.shots, rays=st.rays, residual=res,
                                            twin_bytes=st.twin_bytes, reassigned=h.reassigned))
        est = run.estimate  # the noise-aware estimate (dcrad.estimate.noise), from every subscene's sums
        return pb.Progress(job=job.summary(), barrier=run.barriers, shots=snap.shots, rays=snap.rays,
                           rms_estimate=float(est.rms) if est is not None
                           else residual_estimate(snap.residual, b, area),
                           error=estimate_to_pb(est) if est is not None else None, accuracy=accuracy,
                           ledger=ledger_to_pb(run.ledger), subscenes=subs,
                           bytes_relayed=sum(h.bytes_relayed for h in handles))
