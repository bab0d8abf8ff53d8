"""The energy ledger and convergence measures.

Every watt emitted is, at any moment, in exactly one place::

    emitted = absorbed + unshot (patches) + in_flight (twin buffers)
              + escaped + back_faces

A subscene's own books also carry what crossed its boundaries:
``emitted + imported = ... + exported``; over a whole job imports and exports
cancel.

The solver moves power between these accounts in float64; ``closure()``
reports how far the books are from balancing (round-off only).  ``escaped_light`` and
``flipped_normals`` are the warnings two of the accounts raise (every report's).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from dcrad.config import TOL

if TYPE_CHECKING:
    from dcrad.meshing.patches import Patches

__all__ = ["ACCOUNTS", "MAGNITUDES", "Ledger", "escaped_light", "flipped_normals", "rms_error", "read_error"]


ACCOUNTS = ("emitted", "absorbed", "escaped", "back_faces", "unshot", "in_flight", "imported", "exported")
#: magnitudes kept beside the signed accounts (overshooting makes unshot and twin power signed)
MAGNITUDES = ("unshot_abs", "in_flight_abs")


def _zeros() -> np.ndarray:
    return np.zeros(3, np.float64)


@dataclass
class Ledger:
    """Power accounts (W, RGB, float64).  ``unshot`` and ``in_flight`` are set by their owners."""

    emitted: np.ndarray = field(default_factory=_zeros)  #: W, total emitted power
    absorbed: np.ndarray = field(default_factory=_zeros)  #: W, (1 - rho) share of every hit
    escaped: np.ndarray = field(default_factory=_zeros)  #: W, rays that left the scene
    back_faces: np.ndarray = field(default_factory=_zeros)  #: W, rays that hit a back face
    unshot: np.ndarray = field(default_factory=_zeros)  #: W, sum of dB * A over patches
    in_flight: np.ndarray = field(default_factory=_zeros)  #: W, power held in twin buffers
    unshot_abs: np.ndarray = field(default_factory=_zeros)  #: W, sum of |dB| * A (dB < 0 after overshooting)
    in_flight_abs: np.ndarray = field(default_factory=_zeros)  #: W, sum of |power| over twin entries
    imported: np.ndarray = field(default_factory=_zeros)  #: W, received from neighbours (subscenes)
    exported: np.ndarray = field(default_factory=_zeros)  #: W, handed to neighbours (subscenes)

    def accounted(self) -> np.ndarray:
        """(3,) W: everything the books say is somewhere (or was handed on)."""
        return self.absorbed + self.unshot + self.in_flight + self.escaped + self.back_faces + self.exported

    def closure(self) -> float:
        """Relative imbalance |emitted + imported - accounted| / (emitted + imported)."""
        total = float((self.emitted + self.imported).sum())
        if total <= 0.0:
            return float(np.abs(self.accounted()).sum())
        return float(np.abs(self.emitted + self.imported - self.accounted()).sum() / total)

    def residual(self) -> float:
        """Share of the emitted power not yet settled: (|unshot| + |in flight|) / emitted.

        Overshooting leaves negative unshot radiosity behind, so the residual counts
        magnitudes: a signed sum could vanish while power still has to move.
        """
        total = float(self.emitted.sum())
        if total <= 0.0:
            return 0.0
        unshot = np.maximum(self.unshot_abs, np.abs(self.unshot))
        flight = np.maximum(self.in_flight_abs, np.abs(self.in_flight))
        return float((unshot.sum() + flight.sum()) / total)

    def held(self) -> np.ndarray:
        """(3,) W still to move: the unshot and in-flight magnitudes (as in ``residual``), per channel."""
        return np.maximum(self.unshot_abs, np.abs(self.unshot)) + np.maximum(self.in_flight_abs, np.abs(self.in_flight))

    def __iadd__(self, other: "Ledger") -> "Ledger":
        for name in ACCOUNTS + MAGNITUDES:
            setattr(self, name, getattr(self, name) + getattr(other, name))
        return self

    def to_array(self) -> np.ndarray:
        """(10, 3): every account, in ACCOUNTS + MAGNITUDES order (checkpoints, the wire)."""
        return np.stack([getattr(self, a) for a in ACCOUNTS + MAGNITUDES])

    @staticmethod
    def from_array(rows) -> "Ledger":
        """The inverse of ``to_array``."""
        return Ledger(**{a: np.array(row, np.float64) for a, row in zip(ACCOUNTS + MAGNITUDES, rows)})

    def copy(self) -> "Ledger":
        return Ledger(**{k: np.array(v, np.float64) for k, v in self.as_arrays().items()})

    def as_arrays(self) -> dict:
        return {name: getattr(self, name) for name in ACCOUNTS + MAGNITUDES}

    def as_dict(self) -> dict:
        """JSON-ready: every account as [r, g, b] W, plus closure and residual."""
        out: dict[str, list[float] | float] = {k: [float(x) for x in v] for k, v in self.as_arrays().items()}
        out["closure"] = self.closure()
        out["residual"] = self.residual()
        return out


def escaped_light(ledger: Ledger, patches: Patches) -> list[str]:
    """The escaped-light warning: most of the shot power left the scene without hitting
    anything (above TOL.escape_warn), naming the (at most five) emitting objects."""
    shot = float(ledger.emitted.sum() - ledger.unshot.sum())
    escaped = float(ledger.escaped.sum())
    if not (shot > 0 and escaped / shot > TOL.escape_warn):
        return []
    emitting = np.unique(patches.obj[patches.emission.max(axis=1) > 0])
    names = [patches.names[i] for i in emitting[:5] if i < len(patches.names)]
    return [f"{100 * escaped / shot:.1f}% of the shot power escaped the scene without hitting anything: "
            f"do the lights ({', '.join(names) or '?'}) face away from it (emitters light their front, "
            f"counter-clockwise side), or is the scene open?"]


def flipped_normals(ledger: Ledger, back_by_obj: np.ndarray, names: list[str]) -> list[str]:
    """The flipped-normals warning (back-face share of shot power above TOL.backface_warn),
    naming the (at most five) objects whose back faces took the most power."""
    shot = float(ledger.emitted.sum() - ledger.unshot.sum())
    back = float(ledger.back_faces.sum())
    if not (shot > 0 and back / shot > TOL.backface_warn):
        return []
    back_by_obj = np.asarray(back_by_obj, np.float64)
    order = np.argsort(-back_by_obj)
    worst = [names[i] for i in order[:5] if back_by_obj[i] > 0 and i < len(names)]
    return [f"{100 * back / shot:.1f}% of the shot power hit back faces; normals are probably "
            f"flipped on: {', '.join(worst) or '(no object recorded)'}"]


def rms_error(b: np.ndarray, reference: np.ndarray, area: np.ndarray) -> float:
    """Area-weighted RMS error sqrt(sum_i |B*_i - B_i|^2 A_i / sum_i A_i) (W/m^2).

    b, reference : (n, 3) or (n,) radiosity; area : (n,).  The squared error of a
    patch is the mean over its channels.
    """
    diff = np.asarray(reference, np.float64) - np.asarray(b, np.float64)
    sq = diff * diff
    if sq.ndim == 2:
        sq = sq.mean(axis=1)
    total = float(area.sum())
    if total <= 0.0:
        return 0.0
    return float(np.sqrt(np.dot(sq, area) / total))


def read_error(patches: Patches, b: np.ndarray, reference: np.ndarray, per_triangle: bool = False) -> float:
    """The RMS error of ``b`` against ``reference`` (both (n, 3) over ``patches``) as it is read, over
    the RMS of the reference's reflected light read alike: per element (a cluster's patches share one
    B), or per input triangle side (the area mean of its patches: radiosity.npz's B).  A measurement,
    for benchmarks and tests; noise.py estimates it."""
    reads, a = patches.reads(per_triangle), patches.area
    w = np.bincount(reads, weights=a)
    ok = w > 0

    def mean(x: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(reads, weights=a * x[:, c])[ok] / w[ok] for c in range(3)], axis=1)

    err = mean(np.asarray(b, np.float64) - reference)
    refl = mean(np.asarray(reference, np.float64) - patches.emission)
    den = float((w[ok, None] * refl ** 2).sum())
    return float(np.sqrt((w[ok, None] * err ** 2).sum() / den)) if den > 0 else 0.0
