"""The outputs' views made ahead, in a process of its own at nice 19 (``pipeline.views_of_table``).

What the outputs need that does not depend on B (cameras, both views' primary hits, the
corner pairs, the live preview's view: about 2.5 CPU s at 201k patches) is made while the
workers solve, in a child process at the lowest priority: it runs on what the workers
leave of the CPUs and never holds the coordinator's GIL.  (In a nice-10 thread of the
coordinator it did, while the job streamed shares: the 8x8 office's shared solve took
23-24 s, against 20-22 s without the views ahead and 18.4-20 s with them in a process.)

The child ends once it has sent its one result, when ``close()`` is called, or when the
coordinator is gone (its parent pid changes: a SIGKILLed coordinator leaves nothing).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import threading
import traceback
from concurrent.futures import Future

from dcrad.errors import DcradError
from dcrad.pipeline import views_of_table

from .embedded import DEATHSIG_ENV, PARENT_ENV, die_with_parent

log = logging.getLogger("dcrad.coordinator")

#: nice of the views process (the lowest: it runs on what the workers leave)
VIEWS_NICE = 19


def _child(conn, parent: int, table: dict, names: list, camera: dict | None, width: int, height: int,
           live_size: tuple[int, int]) -> None:
    try:
        os.nice(VIEWS_NICE)
    except OSError:
        pass
    # the coordinator is gone: so is this (its parent-pid watchdog; no death signal, which would
    # follow the job thread that started this process, not the coordinator)
    die_with_parent({PARENT_ENV: str(parent), DEATHSIG_ENV: "0"})
    result: tuple[bool, object]
    try:
        result = (True, views_of_table(table, names, camera, width, height, live_size))
    except Exception:  # the caller falls back to making its own views
        result = (False, traceback.format_exc())
    del table
    conn.send(result)
    conn.close()


class ViewsAhead:
    """``future``: the ``OutputViews`` of ``patches`` (module doc), made in a child process."""

    def __init__(self, patches, camera: dict | None, width: int, height: int, live_size: tuple[int, int]):
        ctx = mp.get_context("spawn")  # never fork a process that runs gRPC threads
        self._recv, send = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_child, args=(send, os.getpid(), patches.table_arrays(), list(patches.names),
                                                      camera, width, height, tuple(live_size)),
                                 name="dcrad-views", daemon=True)
        self._proc.start()
        send.close()
        self.future: Future = Future()
        threading.Thread(target=self._wait, name="views-ahead", daemon=True).start()

    def _wait(self) -> None:
        try:
            ok, result = self._recv.recv()
        except (EOFError, OSError):
            ok, result = False, "the views process ended without a result"
        finally:
            self._recv.close()
        self._proc.join(10)
        if ok:
            self.future.set_result(result)
        else:
            self.future.set_exception(DcradError(f"making the outputs' views ahead failed: {result}"))

    def close(self) -> None:
        """End the child now if it is still at work (a job that failed or was cancelled)."""
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(10)
