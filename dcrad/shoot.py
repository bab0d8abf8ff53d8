"""The shooting kernel: rays out from many shooters at once, power in, on Embree.

One call shoots the unshot power of K patches with a total of up to
``batch_rays`` rays: sample origins and cosine directions for all rays
(vectorised), trace them in one Embree call, and scatter the power onto the
patches that were hit with ``np.bincount``.  Each ray carries shooter power /
rays.  A front hit on patch j deposits ``rho_j * p`` as new radiosity (and
unshot radiosity) on j and ``(1 - rho_j) * p`` in the absorbed account; a back
hit and a ray that escapes go to their own ledger accounts.  Nothing is
dropped, so the ledger closes to float64 round-off.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import TOL
from .patches import Patches
from .rays import MISS, Tracer
from .sampling import cosine_hemisphere, lattice, onb

__all__ = ["RayBatch", "Tally", "ray_lattice", "per_ray_power", "patch_rays", "trace", "deposit"]


@dataclass
class RayBatch:
    """Rays of one Embree call.

    origins (m,3) f8, dirs (m,3) f8 unit, power (m,3) f8 W carried by each ray,
    shooter (m,) i8 index into the batch's list of shooters.
    """

    origins: np.ndarray
    dirs: np.ndarray
    power: np.ndarray
    shooter: np.ndarray

    def __len__(self) -> int:
        return len(self.origins)


@dataclass
class Tally:
    """What one batch of rays did.

    received (n,3) W  power arriving on the front of each patch
    escaped, back_faces (3,) W
    back_by_obj (n_obj,) W  back-face power by object, for the flipped-normal warning
    portal (k,) i8  indices of rays that hit a primitive >= n (a boundary), with
    portal_prim (k,) i8 and portal_t (k,) f8; empty when the scene has no boundary
    landed, kept (3,) W  sums of |received| over patches (times rho, for kept), and
    lost (3,) W  sum of |ray power| over rays that escaped or hit a back face: unlike
    the signed sums, the loss does not cancel when rays of both signs (overshooting)
    meet, and kept/landed is a mean rho whatever the signs; they feed the
    return-ratio estimate (solve.stiffness)
    """

    received: np.ndarray
    escaped: np.ndarray
    back_faces: np.ndarray
    back_by_obj: np.ndarray
    portal: np.ndarray
    portal_prim: np.ndarray
    portal_t: np.ndarray
    landed: np.ndarray
    kept: np.ndarray
    lost: np.ndarray


def ray_offset(patches: Patches) -> float:
    """Distance (m) ray origins are lifted off their surface: relative to scene size."""
    return TOL.ray_offset * patches.scale


def ray_lattice(counts: np.ndarray, rng: np.random.Generator, dtype=np.float64):
    """Stratified 4-D samples for shooters that get ``counts`` (k,) rays each.

    Each shooter has its own randomly shifted R4 lattice.  Returns (owner (m,) i8,
    the shooter of each ray; u (m,4) in [0,1) of ``dtype``).
    """
    k = len(counts)
    owner = np.repeat(np.arange(k), counts)
    start = np.cumsum(counts) - counts
    index = np.arange(int(counts.sum())) - np.repeat(start, counts)
    return owner, lattice(index, np.repeat(rng.random((k, 4)), counts, axis=0), 4, dtype=dtype)


def per_ray_power(power: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(m,3) W each ray carries: its shooter's power (k,3) split evenly over its rays."""
    return np.repeat(power / counts[:, None], counts, axis=0)


