"""The outputs' views made ahead, in a process of its own at nice 19 (``pipeline.table_views``).

What the outputs need that does not depend on B (cameras, both views' primary hits, the
corner pairs, the live preview's view: about 2.5 CPU s at 201k patches) is made while the
workers solve, in a child process at the lowest priority: it runs on what the workers
leave of the CPUs and never holds the coordinator's GIL.  (In a nice-10 thread of the
coordinator it did, while the job streamed shares: the 8x8 office's shared solve took
23-24 s, against 20-22 s without the views ahead and 18.4-20 s with them in a process.)

The child is ``python -m coordinator.ahead``: it imports what it needs, lowers itself to nice
19, then reads the patch table from its stdin and writes the views to its stdout (pickles,
from a thread of the coordinator).  It is not a multiprocessing "spawn" child: that one
re-imported the coordinator's main module, and ``Process.start`` blocked the job until the
child had read its arguments: 0.27 s of the 8x8 office's start.

After the views, the child keeps the patch table, the views and the corner pairs (formed at any
size, in its own memory) and waits for B: ``paint`` sends B and the illuminance once the job is
solved (jobs.py does where its own views came without the pairs: above render.KEEP_PAIRS), and
the child writes scene.glb and the preview and illuminance images
(``pipeline.write_pictures``, at the coordinator's priority) while the coordinator writes
radiosity.npz and patches.ply (at the 20x20 office: the smoothing, the GLB, the two views' shading
and their images, about 6 s of the outputs' single-threaded 8-10 s).  If it fails or dies, the
coordinator writes them itself (``pipeline.write_outputs``): the same files.

The child ends once it has sent the pictures, when its stdin closes, when ``close()`` is called, or
when the coordinator is gone (its parent pid changes: a SIGKILLed coordinator leaves nothing).

One child is kept started ahead (``prestart``: the coordinator starts one once it listens, and
each job that takes it starts the next at nice 19 from its first line), so a job's views do not
begin with 0.6 CPU s of imports: on the 8x8 office they ran beside the patch table's streaming to
the workers, which took 0.5 s where it takes 0.05 s alone.
"""

from __future__ import annotations

import logging
import os
import pickle
import subprocess
import sys
import threading
import traceback
from concurrent.futures import Future

from dcrad.errors import DcradError

from .embedded import DEATHSIG_ENV, PARENT_ENV, die_with_parent

log = logging.getLogger("dcrad.coordinator")

#: nice of the views process (the lowest: it runs on what the workers leave)
VIEWS_NICE = 19


def _child(nice_first: bool = False) -> int:
    """``python -m coordinator.ahead``: read (table, names, camera, width, height, live size) from
    stdin, write (True, OutputViews) or (False, traceback) to stdout; then read (out, B, lux,
    rotation), write the pictures there (``pipeline.write_pictures``) and (True, its result) or
    (False, traceback) to stdout."""
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # anything printed goes to the log, not into the result
    sys.stdout = sys.stderr
    # the coordinator is gone: so is this (its parent-pid watchdog; no death signal, which would
    # follow the job thread that started this process, not the coordinator)
    die_with_parent()
    # the views in a thread at nice 19 (Linux: nice is per thread); this one stays at the
    # coordinator's priority for the pictures, which come after the solve, when the job waits on them
    made: dict = {}
    sent, stop = threading.Event(), threading.Event()
    worker = threading.Thread(target=_views, args=(out, nice_first, made, sent, stop), name="views", daemon=True)
    worker.start()
    sent.wait()
    if "views" not in made:  # no job came, or its views failed: nothing to paint
        return 0
    try:
        request = pickle.load(sys.stdin.buffer)
    except EOFError:  # the job ended without its pictures (it failed, or it paints them itself)
        return 0
    finally:
        stop.set()  # the pairs formed so far are used; the pictures form the rest
    from dcrad.pipeline import write_pictures  # noqa: PLC0415 - imported by the views thread already

    result: tuple[bool, object]
    try:
        folder, radiosity, lux, rotation = request
        del request
        patches, views = made.pop("patches"), made.pop("views")
        patches.radiosity = radiosity
        result = (True, write_pictures(folder, patches, views, lux, rotation))
    except Exception:  # the coordinator writes them itself
        result = (False, traceback.format_exc())
    pickle.dump(result, out, protocol=pickle.HIGHEST_PROTOCOL)
    out.close()
    return 0


