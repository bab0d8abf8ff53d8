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
1.75% at 32, where next-event estimation lost to shooting.  At scale (the office of 8x8
rooms: 128 lamps, 201k receivers) no receivers x lights table is formed: grid cells of
receivers keep lists of the lights whose form factor from the cell can be non-negligible
(``light_lists``, from a bound), farther lights' pairs are drawn by Russian roulette per
half, and the pairs are gathered in runs of CHUNK_PAIRS (bounded memory).

Only for single-subscene runs: a subscene sees only its own emitters and
patches, so a divided run shoots its direct light as before.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dcrad.arrays import ray_runs, take_rows
from dcrad.meshing.patches import Patches
from dcrad.transport.lights import Lights, form_factors, light_polygons
from dcrad.transport.rays import Tracer
from dcrad.transport.sampling import kronecker_alpha, lattice, triangle_points
from dcrad.transport.shoot import Tally

__all__ = ["DirectTally", "gather_direct", "shadow_rays_for", "noise_against_shooting", "landing_rays",
           "rescale_to_landed", "merge", "AnalyticGather", "shared_rate", "PILOT_SHARE", "GATHER_MARGIN",
           "gather_analytic", "light_pairs", "pair_form_factors", "MAX_PAIRS", "MAX_ANALYTIC_RECEIVERS",
           "analytic_lights", "light_lists",
           "LightLists", "FAR_BOUND", "GatherStopped"]

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


class GatherStopped(Exception):
    """A stop request (``should_stop``) ended a direct gather between two of its batches: no tally.
    The 20x20 office's gather takes tens of seconds, and the first Ctrl-C waited for it."""


def _poll(should_stop) -> None:
    if should_stop is not None and should_stop():
        raise GatherStopped


def gather_direct(patches: Patches, tracer: Tracer, emitters: np.ndarray, power: np.ndarray, shadow_rays: int,
                  rng: np.random.Generator, offset: float, batch_rays: int = 262144,
                  receivers: np.ndarray | None = None, should_stop=None) -> DirectTally:
    """Gather the direct light of ``emitters`` (e,) shooting ``power`` (e,3) W onto every patch with rho > 0.

    shadow_rays: S per receiver (even: two halves of S/2); offset: m the ends of a
    shadow ray are lifted off their surfaces.  Traces in chunks of ``batch_rays``.
    receivers: the patches to gather for (sorted, distinct; default every patch with rho > 0).
    should_stop: polled between chunks; True raises GatherStopped.
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
        if lo:
            _poll(should_stop)
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
        visible = tracer.visible(start, seg, np.ones(len(ok)))
        lit = visible > 0
        ok = ok[lit]
        geom = cx[ok] * cy[ok] / (math.pi * r2[ok]) * visible[lit]
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
    rays ``shot`` (a ``shoot.Tally``); None when some channel landed light the gather missed.

    The gather covers the receivers (patches that reflect: rho > 0 in some channel), so it is
    scaled to what the rays landed on receivers only; what they landed on black patches (and
    panes) stays as the rays put it.  Scaled to all they landed, a black floor's share went to
    the grey one beside it: twice its light (tests/test_glass.py)."""
    on_receiver = take_rows(patches.rho, shot.hit).any(axis=1)
    got = gathered.received.sum(axis=0)
    landed = shot.received[on_receiver].sum(axis=0)
    if np.any((got <= 0) & (np.abs(landed) > 0)):
        return None
    scale = np.where(got > 0, landed / np.where(got > 0, got, 1.0), 0.0)
    received = gathered.received * scale
    received_a = gathered.received_a * scale
    hit = gathered.hit
    black = np.flatnonzero(~on_receiver)
    if len(black):  # disjoint from the gathered receivers: merged in row order
        hit = np.concatenate([hit, shot.hit[black]])
        order = np.argsort(hit, kind="stable")
        hit = hit[order]
        shot_a = shot.received_a[black] if shot.received_a is not None else 0.5 * shot.received[black]
        received = np.concatenate([received, shot.received[black]])[order]
        received_a = np.concatenate([received_a, shot_a])[order]
    magnitude = np.abs(received)
    return DirectTally(received, hit, shot.escaped, shot.back_faces, shot.back_by_obj,
                       gathered.portal, gathered.portal_prim, gathered.portal_t, magnitude.sum(axis=0),
                       (magnitude * patches.rho[hit]).sum(axis=0), shot.lost, received_a, gathered.rays)


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
#: expected (receiver, light) pair entries per receiver above which the analytic gather is not
#: used (the sampled one is): CPU time, about 2 us a pair (the 8x8 office; memory is bounded:
#: CHUNK_PAIRS)
MAX_PAIRS = 64
#: receivers above which the analytic gather is not used (measured, one process, bench/RESULTS.md):
#: the 8x8 office (201k patches) at 2% went 304M -> 49M rays and 92 -> 33 CPU s with it;
#: the 20x20 office at 0.4 m (1.27M) at 5% halved its rays but took 1.3-1.5x the CPU and peaked
#: at 1.55 GB.  With the gather's kernel and memory reworked it takes 0.85x shooting's CPU there
#: and itself peaks at 1.09 GB, but the run (final.py's rounds, the output render) still peaks at
#: 1.33-1.49 GB against shooting's 1.04 GB: the ceiling stays
MAX_ANALYTIC_RECEIVERS = 600_000
#: a light whose form factor from every point of a receiver's cell is bounded below this is a
#: far light of that cell: its pairs there are kept by Russian roulette, with probability
#: bound / FAR_BOUND per half, weighted by the inverse (unbiased; the halves draw apart, so the
#: noise estimate sees the roulette's noise).  The office's lamps of rooms further than about
#: two rooms away are far: 67 pairs a receiver on the 8x8 office without it, the lamps of all rooms
FAR_BOUND = 2e-3
#: receiver cells of the light lists: this share of the scene's bounding-box diagonal
LIST_CELL = 1.0 / 64.0
#: cell-light bounds evaluated at once (bounded memory)
_BLOCK = 1 << 17


