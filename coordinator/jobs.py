"""Jobs: validate a scene, partition it, run the barrier loop on workers, write results.

Each job runs ``dcrad.divide.run_divided`` (the same loop as in-process runs) in
a thread, over ``RemoteSubscene`` handles; progress after every barrier is
kept on the job and pushed to watchers on the event loop.
"""

from __future__ import annotations

import asyncio
import logging
import shutil
import threading
import time
import traceback
import uuid
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dcrad.config import SolverConfig
from dcrad.divide import DivideConfig, assemble, build_subscenes
from dcrad.errors import DcradError
from dcrad.pipeline import prepare, write_outputs
from dcrad.report import residual_estimate, run_report, write_json
from dcrad.solve import Solver
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.wire import ledger_to_pb

from .remote import NoWorkers, RemoteSubscene, WorkerPool

log = logging.getLogger("dcrad.coordinator")

TERMINAL = {"done", "failed", "cancelled"}


@dataclass
class Job:
    id: str
    spec: pb.JobSpec
    root: Path  #: job folder: scene/ (upload) and out/ (results)
    state: str = "queued"
    error: str = ""
    started: float = 0.0
    finished: float = 0.0
    subscenes: int = 0
    residual: float = 1.0
    workers: list = field(default_factory=list)
    updates: list = field(default_factory=list)  #: pb.Progress per barrier
    cancel: threading.Event = field(default_factory=threading.Event)
    report: dict | None = None
    _waiters: list = field(default_factory=list)  #: (loop, asyncio.Event) of watchers

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


def solver_config(s: pb.SolverSettings) -> SolverConfig:
    d = SolverConfig()
    return SolverConfig(tol=s.tol or d.tol, time_limit=s.time_limit, max_rays=s.max_rays, seed=s.seed,
                        rays_per_power=s.rays_per_power or d.rays_per_power)


