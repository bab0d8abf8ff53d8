"""Durable jobs: the job record and per-subscene checkpoints on disk, under ``--data``.

Layout of one job (``DATA/jobs/ID/``)::

    job.json                     the record: spec, state, times, the resolved divide settings
    scene/                       the uploaded scene files (written by ``JobManager.create``)
    checkpoints/manifest.json    the last barrier whose checkpoints are all on disk
    checkpoints/cell-K-NNNNNN.ck cell K's checkpoint at barrier N (the worker's state after deliver)
    checkpoints/static-K.ck      cell K's patches and boundaries, as sent to its worker at load
    curve/                       the error curve's kept states while the job runs
    out/                         the results, once the job has ended

The coordinator holds no checkpoint in memory: ``RemoteSubscene`` streams each
checkpoint from its worker straight into its ``.ck`` file (``ChunkFile``: the
wire's ``ArrayChunk`` messages, length-prefixed, between a magic header and an
end mark), keeping only the subscene's radiosity for the live display; a
failover or a resume streams the files back to a worker.  Files are written to a
temporary name and renamed; the ``CheckpointWriter`` thread then fsyncs a
barrier's files and only after that writes the manifest naming them (atomically,
fsynced), so a crash mid-barrier resumes from the barrier before, and files no
manifest names any more are deleted.

Checkpoints are stored whole, not as changes since the last barrier: with exact
forwarding 98-99% of a subscene's rows change between barriers, and the
incremental encoding once used here saved 3% of the bytes on the 8x8 office
(``bench/bench_checkpoint.py``) while holding a second copy of every checkpoint
in memory.

No numerics here: the arrays are stored bit for bit, so a resumed subscene is the
one that was checkpointed.
"""

from __future__ import annotations

import base64
import json
import logging
import os
import re
import shutil
import struct
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TypedDict

from dcrad.v1 import dcrad_pb2 as pb
from dcrad.wire import ArrayAssembler

log = logging.getLogger("dcrad.coordinator")

__all__ = ["JobStore", "JobRecord", "Resume", "StoredPreview", "CheckpointWriter", "ChunkFile", "atomic_write",
           "fsync_file"]

RECORD = "job.json"
CHECKPOINTS = "checkpoints"
MANIFEST = "manifest.json"
VERSION = 1
#: manifest format: 2 names one whole .ck file per cell (1 was npz chains of changes)
MANIFEST_FORMAT = 2
_CELL_FILE = re.compile(r"cell-(\d+)-(\d+)\.ck$")


def cell_file(cell: int, barrier: int) -> str:
    """File name of cell's checkpoint at a barrier."""
    return f"cell-{cell}-{barrier:06d}.ck"