def _views(out, nice_first: bool, made: dict, sent: threading.Event, stop: threading.Event) -> None:
    """The views thread of ``_child``: the views to ``out``, then the corner pairs kept (at any size:
    this process's memory, not the coordinator's) until ``stop``."""
    result: tuple[bool, object]
    views = None
    try:
        try:
            # imported at the coordinator's priority (about 0.6 CPU s) unless started ahead of its job
            # (``nice_first``): at nice 19 from the start a job's own views came too late for a small
            # job's first live previews, which then formed their own
            if nice_first:
                _lower()
            from dcrad.pipeline import table_views  # noqa: PLC0415 - only the child needs it

            _lower()
            try:
                table, names, camera, width, height, live_size = pickle.load(sys.stdin.buffer)
            except EOFError:  # started ahead, and the coordinator ended before a job took it
                return
            patches, made_views = table_views(table, names, camera, width, height, live_size)
            del table
            result = (True, made_views)
        except Exception:  # the caller falls back to making its own views
            result = (False, traceback.format_exc())
        pickle.dump(result, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()
        if result[0]:
            views = made_views
            made.update(patches=patches, views=views)
    finally:
        sent.set()
    if views is not None and views.smoother is not None:
        views.smoother.keep(stop)


def _lower() -> None:
    try:
        os.nice(VIEWS_NICE - os.nice(0))
    except OSError:
        pass


_spare_lock = threading.Lock()
_spare: subprocess.Popen | None = None  #: a views process started ahead, waiting for its job


def _spawn(nice_first: bool) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "coordinator.ahead", *(["--nice-first"] if nice_first else [])]
    env = dict(os.environ, **{PARENT_ENV: str(os.getpid()), DEATHSIG_ENV: "0"})
    return subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)


def prestart(nice_first: bool = False) -> None:
    """Start a views process now, for the next job (module doc); no-op if one is waiting."""
    global _spare
    with _spare_lock:
        if _spare is None or _spare.poll() is not None:
            try:
                _spare = _spawn(nice_first)
            except OSError as exc:  # the job starts its own (or makes its views in a thread)
                log.warning("cannot start a views process ahead: %s", exc)


def _take() -> subprocess.Popen:
    """The views process started ahead if it is alive (the next is started, at nice 19 from its
    first line), else a new one."""
    global _spare
    with _spare_lock:
        proc, _spare = _spare, None
    if proc is not None and proc.poll() is None:
        prestart(nice_first=True)
        return proc
    return _spawn(False)


class ViewsAhead:
    """``future``: the ``OutputViews`` of ``patches`` (module doc), made in a child process;
    ``paint``: the pictures written by that process once B is known."""

    def __init__(self, patches, camera: dict | None, width: int, height: int, live_size: tuple[int, int]):
        self._proc = _take()
        self.future: Future = Future()
        args = (patches.table_arrays(), list(patches.names), camera, width, height, tuple(live_size))
        threading.Thread(target=self._run, args=(args,), name="views-ahead", daemon=True).start()

    def _run(self, args) -> None:
        proc = self._proc
        ok, result = False, "the views process ended without a result"
        try:
            assert proc.stdin is not None and proc.stdout is not None
            pickle.dump(args, proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            proc.stdin.flush()
            del args
            ok, result = pickle.load(proc.stdout)
        except (EOFError, OSError, ValueError, pickle.UnpicklingError) as exc:
            result = f"the views process ended without a result ({exc})"
        if ok:
            self.future.set_result(result)
        else:
            self.close()
            self.future.set_exception(DcradError(f"making the outputs' views ahead failed: {result}"))

    def paint(self, out, radiosity, lux, rotation) -> Future:
        """``pipeline.write_pictures`` into ``out`` by the views process, from B and ``lux`` (40 MB at
        1.27M patches through its stdin), while the coordinator writes the npz and PLY: a Future of its
        result, or of a DcradError if it failed (the process is ended then: it writes nothing more)."""
        done: Future = Future()

        def run() -> None:
            proc = self._proc
            ok, result = False, "the views process ended without the pictures"
            try:
                assert proc.stdin is not None and proc.stdout is not None
                self.future.result()  # its views first (they are in: the outputs used them)
                with proc.stdin:
                    pickle.dump((str(out), radiosity, lux, rotation), proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
                ok, result = pickle.load(proc.stdout)
            except (EOFError, OSError, ValueError, pickle.UnpicklingError, DcradError) as exc:
                result = f"the views process ended without the pictures ({exc})"
            if ok:
                done.set_result(result)
            else:
                self.close()
                done.set_exception(DcradError(f"writing the pictures in the views process failed: {result}"))

        threading.Thread(target=run, name="pictures", daemon=True).start()
        return done

    def close(self) -> None:
        """End the child now if it is still there (its work done, or a job that failed or was
        cancelled)."""
        if self._proc.poll() is None:
            self._proc.kill()
        self._proc.wait(10)
        for pipe in (self._proc.stdin, self._proc.stdout):
            if pipe is not None:
                try:
                    pipe.close()
                except OSError:
                    pass


if __name__ == "__main__":
    sys.exit(_child(nice_first="--nice-first" in sys.argv[1:]))
