"""What the status page shows of a running job, and what the coordinator logs of itself.

``LivePreview`` renders preview PNGs of the assembled radiosity (at most one a barrier and one a
``preview_interval``, plus the final state); ``BarrierDisplay`` does that and keeps the error
curve's snapshots on a background thread, so a barrier does not wait for the pictures;
``ErrorCurve`` keeps the assembled B at geometrically spaced times and measures them against the
final solution when the run ends; ``MemoryLog`` logs the coordinator's RSS after each phase of a
job.  ``jobs.py`` wires them to the jobs.
"""

from __future__ import annotations

import logging
import math
import os
import resource
import shutil
import threading
import time
import traceback
import tracemalloc
from concurrent.futures import Future
from pathlib import Path

import numpy as np

from dcrad.io import export
from dcrad.outputs import render
from dcrad.pipeline import live_view
from dcrad.solving.energy import rms_error

log = logging.getLogger("dcrad.coordinator")

#: live previews take at most this share of the job's wall time (they render beside the workers)
PREVIEW_SHARE = 0.02
#: nice of the coordinator's background threads (display, views built ahead)
BACKGROUND_NICE = 10


class LivePreview:
    """Preview PNGs of the assembled radiosity, for the status page.

    ``due()`` is true at most once per ``interval`` seconds, and only after
    ``1 / PREVIEW_SHARE`` times the last render's shading (a 4 s render of a
    million patches waits 200 s; forming the view and corner pairs once is not
    counted), so previews cost at most 2% of the solve's wall time; the result's
    own preview shows the final state.  Renders run in the job's
    ``BarrierDisplay`` thread, never in the barrier loop.  ``current`` is (version, barrier, png
    bytes), replaced atomically; version 0 means no preview yet.  A failing render is logged and turns
    previews off; it never fails the job.
    """

    def __init__(self, scene, patches, folder: Path, size=(320, 240), interval: float = 2.0,
                 ahead: Future | None = None):
        self.scene, self.patches, self.folder = scene, patches, Path(folder)
        self.size, self.interval = size, interval
        #: the outputs' views made ahead (``JobManager._views_ahead``): once they are there, their
        #: corner pairs and live view serve the previews too (nothing formed twice)
        self.ahead = ahead
        self.smoother: render.CornerSmoother | None = None  #: formed at the first render
        self.current: tuple[int, int, bytes] = (0, -1, b"")
        self.seconds = 0.0  #: total render time
        self._last = -math.inf
        self._cost = 0.0  # s the last render took
        self._view: render.ViewHits | None = None  # traced on first use (its Embree scene is not kept)
        self._broken = False

    @property
    def barrier(self) -> int:
        return self.current[1]

    def close(self) -> None:
        """Free the scene, patch table and view; ``current`` stays for the page."""
        self.scene = self.patches = self._view = self.smoother = self.ahead = None
        self._broken = True

    def due(self) -> bool:
        wait = max(self.interval, self._cost / PREVIEW_SHARE)
        return not self._broken and time.monotonic() - self._last >= wait

    def render(self, b: np.ndarray, barrier: int) -> None:
        if self._broken:
            return
        t0 = t_shade = time.perf_counter()
        try:
            path = self.folder / "preview-live.png"
            if (self._view is None or self.smoother is None) and self.ahead is not None and self.ahead.done():
                views = self.ahead.result() if self.ahead.exception() is None else None
                if views is not None and views.live is not None and views.smoother is not None:
                    self._view, self.smoother = views.live, views.smoother
            if self._view is None or self.smoother is None:  # the visible patches' corners only
                self._view = live_view(self.scene, self.patches, *self.size)
                self.smoother = render.CornerSmoother(self.patches, rows=np.unique(self._view.patch))
            t_shade = time.perf_counter()  # what each preview costs from now on (the view is kept)
            export.write_png(path, render.tonemap(render.shade_view(self._view, self.smoother.apply(b))))
            self.current = (self.current[0] + 1, barrier, path.read_bytes())
        except Exception:  # a preview must never stop a solve
            self._broken = True
            log.warning("preview rendering failed; no more previews for this job\n%s", traceback.format_exc())
        # the next preview waits on this one's shading, not on the one-off view and corner pairs: a
        # first render that formed them (1 s on the 2x3 office, the views process not done yet) held
        # the next one back 50 s
        self._cost = time.perf_counter() - t_shade
        self.seconds += time.perf_counter() - t0
        self._last = time.monotonic()


