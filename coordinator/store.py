"""Durable jobs: the job record and per-subscene checkpoints on disk, under ``--data``.

Layout of one job (``DATA/jobs/ID/``)::

    job.json                     the record: spec, state, times, the resolved divide settings
    scene/                       the uploaded scene files (written by ``JobManager.create``)
    checkpoints/manifest.json    the last barrier whose checkpoints are all on disk
    checkpoints/cell-K-NNNNNN.npz  cell K at barrier N: whole ("full") or the change since N-1
    out/                         the results, once the job has ended

Every file is written atomically: to a temporary name in the same folder, flushed
and fsynced, then renamed over the old one (and the folder fsynced), so a crash
leaves either the old or the new file, never half of one.  A checkpoint barrier
counts only once the manifest names it, and the manifest is written after every
cell's file for that barrier, so a crash mid-barrier resumes from the one before.

Checkpoints are written by a ``CheckpointWriter`` thread, off the barrier loop: the
loop hands over the arrays it already holds (the coordinator replaces, never
mutates, a checkpoint dict) and goes on.  When the writer falls behind, it skips to
the newest barrier.  Writes are incremental: the per-patch arrays (``radiosity``,
``unshot``) are stored as the rows that changed since the previous file when few
did, else as the bitwise XOR with the previous file, byte-shuffled and zlib
compressed when that is at most ``COMPRESS_MAX`` of the raw size, else whole.
A chain of changes is closed by a full file once it would outweigh one.

No numerics here: the arrays are stored bit for bit, so a resumed subscene is the
one that was checkpointed.
"""

from __future__ import annotations

import base64
import io
import json
import logging
import os
import re
import shutil
import threading
import time
import zlib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TypedDict

import numpy as np

from dcrad.v1 import dcrad_pb2 as pb

log = logging.getLogger("dcrad.coordinator")

__all__ = ["JobStore", "JobRecord", "Resume", "StoredPreview", "CheckpointWriter", "atomic_write", "encode_delta",
           "decode_delta", "ROW_ARRAYS"]

RECORD = "job.json"
CHECKPOINTS = "checkpoints"
MANIFEST = "manifest.json"
VERSION = 1
#: per-patch arrays stored incrementally; every other checkpoint array is small and stored whole
ROW_ARRAYS = ("radiosity", "unshot", "noise_diff", "noise_unshot")
#: store changed rows (index + row) when at most this share of the rows changed
ROWS_MAX = 0.25
#: keep the compressed XOR only when it is at most this share of the raw bytes
COMPRESS_MAX = 0.8
#: rows of the XOR tried first, to skip compressing what will not shrink
SAMPLE_ROWS = 4096
_CELL_FILE = re.compile(r"cell-(\d+)-(\d+)\.npz$")


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
                      residual=float(d.get("residual", 1.0)), divide=d.get("divide"))
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
        """The last complete barrier's checkpoints of a job, or None (start over).

        A missing, half-written or inconsistent checkpoint set gives None with a warning.
        """
        folder = self.folder(job_id) / CHECKPOINTS
        path = folder / MANIFEST
        if not path.exists():
            return None
        try:
            man = json.loads(path.read_text())
            cells = {}
            for cell, files in man["cells"].items():
                arrays: dict | None = None
                for name in files:
                    with np.load(folder / name, allow_pickle=False) as z:
                        stored = {k: z[k] for k in z.files}
                    arrays = decode_delta(stored, arrays)
                cells[int(cell)] = arrays
            return Resume(barrier=int(man["barrier"]), elapsed=float(man.get("elapsed_s", 0.0)), cells=cells)
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
    """Checkpoints of every cell at one barrier, as ``RemoteSubscene.checkpoint`` dicts."""

    barrier: int
    elapsed: float  #: s the job had run when that barrier was reached
    cells: dict = field(default_factory=dict)


