"""numpy arrays and files <-> protobuf messages (dcrad.v1), in chunks.

Arrays travel as raw little-endian bytes with dtype and shape
(``ArrayChunk``), split well under gRPC's 4 MB default message size; never
as repeated floats, never pickled.  Only plain numeric dtypes are accepted.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from pathlib import Path, PurePosixPath
from typing import BinaryIO

import numpy as np

from dcrad.division.subscene import BarrierPlan
from dcrad.errors import ExchangeError
from dcrad.solving.energy import ACCOUNTS, MAGNITUDES, Ledger
from dcrad.solving.stiffness import Stiffness
from dcrad.v1 import dcrad_pb2 as pb

__all__ = [
    "CHUNK_BYTES", "ALLOWED_DTYPES", "array_chunks", "arrays_to_chunks", "ArrayAssembler", "assemble_arrays",
    "ledger_to_pb", "ledger_from_pb", "estimate_to_pb", "file_chunks", "FileAssembler", "safe_relpath",
    "path_chunks", "FileSink", "SHARE_PHASES", "share_phase", "share_phase_name",
]

#: a shared run's phases by the names the coordinator and the logs use, and their wire values
SHARE_PHASES: dict[str, pb.SharePhase] = {
    "pilot": pb.SHARE_PHASE_PILOT, "direct": pb.SHARE_PHASE_DIRECT, "replica": pb.SHARE_PHASE_REPLICA,
    "gather": pb.SHARE_PHASE_GATHER, "stop": pb.SHARE_PHASE_STOP,
}


def share_phase(name: str) -> pb.SharePhase:
    """The wire value of a share's phase (``SHARE_PHASES``); ValueError names an unknown one."""
    if name not in SHARE_PHASES:
        raise ValueError(f"no share phase {name!r}: one of {', '.join(SHARE_PHASES)}")
    return SHARE_PHASES[name]


def share_phase_name(value: pb.SharePhase) -> str:
    """The name of a share phase's wire value, or "" when it is none of ``SHARE_PHASES`` (unset, or
    from a newer sender)."""
    return next((name for name, v in SHARE_PHASES.items() if v == value), "")

#: bytes of payload per chunk: far below gRPC's 4 MB default
CHUNK_BYTES = 1 << 20
#: dtypes that may cross the wire (little-endian or byte-sized)
ALLOWED_DTYPES = {"<f8", "<f4", "<i8", "<i4", "<u8", "<u4", "|b1", "|u1", "|i1"}


def _le(arr: np.ndarray) -> np.ndarray:
    arr = np.ascontiguousarray(arr)
    if arr.dtype.byteorder == ">" or (arr.dtype.byteorder == "=" and np.little_endian is False):
        arr = arr.astype(arr.dtype.newbyteorder("<"))
    return arr


def _pieces(raw: bytes, chunk: int):
    """(offset, bytes) pieces of ``raw`` of at most ``chunk`` bytes; one empty piece for b""."""
    offset = 0
    while True:
        piece = raw[offset : offset + chunk]
        yield offset, piece
        offset += len(piece)
        if offset >= len(raw):
            return


def array_chunks(name: str, arr: np.ndarray, chunk: int = CHUNK_BYTES) -> Iterator[pb.ArrayChunk]:
    """Split one array into ArrayChunk messages (at least one, even when empty)."""
    arr = _le(np.asarray(arr))
    dtype = arr.dtype.str
    if dtype not in ALLOWED_DTYPES:
        raise ExchangeError(f"array '{name}': dtype {dtype} cannot go on the wire")
    raw = arr.tobytes()
    for offset, piece in _pieces(raw, chunk):
        yield pb.ArrayChunk(name=name, dtype=dtype, shape=list(arr.shape), offset=offset,
                            total_bytes=len(raw), data=piece)


def arrays_to_chunks(arrays: dict, chunk: int = CHUNK_BYTES) -> Iterator[pb.ArrayChunk]:
    for name, arr in arrays.items():
        yield from array_chunks(name, arr, chunk)


