"""Boundaries, portal cells, twin buffers and the transfer at the barrier.

A boundary is an axis-aligned rectangle shared by two cells of the partition
(van Liere's "ideal translucent surface").  Its frame is (t, b, n) with
n = +e_axis pointing from side A (low) to side B (high), t = e_u, b = e_v,
u = (axis+1) % 3, v = (axis+2) % 3, so t x b = n.  The rectangle is split into
a (nu, nv) grid of portal cells; cell index = iu * nv + iv.

Directions are binned per hemisphere (around +n for A->B, around -n for B->A)
with Malley's projection and the concentric square <-> disk map: the tangent
components (x, y) = (t.d, b.d) are a point of the unit disk, mapped back to the
unit square, which is cut into a solid x solid grid; bin index = i0 * solid + i1.
Equal square areas are equal disk areas, i.e. equal projected solid angle
(pi / solid**2 sr each).  Both hemispheres use the same (t, b), so a world
direction has the same bin index on both sides of the boundary: light recorded
by side A in bin k is re-emitted by side B inside bin k and goes straight on.

Twin buffers hold RGB power (W, float64) per (boundary id, crossing, portal
cell, bin), stored sparsely: only entries light actually crossed exist.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dcrad.errors import ConfigError, ExchangeError, PartitionError
from dcrad.transport.sampling import concentric_disk, concentric_disk_inverse

__all__ = ["Boundary", "make_boundary", "coarsen_directions", "direction_levels", "TwinBuffer", "transfer", "RayParcel",
           "transfer_rays", "KEY_LIMIT", "BoundaryMode", "MODES", "boundary_mode"]

KEY_LIMIT = np.iinfo(np.int64).max  # packed keys must stay <= this


@dataclass(frozen=True)
class Boundary:
    """An axis-aligned rectangle shared by two cells; n = +e_axis points from side A (low) to B (high).

    offset (m) is the plane coordinate along ``axis``; lo, hi (m) the rectangle's
    corners along u = (axis+1) % 3 and v = (axis+2) % 3; cells = (nu, nv) the
    portal grid; solid the bins per side of the direction square (n_bins = solid**2).
    """

    id: int
    axis: int
    offset: float
    lo: tuple[float, float]
    hi: tuple[float, float]
    side_a: int
    side_b: int
    cells: tuple[int, int]
    solid: int

    def __post_init__(self):
        if self.axis not in (0, 1, 2):
            raise PartitionError(f"boundary {self.id}: axis must be 0, 1 or 2, got {self.axis}")
        if not (self.hi[0] > self.lo[0] and self.hi[1] > self.lo[1]):
            raise PartitionError(f"boundary {self.id}: empty rectangle lo={self.lo} hi={self.hi}")
        if not all(math.isfinite(x) for x in (*self.lo, *self.hi, self.offset)):
            raise PartitionError(f"boundary {self.id}: non-finite coordinates")
        if min(self.cells) < 1 or self.solid < 1:
            raise PartitionError(f"boundary {self.id}: cells {self.cells}, solid {self.solid} must be >= 1")
        if self.side_a == self.side_b:
            raise PartitionError(f"boundary {self.id}: both sides are cell {self.side_a}")
        if self.id < 0:
            raise PartitionError(f"boundary id must be >= 0, got {self.id}")

    @property
    def n_cells(self) -> int:
        return self.cells[0] * self.cells[1]

    @property
    def n_bins(self) -> int:
        return self.solid * self.solid

    @property
    def uv(self) -> tuple[int, int]:
        """World axes of the tangent directions t and b."""
        return (self.axis + 1) % 3, (self.axis + 2) % 3

    @property
    def normal(self) -> np.ndarray:
        """(3,) f8 unit normal +e_axis (A -> B)."""
        return np.eye(3)[self.axis]

    @property
    def frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t, b, n), each (3,) f8 world unit vectors, t = e_u, b = e_v, n = e_axis."""
        e = np.eye(3)
        u, v = self.uv
        return e[u], e[v], e[self.axis]

    @property
    def area(self) -> float:
        """Area of the rectangle (m^2)."""
        return (self.hi[0] - self.lo[0]) * (self.hi[1] - self.lo[1])

    def _corner(self, a: float, b: float) -> np.ndarray:
        p = np.empty(3)
        u, v = self.uv
        p[self.axis], p[u], p[v] = self.offset, a, b
        return p

    def triangles(self) -> np.ndarray:
        """(2, 3, 3) f8 world corners of the rectangle as two triangles whose normal is +n."""
        (u0, v0), (u1, v1) = self.lo, self.hi
        c00, c10, c11, c01 = (self._corner(*c) for c in ((u0, v0), (u1, v0), (u1, v1), (u0, v1)))
        return np.array([[c00, c10, c11], [c00, c11, c01]])

    def cell_of(self, points: np.ndarray) -> np.ndarray:
        """(m,3) points on the plane (m) -> (m,) i8 portal cell, clamped to the grid."""
        points = np.asarray(points)
        u, v = self.uv
        nu, nv = self.cells
        iu = np.floor((points[:, u] - self.lo[0]) * (nu / (self.hi[0] - self.lo[0])))
        iv = np.floor((points[:, v] - self.lo[1]) * (nv / (self.hi[1] - self.lo[1])))
        iu = np.clip(iu, 0, nu - 1).astype(np.int64)
        iv = np.clip(iv, 0, nv - 1).astype(np.int64)
        return iu * nv + iv

    def bin_of(self, dirs: np.ndarray) -> np.ndarray:
        """(m,3) directions (need not be unit) -> (m,) i8 bin in [0, n_bins).

        The bin depends on the tangent components (t.d, b.d) only, so d and its
        mirror through the plane share a bin; the hemisphere is given by :meth:`crossing`.
        """
        dirs = np.asarray(dirs)
        u, v = self.uv
        norm = np.sqrt(np.einsum("ij,ij->i", dirs, dirs))
        norm = np.where(norm > 0, norm, 1)
        disk = np.stack([dirs[:, u] / norm, dirs[:, v] / norm], axis=1)
        sq = concentric_disk_inverse(disk)
        i = np.clip(np.floor(sq * self.solid), 0, self.solid - 1).astype(np.int64)
        return i[:, 0] * self.solid + i[:, 1]

    def crossing(self, dirs: np.ndarray) -> np.ndarray:
        """(m,3) directions -> (m,) i1: 0 for A->B (d.n > 0), 1 for B->A (d.n <= 0)."""
        return (np.asarray(dirs)[:, self.axis] <= 0).astype(np.int8)

    def sample(self, cell, bin, crossing, u: np.ndarray, level=0) -> tuple[np.ndarray, np.ndarray]:
        """Ray origins and directions leaving through portal cells inside direction bins.

        cell, bin, crossing : (m,) ints; u : (m,4) in [0,1) (float32 keeps the
        trigonometry fast).  Origins (m,3) f8 are uniform in the portal cell and
        exactly on the plane (the caller offsets them along the direction); dirs
        (m,3) f8 unit are cosine distributed (uniform in projected solid angle)
        within the bin, around +n for crossing 0 and -n for crossing 1.
        level : scalar or (m,) ints >= 0; at level l, ``bin`` is the corner of a
        block of 2**l x 2**l bins (cut at the square's edge) and directions fill
        the whole block (``coarsen_directions``).
        """
        cell = np.asarray(cell, np.int64)
        bin = np.asarray(bin, np.int64)
        crossing = np.asarray(crossing)
        if cell.size and (cell.min() < 0 or cell.max() >= self.n_cells):
            raise ExchangeError(f"boundary {self.id}: portal cell outside [0, {self.n_cells})")
        if bin.size and (bin.min() < 0 or bin.max() >= self.n_bins):
            raise ExchangeError(f"boundary {self.id}: direction bin outside [0, {self.n_bins})")
        nu, nv = self.cells
        ax, (a, b) = self.axis, self.uv
        iu, iv = np.divmod(cell, nv)
        origins = np.empty((len(cell), 3))
        origins[:, ax] = self.offset
        origins[:, a] = self.lo[0] + (iu + u[:, 0]) * ((self.hi[0] - self.lo[0]) / nu)
        origins[:, b] = self.lo[1] + (iv + u[:, 1]) * ((self.hi[1] - self.lo[1]) / nv)

        i0, i1 = np.divmod(bin, self.solid)
        span = np.left_shift(1, np.asarray(level, np.int64))
        w0 = np.minimum(i0 + span, self.solid) - i0  # block width in bins (1 at level 0)
        w1 = np.minimum(i1 + span, self.solid) - i1
        dt = u.dtype if u.dtype.kind == "f" else np.float64
        sq = np.stack([(i0 + w0 * u[:, 2]) / self.solid, (i1 + w1 * u[:, 3]) / self.solid], axis=1).astype(dt)
        disk = concentric_disk(sq).astype(np.float64)
        z = np.sqrt(np.maximum(0.0, 1.0 - np.einsum("ij,ij->i", disk, disk)))
        dirs = np.empty((len(cell), 3))
        dirs[:, a], dirs[:, b] = disk[:, 0], disk[:, 1]
        dirs[:, ax] = np.where(crossing == 0, z, -z)
        dirs /= np.sqrt(np.einsum("ij,ij->i", dirs, dirs))[:, None]
        return origins, dirs