# == incremental encoding ==================================================================
def _shuffle(x: np.ndarray) -> bytes:
    """Bytes grouped by significance (all first bytes, then all second bytes, ...): XOR deltas
    of slowly changing floats are zero in their high bytes, which zlib then squeezes."""
    b = np.ascontiguousarray(x).view(np.uint8).reshape(-1, x.dtype.itemsize)
    return b.T.tobytes()


def _unshuffle(blob: bytes, dtype, shape) -> np.ndarray:
    itemsize = np.dtype(dtype).itemsize
    b = np.frombuffer(blob, np.uint8).reshape(itemsize, -1)
    return np.ascontiguousarray(b.T).view(dtype).reshape(shape)


def encode_delta(arrays: dict, prev: dict | None) -> tuple[dict, str]:
    """Arrays to store for one checkpoint given the previously stored one: (stored, kind).

    kind is "full" (no usable previous) or "delta".  Only ``ROW_ARRAYS`` are encoded;
    ``decode_delta(stored, prev)`` gives back ``arrays`` bit for bit.
    """
    usable = prev is not None and all(
        k in prev and prev[k].shape == arrays[k].shape and prev[k].dtype == arrays[k].dtype
        for k in ROW_ARRAYS if k in arrays)
    out = {k: np.asarray(v) for k, v in arrays.items() if not (usable and k in ROW_ARRAYS)}
    if not usable or prev is None:
        out["_kind"] = np.array("full")
        return out, "full"
    for k in ROW_ARRAYS:
        if k not in arrays:
            continue
        a, p = np.asarray(arrays[k]), prev[k]
        bits = a.view(np.uint64) if a.dtype.itemsize == 8 else a.view(np.uint32)
        pbits = p.view(bits.dtype)
        xor = bits ^ pbits
        rows = np.flatnonzero(xor.reshape(len(a), -1).any(axis=1)) if a.ndim else np.zeros(0, np.int64)
        if len(rows) <= ROWS_MAX * len(a):
            out[f"{k}@rows"] = rows.astype(np.int64)
            out[f"{k}@values"] = a[rows]
            continue
        # compress only when cheap: a sample that does not shrink enough is not worth the whole
        sample = xor[:SAMPLE_ROWS]
        if len(zlib.compress(_shuffle(sample), 1)) <= COMPRESS_MAX * sample.nbytes:
            packed = zlib.compress(_shuffle(xor), 1)
            if len(packed) <= COMPRESS_MAX * a.nbytes:
                out[f"{k}@xorz"] = np.frombuffer(packed, np.uint8)
                continue
        out[k] = a
    out["_kind"] = np.array("delta")
    return out, "delta"


def decode_delta(stored: dict, prev: dict | None) -> dict:
    """Invert ``encode_delta``: the checkpoint arrays from a stored file and the previous ones."""
    kind = str(stored.get("_kind", np.array("full")))
    if kind != "full" and prev is None:
        raise ValueError("a checkpoint change with no full checkpoint before it")
    out = {}
    for k, v in stored.items():
        if k == "_kind" or "@" in k:
            continue
        out[k] = v
    if kind == "full":
        return out
    assert prev is not None  # a change without prev was refused above
    for k in ROW_ARRAYS:
        if k in out or k not in prev:
            continue
        p = prev[k]
        if f"{k}@rows" in stored:
            a = p.copy()
            a[stored[f"{k}@rows"]] = stored[f"{k}@values"]
        elif f"{k}@xorz" in stored:
            pbits = p.view(np.uint64 if p.dtype.itemsize == 8 else np.uint32)
            xor = _unshuffle(zlib.decompress(stored[f"{k}@xorz"].tobytes()), pbits.dtype, pbits.shape)
            a = (pbits ^ xor).view(p.dtype)
        else:  # not in this checkpoint
            continue
        out[k] = a
    return out


