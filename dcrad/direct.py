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

Two gathers: ``gather_analytic`` (used when the emitters make few enough light
polygons, lights.py) takes each receiver's unoccluded form factor to each light
exactly (Lambert's formula) and uses shadow rays only for the visible share, so a
receiver that sees a light whole or not at all has no noise; rays go where a pilot
found penumbrae, and lights the pilot found hidden (the many lights of other
rooms) are traced by Russian roulette.  Cornell at 32 shadow rays per patch: 0.49%
noise on the direct light, against 1.5% for ``gather_direct`` (next-event
estimation with receiver-local light choice, the fallback) at 44; the office 3x3:
1.75% at 32, where next-event estimation lost to shooting.

Only for single-subscene runs: a subscene sees only its own emitters and
patches, so a divided run shoots its direct light as before.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .lights import Lights, light_polygons, polygon_form_factor
from .patches import Patches
from .rays import Tracer
from .sampling import lattice, triangle_points
from .shoot import Tally

__all__ = ["DirectTally", "gather_direct", "shadow_rays_for", "noise_against_shooting", "landing_rays",
           "rescale_to_landed", "merge", "PILOT_SHARE", "GATHER_MARGIN", "gather_analytic", "light_pairs",
           "pair_form_factors", "MAX_PAIRS", "analytic_lights"]

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



# == direct light from exact form factors ========================================================
#: (receiver, light loop) pairs tested above which the analytic gather is not used (the sampled one is)
MAX_PAIRS = 20_000_000


def light_pairs(patches: Patches, lights: Lights, receivers: np.ndarray, chunk: int = 4096):
    """(receiver slot (q,), light (q,)) of every pair that can exchange light: some corner of the
    receiver in front of a loop's plane and some vertex of that loop above the receiver's plane."""
    v = patches.vertices
    origin = lights.loops[:, 0]
    ny = lights.normal[lights.loop_light]
    offset = (origin * ny).sum(axis=1)
    slots, found = [], []
    for lo in range(0, len(receivers), chunk):
        rec = receivers[lo:lo + chunk]
        corners = v[patches.faces[rec]]  # (k,3,3)
        nrm = patches.normal[rec]
        front = (np.einsum("kcj,pj->kcp", corners, ny) > offset[None, None, :]).any(axis=1)
        above = (np.einsum("pvj,kj->kpv", lights.loops, nrm)
                 > (corners[:, 0] * nrm).sum(axis=1)[:, None, None]).any(axis=2)
        k_idx, loop = np.nonzero(front & above)
        code = np.unique((lo + k_idx) * len(lights) + lights.loop_light[loop])
        slots.append(code // len(lights))
        found.append(code % len(lights))
    if not slots:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(slots), np.concatenate(found)


def pair_form_factors(patches: Patches, lights: Lights, rec: np.ndarray, light: np.ndarray,
                      rng: np.random.Generator) -> np.ndarray:
    """(q,2) exact unoccluded form factor from receiver ``rec`` to ``light`` per pair, each half the
    mean over three points of the receiver: a uniform random point and its two cyclic
    permutations of barycentric coordinates.  Each point is uniform on the triangle (unbiased)
    and the three average to the centroid, so the part of F linear over the patch is exact
    (two independent random points per half left 0.8% noise on Cornell's direct light)."""
    v = patches.vertices
    n_loops = np.bincount(lights.loop_light, minlength=len(lights))
    loop_start = np.cumsum(n_loops) - n_loops
    per_pair = n_loops[light]
    owner = np.repeat(np.arange(len(rec)), per_pair)
    loop = loop_start[light][owner] + (np.arange(len(owner)) - np.repeat(np.cumsum(per_pair) - per_pair, per_pair))
    r = rec[owner]
    f = patches.faces[r]
    corners = (v[f[:, 0]], v[f[:, 1]], v[f[:, 2]])
    nx = patches.normal[r]
    ny = lights.normal[lights.loop_light[loop]]
    ff = np.zeros((len(rec), 2))
    u = rng.random((len(rec), 2, 2))
    for h in range(2):
        s = np.sqrt(u[owner, h, 0])
        bary = (1.0 - s, s * (1.0 - u[owner, h, 1]), s * u[owner, h, 1])
        for k in range(3):
            b = (bary[k % 3], bary[(k + 1) % 3], bary[(k + 2) % 3])
            x = b[0][:, None] * corners[0] + b[1][:, None] * corners[1] + b[2][:, None] * corners[2]
            part = polygon_form_factor(x, nx, lights.loops[loop], ny)
            ff[:, h] += np.bincount(owner, weights=part, minlength=len(rec)) / 3.0
    return np.maximum(ff, 0.0)


#: pilot shadow rays per (receiver, light) pair of the pilot's share (not used in the estimate)
PILOT_RAYS = 4
#: share of the pairs (at random) the pilot looks at
PILOT_PAIRS = 0.25
#: the pilot's findings mark the grid cells of this many receiver diameters around each pair
PENUMBRA_CELL = 3.0
#: a pair the pilot found dark (no ray of its light got through nearby) is traced with this
#: probability per half, its share weighted by the inverse (Russian roulette: unbiased)
DARK_KEEP = 0.125


def _visibility(patches: Patches, tracer: Tracer, lights: Lights, emitters: np.ndarray, rec: np.ndarray,
                light: np.ndarray, counts: np.ndarray, rng: np.random.Generator, offset: float,
                batch_rays: int):
    """Shadow rays for entries j with ``counts[j]`` rays from receiver ``rec[j]`` to ``light[j]``:
    (sum G V, sum G, visible rays, rays above both horizons), each (len(counts),).

    Each entry's rays form a randomly shifted 5-D lattice: 2 dimensions on the receiver,
    2 on the light (a parallelogram light as a whole, else a triangle picked by area with
    the fifth)."""
    v = patches.vertices
    order = np.argsort(lights.of_emitter, kind="stable")
    key = np.concatenate([[0.0], np.cumsum(patches.area[emitters[order]] / lights.area[lights.of_emitter[order]])])
    out = np.zeros((4, len(counts)))
    ends = np.cumsum(counts)
    lo = 0
    while lo < len(counts):
        hi = max(int(np.searchsorted(ends, (ends[lo - 1] if lo else 0) + batch_rays, side="right")), lo + 1)
        c = counts[lo:hi]
        m = int(c.sum())
        if m:
            start = np.cumsum(c) - c
            u = lattice(np.arange(m) - np.repeat(start, c), np.repeat(rng.random((len(c), 5)), c, axis=0), 5)
            entry = lo + np.repeat(np.arange(len(c)), c)
            r = rec[entry]
            fr = patches.faces[r]
            x = triangle_points(v[fr[:, 0]], v[fr[:, 1]], v[fr[:, 2]], u[:, 0:2])
            lp = light[entry]
            pick = np.clip(np.searchsorted(key, lp + u[:, 4], side="right") - 1, 0, len(order) - 1)
            g = patches.faces[emitters[order[pick]]]
            y = triangle_points(v[g[:, 0]], v[g[:, 1]], v[g[:, 2]], u[:, 2:4])
            if lights.parallelogram is not None and lights.corner is not None and lights.edges is not None:
                flat = np.flatnonzero(lights.parallelogram[lp])  # the whole light, stratified in 2-D
                ed = lights.edges[lp[flat]]
                y[flat] = lights.corner[lp[flat]] + u[flat, 2:3] * ed[:, 0] + u[flat, 3:4] * ed[:, 1]
            nx, ny = patches.normal[r], lights.normal[lp]
            d = y - x
            r2 = np.einsum("ij,ij->i", d, d)
            w = d / np.sqrt(np.maximum(r2, 1e-300))[:, None]
            cx = np.einsum("ij,ij->i", nx, w)
            cy = -np.einsum("ij,ij->i", ny, w)
            ok = np.flatnonzero((cx > 0) & (cy > 0))
            geom = cx[ok] * cy[ok] / (math.pi * r2[ok])
            start_pt = x[ok] + offset * nx[ok]
            visible = ~tracer.occluded(start_pt, (y[ok] + offset * ny[ok]) - start_pt, np.ones(len(ok)))
            at = entry[ok] - lo
            for row, wgt in enumerate((geom * visible, geom, visible.astype(np.float64), None)):
                out[row, lo:hi] += np.bincount(at, weights=wgt, minlength=hi - lo)
        lo = hi
    return out[0], out[1], out[2], out[3]


def _near(patches: Patches, rec: np.ndarray, light: np.ndarray, probe: np.ndarray,
          flags: list[np.ndarray]) -> list[np.ndarray]:
    """For each flag (one per probed pair ``probe``), (q,) True for the pairs whose grid cell
    (PENUMBRA_CELL receiver diameters) or a neighbouring one holds a probed pair of the same
    light with that flag: penumbrae and shadows are spatially coherent."""
    size = PENUMBRA_CELL * math.sqrt(2.0 * float(np.median(patches.area[rec])))
    cell = np.floor((patches.centroid[rec] - patches.bounds[0]) / max(size, 1e-300)).astype(np.int64) + 1
    dims = cell.max(axis=0) + 2
    n_light = int(light.max(initial=0)) + 1

    def code(c: np.ndarray, lt: np.ndarray) -> np.ndarray:
        return ((c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]) * n_light + lt

    mine = code(cell, light)
    out = []
    for flag in flags:
        hot = probe[flag]
        if len(hot) == 0:
            out.append(np.zeros(len(rec), bool))
            continue
        step = np.array([(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)])
        near = (cell[hot][:, None, :] + step[None, :, :]).reshape(-1, 3)
        keys = np.unique(code(near, np.repeat(light[hot], len(step))))
        pos = np.minimum(np.searchsorted(keys, mine), len(keys) - 1)
        out.append(keys[pos] == mine)
    return out


def gather_analytic(patches: Patches, tracer: Tracer, emitters: np.ndarray, power: np.ndarray,
                    lights: Lights, shadow_rays: int, rng: np.random.Generator, offset: float,
                    batch_rays: int = 262144, receivers: np.ndarray | None = None) -> DirectTally:
    """Direct light from exact unoccluded form factors times the visible share shadow rays find.

    For each receiver i and light L that can see each other, the unoccluded form
    factor F_iL (lights.py: Lambert's formula, averaged over three points of i per
    half, ``pair_form_factors``) is exact.  Shadow rays from uniform points x of i
    to uniform points y of L give the visible share sum G V / sum G, G = cos cos /
    (pi r^2), V = 0 or 1; the pair's share is F_iL times that.  A pair that sees
    its light whole, or not at all, gets exactly F_iL or 0: the noise is in penumbrae
    only.  The ratio's bias is of order 1/n there (n rays of the pair and half; with
    one ray it weighs the light's points by area, not by G).  A control variate
    F - A_L / n sum G (1 - V) (unbiased) was tried: where a light is hidden it is
    the noise of a Monte Carlo F, and it left 2-8% of the receivers' direct light
    negative.  A pair the pilot found dark gets the plain estimate A_L / n sum G V
    (exactly 0 when hidden), traced only with probability DARK_KEEP per half and
    weighted by its inverse (Russian roulette): the many lights of other rooms cost
    few rays.

    Rays go where the penumbrae are: a pilot of PILOT_RAYS rays on a PILOT_PAIRS share
    of the pairs (counted, not used in the estimate) marks the pairs near a partly
    visible one, and those near probed pairs none of whose rays got through
    (``_near``).  Every pair gets one ray per half (a dark one with probability
    DARK_KEEP), and the rest of the budget (S per receiver in all) goes to the pairs
    near a penumbra, or near no probed pair, in proportion to E_L F_iL.  Each half
    has its own points and rays, so the noise estimate sees its noise.
    """
    if receivers is None:
        receivers = np.flatnonzero(patches.rho.any(axis=1))
    slot, light = light_pairs(patches, lights, receivers)
    if len(slot) == 0 or float(power.sum()) <= 0:
        return gather_direct(patches, tracer, emitters, power, shadow_rays, rng, offset, batch_rays,
                             np.zeros(0, np.int64))
    rec = receivers[slot]
    ff = pair_form_factors(patches, lights, rec, light, rng)
    weight = lights.exitance[light].sum(axis=1) * ff.mean(axis=1)
    seen = weight > 0
    # the pilot: where the penumbrae are, and which lights are dark where
    probe = np.flatnonzero(seen & (rng.random(len(slot)) < PILOT_PAIRS))
    pilot = np.full(len(probe), PILOT_RAYS, np.int64)
    _, _, vis, traced = _visibility(patches, tracer, lights, emitters, rec[probe], light[probe], pilot, rng, offset,
                                    batch_rays)
    mixed, lit, known = _near(patches, rec, light, probe, [(vis > 0) & (vis < traced), vis > 0,
                                                          np.ones(len(probe), bool)])
    dark = seen & known & ~mixed & ~lit  # probed nearby, and none of its rays got through
    marked = seen & (mixed | ~known)  # near a penumbra, or nothing known: the budget's share
    keep = np.where(dark[:, None], rng.random((len(slot), 2)) < DARK_KEEP, seen[:, None])  # (q,2) traced halves
    budget = max(shadow_rays * len(receivers) - int(pilot.sum()) - int(keep.sum()), 0)
    extra = np.zeros(len(slot))
    if marked.any():
        extra[marked] = budget * weight[marked] / weight[marked].sum()
    n = np.where(keep, (1 + np.floor(extra / 2.0))[:, None], 0).astype(np.int64)  # rays per pair and half
    counts = n.reshape(-1)  # entry 2q + h: pair q, half h
    num, den, _, _ = _visibility(patches, tracer, lights, emitters, np.repeat(rec, 2), np.repeat(light, 2), counts,
                                 rng, offset, batch_rays)
    num, den = num.reshape(-1, 2), den.reshape(-1, 2)
    # each half's visible form factor: the exact F times the visible share sum G V / sum G of its
    # rays (a half with no ray above both horizons reads the other half's share, or 1); a dark
    # pair's half is the plain estimate A_L / n sum G V over the chance it was traced
    seen_share = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)
    seen_share = np.where(np.isnan(seen_share), seen_share[:, ::-1], seen_share)
    seen_share = np.where(np.isnan(seen_share), 1.0, seen_share)
    per = lights.area[light][:, None] / np.maximum(n, 1)
    share = np.where(dark[:, None], np.where(keep, per * num / DARK_KEEP, 0.0), ff * seen_share)
    area = patches.area[rec]
    colour = lights.exitance[light]
    k = len(receivers)
    halves = np.zeros((2, k, 3))
    for h in range(2):
        contrib = (share[:, h] * area)[:, None] * colour
        for ch in range(3):
            halves[h, :, ch] = np.bincount(slot, weights=contrib[:, ch], minlength=k)
    received = 0.5 * (halves[0] + halves[1])
    keep = np.flatnonzero(received.any(axis=1))
    got = received[keep]
    escaped = power.sum(axis=0) - got.sum(axis=0)
    magnitude = np.abs(got)
    return DirectTally(got, receivers[keep], escaped, np.zeros(3), np.zeros(patches.n_objects),
                       np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), magnitude.sum(axis=0),
                       (magnitude * patches.rho[receivers[keep]]).sum(axis=0), np.abs(escaped),
                       0.5 * halves[0][keep], int(counts.sum() + pilot.sum()))


def analytic_lights(patches: Patches, emitters: np.ndarray, power: np.ndarray, receivers: int) -> Lights | None:
    """The lights for ``gather_analytic``, or None when the sampled gather is to be used (too many
    outline vertices, or receivers x loops above MAX_PAIRS)."""
    lights = light_polygons(patches, emitters, power)
    if lights is None or receivers * len(lights.loops) > MAX_PAIRS:
        return None
    return lights
