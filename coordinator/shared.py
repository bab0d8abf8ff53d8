"""A shared run's shares on remote workers (``dcrad.solving.share``), behind ``LocalShares``' two methods.

Each share is one ``Share`` call: the header, the patch table the first time a
worker serves the job (it keeps it, with its Embree scene, until ``drop``), and
the phase's input; the reply streams the result arrays.  The shares of a phase
run at once, one thread each, on the least loaded live workers; a share index
stays on its worker from phase to phase (its pilot, its final gather's rounds are
held there).  A share is a
pure function of its inputs, so one whose worker is lost (``remote.LOST``) runs
again on another live worker with the same result; a worker that lost the patch
table (restarted) gets it again.  A stop request reaches the workers in every phase (``_watching``):
their shares end at their next batch.
The direct and gather phases have more shares than workers (``share.work_shares``),
taken one at a time by each worker as it comes free (``_queued``); the gather's shot
solution goes to each worker once.
"""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import grpc
import numpy as np

from dcrad.config import SolverConfig
from dcrad.errors import DcradError
from dcrad.settings import to_pb
from dcrad.solving.share import Replica, tally_from_arrays, tally_to_arrays
from dcrad.transport.direct import GatherStopped, shared_rate
from dcrad.transport.source_wire import sources_table
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.wire import ArrayAssembler, arrays_to_chunks, share_phase

from .remote import LOST, NoWorkers, WorkerEntry, WorkerPool

log = logging.getLogger("dcrad.coordinator")

