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


def _child() -> int:
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
        # imported at the coordinator's priority (about 0.6 CPU s): at nice 19 from the start the
        # views came too late for a small job's first live previews, which then formed their own
        from dcrad.pipeline import views_of_table  # noqa: PLC0415 - only the child needs it

        try:
            os.nice(VIEWS_NICE)
        except OSError:
            pass
        table, names, camera, width, height, live_size = pickle.load(sys.stdin.buffer)
        result = (True, views_of_table(table, names, camera, width, height, live_size))
        del table
    except Exception:  # the caller falls back to making its own views
        result = (False, traceback.format_exc())
    pickle.dump(result, out, protocol=pickle.HIGHEST_PROTOCOL)
    out.close()
    return 0


class ViewsAhead:
    """``future``: the ``OutputViews`` of ``patches`` (module doc), made in a child process."""

    def __init__(self, patches, camera: dict | None, width: int, height: int, live_size: tuple[int, int]):
        cmd = [sys.executable, "-m", "coordinator.ahead"]
        env = dict(os.environ, **{PARENT_ENV: str(os.getpid()), DEATHSIG_ENV: "0"})
        self._proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
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
    sys.exit(_child())
