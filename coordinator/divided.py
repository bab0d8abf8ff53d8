"""A divided job's subscenes on the pool's workers: the backend ``dcrad.runs.Divided`` runs on in
the service (``RemoteSubscene`` handles), with what the service adds at every barrier:
checkpoints on disk, the live preview and error curve, progress for watchers and the metrics.
The loop itself is the in-process one (``division.divide.run_divided``)."""

from __future__ import annotations

import logging
import time
from concurrent.futures import Executor, ThreadPoolExecutor

import numpy as np

from dcrad.division.divide import SubsceneSpec
from dcrad.division.placement import expected_work, placement
from dcrad.solving.accuracy import resolve

from .display import BarrierDisplay, LivePreview
from .remote import RemoteSubscene
from .store import CheckpointWriter

log = logging.getLogger("dcrad.coordinator")


class WorkersBackend:
    """``open`` makes the handles, resumes them from the job's checkpoints when they match, marks the
    job running and places them on workers by expected work; ``on_barrier`` is the run's hook;
    ``close`` stops the checkpoints and the display and frees the subscenes on the workers."""

    record = False  #: the service keeps its own B per barrier (the error curve), not the run's snapshots

    def __init__(self, manager, job, scene, patches, views, mem, config):
        self.manager, self.job, self.scene, self.patches, self.views, self.mem = (manager, job, scene, patches,
                                                                                    views, mem)
        self.accuracy = resolve(config).accuracy  # the target every Progress reports (fixed for the job)
        self.handles: list[RemoteSubscene] = []
        self.resume = None
        self.writer: CheckpointWriter | None = None
        self.display: BarrierDisplay | None = None
        #: the whole scene's (n,3) from the subscenes' values concatenated (``runs.Divided.assemble``)
        self.assemble = None
        self._done = {"rays": 0, "bytes_relayed": 0}  # counted into the metrics so far
        self._closed = False

    def open(self, specs: list[SubsceneSpec]) -> list[RemoteSubscene]:
        job, m = self.job, self.manager
        job.subscenes = len(specs)
        folder = job.root / "checkpoints"
        self.handles = handles = [RemoteSubscene(job.id, s, m.pool, m.rpc_timeout, folder) for s in specs]
        self.piece_area = np.concatenate([s.patches.area for s in specs])  # the live estimate's
        self.resume = resume = m._resume_handles(job, handles)
        self.mem("partition")
        job.state, job.started = "running", time.time() - (resume.elapsed if resume else 0.0)
        m._save(job)
        self.writer = CheckpointWriter(folder, start_barrier=resume.barrier if resume else 0)
        # subscenes on workers by expected work (their lamps' power and patch count: LPT,
        # placement.placement), so no worker carries the two brightest cells; results do not
        # depend on it, only which worker waits at a barrier
        workers = m.pool.live()
        slots = placement([expected_work(s.patches) for s in specs], len(workers)) if workers else []
        # all at once: a worker reads one subscene while it builds another's Embree scene, and
        # the coordinator writes one's static file while it streams another (20x20 office,
        # 4 subscenes: 4.8 s one after another)
        with ThreadPoolExecutor(max_workers=len(handles), thread_name_prefix=f"place-{job.id}") as ex:
            list(ex.map(lambda i: handles[i].place(prefer=workers[slots[i]] if workers else None),
                        range(len(handles))))
        job.workers = sorted({h.worker.address for h in handles if h.worker is not None})
        self.mem("load on workers")
        job.preview = LivePreview(self.scene, self.patches, job.root / "live", m.preview_size, m.preview_interval,
                                  self.views)
        job.curve.folder = job.root / "curve"
        self.display = BarrierDisplay(lambda b: self.assemble(b), job.curve, job.preview, m.count)
        job.on_cancel.append(self.interrupt)
        if job.cancel.is_set():  # cancelled while it loaded
            self.interrupt()
        return handles

    def resumed(self) -> tuple[int, float, float]:
        r = self.resume
        return (r.barrier, r.crossing, r.elapsed) if r is not None else (0, -1.0, 0.0)

    def executor(self, n: int) -> Executor:
        return ThreadPoolExecutor(max_workers=n)

    def unshot(self, handle: RemoteSubscene) -> np.ndarray:
        return handle.saved_arrays({"unshot"})["unshot"]

    def interrupt(self) -> None:
        for h in self.handles:
            h.interrupt()

    def on_barrier(self, run) -> None:
        job, m, handles = self.job, self.manager, self.handles
        assert self.writer is not None and self.display is not None
        self.writer.submit(run.barriers, {h.cell: h.checkpoint_path for h in handles}, time.time() - job.started,
                           run.crossing)
        values = np.concatenate([h.radiosity() for h in handles])  # the display thread's copy
        job.residual = run.ledger.residual()
        job.workers = sorted({h.worker.address for h in handles if h.worker is not None})
        # the live estimate over the clipped pieces (same area; no assembly here)
        progress = m._progress(job, run, handles, values, self.piece_area, self.accuracy)
        job.updates.append(progress)
        self.display.offer(progress.job.elapsed_s, run.barriers, values)
        now = {"rays": progress.rays, "bytes_relayed": progress.bytes_relayed}
        m.count(barriers=1, **{k: max(0, now[k] - self._done[k]) for k in now})
        self._done.update(now)
        job.notify()
        self.mem("barrier")

    def close(self, handles) -> None:
        if self._closed:
            return
        self._closed = True
        self.job.on_cancel.clear()
        if self.writer is not None:
            self.writer.close()
        if self.display is not None:
            self.display.close()  # the curve's last states are in (their preview is the outputs')
        self.mem("solve")
        for h in self.handles:  # the workers free the subscenes now, not after the outputs
            h.drop()

    def service_figures(self) -> dict:
        """What the report's ``divided`` section gains on the service."""
        hs, job = self.handles, self.job
        assert self.writer is not None and self.display is not None
        return {
            "reassigned": [h.reassigned for h in hs],
            "bytes_relayed": sum(h.bytes_relayed for h in hs),
            "checkpoint_bytes": sum(h.checkpoint_bytes for h in hs),
            "compute_seconds": [h.compute_s for h in hs],
            "rpc_seconds": [h.rpc_seconds for h in hs],
            "preview_seconds": job.preview.seconds,
            "display_seconds": self.display.seconds,
            "display_cpu_seconds": self.display.cpu_seconds,
            "checkpoints": {k: v for k, v in self.writer.stats.items() if k != "per_barrier"},
        }