def patch_rays(
    patches: Patches,
    shooters: np.ndarray,
    counts: np.ndarray,
    power: np.ndarray,
    rng: np.random.Generator,
) -> RayBatch:
    """Cosine-distributed rays from stratified points of each shooter.

    shooters (k,) i8 patch indices; counts (k,) i8 rays each; power (k,3) W to shoot.
    Each shooter gets its own randomly shifted 4-D lattice (2 dims position, 2 dims
    direction), so its rays are stratified over the triangle and the hemisphere.
    """
    owner, u = ray_lattice(counts, rng, dtype=np.float32)

    # Per-shooter geometry, repeated per ray (np.repeat is ~8x faster than a gather)
    faces = patches.faces[shooters]
    v = patches.vertices
    v0 = v[faces[:, 0]]
    n_k = patches.normal[shooters]
    t_k, b_k = onb(n_k)
    frames = np.repeat(np.stack([t_k, b_k, n_k], axis=1).astype(np.float32), counts, axis=0)
    corners = np.repeat(np.stack([v0, v[faces[:, 1]] - v0, v[faces[:, 2]] - v0], axis=1), counts, axis=0)

    # Stratified points on the triangles (float64 positions), lifted off the surface
    s = np.sqrt(u[:, 0])
    b1 = (s * (1 - u[:, 1])).astype(np.float64)
    b2 = (s * u[:, 1]).astype(np.float64)
    origins = corners[:, 0] + b1[:, None] * corners[:, 1] + b2[:, None] * corners[:, 2]
    origins += ray_offset(patches) * frames[:, 2]

    # Cosine directions in each shooter's frame (float32: Embree's precision)
    local = cosine_hemisphere(u[:, 2:])
    dirs = np.einsum("mi,mij->mj", local, frames)
    return RayBatch(origins=origins, dirs=dirs, power=per_ray_power(power, counts), shooter=owner)


def trace(tracer: Tracer, batch: RayBatch, patches: Patches, channels: int = 3) -> Tally:
    """Trace a batch and tally where its power went (no state is changed).

    channels=1 (grey scenes: every rho, E and ray power has equal channels) tallies
    the first channel and copies it: the result is the same, one bincount instead of three.
    """
    n = len(patches)
    prim, t = tracer.intersect(batch.origins, batch.dirs)
    is_patch = (prim != MISS) & (prim < n)
    missed = prim == MISS
    portal = np.flatnonzero((prim != MISS) & (prim >= n))

    # Front or back: the ray travels against the hit patch's normal on the front
    pidx = np.where(is_patch, prim, 0)
    facing = np.einsum("ij,ij->i", batch.dirs, patches.normal[pidx])
    front = is_patch & (facing < 0.0)
    back = is_patch & ~front

    # Scatter power onto patches, one bincount per channel
    received = np.empty((n, 3), np.float64)
    hit = prim[front]
    for c in range(channels):
        received[:, c] = np.bincount(hit, weights=batch.power[front, c], minlength=n)
    if channels == 1:
        received[:, 1] = received[:, 0]
        received[:, 2] = received[:, 0]

    # landed/kept per patch, not per ray: a gather of rho per ray cost a quarter of trace
    # time, and only the ratio kept/landed (mean rho where light lands) is used
    magnitude = np.abs(received)
    landed = magnitude.sum(axis=0)
    kept = (magnitude * patches.rho).sum(axis=0)
    back_by_obj = np.bincount(
        patches.obj[prim[back]], weights=batch.power[back].sum(axis=1), minlength=patches.n_objects
    )
    return Tally(
        received=received,
        escaped=batch.power[missed].sum(axis=0),
        back_faces=batch.power[back].sum(axis=0),
        back_by_obj=back_by_obj,
        portal=portal,
        portal_prim=prim[portal] - n,
        portal_t=t[portal],
        landed=landed,
        kept=kept,
        lost=np.abs(batch.power[missed | back]).sum(axis=0),
    )


def deposit(patches: Patches, received: np.ndarray) -> np.ndarray:
    """Add received power to B and dB; return the absorbed power (3,) W.

    received (n,3) W.  A patch keeps rho * received as radiosity and unshot
    radiosity (divided by its area) and absorbs the rest.
    """
    hit = np.flatnonzero(received.any(axis=1))
    reflected = patches.rho[hit] * received[hit]
    gain = reflected / patches.area[hit, None]
    patches.radiosity[hit] += gain
    patches.unshot[hit] += gain
    return (received[hit] - reflected).sum(axis=0)
