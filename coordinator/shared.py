"""A shared run's shares on remote workers (``dcrad.share``), behind ``LocalShares``' two methods.

Each share is one ``Share`` call: the header, the patch table the first time a
worker serves the job (it keeps it, with its Embree scene, until ``drop``), and
the phase's input; the reply streams the result arrays.  The shares of a phase
run at once, one thread each, on the least loaded live workers; a share index
stays on its worker from phase to phase (its pilot, its final gather's rounds are
held there).  A share is a
pure function of its inputs, so one whose worker is lost (``remote.LOST``) runs
again on another live worker with the same result; a worker that lost the patch
table (restarted) gets it again.  A stop request cancels the calls in flight.
"""

from __future__ import annotations

import logging
import threading
from concurrent.futures import ThreadPoolExecutor

import grpc
import numpy as np

from dcrad.config import SolverConfig
from dcrad.direct import shared_rate
from dcrad.errors import DcradError
from dcrad.settings import to_pb
from dcrad.share import Replica, tally_from_arrays, tally_to_arrays
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.wire import ArrayAssembler, arrays_to_chunks

from .remote import LOST, NoWorkers, WorkerEntry, WorkerPool

log = logging.getLogger("dcrad.coordinator")


class Cancelled(DcradError):
    """The job was cancelled while its shares ran."""


