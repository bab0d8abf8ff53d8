"""Worker service: load subscenes, iterate them, hand over and accept boundary buffers.

Thin: protocol and bookkeeping only.  The numerics are ``dcrad.division.divide``; they
run in a thread so the event loop keeps answering health checks.  At start the
worker registers with the coordinator, retrying with backoff while the
coordinator is not up, and re-registers every few seconds so a restarted
coordinator learns about it again.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time

import grpc
import numpy as np

from coordinator.rpc import shutdown, start_server, stop_on_signals
from dcrad.config import SolverConfig
from dcrad.division.subscene import Subscene, build_subscene, checkpoint_arrays
from dcrad.errors import DcradError
from dcrad.meshing.patches import Patches
from dcrad.settings import from_pb
from dcrad.solving.share import (
    Shot,
    direct_pilot,
    direct_share,
    gather_share,
    run_replica,
    tally_from_arrays,
    tally_to_arrays,
)
from dcrad.transport.direct import GatherStopped
from dcrad.transport.rays import Tracer
from dcrad.transport.source_wire import sources_from_table
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.v1 import dcrad_pb2_grpc as pb_grpc
from dcrad.wire import ArrayAssembler, arrays_to_chunks, ledger_to_pb, plan_from_pb, share_phase_name

log = logging.getLogger("dcrad.worker")


def status_of(key: pb.SubsceneKey, sub: Subscene, compute_s: float = 0.0) -> pb.SubsceneStatus:
    st = sub.state()
    return pb.SubsceneStatus(key=key, ledger=ledger_to_pb(st.ledger), shots=st.shots, rays=st.rays,
                             twin_entries=st.twin_entries, twin_bytes=st.twin_bytes, compute_s=compute_s,
                             area=st.area, return_tallies=[float(x) for x in st.tallies.ravel()],
                             twins_delivered=st.twins_delivered, twin_blocks=st.twin_blocks,
                             batches=st.batches, trace_s=st.trace_seconds,
                             back_by_obj=[float(x) for x in st.back_by_obj],
                             noise=st.noise.as_list() if st.noise is not None else [])


async def read_stream(request_iterator, head: str):
    """A client stream of one ``head`` message then ArrayChunks: (head or None, arrays assembler)."""
    first, groups = await read_groups(request_iterator, head)
    return first, groups.setdefault("array", ArrayAssembler())


async def read_groups(request_iterator, head: str) -> tuple:
    """A client stream of one ``head`` message then ArrayChunks in the fields of its ``part`` oneof:
    (head or None, {field: arrays assembler})."""
    first = None
    groups: dict[str, ArrayAssembler] = {}
    async for req in request_iterator:
        part = req.WhichOneof("part")
        if part == head:
            first = getattr(req, head)
        elif part is not None:
            groups.setdefault(part, ArrayAssembler()).add(getattr(req, part))
    return first, groups


class WorkerServicer(pb_grpc.WorkerServicer):
    """Holds subscenes by (job id, cell); several jobs may share a worker."""

    def __init__(self):
        self.subscenes: dict[tuple[str, int], Subscene] = {}
        self.locks: dict[tuple[str, int], asyncio.Lock] = {}
        self.compute: dict[tuple[str, int], float] = {}  #: s spent in iterate per subscene
        #: shared runs' patch tables and Embree scenes by job id (dcrad.solving.share), and a lock each:
        #: a replica resets and fills the table, so one share of a job runs here at a time
        self.scenes: dict[str, tuple] = {}
        self.scene_locks: dict[str, asyncio.Lock] = {}
        #: shared runs' final gathers by (job id, share index), continued round by round
        self.gathers: dict[tuple[str, int], object] = {}
        #: shared runs' direct shares after their pilot, by (job id, share index), until gathered
        self.pilots: dict[tuple[str, int], object] = {}
        #: shared runs' shot solutions by job id: what every gather share of the job reads (sent once)
        self.shots: dict[str, Shot] = {}
        #: shared runs asked to stop (phase "stop"): their replicas end cleanly with what they have
        self.stops: dict[str, threading.Event] = {}

    def _get(self, key: pb.SubsceneKey, context):
        k = (key.job_id, key.cell)
        if k not in self.subscenes:
            return None, k
        return self.subscenes[k], k

    async def Load(self, request_iterator, context):
        header, asm = await read_stream(request_iterator, "header")
        if header is None:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "Load needs a header first")
        try:
            arrays = asm.result()
            config = from_pb(SolverConfig, header.solver)
            sub = await asyncio.to_thread(build_subscene, header.key.cell, config, header.power_per_ray,
                                          header.mode or "binned", list(header.names), arrays,
                                          header.local_target)
        except (DcradError, KeyError, TypeError, ValueError) as exc:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"cannot load subscene: {exc}")
        k = (header.key.job_id, header.key.cell)
        self.subscenes[k] = sub
        self.locks[k] = asyncio.Lock()
        log.info("loaded job %s cell %d: %d patches, %d boundaries", k[0], k[1], len(sub.patches),
                 len(sub.boundaries))
        return status_of(header.key, sub)

    async def Iterate(self, request, context):
        sub, k = self._get(request.key, context)
        if sub is None:
            await context.abort(grpc.StatusCode.NOT_FOUND, f"no subscene {k} on this worker")
        try:
            plan = plan_from_pb(request)
        except DcradError as exc:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(exc))
        async with self.locks[k]:
            t0 = time.perf_counter()
            await asyncio.to_thread(sub.iterate, max(1, request.batches), plan)
            self.compute[k] = self.compute.get(k, 0.0) + time.perf_counter() - t0
            out = sub.collect()
            for chunk in arrays_to_chunks(out.to_arrays()):
                yield pb.IterateReply(array=chunk)
            yield pb.IterateReply(status=status_of(request.key, sub, self.compute[k]))

    async def Deliver(self, request_iterator, context):
        key, asm = await read_stream(request_iterator, "key")
        if key is None:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "Deliver needs a key first")
        sub, k = self._get(key, context)
        if sub is None:
            await context.abort(grpc.StatusCode.NOT_FOUND, f"no subscene {k} on this worker")
        try:
            arrays = asm.result()
            buf = sub.boundary_mode.buffer.from_arrays(arrays)
        except (DcradError, KeyError, ValueError) as exc:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"bad boundary buffer: {exc}")
        async with self.locks[k]:
            sub.deliver(buf)
        return status_of(key, sub, self.compute.get(k, 0.0))

    async def Checkpoint(self, request, context):
        sub, k = self._get(request, context)
        if sub is None:
            await context.abort(grpc.StatusCode.NOT_FOUND, f"no subscene {k} on this worker")
        async with self.locks[k]:
            arrays = checkpoint_arrays(sub)
        for chunk in arrays_to_chunks(arrays):
            yield chunk

    async def Share(self, request_iterator, context):
        t_in = time.perf_counter()
        header, groups = await read_groups(request_iterator, "header")
        if header is None:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "Share needs a header first")
        job = header.job_id
        phase = share_phase_name(header.phase)  # "" when unset or unknown: refused below
        stop = self.stops.setdefault(job, threading.Event())
        if phase == "stop":
            stop.set()
            return
        try:
            given = {g: asm.result() for g, asm in groups.items()}
            arrays = given.get("array", {})
            config = from_pb(SolverConfig, header.solver)
            if phase not in ("pilot", "direct", "replica", "gather") or not 0 <= header.index < max(header.count, 1):
                what = phase or f"{header.phase} (unset or unknown)"
                raise ValueError(f"bad share: phase {what}, index {header.index} of {header.count}")
            if header.scene:
                table = given.get("scene", {})
                t_read = time.perf_counter()
                patches = Patches.from_table(table, list(header.names))
                patches.sources = sources_from_table(table)
                self.scenes[job] = (patches, await asyncio.to_thread(Tracer.mesh, patches))
                log.info("job %s: patch table of %d patches (%.0f MB) read in %.2f s, loaded in %.2f s", job,
                         len(patches), sum(v.nbytes for v in table.values()) / 1e6, t_read - t_in,
                         time.perf_counter() - t_read)
                self.scene_locks.setdefault(job, asyncio.Lock())
        except KeyError as exc:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"cannot run share: the request has no array {exc}")
        except (DcradError, TypeError, ValueError) as exc:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"cannot run share: {exc}")
        if job not in self.scenes:
            await context.abort(grpc.StatusCode.NOT_FOUND, f"no patch table of job {job} on this worker")
        patches, tracer = self.scenes[job]
        cancelled = threading.Event()
        context.add_done_callback(lambda _: cancelled.set())
        async with self.scene_locks[job]:
            t0, c0 = time.perf_counter(), time.process_time()
            try:
                rows = np.asarray(arrays.get("rows", np.zeros(0)), np.int64)
                if len(rows) and (rows.min() < 0 or rows.max() >= len(patches)):
                    raise ValueError(f"share rows outside 0..{len(patches) - 1}")
                key = (job, header.index)
                # a cancelled job's share stops at its next batch (the stop phase, or the caller gone)
                def stopping() -> bool:
                    return cancelled.is_set() or stop.is_set()

                if phase == "pilot":
                    pilot = await asyncio.to_thread(direct_pilot, patches, config, tracer, rows, header.index,
                                                    stopping)
                    if pilot is not None:
                        self.pilots[key] = pilot
                    out = {} if pilot is None else {"pilot": np.array([pilot.need, pilot.weight])}
                elif phase == "direct":
                    rate = float(np.asarray(arrays["rate"]).ravel()[0])
                    held = self.pilots.pop(key, None)
                    if held is not None and not np.array_equal(held.receivers, rows):
                        held = None
                    got = await asyncio.to_thread(direct_share, patches, config, tracer, rows, header.index, rate,
                                                  held, stopping)
                    out = {} if got is None else tally_to_arrays(got)
                elif phase == "gather":
                    if "shot" in given:  # sent once a job: every gather share reads it
                        self.shots[job] = Shot.from_arrays(given["shot"], len(patches))
                    shot = self.shots.get(job)
                    if shot is None:
                        await context.abort(grpc.StatusCode.NOT_FOUND, f"no shot solution of job {job} on this "
                                                                       f"worker: send it with the gather share")
                    rounds = [int(r) for r in arrays["rounds"]]
                    fg, traced = await asyncio.to_thread(gather_share, patches, config, tracer, shot, rows,
                                                         header.index, rounds, self.gathers.get(key), stopping)
                    self.gathers[key] = fg
                    out = {"sum_a": fg.sum_a, "sum_b": fg.sum_b, "traced": np.array([traced], np.int64)}
                else:
                    tally = tally_from_arrays(given.get("tally", {}), len(patches))
                    rep = await asyncio.to_thread(run_replica, patches, config, tracer, tally, header.index,
                                                  header.count, stopping)
                    out = rep.to_arrays()
            except GatherStopped:
                await context.abort(grpc.StatusCode.CANCELLED, f"{phase} share {header.index} of job {job} "
                                                               f"stopped: the job was cancelled")
            except KeyError as exc:
                await context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"cannot run {phase} share: "
                                                                      f"the request has no array {exc}")
            except (DcradError, TypeError, ValueError) as exc:
                await context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"cannot run {phase} share: {exc}")
            log.info("job %s: %s share %d of %d in %.2f s (%.2f CPU s; its request read in %.2f s)", job,
                     phase, header.index, header.count, time.perf_counter() - t0, time.process_time() - c0,
                     t0 - t_in)
        t1 = time.perf_counter()
        for chunk in arrays_to_chunks(out):
            yield chunk
        log.info("job %s: %s share %d replied in %.2f s (%.1f MB)", job, phase, header.index,
                 time.perf_counter() - t1, sum(np.asarray(v).nbytes for v in out.values()) / 1e6)

    async def Interrupt(self, request, context):
        sub, _ = self._get(request, context)
        if sub is not None:  # not under its lock: the Iterate in flight holds it, and stops at its next batch
            sub.interrupt()
        return pb.Empty()

    async def Drop(self, request, context):
        if request.cell < 0:  # a shared run's patch table
            self.scenes.pop(request.job_id, None)
            self.scene_locks.pop(request.job_id, None)
            self.stops.pop(request.job_id, None)
            self.shots.pop(request.job_id, None)
            for held in (self.gathers, self.pilots):
                for key in [key for key in held if key[0] == request.job_id]:
                    del held[key]
            return pb.Empty()
        k = (request.job_id, request.cell)
        self.subscenes.pop(k, None)
        self.locks.pop(k, None)
        self.compute.pop(k, None)
        return pb.Empty()


#: s a re-registration (the heartbeat) may wait for a busy coordinator: one streaming a big
#: share's arrays answers late (at the 20x20 office, 1.27M patches, 5 s ran out and the worker
#: logged its coordinator "unreachable" while the job ran on)
HEARTBEAT_TIMEOUT = 30.0


async def register_forever(coordinator: str, address: str, capacity: int, name: str,
                           stop: asyncio.Event, period: float = 5.0) -> None:
    """Register with the coordinator, retrying with backoff; then re-register every ``period`` s."""
    delay = 0.2
    registered = False
    # a worker started beside its coordinator (LocalCluster) registers the moment it listens: the
    # first calls wait for the channel, which retries its connection every 0.1 s
    backoff = [("grpc.initial_reconnect_backoff_ms", 100), ("grpc.min_reconnect_backoff_ms", 100),
               ("grpc.max_reconnect_backoff_ms", 100)]
    async with grpc.aio.insecure_channel(coordinator, options=backoff) as channel:
        stub = pb_grpc.CoordinatorStub(channel)
        while not stop.is_set():
            try:
                await stub.RegisterWorker(pb.WorkerInfo(address=address, capacity=capacity, name=name),
                                          timeout=HEARTBEAT_TIMEOUT if registered else 5.0,
                                          wait_for_ready=not registered)
                if not registered:
                    log.info("registered with coordinator %s as %s", coordinator, address)
                registered, delay = True, period
            except grpc.aio.AioRpcError as exc:
                if registered:
                    log.warning("coordinator %s unreachable (%s); retrying", coordinator, exc.code().name)
                registered = False
                delay = min(max(delay * 2, 0.2), 2.0)
            try:
                await asyncio.wait_for(stop.wait(), timeout=delay)
            except TimeoutError:
                pass


async def serve(port: int = 0, host: str = "127.0.0.1", coordinator: str | None = None,
                advertise: str | None = None, capacity: int = 4, name: str = "",
                ready=None) -> None:
    """Run a worker until SIGTERM/SIGINT; ``ready(port)`` is called once listening."""
    # accept the coordinator's keepalive pings (every 2 s)
    keepalive = [("grpc.http2.min_recv_ping_interval_without_data_ms", 1000),
                 ("grpc.http2.min_ping_interval_without_data_ms", 1000),
                 ("grpc.keepalive_permit_without_calls", 1), ("grpc.http2.max_ping_strikes", 0)]
    servicer = WorkerServicer()
    server, health_servicer, bound = await start_server(
        lambda s: pb_grpc.add_WorkerServicer_to_server(servicer, s), "dcrad.v1.Worker", host, port, keepalive)
    address = advertise or f"{host}:{bound}"
    log.info("worker listening on %s:%d (advertised as %s)", host, bound, address)
    if ready is not None:
        ready(bound)

    stop = stop_on_signals()
    tasks = []
    if coordinator:
        tasks.append(asyncio.create_task(register_forever(coordinator, address, capacity, name or address, stop)))
    await stop.wait()
    await shutdown(server, health_servicer, tasks)