class CheckpointStats(TypedDict):
    """``CheckpointWriter.stats``: barriers written and skipped (superseded), bytes on disk,
    bytes a full checkpoint would have taken, seconds spent writing."""

    barriers: int
    skipped: int
    bytes: int
    full_bytes: int
    seconds: float
    per_barrier: list[tuple[int, int, int, float]]  # (barrier, bytes, full bytes, seconds)


def _npz_bytes(arrays: dict) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


# == the writer thread =====================================================================
class CheckpointWriter:
    """Writes a job's checkpoints in a thread; ``submit`` returns at once.

    ``submit(barrier, {cell: arrays}, elapsed)`` queues the barrier (replacing any
    barrier still waiting: only the newest matters).  ``close()`` writes what is
    queued and stops the thread.  ``stats`` counts what was written: barriers,
    bytes, seconds, and the bytes whole checkpoints would have taken.
    """

    def __init__(self, folder: Path, fsync: bool = True, start_barrier: int = 0):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.fsync = fsync
        self._slot: tuple | None = None
        self._cv = threading.Condition()
        self._closed = False
        self._busy = False
        #: per cell: the arrays of the last file written, and the file chain since its full file
        self._prev: dict[int, dict] = {}
        self._chain: dict[int, list[tuple[str, int]]] = {}
        self._full_bytes: dict[int, int] = {}
        self.barrier = start_barrier  #: the last barrier on disk
        self.stats: CheckpointStats = {"barriers": 0, "skipped": 0, "bytes": 0, "full_bytes": 0, "seconds": 0.0,
                                       "per_barrier": []}
        self.error: str = ""
        self._thread = threading.Thread(target=self._loop, name=f"checkpoints-{self.folder.parent.name}",
                                        daemon=True)
        self._thread.start()

    def submit(self, barrier: int, cells: dict, elapsed: float = 0.0) -> None:
        with self._cv:
            if self._slot is not None:
                self.stats["skipped"] += 1
            self._slot = (barrier, dict(cells), elapsed)
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

    def _write(self, barrier: int, cells: dict, elapsed: float) -> None:
        t0 = time.perf_counter()
        written, whole = 0, 0
        new_files = []
        for cell, arrays in sorted(cells.items()):
            if arrays is None:
                continue
            raw = sum(np.asarray(a).nbytes for a in arrays.values())
            chain = self._chain.get(cell, [])
            prev = self._prev.get(cell)
            # close a chain of changes with a full file once it would outweigh one
            if chain and sum(b for _, b in chain[1:]) >= self._full_bytes.get(cell, raw):
                prev = None
            stored, kind = encode_delta(arrays, prev)
            blob = _npz_bytes(stored)
            name = f"cell-{cell}-{barrier:06d}.npz"
            atomic_write(self.folder / name, blob, fsync=False)
            new_files.append(self.folder / name)
            if kind == "full":
                chain = []
                self._full_bytes[cell] = len(blob)
            chain = chain + [(name, len(blob))]
            self._chain[cell] = chain
            self._prev[cell] = {k: np.asarray(v) for k, v in arrays.items()}
            written += len(blob)
            whole += raw
        if self.fsync:
            for path in new_files:
                fd = os.open(path, os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
        man = {"barrier": barrier, "elapsed_s": elapsed,
               "cells": {str(c): [n for n, _ in ch] for c, ch in sorted(self._chain.items())}}
        atomic_write(self.folder / MANIFEST, json.dumps(man).encode(), fsync=self.fsync)
        self.barrier = barrier
        keep = {n for ch in self._chain.values() for n, _ in ch} | {MANIFEST}
        for path in self.folder.iterdir():  # files no chain needs any more
            if _CELL_FILE.match(path.name) and path.name not in keep:
                path.unlink(missing_ok=True)
        dt = time.perf_counter() - t0
        st = self.stats
        st["barriers"] += 1
        st["bytes"] += written
        st["full_bytes"] += whole
        st["seconds"] += dt
        st["per_barrier"].append((barrier, written, whole, dt))
