"""Light sources that are not surfaces of the scene: the emitter seam.

Two kinds of light reach dcrad's solution.  Emitting surfaces (``Ke``, glTF emissive) are
patches with an exitance E: they sit in the patch table, the shooting shoots their unshot
power like any patch's, and the direct gather reads their outlines (lights.py, direct.py).
Everything else (a luminaire of a photometric file, a point or spot light, the sky and the sun of
sky.py) is an ``Emitter``: an object that says how much it emits, sends its light as rays, and gives
the exact direct irradiance it puts on any point.  What asks them:

* ``Solver`` books their power as emitted and spends it once, at the start of a run, before the
  patches shoot (``DirectPhase.shoot_sources``): with the direct gather on (the default) each patch
  receives the mean of the exact direct irradiance over it (``patch_irradiance``: three points, a
  shadow ray each; a point source has no area, so this has no sampling noise), scaled to the power
  a batch of the source's own rays lands (the books: escaped, back faces), and reflects it like
  any light; with ``--no-direct`` the source is shot with rays;
* ``photometry.direct_irradiance`` adds their exact direct light to the lux of black surfaces
  and of the work plane (a point source: one shadow ray a point is exact).

Their exact direct light is the run's direct light, as the emitting patches' gathered light is: in
accuracy mode a run follows the final plan with them (``DirectPhase.sources_only``; not when a
source had to be shot).  A new kind of emitter implements the three methods below and touches
nothing else.  One whose direct light has no exact form (the sky) says ``exact = False`` and gives
``patch_gather`` and ``pilot``: DirectPhase gathers it in two sampled halves instead.  They run on
every path: in one process, shared by workers and divided (a source belongs to the subscene holding
it, which shoots it first; source_wire.py carries them to workers).  A divided run's sky and sun are
gathered on the whole scene before it is cut, and each subscene is handed what landed on its
patches (``Gathered``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from dcrad.errors import ConfigError
from dcrad.estimate.noise import half_mask
from dcrad.transport.sampling import DEGREE2_RULE, lattice
from dcrad.transport.shoot import RayBatch

__all__ = ["Emitter", "PointSource", "Gathered", "sources_power", "sphere_directions", "patch_irradiance", "visibility",
           "half_lattice", "half_weights"]


@runtime_checkable
class Emitter(Protocol):
    """A light source outside the patch table (module doc)."""

    name: str

    def power(self) -> np.ndarray:
        """(3,) W it emits in all, per channel."""
        ...

    def rays(self, n: int, rng: np.random.Generator) -> RayBatch:
        """``n`` rays carrying its whole power (each ray's share by its direction), split in two
        halves with independent samples (noise.py: the halves are two solutions)."""
        ...

    def irradiance(self, points: np.ndarray, normals: np.ndarray, tracer, offset: float) -> np.ndarray:
        """(m,3) W/m^2 its direct light puts on ``points`` (m,3) facing ``normals`` (m,3), occluders
        included (``tracer``: the scene's Embree scene; ``offset``: m the shadow rays start off the
        surface)."""
        ...


def half_lattice(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(u (n,2) in [0,1), half (n,) bool): ``n`` stratified 2-D samples, the first ceil(n/2) and the
    rest from two independently shifted lattices (the two half-solutions of noise.py)."""
    half = half_mask(np.array([n]), rng)
    u = np.empty((n, 2))
    for which in (True, False):
        rows = np.flatnonzero(half == which)
        if len(rows):
            u[rows] = lattice(np.arange(len(rows)), np.repeat(rng.random((1, 2)), len(rows), axis=0), 2)
    return u, half


def half_weights(weight: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(n,) each ray's share of a source's power from its direction's ``weight`` (n,): each half's
    shares sum to exactly 1/2 (one half alone, a single ray: to 1), so the books close with the
    source's ``power()``; a half whose weights are all 0 (every sample on a dark edge) shares alike."""
    out = np.empty(len(weight))
    split = 0 < int(half.sum()) < len(half)
    for rows in (np.flatnonzero(half), np.flatnonzero(~half)):
        if len(rows):
            w = weight[rows]
            w = w if w.sum() > 0 else np.ones_like(w)
            out[rows] = w / w.sum() * (0.5 if split else 1.0)
    return out


def sphere_directions(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(dirs (n,3) unit, half (n,) bool): stratified uniform directions on the sphere, each half
    from its own shifted lattice (``half_lattice``)."""
    u, half = half_lattice(n, rng)
    z = 1.0 - 2.0 * u[:, 0]
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = 2.0 * math.pi * u[:, 1]
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1), half


@dataclass
class PointSource:
    """A point light at ``position`` (m, the solver's coordinates) with intensity I(direction) (3,)
    W/sr per channel.  ``intensity`` (3,): isotropic, I the same in every direction; a callable
    (dirs (m,3) unit -> (m,3) W/sr) for a distribution (a luminaire's candela table, converted)."""

    position: np.ndarray
    intensity: object = field(default_factory=lambda: np.ones(3))
    name: str = "point source"
    #: directions a numerical integral of a callable intensity takes (the power)
    integration_rays: int = 1 << 16

    def __post_init__(self) -> None:
        self.position = np.asarray(self.position, np.float64).reshape(3)
        if not np.isfinite(self.position).all():
            raise ConfigError(f"{self.name}: position {self.position.tolist()} is not finite")
        if not callable(self.intensity):
            self.intensity = np.asarray(self.intensity, np.float64).reshape(3)
            if not (np.isfinite(self.intensity).all() and (self.intensity >= 0).all()):
                raise ConfigError(f"{self.name}: intensity {self.intensity.tolist()} W/sr must be finite and >= 0")
        self._power: np.ndarray | None = None

    def to_wire(self) -> dict:
        """What rebuilds it on a worker (``from_wire``; source_wire.py), JSON-able and exact.  A
        distribution given as a Python function cannot travel: ConfigError naming the source."""
        if callable(self.intensity):
            raise ConfigError(f"{self.name}: a point source whose intensity is a Python function runs in this "
                              f"process only (--workers 0)")
        return {"name": self.name, "position": self.position.tolist(),
                "intensity": np.asarray(self.intensity, np.float64).tolist()}

    @classmethod
    def from_wire(cls, d: dict) -> "PointSource":
        return cls(np.array(d["position"], np.float64), np.array(d["intensity"], np.float64), name=str(d["name"]))

    def intensity_at(self, dirs: np.ndarray) -> np.ndarray:
        """(m,3) W/sr toward unit ``dirs`` (m,3)."""
        if callable(self.intensity):
            i = np.asarray(self.intensity(dirs), np.float64).reshape(len(dirs), 3)
            if not (np.isfinite(i).all() and (i >= 0).all()):
                raise ConfigError(f"{self.name}: its intensity distribution gave negative or non-finite values")
            return i
        return np.broadcast_to(np.asarray(self.intensity, np.float64), (len(dirs), 3))

    def power(self) -> np.ndarray:
        """4 pi I when isotropic; else the mean of I over ``integration_rays`` stratified directions
        times 4 pi (computed once)."""
        if self._power is None:
            if callable(self.intensity):
                dirs, _ = sphere_directions(self.integration_rays, np.random.default_rng(0))
                self._power = 4.0 * math.pi * self.intensity_at(dirs).mean(axis=0)
            else:
                self._power = 4.0 * math.pi * np.asarray(self.intensity)
        return self._power

    def rays(self, n: int, rng: np.random.Generator) -> RayBatch:
        """Uniform stratified directions, each ray carrying 4 pi I(dir) / n_half / 2 of its half's
        power (for an isotropic source exactly P / n); a distribution's halves are scaled to carry
        exactly half of ``power()`` each, so the ledger closes with it."""
        dirs, half = sphere_directions(n, rng)
        n_a = int(half.sum())
        n_b = n - n_a
        split = n_a > 0 and n_b > 0  # one ray (either half, noise.half_mask) carries it all
        per = np.where(half, 0.5 / max(n_a, 1), 0.5 / max(n_b, 1)) if split else np.full(n, 1.0 / n)
        power = 4.0 * math.pi * self.intensity_at(dirs) * per[:, None]
        if callable(self.intensity):
            # each half carries exactly its half of ``power()`` (the integral the ledger books as
            # emitted): the directions' own sum differs from it by their sampling noise, which left
            # a downlight's books open by 2.5e-5 of its power
            parts = (half, ~half) if split else (np.ones(n, bool),)
            for rows in parts:
                got = power[rows].sum(axis=0)
                want = self.power() / len(parts)
                power[rows] *= np.where(got > 0, want / np.where(got > 0, got, 1.0), 0.0)
        origins = np.broadcast_to(self.position, (n, 3)).copy()
        return RayBatch(origins=origins, dirs=dirs, power=power, shooter=np.zeros(n, np.int64),
                        half=half if split else None)

    def irradiance(self, points: np.ndarray, normals: np.ndarray, tracer, offset: float) -> np.ndarray:
        """I(-d) cos / r^2 where the point sees the source (one shadow ray a point: exact), times the
        transmittance of the panes in between (optics.py)."""
        points = np.asarray(points, np.float64)
        d = self.position - points
        r = np.sqrt(np.einsum("ij,ij->i", d, d))
        toward = d / np.maximum(r, 1e-300)[:, None]
        cos = np.einsum("ij,ij->i", toward, normals)
        lit = np.flatnonzero((cos > 0) & (r > offset))
        out = np.zeros((len(points), 3))
        if not len(lit):
            return out
        seen = visibility(tracer, points[lit] + offset * toward[lit], toward[lit], r[lit] - 2.0 * offset)
        if seen.shape[1] == 3:  # through glass: tau(theta) of every pane crossed
            out[lit] = self.intensity_at(-toward[lit]) * (cos[lit] / r[lit] ** 2)[:, None] * seen
            return out
        lit = lit[seen[:, 0] > 0]  # opaque: the intensity of the points that see it only
        out[lit] = self.intensity_at(-toward[lit]) * (cos[lit] / r[lit] ** 2)[:, None]
        return out


def visibility(tracer, start: np.ndarray, toward: np.ndarray, length: np.ndarray) -> np.ndarray:
    """The share of a source's light that gets from ``start`` along unit ``toward`` over ``length``
    (one shadow ray each): (k,3), the panes' tau(theta) (optics.py), where the scene has glass;
    else (k,1), 1 where nothing is in the way and 0 where something is."""
    if getattr(tracer, "glazing", None) is not None:
        return tracer.transmittance(start, toward, length)
    return (~tracer.occluded(start, toward, length)).astype(np.float64)[:, None]


#: patches whose irradiance ``patch_irradiance`` evaluates at once (three points and a shadow ray each)
PATCH_CHUNK = 1 << 16


def patch_irradiance(source: Emitter, corners: np.ndarray, normals: np.ndarray, tracer, offset: float,
                     glazing=None) -> np.ndarray:
    """(k,3) W/m^2: the mean of ``source``'s direct irradiance over each triangle ``corners`` (k,3,3)
    facing ``normals`` (k,3), by the degree-2 rule (three points, a shadow ray each), in chunks of
    PATCH_CHUNK triangles.  ``glazing`` (optics.Glazing of these k rows, or None): a pane keeps only
    (1 - tau(theta)) of what meets it, the rest goes on through it (a point source's direction)."""
    out = np.zeros((len(corners), 3))
    r = len(DEGREE2_RULE)
    panes = None if glazing is None else np.asarray(glazing.mask, bool)
    position = getattr(source, "position", None)
    direction = getattr(source, "direction", None)  # a parallel beam (the sun): one direction everywhere
    if panes is not None and panes.any() and position is None and direction is None:
        raise ConfigError(f"{source.name}: a light source without a position cannot light glass yet")
    for lo in range(0, len(corners), PATCH_CHUNK):
        c = np.asarray(corners[lo:lo + PATCH_CHUNK], np.float64)
        points = np.einsum("rc,kcx->krx", DEGREE2_RULE, c).reshape(-1, 3)
        facing = np.repeat(normals[lo:lo + PATCH_CHUNK], r, axis=0)
        h = source.irradiance(points, facing, tracer, offset)
        if panes is not None:
            on = np.flatnonzero(np.repeat(panes[lo:lo + len(c)], r))
            if len(on):
                d = (np.asarray(position, np.float64) - points[on] if position is not None
                     else np.repeat(np.asarray(direction, np.float64)[None, :], len(on), axis=0))
                cos = np.abs(np.einsum("ij,ij->i", d, facing[on])) / np.maximum(np.linalg.norm(d, axis=1), 1e-300)
                rows = np.repeat(np.arange(lo, lo + len(c)), r)[on]
                h[on] *= 1.0 - glazing.tau(rows, cos)
        out[lo:lo + len(c)] = h.reshape(len(c), r, 3).mean(axis=1)
    return out


def sources_power(sources) -> np.ndarray:
    """(3,) W all of ``sources`` emit."""
    return sum((np.asarray(s.power(), np.float64) for s in sources), np.zeros(3))


@dataclass
class Gathered:
    """Light already gathered onto some patches (``rows``): the sky and the sun of a divided run,
    gathered on the whole scene before it is cut (division/outside.py), whose lines of sight no
    subscene could follow out of the model.  ``DirectPhase.deposit`` books what landed as its run's
    emitted light (the books of light from outside hold what lands) and lays it down, in the gather's
    two halves (noise.py), and counts the rays it took.  It sends no rays and has no point estimate:
    the outputs read the original sources."""

    name: str
    rows: np.ndarray  #: (m,) i8 the receivers, sorted and distinct
    received: np.ndarray  #: (m,3) W landed on each
    received_a: np.ndarray  #: (m,3) W of it from half A's samples
    rays: int = 0  #: rays the gather traced
    gathered = True  #: DirectPhase lays it down (``deposit``): nothing to trace

    def power(self) -> np.ndarray:
        """(3,) W: what it landed."""
        return self.received.sum(axis=0)

    def to_wire(self) -> dict:
        """source_wire.py: the per-receiver arrays travel as arrays, the rest as JSON."""
        return {"name": self.name, "rows": self.rows, "received": self.received, "received_a": self.received_a,
                "rays": int(self.rays)}

    @classmethod
    def from_wire(cls, d: dict) -> "Gathered":
        return cls(str(d["name"]), np.asarray(d["rows"], np.int64), np.asarray(d["received"], np.float64),
                   np.asarray(d["received_a"], np.float64), int(d["rays"]))