def make_boundary(
    id: int,
    axis: int,
    offset: float,
    lo: tuple[float, float],
    hi: tuple[float, float],
    side_a: int,
    side_b: int,
    cell_size: float,
    solid: int,
) -> Boundary:
    """Boundary with portal cells of about ``cell_size`` (m): ceil(extent / cell_size) per axis."""
    if not cell_size > 0:
        raise PartitionError(f"boundary {id}: cell_size must be > 0, got {cell_size}")
    # the 1e-9 keeps 0.3 / 0.1 = 2.9999999999999996 -> 3 and 1.0 / 0.1 from becoming 11
    cells = (max(1, math.ceil((hi[0] - lo[0]) / cell_size - 1e-9)),
             max(1, math.ceil((hi[1] - lo[1]) / cell_size - 1e-9)))
    return Boundary(
        id=int(id), axis=int(axis), offset=float(offset),
        lo=(float(lo[0]), float(lo[1])), hi=(float(hi[0]), float(hi[1])),
        side_a=int(side_a), side_b=int(side_b), cells=cells, solid=int(solid),
    )


def direction_levels(solid: int) -> int:
    """Levels of the direction quadtree for ``solid`` bins per side: 0 (one bin) up to the hemisphere."""
    return max(0, math.ceil(math.log2(max(int(solid), 1)))) + 1