class RemoteShares:
    """The shares of one job on the pool's workers."""

    def __init__(self, job_id: str, patches, config: SolverConfig, pool: WorkerPool, timeout: float = 600.0):
        self.job_id, self.patches, self.config, self.pool, self.timeout = job_id, patches, config, pool, timeout
        self.settings = to_pb(config, pb.SolverSettings)
        self.loaded: set[str] = set()  #: addresses holding the patch table
        self.used: set[str] = set()  #: addresses that served a share
        self.placed: dict[int, WorkerEntry] = {}  #: the worker of each share index (kept while alive)
        self.reassigned = 0  #: shares run again after their worker was lost
        self.bytes_sent = 0
        self._calls: list = []
        self._lock = threading.Lock()
        self.cancelled = False

    def _requests(self, phase: str, index: int, count: int, inputs: dict, with_scene: bool):
        header = pb.ShareHeader(job_id=self.job_id, phase=phase, index=index, count=count, solver=self.settings,
                                names=list(self.patches.names), scene=with_scene)
        yield pb.ShareRequest(header=header)
        arrays = dict(inputs)
        if with_scene:
            arrays |= {f"scene_{k}": v for k, v in self.patches.table_arrays().items()}
        for chunk in arrays_to_chunks(arrays):
            self.bytes_sent += len(chunk.data)
            yield pb.ShareRequest(array=chunk)

    def _call(self, phase: str, index: int, count: int, inputs: dict) -> dict:
        exclude: set[str] = set()
        while True:
            if self.cancelled:
                raise Cancelled("cancelled")
            w: WorkerEntry | None = self.placed.get(index)
            if w is None or w.address in exclude or not self.pool.take(w):
                try:
                    w = self.pool.pick(exclude)
                except NoWorkers:
                    raise NoWorkers(f"no live worker can take {phase} share {index} of {count}") from None
            self.placed[index] = w  # the same worker for the share's next phase (its pilot, its gather)
            try:
                for attempt in range(2):
                    with_scene = w.address not in self.loaded
                    replies = w.stub().Share(self._requests(phase, index, count, inputs, with_scene),
                                             timeout=self.timeout)
                    with self._lock:
                        self._calls.append(replies)
                    try:
                        asm = ArrayAssembler()
                        for chunk in replies:
                            asm.add(chunk)
                        self.loaded.add(w.address)
                        self.used.add(w.address)
                        return asm.result()
                    except grpc.RpcError as exc:
                        if exc.code() == grpc.StatusCode.NOT_FOUND and attempt == 0:
                            self.loaded.discard(w.address)  # restarted: it needs the table again
                            continue
                        raise
                    finally:
                        with self._lock:
                            self._calls.remove(replies)
            except grpc.RpcError as exc:
                if self.cancelled:
                    raise Cancelled("cancelled") from None
                if exc.code() not in LOST:
                    raise DcradError(f"worker {w.address} refused {phase} share {index}: {exc.details()}") from None
                log.warning("job %s: worker %s lost during %s share %d (%s); it runs elsewhere", self.job_id,
                            w.address, phase, index, exc.code().name)
                self.pool.mark_dead(w)
                self.loaded.discard(w.address)
                exclude.add(w.address)
                self.reassigned += 1
            finally:
                self.pool.release(w)

    def _all(self, phase: str, inputs: list[dict]) -> list[dict]:
        k = len(inputs)
        with ThreadPoolExecutor(max_workers=k) as ex:
            futures = [ex.submit(self._call, phase, i, k, inp) for i, inp in enumerate(inputs)]
            return [f.result() for f in futures]

    def direct(self, shares: list[np.ndarray]):
        """Each share's pilot, then its gather at the shared rate (``direct.shared_rate``): the pilot
        stays on its worker in between; a worker that lost it pilots again (same stream, same light)."""
        rows = [{"rows": np.asarray(r, np.int64)} for r in shares]
        pilots = self._all("pilot", rows)
        if any(not a for a in pilots):
            return [None] * len(shares)
        rate = shared_rate([(float(a["pilot"][0]), float(a["pilot"][1])) for a in pilots])
        out = self._all("direct", [r | {"rate": np.array([rate])} for r in rows])
        return [tally_from_arrays(a, len(self.patches)) if a else None for a in out]

    def replicas(self, direct, k: int, should_stop=None, time_left: float = 0.0) -> list[Replica]:
        """The k replicas at once; ``time_left`` s of the job's time limit for each (0: none)."""
        tally = {f"tally_{name}": v for name, v in tally_to_arrays(direct).items()}
        if time_left:
            self.settings.time_limit = time_left
        stop = threading.Event()
        watcher = None
        if should_stop is not None:
            def watch():
                while not stop.wait(0.2):
                    if should_stop():
                        self.stop()
                        return
            watcher = threading.Thread(target=watch, name=f"share-stop-{self.job_id}", daemon=True)
            watcher.start()
        try:
            out = self._all("replica", [tally] * k)
        finally:
            stop.set()
        return [Replica.from_arrays(a, len(self.patches)) for a in out]

    def gather(self, shot, shares: list[np.ndarray], rounds: list[int]):
        """[(sum_a, sum_b, rays traced)] of each share's final gather after ``rounds``."""
        inputs = shot.to_arrays() | {"rounds": np.asarray(rounds, np.int64)}
        out = self._all("gather", [inputs | {"rows": np.asarray(r, np.int64)} for r in shares])
        for a, rows in zip(out, shares):
            if any(name not in a or np.shape(a[name]) != (len(rows), 3) for name in ("sum_a", "sum_b")):
                raise DcradError("a worker's gather share does not match its receivers")
        return [(a["sum_a"], a["sum_b"], int(a["traced"][0])) for a in out]

    def stop(self) -> None:
        """Ask every worker holding the job to end its replica cleanly (it returns what it has)."""
        header = pb.ShareHeader(job_id=self.job_id, phase="stop")
        for w in self.pool.live():
            try:
                for _ in w.stub().Share(iter([pb.ShareRequest(header=header)]), timeout=10):
                    pass
            except grpc.RpcError as exc:
                log.info("job %s: stop request to %s failed (%s)", self.job_id, w.address, exc.code().name)

    def cancel(self) -> None:
        """Cancel every call in flight (the job was cancelled)."""
        self.cancelled = True
        with self._lock:
            calls = list(self._calls)
        for c in calls:
            c.cancel()

    def drop(self) -> None:
        """The workers free the job's patch table."""
        for w in self.pool.live():
            if w.address in self.loaded:
                try:
                    w.stub().Drop(pb.SubsceneKey(job_id=self.job_id, cell=-1), timeout=10)
                except grpc.RpcError:
                    pass
        self.loaded.clear()