class JobManager:
    """All jobs of a coordinator; jobs run in threads."""

    def __init__(self, root: Path, pool: WorkerPool, worker_wait: float = 60.0, rpc_timeout: float = 300.0):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.pool = pool
        self.jobs: dict[str, Job] = {}
        self.worker_wait = worker_wait
        self.rpc_timeout = rpc_timeout
        self.metrics = {"barriers": 0, "rays": 0, "bytes_relayed": 0}

    def get(self, job_id: str) -> Job | None:
        return self.jobs.get(job_id)

    # == submit ===================================================================
    def create(self, spec: pb.JobSpec, files: dict[str, bytes]) -> Job:
        """Store the upload and validate the scene; raises DcradError for a bad scene."""
        job = Job(id=uuid.uuid4().hex[:12], spec=spec, root=self.root / "jobs")
        job.root = self.root / "jobs" / job.id
        scene_dir = job.root / "scene"
        for rel, data in files.items():
            dest = scene_dir / rel
            dest.parent.mkdir(parents=True, exist_ok=True)
            dest.write_bytes(bytes(data))
        if spec.scene not in files:
            shutil.rmtree(job.root, ignore_errors=True)
            raise DcradError(f"the upload has no file '{spec.scene}' (the scene named in the job)")
        try:
            prepare(scene_dir / spec.scene, spec.solver.patch_size or None, spec.solver.scale or 1.0)
            solver_config(spec.solver)
            self._divide(spec, 1)
        except DcradError as exc:
            shutil.rmtree(job.root, ignore_errors=True)
            # name the file as the user uploaded it, not by the coordinator's folder
            raise type(exc)(str(exc).replace(f"{scene_dir}/", "").replace(str(scene_dir), ".")) from None
        self.jobs[job.id] = job
        return job

    def start(self, job: Job) -> None:
        threading.Thread(target=self._run, args=(job,), name=f"job-{job.id}", daemon=True).start()

    @staticmethod
    def _divide(spec: pb.JobSpec, workers: int) -> DivideConfig:
        d, dflt = spec.divide, DivideConfig()
        return DivideConfig(subscenes=d.subscenes or max(1, workers), iterations=d.iterations or dflt.iterations,
                            solid=d.solid or dflt.solid, cell_size=d.cell_size, mode=d.mode or dflt.mode)

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
        scene, patches, size = prepare(job.root / "scene" / spec.scene, spec.solver.patch_size or None,
                                       spec.solver.scale or 1.0)
        live = self.pool.wait_for(1, self.worker_wait)
        if live == 0:
            raise NoWorkers(f"no worker registered within {self.worker_wait:.0f} s")
        divide = self._divide(spec, live)
        subs, boundaries, parents, part = build_subscenes(patches, config, divide)
        job.subscenes = len(subs)
        handles = [RemoteSubscene(job.id, s, self.pool, self.rpc_timeout) for s in subs]
        job.state, job.started = "running", time.time()
        try:
            for h in handles:
                h.place()
            job.workers = sorted({h.worker.address for h in handles})
            pieces = [s.patches for s in subs]

            def on_barrier(run):
                values = [h.radiosity() for h in handles]
                b = assemble(len(patches), patches.area, parents, pieces, values)
                job.residual = run.ledger.residual()
                job.workers = sorted({h.worker.address for h in handles})
                job.updates.append(self._progress(job, run, handles, b, patches.area))
                self.metrics["barriers"] += 1
                job.notify()

            from dcrad.divide import run_divided

            with ThreadPoolExecutor(max_workers=len(handles)) as ex:
                run = run_divided(handles, boundaries, config, divide.iterations, ex,
                                  on_barrier=on_barrier, should_stop=job.cancel.is_set)
            self.metrics["rays"] += run.snapshots[-1].rays
            self.metrics["bytes_relayed"] += sum(h.bytes_relayed for h in handles)

            # Results: the same files as `dcrad solve`
            patches.radiosity = assemble(len(patches), patches.area, parents, pieces,
                                         [h.radiosity() for h in handles])
            unshot = [h.checkpoint["unshot"] if h.checkpoint else h.static["unshot"] for h in handles]
            patches.unshot = assemble(len(patches), patches.area, parents, pieces, unshot)
            solver = Solver(patches, config)
            solver.adopt_divided(run)
            out = job.root / "out"
            outputs = write_outputs(out, scene, patches, spec.preview_width or 640, spec.preview_height or 480)
            settings = config.as_dict() | {"patch_size_m": size, "scale": spec.solver.scale or 1.0}
            report = run_report(scene, solver, settings, {"solve_s": run.wall_seconds},
                                list(scene.warnings), outputs)
            report["divided"] = {"subscenes": len(subs), "boundaries": len(boundaries), "barriers": run.barriers,
                                 "mode": divide.mode, "iterations": divide.iterations, "solid": divide.solid,
                                 "max_twin_bytes": run.max_twin_bytes,
                                 "max_barrier_closure": max(run.barrier_closures),
                                 "reassigned": [h.reassigned for h in handles],
                                 "bytes_relayed": sum(h.bytes_relayed for h in handles),
                                 "checkpoint_bytes": sum(h.checkpoint_bytes for h in handles),
                                 "compute_seconds": [h.compute_s for h in handles],
                                 "rpc_seconds": [h.rpc_seconds for h in handles],
                                 "partition": part.as_dict()}
            write_json(out / "report.json", report)
            job.report = report
            job.residual = run.ledger.residual()
            job.state = "cancelled" if run.stopped_by == "stopped" else "done"
        finally:
            for h in handles:
                h.drop()

    def _progress(self, job: Job, run, handles, b: np.ndarray, area: np.ndarray) -> pb.Progress:
        snap = run.snapshots[-1]
        subs = []
        for h, st in zip(handles, run.states):
            led = st.ledger
            total = float((led.emitted + led.imported).sum())
            res = float((led.unshot + led.in_flight).sum() / total) if total > 0 else 0.0
            subs.append(pb.SubsceneProgress(cell=h.cell, worker=h.worker.address if h.worker else "",
                                            shots=st.shots, rays=st.rays, residual=res,
                                            twin_bytes=st.twin_bytes, reassigned=h.reassigned))
        return pb.Progress(job=job.summary(), barrier=run.barriers, shots=snap.shots, rays=snap.rays,
                           rms_estimate=residual_estimate(snap.residual, b, area),
                           ledger=ledger_to_pb(run.ledger), subscenes=subs,
                           bytes_relayed=sum(h.bytes_relayed for h in handles))