def coarsen_directions(bid, crossing, cell, bins, power, solid, threshold: float):
    """Directional resolution where the energy is: group weak twin entries into coarser bins.

    Entries are (boundary id, crossing, portal cell, bin) with signed power (k, c)
    W; ``solid`` (k,) or scalar is each entry's bins per side.  A quadtree over
    the direction square: an entry whose power is at least ``threshold`` (one
    ray's power) keeps its bin; the others of a 2x2 block of bins are summed,
    and a block strong enough becomes one group, else it joins the next level,
    up to the whole hemisphere of its portal cell and crossing.  Power is
    summed exactly; only the directions of weak light get coarser.

    Returns (group (k,) i8: the group of each entry, and the groups' arrays
    {bid, crossing, cell, bin (block corner), level, power (g, c)}).
    """
    bid, crossing, cell, bins = (np.asarray(x, np.int64) for x in (bid, crossing, cell, bins))
    power = np.asarray(power, np.float64)
    power = power.reshape(len(bins), power.shape[-1] if power.ndim == 2 else 1)
    k = len(bins)
    solid = np.broadcast_to(np.asarray(solid, np.int64), (k,))
    smax = int(solid.max()) if k else 1
    top = direction_levels(smax) - 1
    i0, i1 = np.divmod(bins, solid)
    cells = int(cell.max()) + 1 if k else 1
    group = np.full(k, -1, np.int64)
    parts: dict[str, list] = {n: [] for n in ("bid", "crossing", "cell", "bin", "level", "power")}
    todo = np.arange(k)
    n_groups = 0
    for level in range(top + 1):
        if len(todo) == 0:
            break
        a, b = i0[todo] >> level, i1[todo] >> level
        key = (((bid[todo] * 2 + crossing[todo]) * cells + cell[todo]) * smax + a) * smax + b
        _, first, inv = np.unique(key, return_index=True, return_inverse=True)
        inv = inv.ravel()
        gp = np.stack([np.bincount(inv, weights=power[todo, c], minlength=len(first))
                       for c in range(power.shape[1])], axis=1)
        strong = np.abs(gp).sum(axis=1) >= threshold if level < top else np.ones(len(first), bool)
        settle = strong[inv]
        new_id = np.cumsum(strong) - 1 + n_groups
        group[todo[settle]] = new_id[inv[settle]]
        rep = todo[first[strong]]
        parts["bid"].append(bid[rep])
        parts["crossing"].append(crossing[rep])
        parts["cell"].append(cell[rep])
        parts["bin"].append(((i0[rep] >> level) << level) * solid[rep] + ((i1[rep] >> level) << level))
        parts["level"].append(np.full(len(rep), level, np.int64))
        parts["power"].append(gp[strong])
        n_groups += int(strong.sum())
        todo = todo[~settle]
    if k == 0:
        return group, {n: np.zeros(0, np.int64) for n in parts} | {"power": np.zeros((0, power.shape[1]))}
    return group, {n: np.concatenate(v) for n, v in parts.items()}


