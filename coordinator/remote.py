"""Subscenes on remote workers, behind the handle interface of ``run_divided``.

``RemoteSubscene`` has the same four methods as an in-process ``Subscene``
(``iterate``, ``collect``, ``deliver``, ``state``), so the barrier loop in
``dcrad.division.divide.run_divided`` drives remote workers unchanged.

Failover: after every successful ``deliver`` (the end of a barrier) the handle
takes a checkpoint of its subscene, streamed from the worker straight into a
file (``coordinator.store.ChunkFile``); the patches and boundaries it sent at
load are in a file too.  The handle keeps in memory only the subscene's radiosity
(for the live display), so the coordinator's memory does not grow with the
checkpoints.  When a worker stops answering, the subscene is loaded on another
live worker from those files.  The solver is deterministic (the checkpoint
carries the RNG state), so replaying the interrupted barrier's ``iterate``
reproduces exactly what was lost: no energy is lost or counted twice.  A disk that
refuses the files (full, read-only) turns the handle to keeping them in memory.
"""

from __future__ import annotations

import logging
import tempfile
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import grpc
import numpy as np

from dcrad.division.boundary import boundary_mode
from dcrad.division.subscene import SubsceneState, subscene_arrays
from dcrad.errors import DcradError
from dcrad.estimate.noise import NoiseSums
from dcrad.settings import to_pb
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.v1 import dcrad_pb2_grpc as pb_grpc
from dcrad.wire import ArrayAssembler, arrays_to_chunks, ledger_from_pb, plan_fields

from .rpc import MAX_MESSAGE
from .store import ChunkFile, cell_file, static_file

log = logging.getLogger("dcrad.coordinator")

#: gRPC codes that mean "this worker is gone", not "the request is bad"
LOST = {grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.NOT_FOUND,
        grpc.StatusCode.CANCELLED, grpc.StatusCode.UNKNOWN, grpc.StatusCode.INTERNAL}


class NoWorkers(DcradError):
    """No live worker can take a subscene."""


@dataclass
class WorkerEntry:
    address: str
    capacity: int = 4
    name: str = ""
    alive: bool = True
    load: int = 0  #: subscenes assigned now
    channel: grpc.Channel | None = field(default=None, repr=False)

    def stub(self) -> pb_grpc.WorkerStub:
        if self.channel is None:
            self.channel = grpc.insecure_channel(self.address, options=[
                ("grpc.max_receive_message_length", MAX_MESSAGE),
                ("grpc.max_send_message_length", MAX_MESSAGE),
                # a worker whose host vanishes (container stopped, cable cut) answers
                # nothing, not even a reset: ping it, and fail the call within seconds
                ("grpc.keepalive_time_ms", 2000),
                ("grpc.keepalive_timeout_ms", 3000),
                ("grpc.keepalive_permit_without_calls", 1),
                ("grpc.http2.max_pings_without_data", 0)])
        return pb_grpc.WorkerStub(self.channel)


class WorkerPool:
    """Registered workers; thread-safe.  Workers re-register as a heartbeat."""

    def __init__(self):
        self._lock = threading.Lock()
        self.workers: dict[str, WorkerEntry] = {}
        self.changed = threading.Condition(self._lock)

    def register(self, address: str, capacity: int, name: str) -> WorkerEntry:
        with self._lock:
            w = self.workers.get(address)
            if w is None:
                w = self.workers[address] = WorkerEntry(address, max(1, capacity), name)
                log.info("worker %s registered (capacity %d)", address, w.capacity)
            elif not w.alive:
                log.info("worker %s is back", address)
                w.alive, w.channel = True, None
            # a worker restarted on the same address may have a new name and capacity
            w.name, w.capacity = name, max(1, capacity)
            self.changed.notify_all()
            return w

    def live(self) -> list[WorkerEntry]:
        with self._lock:
            return [w for w in self.workers.values() if w.alive]

    def mark_dead(self, w: WorkerEntry) -> None:
        with self._lock:
            if w.alive:
                log.warning("worker %s stopped answering; its subscenes move", w.address)
            w.alive = False
            # drop the channel, do not close it: another thread may be calling on it this
            # instant (two subscenes on one worker), and a call on a closed channel raises
            # ValueError, not a gRPC error; it fails UNAVAILABLE and is freed with its stubs
            w.channel = None

    def pick(self, exclude: frozenset[str] | set[str] = frozenset()) -> WorkerEntry:
        """The live worker with the most spare capacity (ties: registration order)."""
        with self._lock:
            cands = [w for w in self.workers.values() if w.alive and w.address not in exclude]
            if not cands:
                raise NoWorkers("no live worker can take the subscene")
            w = min(cands, key=lambda w: w.load / w.capacity)
            w.load += 1
            return w

    def take(self, w: WorkerEntry) -> bool:
        """Count one more subscene on ``w`` if it is alive (False: it is not)."""
        with self._lock:
            if not w.alive:
                return False
            w.load += 1
            return True

    def release(self, w: WorkerEntry) -> None:
        with self._lock:
            w.load = max(0, w.load - 1)

    def wait_for(self, n: int, timeout: float) -> int:
        with self._lock:
            self.changed.wait_for(lambda: sum(w.alive for w in self.workers.values()) >= n, timeout=timeout)
            return sum(w.alive for w in self.workers.values())