def background() -> None:
    """Lower this thread's CPU priority (Linux: nice is per thread): the display and the views built
    ahead use what the workers leave of the coordinator's CPUs (on 2 cores with 2 local workers
    they otherwise take a core's share from the solve)."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), BACKGROUND_NICE)
    except (OSError, AttributeError):
        pass


#: s a display waits at most for the workers' requests to be sent (BarrierDisplay.quiet)
QUIET_WAIT = 30.0


class BarrierDisplay:
    """What the status page shows, kept off the barrier loop: assemble B, record the error
    curve, render previews.

    ``offer`` (in the job thread, at a barrier) only queues the state and returns; a
    daemon thread does the work: every state goes to the error curve (which keeps
    geometrically spaced times), the latest to the preview when one is due.  (Keeping
    only the latest state lost a barrier from the curve while a preview rendered.)
    ``close`` finishes the pending states (the curve; no preview: the outputs make the final
    state's) and ends the thread.
    """

    def __init__(self, assemble_b, curve: "ErrorCurve", preview: LivePreview, count,
                 quiet: threading.Event | None = None):
        self.assemble_b, self.curve, self.preview, self.count = assemble_b, curve, preview, count
        #: the work waits while this is clear (a shared run's requests streaming to the workers)
        self.quiet = quiet
        self.seconds = 0.0  #: s of display work (assembly, curve, previews)
        self.cpu_seconds = 0.0  #: CPU s of it (its thread's: at nice 10 its wall s overstate it)
        self._queue: list[tuple[float, int, np.ndarray]] = []  # (elapsed, barrier, values)
        self._closed = False
        self._cv = threading.Condition()
        self._thread = threading.Thread(target=self._loop, name="barrier-display", daemon=True)
        self._thread.start()

    def offer(self, elapsed: float, barrier: int, values: np.ndarray) -> None:
        """values: the subscenes' radiosity at this barrier, concatenated (a copy the thread owns)."""
        with self._cv:
            self._queue.append((elapsed, barrier, values))
            self._cv.notify()

    def _loop(self) -> None:
        background()
        while True:
            with self._cv:
                self._cv.wait_for(lambda: bool(self._queue) or self._closed)
                if not self._queue:
                    return
                todo, self._queue = self._queue, []
            for i, (elapsed, barrier, values) in enumerate(todo):
                if self.quiet is not None:
                    self.quiet.wait(QUIET_WAIT)
                t0, c0 = time.perf_counter(), time.thread_time()
                try:
                    b = self.assemble_b(values)
                    self.curve.record(elapsed, barrier, b)
                    # once closed, the last state's preview is the outputs' own (the job copies it):
                    # rendering it here held the outputs back
                    if i == len(todo) - 1 and not self._closed and self.preview.due():
                        self.preview.render(b, barrier)
                        self.count(previews=1)
                except Exception:  # the display must never stop a solve
                    log.warning("live display failed at barrier %d\n%s", barrier, traceback.format_exc())
                self.seconds += time.perf_counter() - t0
                self.cpu_seconds += time.thread_time() - c0

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify()
        self._thread.join()


class ErrorCurve:
    """RMS error against wall time: what the status page plots.

    While running, the assembled B (float32) is kept at geometrically spaced
    times (each kept time >= ``ratio`` times the previous, plus the latest), so
    the count grows with log(run time), not with the barriers.  With a ``folder``
    the states are kept there as .npy files, not in memory (a 1.3M-patch B is
    15 MB).  ``measure`` then computes each kept state's area-weighted RMS error
    against the final B and frees the states.
    """

    def __init__(self, ratio: float = 1.05, cap: int = 400, folder: Path | None = None):
        self.ratio, self.cap, self.folder = ratio, cap, folder
        self.kept: list[tuple[float, int, np.ndarray | Path]] = []  # (elapsed s, barrier, B or its file)
        self._tail = False  # the last kept entry is only "the latest"
        self.measured: list[tuple[float, float, int]] | None = None  # (elapsed s, rms W/m^2, barrier)
        self.label = ""

    def _keep(self, barrier: int, b: np.ndarray) -> np.ndarray | Path:
        b32 = np.asarray(b, np.float32)
        if self.folder is None:
            return b32.copy()
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / f"B-{barrier:06d}.npy"
        np.save(path, b32)
        return path

    @staticmethod
    def _drop(entry: tuple[float, int, np.ndarray | Path]) -> None:
        if isinstance(entry[2], Path):
            entry[2].unlink(missing_ok=True)

    def record(self, t: float, barrier: int, b: np.ndarray) -> None:
        if self._tail:
            self._drop(self.kept.pop())
        anchor = self.kept[-1][0] if self.kept else None
        self.kept.append((t, barrier, self._keep(barrier, b)))
        self._tail = anchor is not None and t < anchor * self.ratio
        if len(self.kept) > self.cap:  # a very long run: halve the density
            last = self.kept[-1]
            for e in self.kept[1:-1:2]:
                self._drop(e)
            self.kept = self.kept[:-1:2] + [last]
            self.ratio *= self.ratio

    def measure(self, final: np.ndarray, area: np.ndarray, label: str, final_barrier: int | None = None) -> None:
        """RMS error of each kept state against ``final``; the final state itself (0 by
        construction, float32 round-off in practice) is left out."""
        self.measured = [(t, rms_error(np.load(b) if isinstance(b, Path) else b, final, area), k)
                         for t, k, b in self.kept if k != final_barrier]
        self.label = label
        self.clear()

    def clear(self) -> None:
        """Free the kept states (and their files)."""
        for e in self.kept:
            self._drop(e)
        self.kept = []
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)