class TwinBuffer:
    """Power (W, float64, ``channels`` per entry) per (boundary id, crossing, cell, bin), sparse.

    Entries are int64 keys, sorted and unique, with a (k, channels) power array:

        key = ((boundary_id * 2 + crossing) * max_cells + cell) * max_bins + bin

    Limits: 0 <= cell < max_cells, 0 <= bin < max_bins, crossing in {0, 1} and
    0 <= boundary_id <= max_boundary_id = (2**63 - 1) // (2 * max_cells * max_bins) - 1.
    With max_cells = 2**20 and max_bins = 2**12 that is about 1.1e6 boundaries.
    Violations raise ExchangeError, never a wrapped key.
    """

    def __init__(self, max_cells: int, max_bins: int, channels: int = 3):
        if max_cells < 1 or max_bins < 1 or channels < 1:
            raise ExchangeError("max_cells, max_bins and channels must be >= 1")
        stride = 2 * int(max_cells) * int(max_bins)
        if stride > KEY_LIMIT:
            raise ExchangeError(f"2 * max_cells * max_bins = {stride} overflows int64 keys")
        self.max_cells, self.max_bins, self.channels = int(max_cells), int(max_bins), int(channels)
        self.max_boundary_id = KEY_LIMIT // stride - 1
        self.keys = np.empty(0, np.int64)
        self.power = np.empty((0, self.channels), np.float64)

    @classmethod
    def like(cls, other: "TwinBuffer") -> "TwinBuffer":
        """An empty buffer with the same packing and channels."""
        return cls(other.max_cells, other.max_bins, other.channels)

    # -- keys ----------------------------------------------------------------
    def pack(self, boundary_id, crossing, cell, bin) -> np.ndarray:
        """Broadcast ints -> (m,) i8 keys; ExchangeError on any value out of range."""
        bid, cr, c, b = (np.asarray(x, np.int64) for x in (boundary_id, crossing, cell, bin))
        try:
            bid, cr, c, b = np.broadcast_arrays(bid, cr, c, b)
        except ValueError:
            raise ExchangeError("entry index arrays have different lengths") from None
        checks = (
            (bid, self.max_boundary_id + 1, "boundary id"), (cr, 2, "crossing"),
            (c, self.max_cells, "portal cell"), (b, self.max_bins, "direction bin"),
        )
        for x, top, what in checks:
            if x.size and (x.min() < 0 or x.max() >= top):
                raise ExchangeError(f"{what} outside [0, {top}) in twin buffer entry")
        return ((bid * 2 + cr) * self.max_cells + c) * self.max_bins + b

    def unpack(self, keys: np.ndarray):
        """(k,) i8 keys -> (boundary_id i8, crossing i1, cell i8, bin i8)."""
        rest, b = np.divmod(keys, self.max_bins)
        rest, c = np.divmod(rest, self.max_cells)
        bid, cr = np.divmod(rest, 2)
        return bid, cr.astype(np.int8), c, b

    # -- accumulate ----------------------------------------------------------
    def _accumulate(self, keys: np.ndarray, power: np.ndarray) -> None:
        if len(keys) == 0:
            return
        uk, inv = np.unique(keys, return_inverse=True)
        up = np.empty((len(uk), self.channels))
        for ch in range(self.channels):  # per colour channel, not per entry
            up[:, ch] = np.bincount(inv.ravel(), weights=power[:, ch], minlength=len(uk))
        pos = np.searchsorted(self.keys, uk)
        found = pos < len(self.keys)
        found[found] = self.keys[pos[found]] == uk[found]
        self.power[pos[found]] += up[found]
        new = ~found & up.any(axis=1)  # an all-zero new entry stores nothing
        self.keys = np.insert(self.keys, pos[new], uk[new])
        self.power = np.insert(self.power, pos[new], up[new], axis=0)

    def add(self, boundary_id, crossing, cell, bin, power) -> None:
        """Accumulate power (m, channels) W into (boundary_id, crossing, cell, bin), each (m,) or scalar."""
        power = np.asarray(power, np.float64)
        if power.ndim != 2 or power.shape[1] != self.channels:
            raise ExchangeError(f"power must be (m, {self.channels}), got {power.shape}")
        if not np.isfinite(power).all():
            raise ExchangeError("non-finite power in twin buffer entry")
        keys = self.pack(boundary_id, crossing, cell, bin)
        if keys.ndim > 1 or keys.size not in (1, len(power)):
            raise ExchangeError(f"{keys.shape} entry indices for {len(power)} power rows")
        self._accumulate(np.broadcast_to(keys.ravel(), (len(power),)), power)

    def merge(self, other: "TwinBuffer") -> None:
        """Add every entry of ``other`` (repacked if its limits differ)."""
        if other.channels != self.channels:
            raise ExchangeError(f"cannot merge {other.channels} channels into {self.channels}")
        if (other.max_cells, other.max_bins) == (self.max_cells, self.max_bins):
            self._accumulate(other.keys, other.power)
        else:
            self.add(*other.entries())

    # -- inspect -------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.keys)

    def total(self) -> np.ndarray:
        """(channels,) f8 W held by the buffer (signed: overshooting sends negative power too)."""
        return self.power.sum(axis=0)

    def total_abs(self) -> np.ndarray:
        """(channels,) f8 W: sum of magnitudes over entries."""
        return np.abs(self.power).sum(axis=0)

    def nbytes(self) -> int:
        """Bytes held by keys and power (grows with entries, not with the grid)."""
        return int(self.keys.nbytes + self.power.nbytes)

    def entries(self):
        """(boundary_id (k,) i8, crossing (k,) i1, cell (k,) i8, bin (k,) i8, power (k, channels) f8)."""
        return (*self.unpack(self.keys), self.power.copy())

    # -- move ----------------------------------------------------------------
    def take(self, index) -> "TwinBuffer":
        """Remove the entries at ``index`` (positions or a boolean mask) and return them."""
        keep = np.ones(len(self.keys), bool)
        keep[index] = False
        out = TwinBuffer.like(self)
        out.keys, out.power = self.keys[~keep], self.power[~keep]
        self.keys, self.power = self.keys[keep], self.power[keep]
        return out

    def drain(self) -> "TwinBuffer":
        """Take every entry, leaving this buffer empty."""
        out = TwinBuffer.like(self)
        out.keys, out.power = self.keys, self.power
        self.keys = np.empty(0, np.int64)
        self.power = np.empty((0, self.channels), np.float64)
        return out

    # -- wire ----------------------------------------------------------------
    def to_arrays(self) -> dict[str, np.ndarray]:
        """keys (k,) i8, power (k, channels) f8, limits (2,) i8 = (max_cells, max_bins)."""
        return {
            "keys": self.keys.copy(),
            "power": self.power.copy(),
            "limits": np.array([self.max_cells, self.max_bins], np.int64),
        }

    @classmethod
    def from_arrays(cls, d: dict[str, np.ndarray]) -> "TwinBuffer":
        """Inverse of :meth:`to_arrays`; ExchangeError on missing or inconsistent arrays."""
        try:
            keys, power, limits = (np.asarray(d[k]) for k in ("keys", "power", "limits"))
        except KeyError as e:
            raise ExchangeError(f"twin buffer arrays lack {e}") from None
        if keys.dtype != np.int64 or keys.ndim != 1 or limits.shape != (2,):
            raise ExchangeError("twin buffer keys must be (k,) int64 and limits (2,)")
        if power.dtype != np.float64 or power.ndim != 2 or len(power) != len(keys):
            raise ExchangeError(f"twin buffer power must be ({len(keys)}, c) float64, got {power.shape}")
        out = cls(int(limits[0]), int(limits[1]), power.shape[1])
        top = (out.max_boundary_id + 1) * 2 * out.max_cells * out.max_bins  # <= 2**63 - 1
        if len(keys) and (keys[0] < 0 or keys[-1] >= top):
            raise ExchangeError("twin buffer key outside the packing's range")
        if np.any(np.diff(keys) <= 0):
            raise ExchangeError("twin buffer keys are not sorted and unique")
        if not np.isfinite(power).all():
            raise ExchangeError("non-finite power in twin buffer arrays")
        out.keys, out.power = keys.copy(), power.copy()
        return out