#: seconds between two looks at the job's stop request while a phase's shares run
STOP_POLL = 0.2


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
        #: a stop was asked of the workers (``stop``): a share they end early answers CANCELLED
        self.stopping = False
        self.shot_on: set[str] = set()  #: addresses holding the gather's shot solution (sent once each)
        #: set while no request is streaming: the job's display waits for it (a preview rendered while
        #: the gather's shot streamed to the workers held the coordinator's GIL: 0.75 s to read 19 MB)
        self.quiet = threading.Event()
        self.quiet.set()
        self._streaming = 0

    def _requests(self, phase: str, index: int, count: int, inputs: dict, with_scene: bool, with_shot: bool = True):
        """The Share call's stream: the header, then each group of arrays in its own field of
        ShareRequest (``inputs``: group -> arrays; the patch table as ``scene`` when ``with_scene``,
        the shot solution only ``with_shot``)."""
        header = pb.ShareHeader(job_id=self.job_id, phase=share_phase(phase), index=index, count=count,
                                solver=self.settings, names=list(self.patches.names), scene=with_scene)
        with self._lock:
            self._streaming += 1
            self.quiet.clear()
        try:
            yield pb.ShareRequest(header=header)
            groups = {g: arrays for g, arrays in inputs.items() if with_shot or g != "shot"}
            if with_scene:  # the patch table and its light sources that are not patches
                groups["scene"] = self.patches.table_arrays() | sources_table(self.patches.sources)
            for group, arrays in groups.items():
                for chunk in arrays_to_chunks(arrays):
                    self.bytes_sent += len(chunk.data)
                    yield pb.ShareRequest(**{group: chunk})
        finally:
            with self._lock:
                self._streaming -= 1
                if not self._streaming:
                    self.quiet.set()

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
                    with_shot = w.address not in self.shot_on  # the worker keeps it for the job
                    sent = time.perf_counter()
                    replies = w.stub().Share(self._requests(phase, index, count, inputs, with_scene, with_shot),
                                             timeout=self.timeout)
                    with self._lock:
                        self._calls.append(replies)
                    try:
                        asm = ArrayAssembler()
                        for chunk in replies:
                            asm.add(chunk)
                        self.loaded.add(w.address)
                        self.used.add(w.address)
                        if "shot" in inputs:
                            self.shot_on.add(w.address)
                        log.info("job %s: %s share %d back from %s %.2f s after it was sent", self.job_id, phase,
                                 index, w.address, time.perf_counter() - sent)
                        return asm.result()
                    except grpc.RpcError as exc:
                        if exc.code() == grpc.StatusCode.NOT_FOUND and attempt == 0:
                            self.loaded.discard(w.address)  # restarted: it needs the table again
                            self.shot_on.discard(w.address)
                            continue
                        raise
                    finally:
                        with self._lock:
                            self._calls.remove(replies)
            except grpc.RpcError as exc:
                if self.cancelled:
                    raise Cancelled("cancelled") from None
                if self.stopping and exc.code() == grpc.StatusCode.CANCELLED:
                    # a pilot or direct share ended by the stop: nothing of the gather is booked
                    raise GatherStopped(f"{phase} share {index} stopped") from None
                if exc.code() not in LOST:
                    raise DcradError(f"worker {w.address} refused {phase} share {index}: {exc.details()}") from None
                log.warning("job %s: worker %s lost during %s share %d (%s); it runs elsewhere", self.job_id,
                            w.address, phase, index, exc.code().name)
                self.pool.mark_dead(w)
                self.loaded.discard(w.address)
                self.shot_on.discard(w.address)
                exclude.add(w.address)
                self.reassigned += 1
            finally:
                self.pool.release(w)

    def _all(self, phase: str, inputs: list[dict]) -> list[dict]:
        """One share per worker, all at once (the replicas)."""
        k = len(inputs)
        with ThreadPoolExecutor(max_workers=k) as ex:
            futures = [ex.submit(self._call, phase, i, k, inp) for i, inp in enumerate(inputs)]
            return [f.result() for f in futures]

    def _queued(self, phase: str, inputs: list[dict], sticky: bool = False) -> list[dict]:
        """The shares of a phase, one at a time per live worker, each worker taking the next as it
        comes free (``share.work_shares`` orders them big ones first): first those placed on it by
        an earlier phase (its pilot, its gather's rounds are held there), then unplaced ones, then
        (unless ``sticky``) the last share waiting for another worker, which it runs from the
        start (a share is a pure function of its inputs: the same result wherever it runs)."""
        n = len(inputs)
        results: list[dict | None] = [None] * n
        pending = list(range(n))
        lock = threading.Lock()
        errors: list[BaseException] = []

        def placed_on(i: int) -> WorkerEntry | None:
            w = self.placed.get(i)
            return w if w is not None and w.alive else None

        def next_for(w: WorkerEntry) -> int | None:
            mine = [i for i in pending if (p := placed_on(i)) is not None and p.address == w.address]
            free = [i for i in pending if placed_on(i) is None]
            if mine or free:
                return (mine or free)[0]
            return None if sticky or not pending else pending[-1]

        def serve(w: WorkerEntry) -> None:
            while w.alive and not errors and not self.cancelled:
                with lock:
                    i = next_for(w)
                    if i is None:
                        return
                    pending.remove(i)
                    self.placed[i] = w
                try:
                    results[i] = self._call(phase, i, n, inputs[i])
                except BaseException as exc:  # noqa: BLE001 - raised below, in the caller's thread
                    errors.append(exc)
                    return

        workers = self.pool.live()
        if not workers:
            raise NoWorkers(f"no live worker can take the {phase} shares")
        threads = [threading.Thread(target=serve, args=(w,), name=f"share-{phase}-{self.job_id}")
                   for w in workers]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        if errors:
            raise errors[0]
        for i in list(pending):  # their workers were lost while they waited (sticky): anywhere now
            results[i] = self._call(phase, i, n, inputs[i])
        return [r if r is not None else {} for r in results]

    @contextmanager
    def _watching(self, should_stop):
        """While a phase runs: ``should_stop()`` True asks the workers to stop (``stop``), polled
        every STOP_POLL s, so that a stop is answered at the workers' next batch in every phase."""
        done = threading.Event()
        if should_stop is not None:
            def watch():
                while not done.wait(STOP_POLL):
                    if should_stop():
                        self.stop()
                        return
            threading.Thread(target=watch, name=f"share-stop-{self.job_id}", daemon=True).start()
        try:
            yield
        finally:
            done.set()

    def direct(self, shares: list[np.ndarray], should_stop=None):
        """Each share's pilot, then its gather at the shared rate (``direct.shared_rate``): the pilot
        stays on its worker in between; a worker that lost it pilots again (same stream, same light).
        A stop (``should_stop``) raises direct.GatherStopped, as ``LocalShares.direct``."""
        rows = [{"array": {"rows": np.asarray(r, np.int64)}} for r in shares]
        with self._watching(should_stop):
            pilots = self._queued("pilot", rows)
            if any(not a for a in pilots):
                return [None] * len(shares)
            rate = shared_rate([(float(a["pilot"][0]), float(a["pilot"][1])) for a in pilots])
            if self.stopping:
                raise GatherStopped("stopped between the pilots and the gather")
            out = self._queued("direct", [{"array": r["array"] | {"rate": np.array([rate])}} for r in rows])
        return [tally_from_arrays(a, len(self.patches)) if a else None for a in out]

    def replicas(self, direct, k: int, should_stop=None, time_left: float = 0.0) -> list[Replica]:
        """The k replicas at once; ``time_left`` s of the job's time limit for each (0: none)."""
        tally = {"tally": tally_to_arrays(direct)}
        if time_left:
            self.settings.time_limit = time_left
        with self._watching(should_stop):
            out = self._all("replica", [tally] * k)
        return [Replica.from_arrays(a, len(self.patches)) for a in out]

    def gather(self, shot, shares: list[np.ndarray], rounds: list[int], should_stop=None):
        """[(sum_a, sum_b, rays traced)] of each share's final gather after ``rounds``; a stop
        (``should_stop``) ends each share's round at its next batch (the receivers reached keep it)."""
        inputs = {"shot": shot.to_arrays(), "array": {"rounds": np.asarray(rounds, np.int64)}}
        if len(rounds) == 1:  # a new shot: the placements were the direct shares'
            self.shot_on.clear()
            for i in range(len(shares)):
                self.placed.pop(i, None)
        # after the first round a share's gather so far is held on its worker: it stays there
        with self._watching(should_stop):
            out = self._queued("gather", [inputs | {"array": inputs["array"] | {"rows": np.asarray(r, np.int64)}}
                                          for r in shares], sticky=len(rounds) > 1)
        for a, rows in zip(out, shares):
            if any(name not in a or np.shape(a[name]) != (len(rows), 3) for name in ("sum_a", "sum_b")):
                raise DcradError("a worker's gather share does not match its receivers")
        return [(a["sum_a"], a["sum_b"], int(a["traced"][0])) for a in out]

    def stop(self) -> None:
        """Ask every worker holding the job to end its share cleanly: a replica or a gather returns what
        it has, a pilot or direct share answers CANCELLED (``_call``: GatherStopped)."""
        self.stopping = True
        header = pb.ShareHeader(job_id=self.job_id, phase=share_phase("stop"))
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