def rss_mb() -> tuple[float, float]:
    """(resident set, its high-water mark) of this process in MB, from /proc (0, 0 elsewhere)."""
    try:
        st = dict(line.split(":", 1) for line in Path("/proc/self/status").read_text().splitlines() if ":" in line)
        return int(st["VmRSS"].split()[0]) / 1024, int(st["VmHWM"].split()[0]) / 1024
    except (OSError, KeyError, ValueError):
        return 0.0, 0.0


class MemoryLog:
    """The coordinator's RSS after each phase of a job: logged, and kept for the report.

    Under ``PYTHONTRACEMALLOC=1`` the log lines add the traced total and the largest
    allocation sites (what the RSS is made of, less Embree, gRPC and the allocator's slack).
    """

    def __init__(self, job_id: str):
        self.job_id = job_id
        self.phases: dict[str, float] = {}

    def __call__(self, phase: str) -> None:
        rss, peak = rss_mb()
        self.phases[phase] = round(max(rss, self.phases.get(phase, 0.0)), 1)  # a repeated phase: its max
        self.phases["peak"] = round(peak, 1)
        extra = ""
        if tracemalloc.is_tracing():
            cur, tpeak = tracemalloc.get_traced_memory()
            extra = f" (traced {cur / 2**20:.0f} MB, traced peak {tpeak / 2**20:.0f} MB)"
            top = tracemalloc.take_snapshot().statistics("lineno")[:8]
            extra += "".join(f"\n    {st.size / 2**20:8.1f} MB {st.traceback}" for st in top)
        use = resource.getrusage(resource.RUSAGE_SELF)
        log.info("job %s: coordinator RSS %.0f MB after %s, peak %.0f MB%s; so far %.1f user + %.1f system CPU s, "
                 "%d page faults", self.job_id, rss, phase, peak, extra, use.ru_utime, use.ru_stime, use.ru_minflt)
