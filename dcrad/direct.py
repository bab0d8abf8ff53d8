"""Direct light gathered with shadow rays (next-event estimation), before any shooting.

Shooting the emitters' power with rays leaves each receiver with the few rays
that happen to hit it: most of a run's noise is there.  Instead every receiving
patch i gathers its direct light itself, with S stratified shadow rays from
points x on i to points y on the emitters, y chosen in proportion to emitted
power (emitter by power, then uniformly on its triangle):

    P_i = A_i / S * sum_s  Phi * G(x_s, y_s) * V(x_s, y_s) * E_c(y_s) / E(y_s)

with G = cos(theta_x) cos(theta_y) / (pi r^2), V the visibility (one Embree
occlusion query), Phi the total emitted power and E(y) the emitter's exitance
summed over channels.  That is an unbiased estimate of the power arriving on
the front of i.  Receivers keep rho_i P_i as radiosity and unshot radiosity (to
be shot on as reflected light), absorb the rest; the emitters' unshot power is
spent.  Each receiver's samples form two lattices with independent shifts (the
two half-solutions of noise.py), so the estimate sees this noise too.

The books: the emitters' power Phi leaves the unshot account.  How much of it
lands, escapes or meets back faces is measured, exactly as shooting measures
it, by a modest number of ordinary rays from the emitters (``landing_rays``);
the gather only says *where* on the fronts the landed light goes: receiver i
gets P_i * L / sum_j P_j per channel, L the power those rays landed.  So the
ledger closes to round-off, a closed scene keeps exactly all its light (which
the identity Phi / (1 - rho) of a stiff furnace needs), and the gather's noise
on the total does not reach the books.

The gather is kept only when it is the quieter choice (``noise_against_shooting``):
uniform area sampling of an emitter is poor for receivers right next to it
(1/r^2 near a shared edge: a luminous ceiling and the walls it meets), where
shooting the emitter's power with rays does better; then the gather's rays are
counted and the emitters are shot instead.

Only for single-subscene runs: a subscene sees only its own emitters and
patches, so a divided run shoots its direct light as before.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .patches import Patches
from .rays import Tracer
from .sampling import lattice, triangle_points
from .shoot import Tally

__all__ = ["DirectTally", "gather_direct", "shadow_rays_for", "noise_against_shooting", "landing_rays",
           "rescale_to_landed", "merge", "PILOT_SHARE", "GATHER_MARGIN"]

#: share of the receivers (at random) gathered first to decide whether gathering beats shooting
PILOT_SHARE = 0.125
#: the pilot's noise must be below this share of shooting's: a gather's noise is heavy-tailed
#: next to an emitter (1/r^2 at a shared edge), and a pilot of few patches sees too little of it
GATHER_MARGIN = 0.7


def shadow_rays_for(rays_per_power: float, patches: int) -> int:
    """Shadow rays per receiving patch (even, 8..512): a quarter of the rays the emitters
    would shoot per patch at this density (rays_per_power / patches).

    Shooting gives receiver i about rays_per_power * F_i hits; a stratified gather
    of S samples per patch has far less variance per ray, so a quarter of that
    budget is enough to beat it where it can be beaten (bench/RESULTS.md).
    """
    s = int(math.ceil(rays_per_power / max(patches, 1) / 4.0))
    return int(min(max(s + (s % 2), 8), 512))


@dataclass
class DirectTally(Tally):
    """What a gather did: a ``shoot.Tally`` (so ``Solver.commit`` books it alike) whose
    ``received_a`` is always set (half A's samples) and whose ``escaped`` is Phi - sum of
    received (``rescale_to_landed``: the emitter rays' own), plus the shadow rays traced."""

    received_a: np.ndarray  #: (k,3) W of ``received`` from half A's samples (never None here)
    rays: int = 0  #: shadow rays traced


#: light groups (emitting objects) chosen per receiver by importance; more fall back to power alone
MAX_GROUPS = 256
#: share of each receiver's emitter choice kept in proportion to power (a defensive mixture:
#: the importance may miss light, so every emitter keeps a probability)
POWER_SHARE = 0.3


def _light_groups(patches: Patches, emitters: np.ndarray, total: np.ndarray):
    """Group emitters by object: (group of each emitter (e,), power (G,), power-weighted centroid
    (G,3), spread^2 (G,), mean normal (G,3)); one group when there are more than MAX_GROUPS."""
    _, gid = np.unique(patches.obj[emitters], return_inverse=True)
    if gid.max(initial=0) + 1 > MAX_GROUPS:
        gid = np.zeros(len(emitters), np.int64)
    g = int(gid.max(initial=0)) + 1
    phi_g = np.bincount(gid, weights=total, minlength=g)
    c = patches.centroid[emitters]
    centre = (np.stack([np.bincount(gid, weights=total * c[:, j], minlength=g) for j in range(3)], 1)
              / np.maximum(phi_g, 1e-300)[:, None])
    spread = np.bincount(gid, weights=total * ((c - centre[gid]) ** 2).sum(axis=1), minlength=g)
    spread = spread / np.maximum(phi_g, 1e-300) + patches.area[emitters].max() + 1e-12
    nrm = patches.normal[emitters]
    normal = (np.stack([np.bincount(gid, weights=total * nrm[:, j], minlength=g) for j in range(3)], 1)
              / np.maximum(phi_g, 1e-300)[:, None])
    return gid, phi_g, centre, spread, normal


def _importance(xc: np.ndarray, nx: np.ndarray, centre, spread, normal, phi_g) -> np.ndarray:
    """(k,G) probability of each light group for receivers at xc (k,3) facing nx (k,3):
    power x unoccluded cosines / distance^2 at the groups' centres, mixed with power alone."""
    d = centre[None, :, :] - xc[:, None, :]
    r2 = (d * d).sum(axis=2)
    inv = 1.0 / np.sqrt(np.maximum(r2, 1e-300))
    cos_x = np.clip((nx[:, None, :] * d).sum(axis=2) * inv, 0.0, 1.0)
    flat = np.linalg.norm(normal, axis=1) > 0.5  # a lamp with one facing (not a closed shape)
    cos_l = np.where(flat[None, :], np.clip(-(normal[None, :, :] * d).sum(axis=2) * inv, 0.0, 1.0), 1.0)
    w = phi_g[None, :] * (cos_x * cos_l + 0.02) / (r2 + spread[None, :])
    w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    return (1.0 - POWER_SHARE) * w + POWER_SHARE * (phi_g / phi_g.sum())[None, :]


def gather_direct(patches: Patches, tracer: Tracer, emitters: np.ndarray, power: np.ndarray, shadow_rays: int,
                  rng: np.random.Generator, offset: float, batch_rays: int = 262144,
                  receivers: np.ndarray | None = None) -> DirectTally:
    """Gather the direct light of ``emitters`` (e,) shooting ``power`` (e,3) W onto every patch with rho > 0.

    shadow_rays: S per receiver (even: two halves of S/2); offset: m the ends of a
    shadow ray are lifted off their surfaces.  Traces in chunks of ``batch_rays``.
    receivers: the patches to gather for (sorted, distinct; default every patch with rho > 0).
    Each sample picks a light group (an emitting object) with the receiver's own
    probabilities (``_importance``: lights in other rooms get few samples), then an
    emitter patch of the group in proportion to power, then a point on it; the
    sample's weight divides by that probability, so the estimate stays unbiased.
    """
    total = power.sum(axis=1)
    phi = float(total.sum())
    if receivers is None:
        receivers = np.flatnonzero(patches.rho.any(axis=1))
    if phi <= 0 or len(receivers) == 0:
        z = np.zeros(3)
        return DirectTally(np.zeros((0, 3)), np.zeros(0, np.int64), power.sum(axis=0), z.copy(),
                           np.zeros(patches.n_objects), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0),
                           z.copy(), z.copy(), np.abs(power).sum(axis=0), np.zeros((0, 3)), 0)
    colour = power / np.maximum(total, 1e-300)[:, None]  # E_c / E of each emitter
    gid, phi_g, centre, spread, normal = _light_groups(patches, emitters, total)
    n_groups = len(phi_g)
    # emitters in group order; key = group + cumulative power share within the group
    order = np.argsort(gid, kind="stable")
    # each group's shares sum to one, so the running sum is group + share so far within it
    key = np.cumsum(total[order] / phi_g[gid[order]])
    start_of = np.concatenate([[0], np.cumsum(np.bincount(gid, minlength=n_groups))])
    half = max(shadow_rays // 2, 1)
    s = 2 * half
    received = np.zeros((len(receivers), 3))
    received_a = np.zeros((len(receivers), 3))
    v = patches.vertices
    per_chunk = max(min(batch_rays, 8_000_000 // n_groups) // s, 1)
    for lo in range(0, len(receivers), per_chunk):
        rec = receivers[lo:lo + per_chunk]
        k = len(rec)
        # 5-D stratified samples: 2 on the receiver, 1 for the emitter, 2 on the emitter;
        # each receiver has two lattices (halves A and B) with their own random shifts
        index = np.tile(np.arange(half), 2 * k)
        shift = np.repeat(rng.random((2 * k, 5)), half, axis=0)
        u = lattice(index, shift, 5)
        owner = np.repeat(np.arange(k), s)
        in_a = np.tile(np.repeat([True, False], half), k)
        r = rec[owner]
        f = patches.faces[r]
        x = triangle_points(v[f[:, 0]], v[f[:, 1]], v[f[:, 2]], u[:, 0:2])
        # the light group by the receiver's importance, then the patch by power within it
        q = _importance(patches.centroid[rec], patches.normal[rec], centre, spread, normal, phi_g)
        cdf = np.cumsum(q, axis=1)
        cdf[:, -1] = 1.0
        grp = np.minimum((cdf[owner] <= u[:, 2:3]).sum(axis=1), n_groups - 1)
        q_sel = q[owner, grp]
        rest = np.clip((u[:, 2] - (cdf[owner, grp] - q_sel)) / np.maximum(q_sel, 1e-300), 0.0, 1.0 - 1e-12)
        pick = np.searchsorted(key, grp + rest, side="right")
        pick = np.clip(pick, start_of[grp], start_of[grp + 1] - 1)
        e_local = order[pick]
        e = emitters[e_local]
        g = patches.faces[e]
        y = triangle_points(v[g[:, 0]], v[g[:, 1]], v[g[:, 2]], u[:, 3:5])
        nx, ny = patches.normal[r], patches.normal[e]
        d = y - x
        r2 = np.einsum("ij,ij->i", d, d)
        dist = np.sqrt(np.maximum(r2, 1e-300))
        w = d / dist[:, None]
        cx = np.einsum("ij,ij->i", nx, w)
        cy = -np.einsum("ij,ij->i", ny, w)
        ok = np.flatnonzero((cx > 0) & (cy > 0) & (r != e))
        start = x[ok] + offset * nx[ok]
        seg = (y[ok] + offset * ny[ok]) - start
        visible = ~tracer.occluded(start, seg, np.ones(len(ok)))
        ok = ok[visible]
        geom = cx[ok] * cy[ok] / (math.pi * r2[ok])
        weight = phi_g[grp[ok]] / q_sel[ok]  # Phi_L / P(L | receiver): power over the choice's probability
        contrib = (weight * patches.area[r[ok]] / s * geom)[:, None] * colour[e_local[ok]]
        slot = owner[ok]
        a = in_a[ok]
        _scatter(received[lo:lo + k], slot, contrib)
        _scatter(received_a[lo:lo + k], slot[a], contrib[a])
    keep = np.flatnonzero(received.any(axis=1))
    got = received[keep]
    landed_power = got.sum(axis=0)
    escaped = power.sum(axis=0) - landed_power
    magnitude = np.abs(got)
    return DirectTally(got, receivers[keep], escaped, np.zeros(3), np.zeros(patches.n_objects),
                       np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), magnitude.sum(axis=0),
                       (magnitude * patches.rho[receivers[keep]]).sum(axis=0), np.abs(escaped),
                       received_a[keep], int(len(receivers) * s))


def _scatter(into: np.ndarray, rows: np.ndarray, values: np.ndarray) -> None:
    """into[rows] += values, rows repeating (one bincount per channel); ``into`` is a view."""
    m = len(into)
    for c in range(values.shape[1]):
        into[:, c] += np.bincount(rows, weights=values[:, c], minlength=m)


def noise_against_shooting(patches: Patches, tally: DirectTally, power: np.ndarray,
                           power_per_ray: float) -> tuple[float, float]:
    """(gather, shooting): sum_i A_i |noise of B_i|^2 of the direct light (W^2/m^2 m^2, channel mean).

    The gather's from its two halves (noise.py: |D/2|^2, D = 2 rho (2 P_A - P) / A);
    shooting's predicted: a receiver of direct power P_c gets hits of Phi_c / N W
    each from the N = Phi / power_per_ray rays, variance P_c Phi_c / N (Poisson).
    """
    rows = tally.hit
    if len(rows) == 0:
        return 0.0, 0.0
    area = patches.area[rows]
    rho = patches.rho[rows]
    d = rho * 2.0 * (2.0 * tally.received_a - tally.received) / area[:, None]
    gather = float(np.dot((d * d).mean(axis=1), area)) / 4.0
    phi = power.sum(axis=0)
    rays = max(float(phi.sum()) / max(power_per_ray, 1e-300), 1.0)
    var = np.abs(tally.received) * (phi / rays)[None, :] * (rho / area[:, None]) ** 2
    shoot = float(np.dot(var.mean(axis=1), area))
    return gather, shoot


def landing_rays(shadow_rays: int, receivers: int, emitters: int, batch_rays: int) -> int:
    """Rays from the emitters that measure where the gathered light's total goes: an
    eighth of the shadow rays, at least 4096 and 2 per emitter, at most one batch."""
    return int(min(max(shadow_rays * receivers // 8, 4096, 2 * emitters), max(batch_rays, 2 * emitters)))


def rescale_to_landed(gathered: DirectTally, shot, patches: Patches) -> DirectTally | None:
    """The gather's distribution with the landed total and the losses of the emitters' own
    rays ``shot`` (a ``shoot.Tally``); None when some channel landed light the gather missed."""
    got = gathered.received.sum(axis=0)
    landed = shot.received.sum(axis=0)
    if np.any((got <= 0) & (np.abs(landed) > 0)):
        return None
    scale = np.where(got > 0, landed / np.where(got > 0, got, 1.0), 0.0)
    received = gathered.received * scale
    received_a = gathered.received_a * scale
    magnitude = np.abs(received)
    return DirectTally(received, gathered.hit, shot.escaped, shot.back_faces, shot.back_by_obj,
                       gathered.portal, gathered.portal_prim, gathered.portal_t, magnitude.sum(axis=0),
                       (magnitude * patches.rho[gathered.hit]).sum(axis=0), shot.lost, received_a, gathered.rays)


def merge(a: DirectTally, b: DirectTally, patches: Patches) -> DirectTally:
    """One tally of two gathers over disjoint receivers (``a.escaped`` must be recomputed
    by ``rescale_to_landed``, which replaces it with the emitters' rays' own)."""
    hit = np.concatenate([a.hit, b.hit])
    order = np.argsort(hit, kind="stable")
    received = np.concatenate([a.received, b.received])[order]
    magnitude = np.abs(received)
    return DirectTally(received, hit[order], a.escaped + b.escaped, a.back_faces + b.back_faces,
                       a.back_by_obj + b.back_by_obj, a.portal, a.portal_prim, a.portal_t, magnitude.sum(axis=0),
                       (magnitude * patches.rho[hit[order]]).sum(axis=0), a.lost + b.lost,
                       np.concatenate([a.received_a, b.received_a])[order], a.rays + b.rays)