class ArrayAssembler:
    """Rebuild arrays from chunks, checking dtype, shape, offsets and sizes.

    Each array's bytes go straight into one buffer of its final size, taken when its
    first chunk arrives (within ``max_bytes``); ``result`` views it without copying, so
    an array is in memory once while it is assembled, not three times.
    """

    def __init__(self, max_bytes: int = 1 << 34):
        self.max_bytes = max_bytes
        self._parts: dict[str, tuple[pb.ArrayChunk, np.ndarray, int]] = {}  # head, buffer, bytes filled
        self._bytes = 0

    def add(self, c: pb.ArrayChunk) -> None:
        if c.dtype not in ALLOWED_DTYPES:
            raise ExchangeError(f"array '{c.name}': dtype {c.dtype!r} is not allowed on the wire")
        expect = int(np.prod(c.shape, dtype=np.int64)) * np.dtype(c.dtype).itemsize
        if expect != c.total_bytes:
            raise ExchangeError(f"array '{c.name}': shape {list(c.shape)} needs {expect} bytes, "
                                f"chunk says {c.total_bytes}")
        if c.name not in self._parts:
            if self._bytes + c.total_bytes > self.max_bytes:
                raise ExchangeError(f"arrays exceed the limit of {self.max_bytes} bytes")
            self._bytes += c.total_bytes
            self._parts[c.name] = (c, np.empty(c.total_bytes, np.uint8), 0)
        head, buf, filled = self._parts[c.name]
        if head.dtype != c.dtype or list(head.shape) != list(c.shape):
            raise ExchangeError(f"array '{c.name}': chunks disagree on dtype or shape")
        if c.offset != filled:
            raise ExchangeError(f"array '{c.name}': chunk at offset {c.offset}, expected {filled}")
        if filled + len(c.data) > c.total_bytes:
            raise ExchangeError(f"array '{c.name}': more bytes than its shape holds")
        buf[filled : filled + len(c.data)] = np.frombuffer(c.data, np.uint8)
        self._parts[c.name] = (head, buf, filled + len(c.data))

    def result(self) -> dict:
        out = {}
        for name, (head, buf, filled) in self._parts.items():
            if filled != head.total_bytes:
                raise ExchangeError(f"array '{name}': got {filled} of {head.total_bytes} bytes")
            out[name] = buf.view(np.dtype(head.dtype)).reshape(tuple(head.shape))
        return out


def assemble_arrays(chunks: Iterable[pb.ArrayChunk]) -> dict:
    asm = ArrayAssembler()
    for c in chunks:
        asm.add(c)
    return asm.result()


def ledger_to_pb(led: Ledger) -> pb.Ledger:
    msg = pb.Ledger(closure=led.closure(), residual=led.residual())
    for name in ACCOUNTS + MAGNITUDES:
        getattr(msg, name).extend(float(x) for x in getattr(led, name))
    return msg


def estimate_to_pb(est) -> pb.ErrorEstimate:
    """``noise.Estimate`` -> ``ErrorEstimate`` (an infinite ratio, before any light landed, as 0)."""
    def f(x: float) -> float:
        return float(x) if math.isfinite(x) else 0.0

    return pb.ErrorEstimate(rms=f(est.rms), rms_norm=f(est.rms_norm), rms_refl=f(est.rms_refl),
                            noise_refl=f(est.noise_refl), bias_refl=f(est.bias_refl), method=est.method)


def ledger_from_pb(msg: pb.Ledger) -> Ledger:
    led = Ledger()
    for name in ACCOUNTS + MAGNITUDES:
        values = list(getattr(msg, name))
        setattr(led, name, np.array(values if values else [0.0, 0.0, 0.0], np.float64))
    return led


def plan_fields(plan) -> dict:
    """IterateRequest fields for a ``dcrad.division.subscene.BarrierPlan`` (None: none, shoot plainly)."""
    if plan is None:
        return {}
    return {"ambient_scale": [float(x) for x in plan.stiffness.scale],
            "ambient_rest": [float(x) for x in plan.rest], "ray_factor": float(plan.stiffness.ray_factor),
            "return_ratio": float(plan.stiffness.ret), "time_left_s": float(plan.time_left),
            "goal_share": float(plan.goal), "rays_left": int(plan.rays_left)}