def static_file(cell: int) -> str:
    return f"static-{cell}.ck"


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write(path: Path, data: bytes, fsync: bool = True) -> None:
    """Write ``data`` to ``path`` so a crash leaves the old file or the new one, whole."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        if fsync:
            os.fsync(f.fileno())
    os.replace(tmp, path)
    if fsync:
        _fsync_dir(path.parent)


def fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


# == chunk files ======================================================================
class ChunkFile:
    """Arrays on disk as the wire's ``ArrayChunk`` messages: streamed in and out, never whole in memory.

    Layout: ``MAGIC``, then per chunk an 8-byte little-endian length and the serialized
    message, then a zero length (the end mark: a file cut short has none and is refused).
    """

    MAGIC = b"DCRADCK1"
    _LEN = struct.Struct("<Q")
    #: largest record accepted on reading (a chunk carries at most wire.CHUNK_BYTES of data)
    MAX_RECORD = 64 << 20

    @classmethod
    def write(cls, path: Path, chunks: Iterable[pb.ArrayChunk], keep: Iterable[str] = ()) -> tuple[int, dict]:
        """Write chunks to ``path`` (a temporary name, then renamed; not fsynced).

        Returns (payload bytes, {name: array} for the names in ``keep``, assembled as they pass).
        """
        path = Path(path)
        keep = set(keep)
        asm = ArrayAssembler()
        tmp = path.with_name(f".{path.name}.tmp")
        nbytes = 0
        try:
            with open(tmp, "wb") as f:
                f.write(cls.MAGIC)
                for c in chunks:
                    blob = c.SerializeToString()
                    f.write(cls._LEN.pack(len(blob)))
                    f.write(blob)
                    nbytes += len(c.data)
                    if c.name in keep:
                        asm.add(c)
                f.write(cls._LEN.pack(0))
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return nbytes, asm.result()

    @classmethod
    def chunks(cls, path: Path, skip: Iterable[str] = ()) -> Iterator[pb.ArrayChunk]:
        """The chunks of a file, in order, leaving out the arrays named in ``skip``;
        ValueError for a file that is not a whole chunk file."""
        skip = set(skip)
        with open(path, "rb") as f:
            if f.read(len(cls.MAGIC)) != cls.MAGIC:
                raise ValueError(f"{Path(path).name} is not a dcrad chunk file")
            while True:
                head = f.read(cls._LEN.size)
                if len(head) != cls._LEN.size:
                    raise ValueError(f"{Path(path).name} is cut short (no end mark)")
                (n,) = cls._LEN.unpack(head)
                if n == 0:
                    return
                if n > cls.MAX_RECORD:
                    raise ValueError(f"{Path(path).name}: a record of {n} bytes")
                blob = f.read(n)
                if len(blob) != n:
                    raise ValueError(f"{Path(path).name} is cut short")
                c = pb.ArrayChunk()
                c.ParseFromString(blob)
                if c.name not in skip:
                    yield c

    @classmethod
    def read(cls, path: Path, names: Iterable[str] | None = None) -> dict:
        """The arrays of a file ({name: array}); only ``names`` when given."""
        want = None if names is None else set(names)
        asm = ArrayAssembler()
        for c in cls.chunks(path):
            if want is None or c.name in want:
                asm.add(c)
        return asm.result()

    @classmethod
    def names(cls, path: Path) -> set[str]:
        """The array names in a whole file (reads it through: checks it is whole)."""
        return {c.name for c in cls.chunks(path)}


# == the job record ====================================================================
@dataclass
class JobRecord:
    """What ``job.json`` holds (the scene files sit beside it in ``scene/``)."""

    id: str
    spec: pb.JobSpec
    state: str = "queued"
    error: str = ""
    created: float = 0.0
    started: float = 0.0
    finished: float = 0.0
    subscenes: int = 0
    residual: float = 1.0
    #: the DivideConfig the job runs with, once it has started (a resume must cut the same way)
    divide: dict | None = None
    #: the workers' addresses at the end (the job list shows them after a restart too)
    workers: list = field(default_factory=list)

    def to_json(self) -> bytes:
        plain = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "spec"}
        d = {"version": VERSION, **plain, "spec": base64.b64encode(self.spec.SerializeToString()).decode("ascii")}
        return json.dumps(d, indent=1).encode()

    @classmethod
    def from_json(cls, blob: bytes) -> "JobRecord":
        """Parse a record; ValueError (with the reason) for anything malformed."""
        try:
            d = json.loads(blob.decode("utf-8"))
            if not isinstance(d, dict) or d.get("version") != VERSION:
                raise ValueError(f"unknown record version {d.get('version') if isinstance(d, dict) else '?'}")
            spec = pb.JobSpec()
            spec.ParseFromString(base64.b64decode(d["spec"], validate=True))
            rec = cls(id=str(d["id"]), spec=spec, state=str(d["state"]), error=str(d.get("error", "")),
                      created=float(d.get("created", 0.0)), started=float(d.get("started", 0.0)),
                      finished=float(d.get("finished", 0.0)), subscenes=int(d.get("subscenes", 0)),
                      residual=float(d.get("residual", 1.0)), divide=d.get("divide"),
                      workers=[str(w) for w in d.get("workers", [])])
        except ValueError:
            raise
        except Exception as exc:  # KeyError, TypeError, binascii/protobuf decode errors
            raise ValueError(f"{type(exc).__name__}: {exc}") from None
        if not rec.spec.scene:
            raise ValueError("the record's job spec names no scene")
        return rec


class JobStore:
    """Job records under ``root`` (``DATA/jobs``): save one, load them all."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    def folder(self, job_id: str) -> Path:
        return self.root / job_id

    def save(self, rec: JobRecord) -> None:
        folder = self.folder(rec.id)
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write(folder / RECORD, rec.to_json())

    def load_all(self) -> list[JobRecord]:
        """Every readable record, oldest first; an unreadable one is skipped with a warning."""
        out = []
        for folder in sorted(p for p in self.root.iterdir() if p.is_dir()):
            path = folder / RECORD
            if not path.exists():
                log.warning("job folder %s has no %s (a job from an older coordinator, or "
                            "half-created); skipped", folder.name, RECORD)
                continue
            try:
                rec = JobRecord.from_json(path.read_bytes())
                if rec.id != folder.name:
                    raise ValueError(f"it names job '{rec.id}'")
            except (OSError, ValueError) as exc:
                log.warning("job record %s is unreadable (%s); job skipped", path, exc)
                continue
            out.append(rec)
        out.sort(key=lambda r: r.created)
        return out

    def drop_checkpoints(self, job_id: str) -> None:
        """An ended job needs no checkpoints: its results are in out/."""
        shutil.rmtree(self.folder(job_id) / CHECKPOINTS, ignore_errors=True)

    def resume(self, job_id: str) -> "Resume | None":
        """The last complete barrier's checkpoint files of a job, or None (start over).

        A missing, half-written or inconsistent checkpoint set gives None with a warning.
        Each file is read through once (to know it is whole), not kept in memory.
        """
        folder = self.folder(job_id) / CHECKPOINTS
        path = folder / MANIFEST
        if not path.exists():
            return None
        try:
            man = json.loads(path.read_text())
            if man.get("format") != MANIFEST_FORMAT:
                raise ValueError(f"manifest format {man.get('format', 1)}, this coordinator reads "
                                 f"{MANIFEST_FORMAT}")
            cells = {}
            for cell, name in man["cells"].items():
                if not isinstance(name, str) or not _CELL_FILE.match(name):
                    raise ValueError(f"cell {cell}: {name!r} is not a checkpoint file name")
                if not {"radiosity", "unshot", "ledger"} <= ChunkFile.names(folder / name):
                    raise ValueError(f"{name} lacks the subscene state")
                cells[int(cell)] = folder / name
            return Resume(barrier=int(man["barrier"]), elapsed=float(man.get("elapsed_s", 0.0)), cells=cells,
                          crossing=float(man.get("crossing", -1.0)))
        except Exception as exc:  # any damage: a warning and a fresh start, never a crash
            log.warning("job %s: checkpoints in %s are unreadable (%s: %s); the job starts over",
                        job_id, folder, type(exc).__name__, exc)
            return None