def transfer(incoming: dict[int, TwinBuffer], boundaries: list[Boundary]) -> dict[int, TwinBuffer]:
    """transferEnergy at the barrier: per-cell incoming buffers -> per-cell outgoing buffers.

    ``incoming[c]`` is what subscene c recorded on its boundaries: crossing 0
    (A->B) entries must be recorded by ``side_a`` and go to ``side_b``; crossing
    1 (B->A) by ``side_b`` to ``side_a``.  Portal cell and bin index are kept.
    Returns a buffer for every cell named by a boundary (empty when nothing
    arrives).  The incoming buffers are not modified.  ExchangeError when an
    entry names an unknown boundary, a cell or bin outside it, or was recorded
    by the wrong cell; the total power moved is checked against the total recorded.
    """
    if not boundaries:
        if any(len(b) for b in incoming.values()):
            raise ExchangeError("twin buffer entries but no boundaries")
        return {}
    ids = np.array([b.id for b in boundaries], np.int64)
    order = np.argsort(ids, kind="stable")
    ids_sorted = ids[order]
    if np.any(np.diff(ids_sorted) == 0):
        raise ExchangeError("duplicate boundary ids")
    side = np.array([[b.side_a, b.side_b] for b in boundaries], np.int64)[order]
    n_cells = np.array([b.n_cells for b in boundaries], np.int64)[order]
    n_bins = np.array([b.n_bins for b in boundaries], np.int64)[order]
    channels = {buf.channels for buf in incoming.values()} or {3}
    if len(channels) != 1:
        raise ExchangeError(f"incoming buffers disagree on channels: {sorted(channels)}")
    (ch,) = channels
    out = {int(c): TwinBuffer(int(n_cells.max()), int(n_bins.max()), ch) for c in np.unique(side)}

    recorded = np.zeros(ch)
    for recorder, buf in incoming.items():  # one pass per subscene, vectorised inside
        if len(buf) == 0:
            continue
        bid, cr, cell, bn, power = buf.entries()
        recorded += power.sum(axis=0)
        k = np.minimum(np.searchsorted(ids_sorted, bid), len(ids_sorted) - 1)
        if np.any(ids_sorted[k] != bid):
            bad = int(bid[ids_sorted[k] != bid][0])
            raise ExchangeError(f"cell {recorder} recorded power on unknown boundary {bad}")
        if np.any(cell >= n_cells[k]) or np.any(bn >= n_bins[k]):
            raise ExchangeError(f"cell {recorder}: portal cell or bin outside its boundary")
        src = side[k, cr]
        if np.any(src != recorder):
            bad = int(bid[src != recorder][0])
            raise ExchangeError(f"cell {recorder} recorded power on boundary {bad} from the wrong side")
        dst = side[k, 1 - cr]
        for d in np.unique(dst):  # one pass per neighbour cell
            m = dst == d
            out[int(d)].add(bid[m], cr[m], cell[m], bn[m], power[m])

    moved = sum((b.total() for b in out.values()), np.zeros(ch))
    scale = sum((np.abs(b.power).sum(axis=0) for b in incoming.values() if len(b)), np.zeros(ch))
    if np.any(np.abs(moved - recorded) > 1e-12 * scale + 1e-300):
        raise ExchangeError(f"transfer lost power: recorded {recorded}, moved {moved}")
    return out