def _gather(replies) -> tuple[dict, pb.SubsceneStatus | None]:
    asm = ArrayAssembler()
    status = None
    for r in replies:
        if r.HasField("status"):
            status = r.status
        else:
            asm.add(r.array)
    return asm.result(), status


class _Saved:
    """Arrays kept for a subscene: a chunk file, or (the disk refused it) the chunks in memory."""

    def __init__(self, path: Path | None = None, chunks: list | None = None, nbytes: int = 0):
        self.path, self._chunks, self.nbytes = path, chunks, nbytes

    @classmethod
    def write(cls, path: Path, chunks: Iterable[pb.ArrayChunk], keep=()) -> tuple["_Saved", dict]:
        nbytes, kept = ChunkFile.write(path, chunks, keep)
        return cls(path=path, nbytes=nbytes), kept

    @classmethod
    def in_memory(cls, chunks: Iterable[pb.ArrayChunk], keep=()) -> tuple["_Saved", dict]:
        held = list(chunks)
        asm = ArrayAssembler()
        for c in held:
            if c.name in keep:
                asm.add(c)
        return cls(chunks=held, nbytes=sum(len(c.data) for c in held)), asm.result()

    def chunks(self, skip=()):
        if self._chunks is not None:
            return (c for c in self._chunks if c.name not in skip)
        assert self.path is not None
        return ChunkFile.chunks(self.path, skip)

    def read(self, names) -> dict:
        asm = ArrayAssembler()
        for c in self.chunks():
            if c.name in names:
                asm.add(c)
        return asm.result()