@dataclass
class StoredPreview:
    """The last live preview of an ended job, read back from disk after a restart: what
    the status page reads of a ``LivePreview`` (``current``: version, barrier, png bytes)."""

    current: tuple[int, int, bytes]

    @property
    def barrier(self) -> int:
        return self.current[1]

    def close(self) -> None:
        pass

    @classmethod
    def load(cls, path: Path, barrier: int) -> "StoredPreview | None":
        try:
            return cls((1, barrier, Path(path).read_bytes())) if Path(path).is_file() else None
        except OSError:
            return None


@dataclass
class Resume:
    """Every cell's checkpoint file at one barrier (``ChunkFile``, read by ``RemoteSubscene``)."""

    barrier: int
    elapsed: float  #: s the job had run when that barrier was reached
    cells: dict = field(default_factory=dict)
    crossing: float = -1.0  #: ``DividedRun.crossing`` at that barrier (-1: not known)


class CheckpointStats(TypedDict):
    """``CheckpointWriter.stats``: barriers made durable and skipped (superseded), bytes of
    their files, seconds spent syncing them."""

    barriers: int
    skipped: int
    bytes: int
    seconds: float
    per_barrier: list[tuple[int, int, float]]  # (barrier, bytes, seconds)


# == the writer thread =====================================================================
class CheckpointWriter:
    """Makes a job's checkpoint barriers durable in a thread; ``submit`` returns at once.

    ``submit(barrier, {cell: file}, elapsed)`` hands over the barrier's checkpoint files
    (already written by the handles, see ``ChunkFile``), replacing any barrier still
    waiting: only the newest matters.  The thread fsyncs the files, writes the manifest
    naming them, and deletes the older cell files.  ``close()`` finishes what is
    queued and stops the thread.  ``stats`` counts barriers, bytes and seconds.
    """

    def __init__(self, folder: Path, fsync: bool = True, start_barrier: int = 0):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.fsync = fsync
        self._slot: tuple | None = None
        self._cv = threading.Condition()
        self._closed = False
        self._busy = False
        self.barrier = start_barrier  #: the last barrier on disk
        self.stats: CheckpointStats = {"barriers": 0, "skipped": 0, "bytes": 0, "seconds": 0.0, "per_barrier": []}
        self.error: str = ""
        self._thread = threading.Thread(target=self._loop, name=f"checkpoints-{self.folder.parent.name}",
                                        daemon=True)
        self._thread.start()

    def submit(self, barrier: int, cells: dict[int, Path | None], elapsed: float = 0.0, crossing: float = -1.0) -> None:
        """cells: each cell's checkpoint file at this barrier (None: not on disk, so no manifest);
        crossing: the run's ``DividedRun.crossing`` then (a resumed run's landing needs it)."""
        with self._cv:
            if self._slot is not None:
                self.stats["skipped"] += 1
            self._slot = (barrier, dict(cells), elapsed, crossing)
            self._cv.notify()

    def flush(self, timeout: float = 120.0) -> None:
        """Wait until every submitted barrier is on disk (or skipped for a newer one)."""
        with self._cv:
            self._cv.wait_for(lambda: (self._slot is None and not self._busy) or not self._thread.is_alive(),
                              timeout=timeout)

    def close(self, timeout: float = 120.0) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify()
        self._thread.join(timeout)

    def _loop(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._slot is not None or self._closed)
                item, self._slot = self._slot, None
                if item is None:
                    return
                self._busy = True
            try:
                self._write(*item)
            except Exception as exc:  # a full disk must not stop the solve; it stops durability
                self.error = f"{type(exc).__name__}: {exc}"
                log.warning("checkpoints in %s: writing failed (%s); the job goes on without them",
                            self.folder, self.error)
                return
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()

    def _write(self, barrier: int, cells: dict, elapsed: float, crossing: float = -1.0) -> None:
        t0 = time.perf_counter()
        if any(p is None for p in cells.values()):
            missing = sorted(c for c, p in cells.items() if p is None)
            raise OSError(f"barrier {barrier}: the checkpoints of cells {missing} are not on disk")
        paths = {c: Path(p) for c, p in cells.items()}
        written = 0
        for path in paths.values():
            if self.fsync:
                fsync_file(path)
            written += path.stat().st_size
        man = {"format": MANIFEST_FORMAT, "barrier": barrier, "elapsed_s": elapsed, "crossing": crossing,
               "cells": {str(c): p.name for c, p in sorted(paths.items())}}
        atomic_write(self.folder / MANIFEST, json.dumps(man).encode(), fsync=self.fsync)
        self.barrier = barrier
        for path in self.folder.iterdir():  # older barriers' files: no manifest names them now
            m = _CELL_FILE.match(path.name)
            if m and int(m.group(2)) < barrier:
                path.unlink(missing_ok=True)
        dt = time.perf_counter() - t0
        st = self.stats
        st["barriers"] += 1
        st["bytes"] += written
        st["seconds"] += dt
        st["per_barrier"].append((barrier, written, dt))