class RayParcel:
    """Exact forwarding: crossing rays kept whole (no angular or spatial blur).

    boundary (m,) i8, origins (m,3) f8 on the plane, dirs (m,3) f8 unit, power (m,3) f8 W.
    Memory grows with the rays: 80 bytes each.

    Rays are recorded a batch at a time and continued a batch at a time, so
    ``add``/``merge`` keep the new rays as a separate part (joined once, when the
    arrays are read) and ``take_front`` hands out the first rays as a slice: a
    batch costs O(its own rays), not O(rays held) (joining on every add made
    recording a barrier's crossings quadratic in them).
    """

    _FIELDS = ("boundary", "origins", "dirs", "power")

    def __init__(self, boundary=None, origins=None, dirs=None, power=None):
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = [(
            np.zeros(0, np.int64) if boundary is None else np.asarray(boundary, np.int64),
            np.zeros((0, 3)) if origins is None else np.asarray(origins, np.float64),
            np.zeros((0, 3)) if dirs is None else np.asarray(dirs, np.float64),
            np.zeros((0, 3)) if power is None else np.asarray(power, np.float64))]
        self._n = len(self._parts[0][0])

    def _joined(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        if len(self._parts) > 1:
            self._parts = [tuple(np.concatenate(col) for col in zip(*self._parts))]  # type: ignore[list-item]
        return self._parts[0]

    @property
    def boundary(self) -> np.ndarray:
        return self._joined()[0]

    @property
    def origins(self) -> np.ndarray:
        return self._joined()[1]

    @property
    def dirs(self) -> np.ndarray:
        return self._joined()[2]

    @property
    def power(self) -> np.ndarray:
        return self._joined()[3]

    def __len__(self) -> int:
        return self._n

    def total(self) -> np.ndarray:
        return self.power.sum(axis=0) if len(self) else np.zeros(3)

    def total_abs(self) -> np.ndarray:
        return np.abs(self.power).sum(axis=0) if len(self) else np.zeros(3)

    def nbytes(self) -> int:
        return int(sum(a.nbytes for part in self._parts for a in part))

    def add(self, boundary, origins, dirs, power) -> None:
        self.merge(RayParcel(np.broadcast_to(boundary, (len(origins),)), origins, dirs, power))

    def merge(self, other: "RayParcel") -> None:
        if len(other) == 0:
            return
        if self._n == 0:
            self._parts = list(other._parts)
        else:
            self._parts.extend(other._parts)
        self._n += len(other)

    def take_front(self, m: int) -> "RayParcel":
        """Remove the first ``m`` rays and return them (copies; the rest stays a slice)."""
        b, o, d, p = self._joined()
        m = min(int(m), self._n)
        out = RayParcel(b[:m].copy(), o[:m].copy(), d[:m].copy(), p[:m].copy())
        self._parts = [(b[m:], o[m:], d[m:], p[m:])]
        self._n -= m
        return out

    def take(self, index) -> "RayParcel":
        """Remove the rays at ``index`` (positions) and return them."""
        b, o, d, p = self._joined()
        keep = np.ones(len(self), bool)
        keep[index] = False
        out = RayParcel(b[index], o[index], d[index], p[index])
        self._parts = [(b[keep], o[keep], d[keep], p[keep])]
        self._n = int(keep.sum())
        return out

    def drain(self) -> "RayParcel":
        out = RayParcel(*self._joined())
        self._parts = RayParcel()._parts
        self._n = 0
        return out

    def to_arrays(self) -> dict:
        return dict(zip(self._FIELDS, self._joined()))

    @classmethod
    def from_arrays(cls, d: dict) -> "RayParcel":
        return cls(d["boundary"], d["origins"], d["dirs"], d["power"])


def transfer_rays(incoming: dict, boundaries: list) -> dict:
    """Route recorded crossing rays to the cell on the far side of their boundary."""
    by_id = {b.id: b for b in boundaries}
    out: dict[int, RayParcel] = {}
    for b in boundaries:
        out.setdefault(b.side_a, RayParcel())
        out.setdefault(b.side_b, RayParcel())
    moved = np.zeros(3)
    recorded = np.zeros(3)
    n_moved = n_recorded = 0
    scale = 0.0
    for cell, parcel in incoming.items():
        recorded += parcel.total()
        n_recorded += len(parcel)
        scale += float(parcel.total_abs().sum())
        for bid in np.unique(parcel.boundary):
            if int(bid) not in by_id:
                raise ExchangeError(f"ray parcel from cell {cell} names unknown boundary {int(bid)}")
            b = by_id[int(bid)]
            if cell not in (b.side_a, b.side_b):
                raise ExchangeError(f"cell {cell} sent rays through boundary {b.id}, which it does not touch")
            dest = b.side_b if cell == b.side_a else b.side_a
            sel = np.flatnonzero(parcel.boundary == bid)
            part = RayParcel(parcel.boundary[sel], parcel.origins[sel], parcel.dirs[sel], parcel.power[sel])
            out[dest].merge(part)
            moved += part.total()
            n_moved += len(part)
    # routing only sorts rays: every one goes exactly once (exact), and the power sums agree
    # to the round-off of summing them in another order (1e6 rays: ~1e-12 of the total)
    if n_moved != n_recorded or np.abs(moved - recorded).sum() > 1e-9 * max(scale, 1e-300):
        raise ExchangeError(f"ray transfer lost power: moved {n_moved} rays, {moved} W; "
                            f"recorded {n_recorded} rays, {recorded} W")
    return out


# == the boundary modes, each in one place ==========================================

def _record_twins(sent: TwinBuffer, b: Boundary, points, dirs, crossing, power) -> None:
    sent.add(np.full(len(points), b.id), crossing, b.cell_of(points), b.bin_of(dirs), power)


def _record_rays(sent: RayParcel, b: Boundary, points, dirs, crossing, power) -> None:
    sent.add(b.id, points, dirs, power)


@dataclass(frozen=True)
class BoundaryMode:
    """What a boundary mode is: what crosses at a barrier and how it is routed.

    buffer   : the type recorded while iterating and handed over at the barrier
    sent     : (max_cells, max_bins) -> an empty ``buffer`` to record crossings in
    record   : (sent, boundary, points, dirs, crossing, power) -> None, for rays
               that hit ``boundary`` (points on it, crossing 0: side A to B)
    transfer : transferEnergy, {cell: buffer} -> {cell: buffer} for the far sides
    """

    name: str
    buffer: type[TwinBuffer] | type[RayParcel]
    sent: Callable[[int, int], TwinBuffer | RayParcel]
    record: Callable[..., None]
    transfer: Callable[[dict, list], dict]

    def empty(self) -> TwinBuffer | RayParcel:
        """An empty delivery (for a cell that nothing crossed into)."""
        return self.sent(1, 1)


#: "binned": the paper's twins, power by (portal cell, direction bin); "exact": whole rays
MODES = {
    "binned": BoundaryMode("binned", TwinBuffer, TwinBuffer, _record_twins, transfer),
    "exact": BoundaryMode("exact", RayParcel, lambda max_cells, max_bins: RayParcel(), _record_rays, transfer_rays),
}


def boundary_mode(name: str) -> BoundaryMode:
    """The BoundaryMode called ``name``; a ConfigError naming the choices otherwise."""
    if name not in MODES:
        raise ConfigError(f"boundary mode must be one of {', '.join(MODES)}, not {name!r}")
    return MODES[name]
