"""The outputs' views made ahead, in a process of its own at nice 19 (``pipeline.views_of_table``).

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

The child ends once it has sent its one result, when ``close()`` is called, or when the
coordinator is gone (its parent pid changes: a SIGKILLed coordinator leaves nothing).

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
    stdin, write (True, OutputViews) or (False, traceback) to stdout."""
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # anything printed goes to the log, not into the result
    sys.stdout = sys.stderr
    # the coordinator is gone: so is this (its parent-pid watchdog; no death signal, which would
    # follow the job thread that started this process, not the coordinator)
    die_with_parent()
    result: tuple[bool, object]
    try:
        # imported at the coordinator's priority (about 0.6 CPU s) unless started ahead of its job
        # (``nice_first``): at nice 19 from the start a job's own views came too late for a small
        # job's first live previews, which then formed their own
        if nice_first:
            _lower()
        from dcrad.pipeline import views_of_table  # noqa: PLC0415 - only the child needs it

        _lower()
        try:
            table, names, camera, width, height, live_size = pickle.load(sys.stdin.buffer)
        except EOFError:  # started ahead, and the coordinator ended before a job took it
            return 0
        result = (True, views_of_table(table, names, camera, width, height, live_size))
        del table
    except Exception:  # the caller falls back to making its own views
        result = (False, traceback.format_exc())
    pickle.dump(result, out, protocol=pickle.HIGHEST_PROTOCOL)
    out.close()
    return 0


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
    """``future``: the ``OutputViews`` of ``patches`` (module doc), made in a child process."""

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
            with proc.stdin:
                pickle.dump(args, proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            del args
            ok, result = pickle.load(proc.stdout)
        except (EOFError, OSError, pickle.UnpicklingError) as exc:
            result = f"the views process ended without a result ({exc})"
        finally:
            if proc.stdout is not None:
                proc.stdout.close()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
        if ok:
            self.future.set_result(result)
        else:
            self.future.set_exception(DcradError(f"making the outputs' views ahead failed: {result}"))

    def close(self) -> None:
        """End the child now if it is still at work (a job that failed or was cancelled)."""
        if self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait(10)


if __name__ == "__main__":
    sys.exit(_child(nice_first="--nice-first" in sys.argv[1:]))
