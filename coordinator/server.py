"""Coordinator service (grpc.aio): the servicer maps domain errors to status codes.

Handlers stay thin: uploads are assembled with ``dcrad.wire``, jobs live in
``JobManager``, workers in ``WorkerPool``.  ``serve`` also starts the web status
endpoint (``coordinator.web``) on the same event loop.  Only this module turns DcradError
into gRPC status codes: INVALID_ARGUMENT for a bad scene, NOT_FOUND for an
unknown job, RESOURCE_EXHAUSTED for an upload over the limit,
FAILED_PRECONDITION for results of a job that is not done.
"""

from __future__ import annotations

import asyncio
import ctypes
import logging
import shutil
import threading
import uuid
from pathlib import Path

import grpc

from dcrad.errors import DcradError, ExchangeError
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.v1 import dcrad_pb2_grpc as pb_grpc
from dcrad.wire import FileSink, path_chunks

from . import ahead
from .jobs import TERMINAL, JobManager
from .remote import WorkerPool
from .rpc import shutdown, start_server, stop_on_signals
from .web import start_web

log = logging.getLogger("dcrad.coordinator")

#: default upload limit (bytes) for one job's scene files
MAX_UPLOAD = 512 * 1024 * 1024
#: glibc's mallopt parameter, and the size from which the coordinator's allocations are mmapped
_M_MMAP_THRESHOLD, MMAP_THRESHOLD = -3, 8 * 1024 * 1024


def return_freed_memory() -> bool:
    """Have glibc hand every allocation of MMAP_THRESHOLD bytes or more back to the system when freed.

    The coordinator's arrays (checkpoint and twin-buffer chunks, assembled radiosity) come and
    go at every barrier, in several threads.  glibc's default threshold grows up to 32 MB as
    such blocks are freed, after which they come from heaps that keep the freed space: the 8x8
    office's coordinator peaked at 1230 MB RSS for 540 MB allocated; with a fixed 256 KiB
    threshold at 680 MB.  But each mmapped block is fresh pages, faulted in and zeroed by the
    kernel: at 256 KiB the 20x20 office's divided coordinator (--max-rays 2e7) took 3.6M page
    faults and 13.2 system CPU s, the 8x8 office's shared one 1.06M and 3.6 s, CPU the workers
    lost.  At 8 MiB: 0.83M faults and 4.8 s at 20x20, the same peak (1088 against 1108 MB).
    False where there is no glibc.
    """
    try:
        return bool(ctypes.CDLL("libc.so.6").mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD))
    except (OSError, AttributeError):
        return False