class RemoteSubscene:
    """One subscene on a worker, with checkpoints and failover.

    job_id, cell : identity; sub : the SubsceneSpec (or Subscene) built by the coordinator
    (only its arrays are sent; it is not iterated here); pool : WorkerPool; folder : where
    the handle's files go (the job's checkpoints folder; None: a temporary folder of its own).
    ``barrier`` counts the handle's barriers (delivers), from ``resume_from``'s barrier.
    """

    def __init__(self, job_id: str, sub, pool: WorkerPool, timeout: float = 600.0, folder: Path | None = None):
        self.job_id, self.cell, self.pool, self.timeout = job_id, sub.cell, pool, timeout
        self.mode = sub.mode
        self.key = pb.SubsceneKey(job_id=job_id, cell=sub.cell)
        self.header = pb.SubsceneHeader(key=self.key, solver=to_pb(sub.config, pb.SolverSettings),
                                        power_per_ray=sub.power_per_ray, mode=sub.mode,
                                        names=list(sub.patches.names), local_target=sub.local_target)
        self.folder = Path(folder) if folder is not None else None
        self._own_folder: tempfile.TemporaryDirectory[str] | None = None
        #: the arrays sent at load, until the first place() saves them (then dropped from memory)
        self._static: dict | None = subscene_arrays(sub)
        self._static_saved: _Saved | None = None
        self._checkpoint: _Saved | None = None  #: state after the last barrier
        self._radiosity: np.ndarray = sub.patches.radiosity  #: (n,3) at the last barrier
        self.barrier = 0
        self.worker: WorkerEntry | None = None
        self.reassigned = 0
        self.bytes_relayed = 0
        self._status: pb.SubsceneStatus | None = None
        self._collected = None
        self._last_batches = 0
        self._last_plan = None
        self.interrupted = False  #: the job was cancelled: a worker it moves to is told at once
        self._state0 = sub.state()
        #: s of wall time in each kind of rpc (includes the worker's compute for iterate)
        self.rpc_seconds = {"load": 0.0, "iterate": 0.0, "deliver": 0.0, "checkpoint": 0.0}
        self.checkpoint_bytes = 0  #: bytes of checkpoints fetched
        self.compute_s = 0.0  #: s the workers spent iterating this subscene

    # -- files ------------------------------------------------------------------
    def _dir(self) -> Path:
        if self.folder is None:
            self._own_folder = tempfile.TemporaryDirectory(prefix="dcrad-subscene-")
            self.folder = Path(self._own_folder.name)
        self.folder.mkdir(parents=True, exist_ok=True)
        return self.folder

    def _save(self, name: str, make_chunks, keep=()) -> tuple[_Saved, dict]:
        """Stream ``make_chunks()`` into the file ``name``; a disk that refuses it: a second
        ``make_chunks()`` into memory (logged)."""
        try:
            return _Saved.write(self._dir() / name, make_chunks(), keep)
        except OSError as exc:
            log.warning("job %s cell %d: cannot write %s (%s); kept in memory, not durable",
                        self.job_id, self.cell, name, exc)
            return _Saved.in_memory(make_chunks(), keep)

    def _save_static(self) -> None:
        if self._static is None:
            return
        static = self._static
        self._static_saved, _ = self._save(static_file(self.cell), lambda: arrays_to_chunks(static))
        self._static = None

    def resume_from(self, path: Path, barrier: int) -> None:
        """Start from a checkpoint file on disk (a coordinator restart) at that barrier."""
        self._checkpoint = _Saved(path=Path(path))
        self._radiosity = self._checkpoint.read({"radiosity"})["radiosity"]
        self.barrier = barrier

    @property
    def checkpoint_path(self) -> Path | None:
        """The file of the last barrier's checkpoint (None: none yet, or kept in memory)."""
        return self._checkpoint.path if self._checkpoint is not None else None

    def saved_arrays(self, names: set[str]) -> dict:
        """Arrays of the subscene's state at the last barrier (the checkpoint's, else the loaded ones)."""
        if self._checkpoint is not None:
            return self._checkpoint.read(names)
        if self._static is not None:
            return {k: self._static[k] for k in names}
        assert self._static_saved is not None
        return self._static_saved.read(names)

    # -- placement --------------------------------------------------------------
    def _load(self, w: WorkerEntry) -> None:
        self._save_static()
        assert self._static_saved is not None
        static, ckpt = self._static_saved, self._checkpoint

        def requests():
            yield pb.LoadRequest(header=self.header)
            # the checkpoint's radiosity and unshot replace the loaded ones
            for c in static.chunks(skip={"radiosity", "unshot"} if ckpt is not None else ()):
                yield pb.LoadRequest(array=c)
            if ckpt is not None:
                for c in ckpt.chunks():
                    yield pb.LoadRequest(array=c)

        t0 = time.perf_counter()
        self._status = w.stub().Load(requests(), timeout=self.timeout)
        self.rpc_seconds["load"] += time.perf_counter() - t0
        self.worker = w
    def place(self, prefer: WorkerEntry | None = None) -> None:
        """Load on ``prefer`` (the job's placement by expected work) if it is alive, else on
        the least busy live worker, moving on when one fails."""
        tried: set[str] = set()
        while True:
            if prefer is not None and prefer.address not in tried and self.pool.take(prefer):
                w = prefer
            else:
                w = self.pool.pick(exclude=tried)
            try:
                self._load(w)
                return
            except grpc.RpcError as exc:
                self.pool.release(w)
                if exc.code() not in LOST:
                    raise
                self.pool.mark_dead(w)
                tried.add(w.address)

    def _failover(self, exc: grpc.RpcError) -> None:
        if exc.code() not in LOST:
            raise exc
        old = self.worker
        if old is not None:
            self.pool.mark_dead(old)
            self.pool.release(old)
        self.reassigned += 1
        log.warning("job %s cell %d: worker %s lost (%s); resuming from the last barrier",
                    self.job_id, self.cell, old.address if old else "?", exc.code().name)
        self.place()

    def _stub(self) -> pb_grpc.WorkerStub:
        if self.worker is None:
            raise NoWorkers(f"job {self.job_id} cell {self.cell} is on no worker")
        return self.worker.stub()

    # -- the handle interface ------------------------------------------------------
    def _iterate_once(self, n: int, plan=None):
        t0 = time.perf_counter()
        if self.interrupted:  # a worker taken over after the cancel shoots nothing either
            self._tell_interrupt()
        request = pb.IterateRequest(key=self.key, batches=n, **plan_fields(plan))
        replies = self._stub().Iterate(request, timeout=self.timeout)
        arrays, status = _gather(replies)
        self.rpc_seconds["iterate"] += time.perf_counter() - t0
        return boundary_mode(self.mode).buffer.from_arrays(arrays), status

    def iterate(self, n: int, plan=None) -> int:
        self._last_batches, self._last_plan = n, plan
        while True:
            try:
                buf, status = self._iterate_once(n, plan)
                break
            except grpc.RpcError as exc:
                self._failover(exc)
        before = self._status.rays if self._status is not None else 0
        prev = self._status.compute_s if self._status is not None else 0.0
        self.compute_s += max(0.0, status.compute_s - prev) if status.compute_s >= prev else status.compute_s
        self._status, self._collected = status, buf
        return status.rays - before

    def collect(self):
        out, self._collected = self._collected, None
        self.bytes_relayed += out.nbytes()
        return out

    def deliver(self, buffer) -> None:
        arrays = buffer.to_arrays()
        while True:
            try:
                def requests():
                    yield pb.DeliverRequest(key=self.key)
                    for c in arrays_to_chunks(arrays):
                        yield pb.DeliverRequest(array=c)

                t0 = time.perf_counter()
                self._status = self._stub().Deliver(requests(), timeout=self.timeout)
                t1 = time.perf_counter()
                self._fetch_checkpoint(self.barrier + 1)
                self.barrier += 1
                self.rpc_seconds["deliver"] += t1 - t0
                self.rpc_seconds["checkpoint"] += time.perf_counter() - t1
                return
            except grpc.RpcError as exc:
                # the new worker starts from the previous barrier: replay this barrier's
                # iterate (deterministic: same buffer, same state), then deliver again
                self._failover(exc)
                try:
                    self._iterate_once(self._last_batches, self._last_plan)
                except grpc.RpcError as again:
                    self._failover(again)

    def _fetch_checkpoint(self, barrier: int) -> None:
        """The worker's state after this barrier's deliver, streamed into its file; only the
        radiosity stays in memory.  (The Checkpoint call changes nothing on the worker, so a
        refused file is simply fetched again, into memory.)"""
        def stream():
            return self._stub().Checkpoint(self.key, timeout=self.timeout)

        saved, kept = self._save(cell_file(self.cell, barrier), stream, keep={"radiosity"})
        self._checkpoint, self._radiosity = saved, kept["radiosity"]
        self.checkpoint_bytes += saved.nbytes

    def state(self) -> SubsceneState:
        s = self._status
        if s is None:
            return self._state0
        tallies = np.array(list(s.return_tallies) or [0.0] * 12, np.float64).reshape(4, 3)
        return SubsceneState(self.cell, ledger_from_pb(s.ledger), s.shots, s.rays, s.twin_entries, s.twin_bytes,
                             s.area, tallies, s.twins_delivered, s.twin_blocks, s.batches, s.trace_s,
                             np.array(s.back_by_obj, np.float64),
                             NoiseSums.from_list(s.noise) if len(s.noise) else None)

    def radiosity(self) -> np.ndarray:
        """(n,3) radiosity of the subscene's patches at the last barrier."""
        return self._radiosity

    def interrupt(self) -> None:
        """End the worker's doIterations in flight after its current batch (the job was cancelled);
        a worker gone or never reached is left alone (the job stops at the barrier anyway)."""
        self.interrupted = True
        if self.worker is not None:
            try:
                self._tell_interrupt()
            except grpc.RpcError as exc:
                log.info("job %s cell %d: interrupt not delivered: %s", self.job_id, self.cell, exc.code())

    def _tell_interrupt(self) -> None:
        self._stub().Interrupt(self.key, timeout=10)

    def drop(self) -> None:
        """Free the subscene on its worker and what the handle holds (a second call does nothing)."""
        if self.worker is not None:
            try:
                self._stub().Drop(self.key, timeout=10)
            except grpc.RpcError:
                pass
            self.pool.release(self.worker)
            self.worker = None
        self._radiosity = np.zeros((0, 3))
        self._static = None
        if self._own_folder is not None:
            self._own_folder.cleanup()
            self._own_folder = None