def plan_from_pb(req: pb.IterateRequest):
    """The BarrierPlan an IterateRequest carries, or None."""

    if (not req.ambient_scale and req.ray_factor <= 0 and req.time_left_s <= 0 and req.goal_share <= 0
            and req.rays_left <= 0):
        return None
    scale = np.array(list(req.ambient_scale) or [0.0] * 3, np.float64)
    rest = np.array(list(req.ambient_rest) or [0.0] * 3, np.float64)
    if scale.shape != (3,) or rest.shape != (3,) or not (np.isfinite(scale).all() and np.isfinite(rest).all()):
        raise ExchangeError("barrier plan needs finite RGB ambient_scale and ambient_rest")
    if not math.isfinite(req.time_left_s) or req.time_left_s < 0:
        raise ExchangeError(f"barrier plan: time_left_s must be finite and >= 0, not {req.time_left_s}")
    if not 0.0 <= req.goal_share < 1.0:  # NaN fails too
        raise ExchangeError(f"barrier plan: goal_share must be in [0, 1), not {req.goal_share}")
    if req.rays_left < 0:
        raise ExchangeError(f"barrier plan: rays_left must be >= 0, not {req.rays_left}")
    return BarrierPlan(Stiffness(scale, max(1.0, float(req.ray_factor)), float(req.return_ratio)), rest,
                       float(req.time_left_s), float(req.goal_share), int(req.rays_left))


def safe_relpath(path: str) -> str:
    """A relative '/'-path without '..' or absolute parts; ExchangeError otherwise."""
    p = PurePosixPath(path.replace("\\", "/"))
    if not path or p.is_absolute() or any(part in ("..", "") for part in p.parts) or ":" in p.parts[0]:
        raise ExchangeError(f"file path {path!r} must be relative, without '..'")
    return str(p)


def file_chunks(data: bytes, relpath: str, chunk: int = CHUNK_BYTES) -> Iterator[pb.FileChunk]:
    for offset, piece in _pieces(data, chunk):
        yield pb.FileChunk(path=relpath, offset=offset, total_bytes=len(data), data=piece)


def path_chunks(path, relpath: str, chunk: int = CHUNK_BYTES) -> Iterator[pb.FileChunk]:
    """``file_chunks`` of a file on disk, read one chunk at a time (memory: one chunk)."""
    path = Path(path)
    total = path.stat().st_size
    offset = 0
    with open(path, "rb") as f:
        while True:
            piece = f.read(chunk)
            if not piece and offset > 0:
                return
            yield pb.FileChunk(path=relpath, offset=offset, total_bytes=total, data=piece)
            offset += len(piece)
            if not piece or offset >= total:
                return


class FileSink:
    """Write FileChunk messages under ``folder`` as they come (memory: one chunk), with
    the same checks as ``FileAssembler``: safe relative paths, chunks in order, at most
    ``max_bytes`` in all.  ``files`` is {relpath: bytes written}."""

    def __init__(self, folder, max_bytes: int):
        self.folder, self.max_bytes = Path(folder), max_bytes
        self.files: dict[str, int] = {}
        self.total = 0
        self._open: tuple[str, BinaryIO] | None = None

    def add(self, c: pb.FileChunk) -> None:
        path = safe_relpath(c.path)
        if c.total_bytes > self.max_bytes:
            raise ExchangeError(f"upload too large: {path} is {c.total_bytes} bytes, limit {self.max_bytes}")
        have = self.files.get(path, 0)
        if c.offset != have:
            raise ExchangeError(f"file {path}: chunk at offset {c.offset}, expected {have}")
        self.total += len(c.data)
        if self.total > self.max_bytes:
            raise ExchangeError(f"upload too large: more than the limit of {self.max_bytes} bytes")
        if self._open is None or self._open[0] != path:
            self.close()
            target = self.folder.joinpath(*path.split("/"))
            target.parent.mkdir(parents=True, exist_ok=True)
            self._open = (path, open(target, "ab" if have else "wb"))
        self._open[1].write(c.data)
        self.files[path] = have + len(c.data)

    def close(self) -> None:
        if self._open is not None:
            self._open[1].close()
            self._open = None


class FileAssembler:
    """Collect FileChunk messages into {relpath: bytes}, enforcing a total size limit."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self.files: dict[str, bytearray] = {}
        self.total = 0

    def add(self, c: pb.FileChunk) -> None:
        path = safe_relpath(c.path)
        if c.total_bytes > self.max_bytes:
            raise ExchangeError(f"upload too large: {path} is {c.total_bytes} bytes, limit {self.max_bytes}")
        buf = self.files.setdefault(path, bytearray())
        if c.offset != len(buf):
            raise ExchangeError(f"file {path}: chunk at offset {c.offset}, expected {len(buf)}")
        self.total += len(c.data)
        if self.total > self.max_bytes:
            raise ExchangeError(f"upload too large: more than the limit of {self.max_bytes} bytes")
        buf.extend(c.data)