@dataclass
class LightLists:
    """Receiver-local light lists: the receivers in grid cells and, per cell and light, the
    chance q a pair is kept (1 near, bound / FAR_BOUND far, 0 where the cell is behind the light)."""

    order: np.ndarray  #: (k,) receiver slots sorted by cell
    start: np.ndarray  #: (C,) first entry of each cell in ``order``
    count: np.ndarray  #: (C,) receivers in each cell
    cell: np.ndarray  #: (m,) the cell of each listed (cell, light)
    light: np.ndarray  #: (m,) its light
    q: np.ndarray  #: (m,) keep chance per half, in (0, 1]
    #: (m,) True where light_pairs' plane tests hold for every receiver of the cell (bounds over
    #: the cell's boxes, with a margin): its pairs need no test of their own
    sure: np.ndarray | None = None

    def expected_pairs(self) -> float:
        """Expected pair entries (a near pair is one entry, a far one draws per half)."""
        return float(self.per_cell().sum())

    def per_cell(self, step: int = 1 << 20) -> np.ndarray:
        """(C,) expected pair entries of each cell, from runs of about ``step`` listed lights
        cut at cells (each cell's sum in one piece: the same sums as all at once, without
        three float64 copies of the whole list)."""
        out = np.zeros(len(self.count))
        cuts = np.searchsorted(self.cell, self.cell[::step], side="left")
        cuts = np.unique(np.concatenate([cuts, [len(self.cell)]]))
        for lo, hi in zip(cuts[:-1], cuts[1:]):
            cell, q = self.cell[lo:hi], self.q[lo:hi]
            n = self.count[cell].astype(np.float64)
            out += np.bincount(cell, weights=np.where(q >= 1.0, n, 2.0 * n * q), minlength=len(self.count))
        return out