class CoordinatorServicer(pb_grpc.CoordinatorServicer):
    def __init__(self, manager: JobManager, max_upload: int = MAX_UPLOAD):
        self.manager = manager
        self.max_upload = max_upload

    async def _job(self, job_id: str, context):
        job = self.manager.get(job_id)
        if job is None:
            await context.abort(grpc.StatusCode.NOT_FOUND, f"job '{job_id}' not found")
        return job

    async def Submit(self, request_iterator, context):
        spec = None
        # the upload goes to disk chunk by chunk (memory: one chunk), then becomes the job's scene/
        staging = self.manager.root / "incoming" / uuid.uuid4().hex
        files = FileSink(staging, self.max_upload)
        try:
            try:
                async for req in request_iterator:
                    if req.HasField("spec"):
                        spec = req.spec
                    elif spec is None:
                        await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "Submit must start with the job spec")
                    else:
                        files.add(req.file)
            except ExchangeError as exc:
                code = (grpc.StatusCode.RESOURCE_EXHAUSTED if "too large" in str(exc)
                        else grpc.StatusCode.INVALID_ARGUMENT)
                await context.abort(code, str(exc))
            finally:
                files.close()
            if spec is None:
                await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "Submit had no job spec")
            staging.mkdir(parents=True, exist_ok=True)  # an upload of no files is still a folder
            try:
                job = await asyncio.to_thread(self.manager.create, spec, staging)
            except DcradError as exc:
                await context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(exc))
        finally:
            shutil.rmtree(staging, ignore_errors=True)  # moved into the job, or refused
        self.manager.start(job)
        log.info("job %s submitted: %s", job.id, spec.scene)
        return job.summary()

    async def Watch(self, request, context):
        job = await self._job(request.job_id, context)
        async for update in job.changes():
            yield update

    async def Fetch(self, request, context):
        job = await self._job(request.job_id, context)
        out = job.root / "out"
        if job.state not in ("done", "cancelled") or not (out / "report.json").exists():
            await context.abort(grpc.StatusCode.FAILED_PRECONDITION,
                                f"job '{job.id}' is {job.state}; results exist for done jobs "
                                f"(and for cancelled ones, up to where they stopped)")
        for path in sorted(p for p in out.rglob("*") if p.is_file()):
            rel = path.relative_to(out).as_posix()
            for chunk in path_chunks(path, rel):
                yield chunk

    async def Cancel(self, request, context):
        job = await self._job(request.job_id, context)
        if job.state not in TERMINAL:
            job.request_cancel()
        return job.summary()

    async def ListJobs(self, request, context):
        return pb.JobList(jobs=[j.summary() for j in self.manager.jobs.values()])

    async def RegisterWorker(self, request, context):
        if not request.address:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "a worker must give its address")
        w = self.manager.pool.register(request.address, request.capacity or 4, request.name)
        return pb.RegisterReply(worker_id=w.address)

    async def ListWorkers(self, request, context):
        return pb.WorkerList(workers=[pb.WorkerInfo(address=w.address, capacity=w.capacity, name=w.name,
                                                    alive=w.alive, load=w.load)
                                      for w in list(self.manager.pool.workers.values())])


def _warm_imports() -> None:
    """Import what loading a scene needs (dcrad.io.scene imports trimesh lazily)."""
    import trimesh.exchange.obj  # noqa: F401, PLC0415
    import trimesh.remesh  # noqa: F401, PLC0415
    import trimesh.transformations  # noqa: F401, PLC0415


async def serve(port: int = 50051, host: str = "127.0.0.1", root: str | Path = "dcrad-coordinator",
                max_upload: int = MAX_UPLOAD, worker_wait: float = 60.0, ready=None, stop: asyncio.Event | None = None,
                web_port: int | None = None, web_host: str = "127.0.0.1", web_ready=None,
                preview_interval: float = 2.0) -> None:
    """Run the coordinator until SIGTERM/SIGINT (or ``stop``); ``ready(port)`` once listening.

    web_port : the status pages' port (0: any free port; None: no web endpoint), on
               ``web_host``, served on this same event loop; ``web_ready(url)`` once bound.
    """
    return_freed_memory()
    pool = WorkerPool()
    manager = JobManager(Path(root), pool, worker_wait=worker_wait, preview_interval=preview_interval)
    servicer = CoordinatorServicer(manager, max_upload)
    server, health_servicer, bound = await start_server(
        lambda s: pb_grpc.add_CoordinatorServicer_to_server(servicer, s), "dcrad.v1.Coordinator", host, port)
    log.info("coordinator listening on %s:%d, jobs in %s", host, bound, root)
    runner = None
    if web_port is not None:
        try:
            runner, web_url = await start_web(manager, web_host, web_port)
        except OSError as exc:
            await server.stop(grace=None)
            raise DcradError(f"web status page: cannot listen on {web_host}:{web_port}: "
                             f"{exc.strerror or exc}") from None
        log.info("status pages on %s", web_url)
        if web_ready is not None:
            web_ready(web_url)
    if ready is not None:
        ready(bound)
    # the first job's load needs trimesh (0.5 s of imports) and its views a process (ahead.py):
    # both started now, while the client prepares its upload, not after it
    ahead.prestart()
    threading.Thread(target=_warm_imports, name="warm-imports", daemon=True).start()
    stop = stop_on_signals(stop)
    await stop.wait()
    tasks = [asyncio.create_task(runner.cleanup())] if runner is not None else []
    await shutdown(server, health_servicer, tasks)