def light_lists(patches: Patches, lights: Lights, receivers: np.ndarray) -> LightLists:
    """The lights each grid cell of receivers can see non-negligibly (``LightLists``), from a bound
    of the unoccluded form factor from anywhere in the cell's box of receiver corners to a light:
    F <= A_L h hx / (pi d^4), d the distance between the cell's box and the light's, h the greatest
    height of the cell's box above the light's plane (cos of the light's angle <= h / d), hx a
    bound of n_x . (y - x) by interval arithmetic over the cell's normals and the boxes (the
    receiver's cos <= hx / d), r >= d.  Cells are grid cells split by the receivers' facing
    (six cube faces), so the normals of a cell are close.  Never forms receivers x lights."""
    v = patches.vertices
    box = patches.bounds
    size = max(float(np.linalg.norm(box[1] - box[0])) * LIST_CELL, 1e-300)
    dims = np.floor((box[1] - box[0]) / size).astype(np.int64) + 1
    step_r = 1 << 16
    key = np.empty(len(receivers), np.int64)
    for a in range(0, len(receivers), step_r):  # cell of the centroid, split by facing (six cube faces)
        rows = receivers[a:a + step_r]
        idx = np.clip(np.floor((patches.centroid[rows] - box[0]) / size).astype(np.int64), 0, dims - 1)
        nrm = patches.normal[rows]
        axis = np.abs(nrm).argmax(axis=1)
        face = 2 * axis + (nrm[np.arange(len(rows)), axis] < 0)
        key[a:a + step_r] = ((idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]) * 6 + face
    order = np.argsort(key, kind="stable")
    cells, start, count = np.unique(key[order], return_index=True, return_counts=True)
    del key
    cell_of = np.repeat(np.arange(len(cells)), count)  # cell of each sorted receiver
    lo_c = np.full((len(cells), 3), np.inf)
    hi_c = np.full((len(cells), 3), -np.inf)
    nlo = np.full((len(cells), 3), np.inf)
    nhi = np.full((len(cells), 3), -np.inf)
    for a in range(0, len(order), step_r):  # the cells' boxes of corners and of normals, in chunks
        rows = receivers[order[a:a + step_r]]
        at = cell_of[a:a + step_r]
        first = np.flatnonzero(np.r_[True, at[1:] != at[:-1]])
        c = v[patches.faces[rows]]
        n = patches.normal[rows]
        for out, values, op in ((lo_c, c.min(axis=1), np.minimum), (hi_c, c.max(axis=1), np.maximum),
                                (nlo, n, np.minimum), (nhi, n, np.maximum)):
            cell = at[first]
            out[cell] = op(out[cell], op.reduceat(values, first, axis=0))
    del cell_of
    n_l = len(lights)
    pts = lights.loops.reshape(-1, 3)
    owner = np.repeat(lights.loop_light, lights.loops.shape[1])
    lo_l = np.full((n_l, 3), np.inf)
    hi_l = np.full((n_l, 3), -np.inf)
    np.minimum.at(lo_l, owner, pts)
    np.maximum.at(hi_l, owner, pts)
    ny = lights.normal
    offset = _plane_offsets(lights)
    n_c = len(cells)
    margin = 1e-9 * patches.scale
    out_c, out_l, out_q, out_s = [], [], [], []
    step = max(1, _BLOCK // max(n_l, 1))
    for a in range(0, n_c, step):
        lc, hc = lo_c[a:a + step, None, :], hi_c[a:a + step, None, :]
        gap = np.maximum(np.maximum(lo_l[None] - hc, lc - hi_l[None]), 0.0)
        d = np.sqrt((gap * gap).sum(axis=2))
        h = np.maximum(ny[None] * lc, ny[None] * hc).sum(axis=2) - offset[None]
        # n_x . (y - x) <= hx by interval arithmetic: n_x within the cell's normal box, y - x
        # within [lo_L - hi_c, hi_L - lo_c]
        dlo, dhi = lo_l[None] - hc, hi_l[None] - lc
        a_lo, a_hi = nlo[a:a + step, None, :], nhi[a:a + step, None, :]
        hx = np.maximum(np.maximum(a_lo * dlo, a_lo * dhi), np.maximum(a_hi * dlo, a_hi * dhi)).sum(axis=2)
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = np.where(d > 0, lights.area[None] * np.minimum(h, d) * np.clip(hx, 0.0, d)
                             / (math.pi * d ** 4), np.inf)
        h = np.where(hx > 0, h, 0.0)  # no receiver of the cell faces the light
        q = np.where(h > 0, np.minimum(bound / FAR_BOUND, 1.0), 0.0)
        ci, li = np.nonzero(q > 0)
        out_c.append((a + ci).astype(np.int32))
        out_l.append(li.astype(np.int32))
        out_q.append(q[ci, li].astype(np.float32))
        # light_pairs' tests by lower bounds: the whole cell box in front of the light's plane,
        # and n_x . (y - x) > 0 for every normal of the cell, corner of its box and point of the
        # light's box (so every vertex of the light is above every receiver's plane)
        lc, hc, dlo, dhi, a_lo, a_hi = (t[ci, 0] if t.shape[1] == 1 else t[ci, li]
                                        for t in (lc, hc, dlo, dhi, a_lo, a_hi))
        in_front = np.minimum(ny[li] * lc, ny[li] * hc).sum(axis=1) - offset[li]
        hx_lo = np.minimum(np.minimum(a_lo * dlo, a_lo * dhi), np.minimum(a_hi * dlo, a_hi * dhi)).sum(axis=1)
        out_s.append((in_front > margin) & (hx_lo > margin))
    cat = (lambda parts, dt: np.concatenate(parts).astype(dt, copy=False) if parts else np.zeros(0, dt))
    # compact: on the 20x20 office most of the 800 lamps are far lights of most cells (q tiny, > 0)
    return LightLists(order, start, count, cat(out_c, np.int32), cat(out_l, np.int32), cat(out_q, np.float32),
                      cat(out_s, bool))


def light_pairs(patches: Patches, lights: Lights, receivers: np.ndarray, rng: np.random.Generator,
                lists: LightLists | None = None, chunk: int = 1 << 18, cells: tuple[int, int] | None = None):
    """Pair entries (receiver slot (q,), light (q,), halves present (q,2) bool, 1/keep chance (q,))
    of the receivers and the lights of their cell's list (``light_lists``) that can exchange
    light: some corner of the receiver in front of the light's plane and some vertex of its
    outline above the receiver's plane.  A near light's pairs are present in both halves; a far
    one's are drawn per half: Binomial(n, q) receivers of the cell's n, uniformly with replacement,
    each weighted 1/q (each receiver is drawn q times on average: unbiased).  Sorted by receiver.
    ``cells``: only the receivers of cells c0 <= c < c1 (of ``lists``)."""
    if lists is None:
        lists = light_lists(patches, lights, receivers)
    # (the bounds in the cells' own type: a Python int would make a 64-bit copy of the list)
    lo, hi = (0, len(lists.cell)) if cells is None else np.searchsorted(lists.cell, np.asarray(cells, lists.cell.dtype))
    l_cell, l_light, l_q = lists.cell[lo:hi], lists.light[lo:hi], lists.q[lo:hi]
    l_sure = lists.sure[lo:hi] if lists.sure is not None else np.zeros(hi - lo, bool)
    v = patches.vertices
    near = l_q >= 1.0
    parts_s, parts_l, parts_m, parts_w, parts_t = [], [], [], [], []
    # near lights: every receiver of the cell, both halves
    nc, nl = l_cell[near], l_light[near]
    per = lists.count[nc]
    rows = np.repeat(np.arange(len(nc)), per)
    within = np.arange(len(rows)) - np.repeat(np.cumsum(per) - per, per)
    parts_s.append(lists.order[lists.start[nc][rows] + within])
    parts_l.append(nl[rows])
    parts_m.append(np.full(len(rows), 3, np.int8))
    parts_w.append(np.ones(len(rows)))
    parts_t.append(l_sure[near][rows])
    del rows, within
    # far lights: drawn per half
    fc, fl, fq, fs = l_cell[~near], l_light[~near], l_q[~near], l_sure[~near]
    for h in range(2):
        drawn = rng.binomial(lists.count[fc], fq.astype(np.float64))
        rows = np.repeat(np.arange(len(fc)), drawn)
        pick = np.floor(rng.random(len(rows)) * lists.count[fc][rows]).astype(np.int64)
        parts_s.append(lists.order[lists.start[fc][rows] + pick])
        parts_l.append(fl[rows])
        parts_m.append(np.full(len(rows), 1 << h, np.int8))
        parts_w.append(1.0 / fq[rows].astype(np.float64))  # 1/q of the very q drawn with
        parts_t.append(fs[rows])
    slot, light = np.concatenate(parts_s), np.concatenate(parts_l)
    mask, inv_q = np.concatenate(parts_m), np.concatenate(parts_w)
    ok = np.concatenate(parts_t)  # the cells' bounds say the tests hold
    del parts_s, parts_l, parts_m, parts_w, parts_t
    # the exact plane tests per entry the bounds did not settle, in chunks
    ny = lights.normal
    offset = _plane_offsets(lights)
    verts = _light_vertices(lights)  # (L, W, 3)
    test = np.flatnonzero(~ok)
    for a in range(0, len(test), chunk):
        at = test[a:a + chunk]
        r = receivers[slot[at]]
        lt = light[at]
        corners = v[patches.faces[r]]  # (m,3,3)
        front = (np.einsum("mcj,mj->mc", corners, ny[lt]) > offset[lt][:, None]).any(axis=1)
        nrm = patches.normal[r]
        base = (corners[:, 0] * nrm).sum(axis=1)
        above = (np.einsum("mvj,mj->mv", verts[lt], nrm) > base[:, None]).any(axis=1)
        ok[at] = front & above
    keep = np.flatnonzero(ok)
    srt = keep[np.argsort(slot[keep], kind="stable")]
    present = np.stack([(mask[srt] & 1) > 0, (mask[srt] & 2) > 0], axis=1)
    return slot[srt], light[srt], present, inv_q[srt]


def _light_vertices(lights: Lights) -> np.ndarray:
    """(L, W, 3) every outline vertex of each light (its loops one after the other), padded by
    repeating its first vertex."""
    n_l = len(lights)
    per = np.bincount(lights.loop_light, minlength=n_l)
    v = lights.loops.shape[1]
    width = int(per.max(initial=1)) * v
    order = np.argsort(lights.loop_light, kind="stable")
    slot = np.arange(len(order)) - np.repeat(np.cumsum(per) - per, per)
    out = np.empty((n_l, width, 3))
    first = lights.loops[order[np.cumsum(per) - per], 0]
    out[:] = first[:, None, :]
    lt = lights.loop_light[order]
    for j in range(v):
        out[lt, slot * v + j] = lights.loops[order, j]
    return out


def _plane_offsets(lights: Lights) -> np.ndarray:
    """(L,) n . y of each light's plane (from the first vertex of its first loop)."""
    per = np.bincount(lights.loop_light, minlength=len(lights))
    order = np.argsort(lights.loop_light, kind="stable")
    first = order[np.cumsum(per) - per]
    return (lights.loops[first, 0] * lights.normal).sum(axis=1)


def pair_form_factors(patches: Patches, lights: Lights, rec: np.ndarray, light: np.ndarray,
                      rng: np.random.Generator, chunk: int = 1 << 14) -> np.ndarray:
    """(q,2) exact unoccluded form factor from receiver ``rec`` to ``light`` per pair, each half the
    mean over three points of the receiver: a uniform random point and its two cyclic
    permutations of barycentric coordinates.  Each point is uniform on the triangle (unbiased)
    and the three average to the centroid, so the part of F linear over the patch is exact
    (two independent random points per half left 0.8% noise on Cornell's direct light).
    ``chunk`` pairs at a time (bounded memory)."""
    ff = np.zeros((len(rec), 2))
    u = rng.random((len(rec), 2, 2))
    for a in range(0, len(rec), chunk):
        ff[a:a + chunk] = _pair_form_factors(patches, lights, rec[a:a + chunk], light[a:a + chunk], u[a:a + chunk])
    return ff


def _pair_form_factors(patches: Patches, lights: Lights, rec: np.ndarray, light: np.ndarray,
                       u: np.ndarray | None, chunk: int = 1 << 14) -> np.ndarray:
    """(q,2) per half the mean of F over the three rotated points of ``u`` (q,2,2); u None: (q,1)
    F at the centroid (in chunks)."""
    if u is None:
        out = np.zeros((len(rec), 1))
        for a in range(0, len(rec), chunk):
            out[a:a + chunk, 0] = _centroid_form_factors(patches, lights, rec[a:a + chunk], light[a:a + chunk])
        return out
    return _rotated_form_factors(patches, lights, rec, light, u)


def _loops_of(lights: Lights, rec: np.ndarray, light: np.ndarray):
    """(owner (m,), loop (m,)): every loop of each pair's light."""
    n_loops = np.bincount(lights.loop_light, minlength=len(lights))
    loop_start = np.cumsum(n_loops) - n_loops
    per_pair = n_loops[light]
    owner = np.repeat(np.arange(len(rec)), per_pair)
    loop = loop_start[light][owner] + (np.arange(len(owner)) - np.repeat(np.cumsum(per_pair) - per_pair, per_pair))
    return owner, loop


def _centroid_form_factors(patches: Patches, lights: Lights, rec: np.ndarray, light: np.ndarray) -> np.ndarray:
    owner, loop = _loops_of(lights, rec, light)
    r = rec[owner]
    part = form_factors(patches.centroid[r][:, None, :], patches.normal[r], lights.loops[loop],
                        lights.normal[lights.loop_light[loop]])[:, 0]
    if len(owner) == len(rec):  # one loop per light: owner is 0, 1, 2, ...
        return np.maximum(part, 0.0)
    return np.maximum(np.bincount(owner, weights=part, minlength=len(rec)), 0.0)


def _rotated_form_factors(patches: Patches, lights: Lights, rec: np.ndarray, light: np.ndarray,
                          u: np.ndarray) -> np.ndarray:
    v = patches.vertices
    owner, loop = _loops_of(lights, rec, light)
    r = rec[owner]
    corners = v[patches.faces[r]]  # (m,3,3)
    # the six points of each entry: half h, rotation k (barycentric coordinates shifted by k)
    s = np.sqrt(u[owner, :, 0])  # (m,2)
    bary = np.stack([1.0 - s, s * (1.0 - u[owner, :, 1]), s * u[owner, :, 1]], axis=2)  # (m,2,3)
    x = np.empty((len(owner), 2, 3, 3))
    for k in range(3):
        for j in range(3):
            x[:, :, k, j] = (bary[:, :, k % 3] * corners[:, None, 0, j]
                             + bary[:, :, (k + 1) % 3] * corners[:, None, 1, j]
                             + bary[:, :, (k + 2) % 3] * corners[:, None, 2, j])
    part = form_factors(x.reshape(len(owner), 6, 3), patches.normal[r], lights.loops[loop],
                        lights.normal[lights.loop_light[loop]]).reshape(-1, 2, 3)
    part = part[:, :, 0] / 3.0 + part[:, :, 1] / 3.0 + part[:, :, 2] / 3.0
    if len(owner) == len(rec):
        return np.maximum(part, 0.0)
    ff = np.stack([np.bincount(owner, weights=part[:, h], minlength=len(rec)) for h in range(2)], axis=1)
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
    vc = [np.ascontiguousarray(v[:, j]) for j in range(3)]
    alpha = kronecker_alpha(5)
    order = np.argsort(lights.of_emitter, kind="stable")
    key = np.concatenate([[0.0], np.cumsum(patches.area[emitters[order]] / lights.area[lights.of_emitter[order]])])
    para = lights.parallelogram if lights.corner is not None and lights.edges is not None else None
    out = np.zeros((4, len(counts)))
    for lo, hi, local, index in ray_runs(counts, batch_rays):
        c = counts[lo:hi]
        m = len(index)
        # per component on (m,) rows: the lattice (sampling.lattice's arithmetic, one dimension
        # at a time), the receiver's corners per entry, then each ray's points
        shift = rng.random((len(c), 5))
        u = []
        for dim in range(5):
            ud = (index + 0.5) * alpha[dim] + np.repeat(shift[:, dim], c)
            ud -= np.floor(ud)
            u.append(ud)
        sq = np.sqrt(u[0])
        b1, b2 = sq * (1.0 - u[1]), sq * u[1]
        fr = patches.faces[rec[lo:hi]]
        nrm = patches.normal[rec[lo:hi]]
        x, nx = [], []
        for j in range(3):
            c0 = vc[j][fr[:, 0]]
            x.append(c0[local] + b1 * (vc[j][fr[:, 1]] - c0)[local] + b2 * (vc[j][fr[:, 2]] - c0)[local])
            nx.append(nrm[local, j])
        lp = light[lo:hi][local]
        y = [np.empty(m) for _ in range(3)]
        if para is not None and lights.corner is not None and lights.edges is not None:
            is_flat = para[lp]
            flat = np.flatnonzero(is_flat)  # the whole light, stratified in 2-D
            lf = lp[flat]
            u2, u3 = u[2][flat], u[3][flat]
            for j in range(3):
                y[j][flat] = lights.corner[lf, j] + u2 * lights.edges[lf, 0, j] + u3 * lights.edges[lf, 1, j]
            tri = np.flatnonzero(~is_flat)
        else:
            tri = np.arange(m)
        if len(tri):  # a triangle of the light by area, then a point on it
            pick = np.clip(np.searchsorted(key, lp[tri] + u[4][tri], side="right") - 1, 0, len(order) - 1)
            g = patches.faces[emitters[order[pick]]]
            pts = triangle_points(v[g[:, 0]], v[g[:, 1]], v[g[:, 2]], np.stack([u[2][tri], u[3][tri]], axis=1))
            for j in range(3):
                y[j][tri] = pts[:, j]
        ny = [lights.normal[lp, j] for j in range(3)]
        d = [y[j] - x[j] for j in range(3)]
        r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        dist = np.sqrt(np.maximum(r2, 1e-300))
        cx = (nx[0] * d[0] + nx[1] * d[1] + nx[2] * d[2]) / dist
        cy = -(ny[0] * d[0] + ny[1] * d[1] + ny[2] * d[2]) / dist
        ok = np.flatnonzero((cx > 0) & (cy > 0))
        geom = cx[ok] * cy[ok] / (math.pi * r2[ok])
        origin = np.empty((len(ok), 3))
        seg = np.empty((len(ok), 3))
        for j in range(3):
            origin[:, j] = x[j][ok] + offset * nx[j][ok]
            seg[:, j] = (y[j][ok] + offset * ny[j][ok]) - origin[:, j]
        visible = tracer.visible(origin, seg, np.ones(len(ok)))  # through glass: its transmittance
        at = local[ok]
        for row, wgt in enumerate((geom * visible, geom, visible, None)):
            out[row, lo:hi] += np.bincount(at, weights=wgt, minlength=hi - lo)
    return out[0], out[1], out[2], out[3]


class _ProbeGrid:
    """Grid cells of PENUMBRA_CELL receiver diameters over the whole scene, coded with a light:
    what the pilot found is kept as sets of (cell, light) codes, so runs of receivers gathered
    apart (``gather_analytic``'s chunks) still see their neighbours' probes."""

    STEP = np.array([(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)])

    def __init__(self, patches: Patches, receivers: np.ndarray, lights: int):
        self.patches = patches
        # the receivers' typical area by area, not by count: a model's thousands of millimetre
        # triangles (the ice-cream store's) made the cells so small that the pilot's sets of cell
        # codes took 10 of its 27 s; half of the area lies in receivers at least this large
        area = np.sort(patches.area[receivers])
        half = area[min(int(np.searchsorted(np.cumsum(area), 0.5 * area.sum())), len(area) - 1)] if len(area) else 0.0
        self.size = max(PENUMBRA_CELL * math.sqrt(2.0 * float(half)), 1e-300)
        self.dims = np.floor((patches.bounds[1] - patches.bounds[0]) / self.size).astype(np.int64) + 3
        self.lights = lights

    def cells(self, rec: np.ndarray) -> np.ndarray:
        c = np.floor((self.patches.centroid[rec] - self.patches.bounds[0]) / self.size).astype(np.int64) + 1
        return np.clip(c, 1, self.dims - 2)

    def code(self, c: np.ndarray, lt: np.ndarray) -> np.ndarray:
        return ((c[:, 0] * self.dims[1] + c[:, 1]) * self.dims[2] + c[:, 2]) * self.lights + lt

    def spread(self, codes: np.ndarray) -> np.ndarray:
        """The sorted codes of the cells next to (or at) ``codes``' cells, same lights."""
        hc = np.unique(codes)
        lt, rest = hc % self.lights, hc // self.lights
        cell = np.stack([rest // (self.dims[1] * self.dims[2]), (rest // self.dims[2]) % self.dims[1],
                         rest % self.dims[2]], axis=1)
        near = (cell[:, None, :] + self.STEP[None, :, :]).reshape(-1, 3)
        return np.unique(self.code(near, np.repeat(lt, len(self.STEP))))

    # the findings: a bitmap per flag over every (cell, light) code when that is small
    # (DENSE_CODES; a bit a code, the lights of a cell in ceil(L/8) bytes), dilated by one cell
    # at the end; else sorted sets of spread codes
    def start(self, flags: int) -> None:
        self.dense = int(np.prod(self.dims)) * self.lights <= DENSE_CODES
        self.row = (self.lights + 7) // 8  # bytes of a cell's lights
        size = int(np.prod(self.dims)) * self.row if self.dense else 0
        self.maps = [np.zeros(size, np.uint8) for _ in range(flags)]
        self.parts: list[list[np.ndarray]] = [[] for _ in range(flags)]

    def _bits(self, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(byte, bit mask) of each code in a map."""
        cell, lt = np.divmod(codes, self.lights)
        return cell * self.row + (lt >> 3), (1 << (lt & 7)).astype(np.uint8)

    def mark(self, flag: int, codes: np.ndarray) -> None:
        if self.dense:
            byte, bit = self._bits(codes)
            np.bitwise_or.at(self.maps[flag], byte, bit)
        elif len(codes):
            self.parts[flag].append(self.spread(codes))

    def finish(self) -> None:
        if self.dense:
            shape = (int(self.dims[0]), int(self.dims[1]), int(self.dims[2]), self.row)
            for m in self.maps:
                b = m.reshape(shape)
                for axis in range(3):  # the 3x3x3 neighbourhood: one cell each way per axis
                    src = b.copy()
                    lo = [slice(None)] * 4
                    hi = [slice(None)] * 4
                    lo[axis], hi[axis] = slice(0, -1), slice(1, None)
                    b[tuple(lo)] |= src[tuple(hi)]
                    b[tuple(hi)] |= src[tuple(lo)]
                    del src
        else:
            self.sets = [np.unique(np.concatenate(p)) if p else np.zeros(0, np.int64) for p in self.parts]
            self.parts = []

    def near(self, flag: int, codes: np.ndarray) -> np.ndarray:
        """(m,) True for the codes next to a probed pair with that flag."""
        if self.dense:
            byte, bit = self._bits(codes)
            return (self.maps[flag][byte] & bit) > 0
        return _member(self.sets[flag], codes)


#: (cell, light) codes up to which the pilot's findings are bitmaps (a bit a code, per flag:
#: 64 MB each at this size; the 20x20 office has 68M codes)
DENSE_CODES = 1 << 29


def _member(keys: np.ndarray, mine: np.ndarray) -> np.ndarray:
    if len(keys) == 0:
        return np.zeros(len(mine), bool)
    pos = np.minimum(np.searchsorted(keys, mine), len(keys) - 1)
    return keys[pos] == mine


def gather_analytic(patches: Patches, tracer: Tracer, emitters: np.ndarray, power: np.ndarray,
                    lights: Lights, shadow_rays: int, rng: np.random.Generator, offset: float,
                    batch_rays: int = 262144, receivers: np.ndarray | None = None, should_stop=None) -> DirectTally:
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
    gather = AnalyticGather(patches, tracer, emitters, power, lights, shadow_rays, rng, offset, batch_rays,
                            receivers, should_stop)
    return gather.finish(should_stop=should_stop)


class AnalyticGather:
    """``gather_analytic`` in its two passes: the pilot (at construction) and the gather (``finish``).

    Between them, ``need`` (the shadow rays left for the pairs near a penumbra) and ``weight``
    (their total E F / q) set the rate of rays per weight, ``need / weight``.  A shared run
    (share.py) pilots its shares of the receivers apart and gathers them all at one rate, the
    sums' over every share (``shared_rate``), as one gather of every receiver would: at a rate
    of its own, a share with more penumbrae than the others gets fewer rays there (the office
    3x3 split in two: 24% more noise in the direct light).
    """

    def __init__(self, patches: Patches, tracer: Tracer, emitters: np.ndarray, power: np.ndarray,
                 lights: Lights, shadow_rays: int, rng: np.random.Generator, offset: float,
                 batch_rays: int = 262144, receivers: np.ndarray | None = None, should_stop=None):
        self.need, self.weight = 0.0, 0.0
        self.empty: DirectTally | None = None  #: the result when there is nothing to gather (no pairs)
        if receivers is None:
            receivers = np.flatnonzero(patches.rho.any(axis=1))
        lists = _lists_for(patches, lights, receivers)
        if len(lists.cell) == 0 or float(power.sum()) <= 0:
            self.empty = gather_direct(patches, tracer, emitters, power, shadow_rays, rng, offset, batch_rays,
                                       np.zeros(0, np.int64))
            return
        k = len(receivers)
        halves = np.zeros((2, k, 3))
        # receivers in runs of whole cells (cell order: slabs of the scene) of about CHUNK_PAIRS
        # expected pair entries each: bounded memory at any size.  Two passes: the pilot on every
        # run (its findings kept as (cell, light) sets of the whole scene, so a run's edge sees the
        # next run's probes), then the gather; each run's pairs drawn twice from its own seed
        ends = np.cumsum(lists.per_cell())
        runs = []
        c0 = 0
        while c0 < len(lists.count):
            c1 = max(int(np.searchsorted(ends, (ends[c0 - 1] if c0 else 0.0) + CHUNK_PAIRS, side="right")), c0 + 1)
            runs.append((c0, c1))
            c0 = c1
        seeds = rng.integers(0, 2**63 - 1, size=len(runs))
        grid = _ProbeGrid(patches, receivers, len(lights))
        grid.start(3)
        rays = 0
        # per (cell, light) code of each run: the weight E F / q (F at the centroid) and the present
        # halves, to share the budget over the whole scene at one rate of rays per weight (per run
        # it would be a small difference of large numbers: pilot and one ray a half take most of
        # it); compact (int32 codes where they fit, float32 counts): on the 20x20 office 5.5M codes
        tallies: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        code_type = np.int32 if int(np.prod(grid.dims)) * len(lights) < 2**31 else np.int64
        for (c0, c1), seed in zip(runs, seeds):
            if c0:
                _poll(should_stop)
            slot, light, present, inv_q = light_pairs(patches, lights, receivers, np.random.default_rng(seed), lists,
                                                      cells=(c0, c1))
            rec = receivers[slot]
            f0 = _pair_form_factors(patches, lights, rec, light, None)[:, 0]
            mine, at = np.unique(grid.code(grid.cells(rec), light), return_inverse=True)
            w0 = lights.exitance[light].sum(axis=1) * f0 * inv_q
            tallies.append((mine.astype(code_type), np.bincount(at, weights=w0, minlength=len(mine)),
                            np.bincount(at, weights=present.sum(axis=1), minlength=len(mine)).astype(np.float32)))
            del mine, at, w0, present, inv_q
            probe = np.flatnonzero((f0 > 0) & (rng.random(len(slot)) < PILOT_PAIRS))
            _, _, vis, traced = _visibility(patches, tracer, lights, emitters, rec[probe], light[probe],
                                            np.full(len(probe), PILOT_RAYS, np.int64), rng, offset,
                                            min(batch_rays, VIS_BATCH))
            rays += PILOT_RAYS * len(probe)
            codes = grid.code(grid.cells(rec[probe]), light[probe])
            for j, flag in enumerate(((vis > 0) & (vis < traced), vis > 0, np.ones(len(probe), bool))):
                if flag.any():
                    grid.mark(j, codes[flag])
            del slot, light, rec, f0, probe, vis, traced, codes
        grid.finish()
        # the rays of one a half (dark pairs: DARK_KEEP of one) and the weight near penumbrae, run by
        # run (a code two runs share is counted in each: its sums add up, no merge of all the codes)
        one_each = 0.0
        w_marked = 0.0
        while tallies:
            codes, w_code, h_code = tallies.pop()
            mixed, lit, known = (grid.near(j, codes.astype(np.int64)) for j in range(3))
            dark = known & ~mixed & ~lit
            marked = ~dark & (mixed | ~known)
            one_each += float(np.where(dark, DARK_KEEP * h_code, np.where(w_code > 0, h_code, 0.0)).sum())
            w_marked += float(w_code[marked].sum())
            del codes, w_code, h_code, mixed, lit, known, dark, marked
        self.need = max(shadow_rays * k - rays - one_each, 0.0)
        self.weight = w_marked
        self.patches, self.tracer, self.emitters, self.power, self.lights = patches, tracer, emitters, power, lights
        self.rng, self.offset, self.batch_rays, self.receivers = rng, offset, batch_rays, receivers
        self.lists, self.runs, self.seeds, self.grid, self.halves, self.rays = lists, runs, seeds, grid, halves, rays

    @property
    def rate(self) -> float:
        """Its own rate of extra rays per unit weight (``need / weight``)."""
        return self.need / self.weight if self.weight > 0 else 0.0

    def finish(self, rate: float | None = None, should_stop=None) -> DirectTally:
        """The gather pass at ``rate`` (None: its own) and the tally (once: it frees the pilot's state).
        ``should_stop``: polled between runs of cells; True raises GatherStopped."""
        if self.empty is not None:
            return self.empty
        rate = self.rate if rate is None else rate
        patches, tracer, emitters, power, lights = self.patches, self.tracer, self.emitters, self.power, self.lights
        rng, offset, batch_rays, receivers = self.rng, self.offset, self.batch_rays, self.receivers
        lists, runs, seeds, grid, halves, rays = self.lists, self.runs, self.seeds, self.grid, self.halves, self.rays
        self.lists = self.grid = self.halves = None  # type: ignore[assignment]
        for (c0, c1), seed in zip(runs, seeds):
            if c0:
                _poll(should_stop)
            slot, light, present, inv_q = light_pairs(patches, lights, receivers, np.random.default_rng(seed), lists,
                                                      cells=(c0, c1))
            if len(slot) == 0:
                continue
            rays += _gather_pairs(patches, tracer, lights, emitters, receivers, slot, light, present, inv_q,
                                  rate, rng, offset, batch_rays, halves, grid)
        lights.cache.pop("lists", None)
        del lists, grid, runs, seeds
        received = 0.5 * (halves[0] + halves[1])
        keep = np.flatnonzero(received.any(axis=1))
        got = received[keep]
        del received
        received_a = 0.5 * halves[0][keep]
        del halves
        escaped = power.sum(axis=0) - got.sum(axis=0)
        magnitude = np.abs(got)
        return DirectTally(got, receivers[keep], escaped, np.zeros(3), np.zeros(patches.n_objects),
                           np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), magnitude.sum(axis=0),
                           (magnitude * patches.rho[receivers[keep]]).sum(axis=0), np.abs(escaped),
                           received_a, rays)


def shared_rate(parts) -> float:
    """One rate for the pilots of several shares of the receivers, from their (``need``, ``weight``)
    pairs: their rays left over their weight."""
    weight = sum(w for _, w in parts)
    return sum(n for n, _ in parts) / weight if weight > 0 else 0.0


#: shadow rays traced at once by the analytic gather (about 0.5 KB a ray in ``_visibility``)
VIS_BATCH = 1 << 16
#: expected pair entries gathered at once (``gather_analytic``: about 0.3 KB each at the peak;
#: 2^20 of them took 650 MB on the 20x20 office)
CHUNK_PAIRS = 1 << 18


def _gather_pairs(patches: Patches, tracer: Tracer, lights: Lights, emitters: np.ndarray, receivers: np.ndarray,
                  slot: np.ndarray, light: np.ndarray, present: np.ndarray, inv_q: np.ndarray, rate: float,
                  rng: np.random.Generator, offset: float, batch_rays: int, halves: np.ndarray,
                  grid: _ProbeGrid) -> int:
    """``gather_analytic`` on one run of pair entries: adds each half's received power to
    ``halves`` (2,k,3) at the receivers' slots; returns the shadow rays traced (the pilot's
    not included).  ``rate``: the extra rays per unit weight E F / q of a pair near a penumbra.
    ``grid``: the pilot's findings (pairs next to a probed one found partly visible, lit, probed)."""
    rec = receivers[slot]
    mine = grid.code(grid.cells(rec), light)
    mixed, lit, known = (grid.near(j, mine) for j in range(3))
    del mine
    dark = known & ~mixed & ~lit  # probed nearby, and none of its rays got through
    ff = np.zeros((len(slot), 2))
    lit_rows = np.flatnonzero(~dark)
    ff[lit_rows] = pair_form_factors(patches, lights, rec[lit_rows], light[lit_rows], rng)
    weight = lights.exitance[light].sum(axis=1) * ff.mean(axis=1) * inv_q
    seen = dark | (weight > 0)  # a dark pair passed the plane tests (light_pairs): traced by roulette
    marked = ~dark & seen & (mixed | ~known)  # near a penumbra, or nothing known: the budget's share
    keep = present & np.where(dark[:, None], rng.random((len(slot), 2)) < DARK_KEEP, seen[:, None])  # traced halves
    extra = np.where(marked, rate * weight, 0.0)
    n = np.where(keep, (1 + np.floor(extra / 2.0))[:, None], 0).astype(np.int64)  # rays per pair and half
    counts = n.reshape(-1)  # entry 2q + h: pair q, half h
    num, den, _, _ = _visibility(patches, tracer, lights, emitters, np.repeat(rec, 2), np.repeat(light, 2), counts,
                                 rng, offset, min(batch_rays, VIS_BATCH))
    num, den = num.reshape(-1, 2), den.reshape(-1, 2)
    # each half's visible form factor: the exact F times the visible share sum G V / sum G of its
    # rays (a half with no ray above both horizons reads the other half's share, or 1); a dark
    # pair's half is the plain estimate A_L / n sum G V over the chance it was traced
    seen_share = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)
    seen_share = np.where(np.isnan(seen_share), seen_share[:, ::-1], seen_share)
    seen_share = np.where(np.isnan(seen_share), 1.0, seen_share)
    per = lights.area[light][:, None] / np.maximum(n, 1)
    share = np.where(dark[:, None], np.where(keep, per * num / DARK_KEEP, 0.0), ff * seen_share * present)
    share *= inv_q[:, None]  # a far light's pair, drawn with chance q per half (light_pairs)
    area = patches.area[rec]
    colour = lights.exitance[light]
    k = halves.shape[1]
    for h in range(2):
        contrib = (share[:, h] * area)[:, None] * colour
        for ch in range(3):
            halves[h, :, ch] += np.bincount(slot, weights=contrib[:, ch], minlength=k)
    return int(counts.sum())


def analytic_lights(patches: Patches, emitters: np.ndarray, power: np.ndarray, receivers: int,
                    rows: np.ndarray | None = None) -> Lights | None:
    """The lights for ``gather_analytic``, or None when the sampled gather is to be used (too many
    outline vertices, more than MAX_ANALYTIC_RECEIVERS receivers, or more than MAX_PAIRS expected
    pair entries per receiver from the receivers' light lists, ``light_lists``).  ``receivers``:
    the receiving patches' count (the receivers are the patches with a reflectance); ``rows``: the
    receivers whose lists decide (None: all; a shared run's share, whose gather then reuses them)."""
    if receivers > MAX_ANALYTIC_RECEIVERS:
        return None
    lights = light_polygons(patches, emitters, power)
    if lights is None:
        return None
    rows = np.flatnonzero(patches.rho.any(axis=1)) if rows is None else rows
    if len(rows) and _lists_for(patches, lights, rows).expected_pairs() > MAX_PAIRS * len(rows):
        return None
    return lights


def _lists_for(patches: Patches, lights: Lights, receivers: np.ndarray) -> LightLists:
    """``light_lists``, kept on ``lights`` for the same receivers (analytic_lights, then the gather)."""
    got = lights.cache.get("lists")
    if got is not None and len(got[0]) == len(receivers) and np.array_equal(got[0], receivers):
        return got[1]
    lists = light_lists(patches, lights, receivers)
    lights.cache["lists"] = (receivers.copy(), lists)
    return lists
