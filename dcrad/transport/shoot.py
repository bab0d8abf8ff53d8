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

from dataclasses import dataclass, field

import numpy as np

from dcrad.arrays import colsum, put_rows, rowsum, take_rows
from dcrad.config import TOL
from dcrad.estimate.noise import half_mask, split_power
from dcrad.meshing.patches import Patches
from dcrad.transport.optics import MAX_PANES
from dcrad.transport.rays import MISS, Tracer
from dcrad.transport.sampling import cosine_hemisphere_columns, kronecker_alpha, lattice, onb

__all__ = ["RayBatch", "Tally", "ray_lattice", "per_ray_power", "patch_rays", "compact", "trace", "deposit",
           "Landing", "landing"]


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
    #: (m,) bool, True for rays of half A of their shooter (noise.py); None: not split
    half: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.origins)


@dataclass
class Tally:
    """What one batch of rays did.

    received (k,3) W  power arriving on the front of the patches ``hit`` (k,) i8 (distinct;
    only patches that were hit have a row, so a tally costs O(rays), not O(patches))
    escaped, back_faces (3,) W
    back_by_obj (n_obj,) W  back-face power by object, for the flipped-normal warning
    portal (k,) i8  indices of rays that hit a primitive >= n (a boundary), with
    portal_prim (k,) i8 and portal_t (k,) f8; empty when the scene has no boundary
    landed, kept (3,) W  sums of |received| over patches (times rho, for kept), and
    lost (3,) W  sum of |ray power| over rays that escaped or hit a back face: unlike
    the signed sums, the loss does not cancel when rays of both signs (overshooting)
    meet, and kept/landed is a mean rho whatever the signs; they feed the
    return-ratio estimate (stiffness.stiffness)
    """

    received: np.ndarray
    hit: np.ndarray
    escaped: np.ndarray
    back_faces: np.ndarray
    back_by_obj: np.ndarray
    portal: np.ndarray
    portal_prim: np.ndarray
    portal_t: np.ndarray
    landed: np.ndarray
    kept: np.ndarray
    lost: np.ndarray
    #: (k,3) W of ``received`` that came by rays of half A (noise.py); None: rays not split
    received_a: np.ndarray | None = None
    #: the rays ``portal`` indexes when they are not the batch's: through glass, one row per power
    #: that ends somewhere, from where it set out (``through_panes``); None: the batch's own
    ends: RayBatch | None = field(default=None, kw_only=True)


def ray_offset(patches: Patches) -> float:
    """Distance (m) ray origins are lifted off their surface: relative to scene size."""
    return TOL.ray_offset * patches.scale


def ray_lattice(counts: np.ndarray, rng: np.random.Generator, dtype=np.float64, halves: bool = False):
    """Stratified 4-D samples for shooters that get ``counts`` (k,) rays each.

    Each shooter has its own randomly shifted R4 lattice.  Returns (owner (m,) i8,
    the shooter of each ray; u (m,4) in [0,1) of ``dtype``).  ``halves``: each
    shooter's first ceil(c/2) rays and the rest are two lattices with independent
    shifts (the two half-solutions of noise.py).
    """
    k = len(counts)
    owner = np.repeat(np.arange(k), counts)
    sets = np.stack([(counts + 1) // 2, counts // 2], axis=1).ravel() if halves else counts
    start = np.cumsum(sets) - sets
    index = np.arange(int(counts.sum())) - np.repeat(start, sets)
    return owner, lattice(index, np.repeat(rng.random((len(sets), 4)), sets, axis=0), 4, dtype=dtype)


def per_ray_power(power: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(m,3) W each ray carries: its shooter's power (k,3) split evenly over its rays."""
    return np.repeat(power / counts[:, None], counts, axis=0)


def patch_rays(
    patches: Patches,
    shooters: np.ndarray,
    counts: np.ndarray,
    power: np.ndarray,
    rng: np.random.Generator,
    diff: np.ndarray | None = None,
) -> RayBatch:
    """Cosine-distributed rays from stratified points of each shooter.

    shooters (k,) i8 patch indices; counts (k,) i8 rays each; power (k,3) W to shoot;
    diff (k,3) W the half-solutions' difference of that power (noise.py; None: 0).
    Each shooter gets two randomly shifted 4-D lattices (2 dims position, 2 dims
    direction), one per half, so its rays are stratified over the triangle and the
    hemisphere and the halves are independent.

    Per-ray work runs on contiguous coordinate columns (structure of arrays): the
    (m,3) views' strided columns made the frame products 3x slower (bench_scale).
    Positions: the shooter's lifted corner in float64 plus its edges in float32.
    """
    owner, u = ray_columns(counts, rng, halves=True)

    # Per-shooter geometry (k rows), repeated per ray as columns (np.repeat: ~8x a gather)
    faces = patches.faces[shooters]
    v = patches.vertices
    v0 = v[faces[:, 0]]
    n_k = patches.normal[shooters]
    t_k, b_k = onb(n_k)
    edges = np.concatenate([v[faces[:, 1]] - v0, v[faces[:, 2]] - v0, t_k, b_k, n_k], axis=1)
    g = np.repeat(np.ascontiguousarray(edges.T, np.float32), counts, axis=1)  # (15, m)
    base = np.repeat(np.ascontiguousarray((v0 + ray_offset(patches) * n_k).T), counts, axis=1)  # (3, m)

    # Stratified points on the triangles (square-root map), lifted off the surface
    s = np.sqrt(u[0])
    b2 = s * u[1]
    b1 = s - b2
    m = len(owner)
    origins = np.empty((m, 3))
    dirs = np.empty((m, 3), np.float32)
    x, y, z = cosine_hemisphere_columns(u[2], u[3])  # cosine directions in the shooter's frame
    for c in range(3):
        origins[:, c] = base[c] + (b1 * g[c] + b2 * g[3 + c])
        dirs[:, c] = x * g[6 + c] + y * g[9 + c] + z * g[12 + c]
    return RayBatch(origins=origins, dirs=dirs, power=split_power(power, counts, diff), shooter=owner,
                    half=half_mask(counts, rng))


def ray_columns(counts: np.ndarray, rng: np.random.Generator, halves: bool = False):
    """:func:`ray_lattice` as float32 columns: (owner (m,) i8, u (4, m) f32), the same numbers.

    Draws the same random shifts from ``rng`` in the same order.
    """
    k = len(counts)
    owner = np.repeat(np.arange(k), counts)
    sets = np.stack([(counts + 1) // 2, counts // 2], axis=1).ravel() if halves else counts
    start = np.cumsum(sets) - sets
    index = np.arange(int(counts.sum())) - np.repeat(start, sets)
    shift = np.repeat(np.ascontiguousarray(rng.random((len(sets), 4)).T), sets, axis=1)
    u = (index + 0.5)[None, :] * kronecker_alpha(4)[:, None] + shift
    u -= np.floor(u)
    return owner, u.astype(np.float32)


def compact(index: np.ndarray, scratch: np.ndarray):
    """Distinct values of ``index`` (m,), sorted, and each entry's slot among them.

    scratch: an int array at least as long as the largest value + 1 (its content
    does not matter and is overwritten).  Returns (rows (k,) the distinct values in
    increasing order, slot (m,) with ``rows[slot] == index``).  O(m + k log k): no
    pass over the whole scratch array, so the cost follows the rays, not the
    patches.  Sorted rows keep every later gather and scatter on the patch table
    (deposit, the ledger, the noise tallies) in memory order: at random rows those
    cost 5-20x more on this machine (bench/RESULTS.md).
    """
    m = len(index)
    order = np.arange(m, dtype=scratch.dtype)
    scratch[index] = order  # the last entry to write a value speaks for it
    rows = np.sort(index[scratch[index] == order])
    scratch[rows] = np.arange(len(rows), dtype=scratch.dtype)
    return rows, scratch[index]


def trace(tracer: Tracer, batch: RayBatch, patches: Patches, channels: int = 3) -> Tally:
    """Trace a batch and tally where its power went (no state is changed).

    The tally is sparse: ``received`` holds one row per patch hit on the front
    (``hit``, sorted), so its cost follows the rays, not the size of the patch table.
    Front or back comes from Embree's geometric normal of the hit (no gather of
    patch normals at random rows).
    channels=1 (grey scenes: every rho, E and ray power has equal channels) tallies
    the first channel and copies it: the result is the same, one bincount instead of three.
    """
    n = len(patches)
    prim, t, ng = tracer.intersect(batch.origins, batch.dirs, normals=True)
    if tracer.glazing is not None:  # panes pass tau(theta) of a ray on: tally what ends where
        prim, t, ng, batch = through_panes(tracer, batch, prim, t, ng)
    missed = prim == MISS
    if tracer.n > n:  # boundary primitives follow the patches (subscenes)
        on_patch = ~missed & (prim < n)
        portal = np.flatnonzero(~missed & (prim >= n))
    else:
        on_patch = ~missed
        portal = np.zeros(0, np.int64)

    # Front or back: the ray travels against the hit patch's normal on the front
    facing = np.einsum("ij,ij->i", batch.dirs, ng)
    front_mask = on_patch & (facing < 0.0)
    if patches.two_sided:  # a two-sided patch met from behind: the ray lands on its back side (twin)
        behind = np.flatnonzero(on_patch & ~front_mask)
        twin = patches.twin[prim[behind]]
        flip = behind[twin >= 0]
        prim = prim.copy()
        prim[flip] = twin[twin >= 0]
        front_mask[flip] = True
    front = np.flatnonzero(front_mask)
    back = np.flatnonzero(on_patch & ~front_mask)

    # Scatter power onto the patches hit, one bincount per channel over the compact slots
    hit, slot = compact(prim[front], patches.scratch)
    k = len(hit)
    power_front = take_rows(batch.power, front)
    received = np.empty((k, 3), np.float64)
    for c in range(channels):
        received[:, c] = np.bincount(slot, weights=power_front[:, c], minlength=k)
    if channels == 1:
        received[:, 1] = received[:, 0]
        received[:, 2] = received[:, 0]
    # The same for the rays of half A, when the batch is split (noise.py): one more bincount.
    # Half B's rays weigh 0 (adding +-0 leaves every sum as it was): 4-9x cheaper than
    # selecting half A's slots and weights with the mask first (262k rays: 1.0 vs 5-12 ms)
    received_a = None
    if batch.half is not None:
        in_a = batch.half[front]
        received_a = np.empty((k, 3), np.float64)
        for c in range(channels):
            received_a[:, c] = np.bincount(slot, weights=power_front[:, c] * in_a, minlength=k)
        if channels == 1:
            received_a[:, 1:] = received_a[:, :1]

    # landed/kept per patch, not per ray: a gather of rho per ray cost a quarter of trace
    # time, and only the ratio kept/landed (mean rho where light lands) is used
    magnitude = np.abs(received)
    landed = colsum(magnitude)
    kept = colsum(magnitude * take_rows(patches.rho, hit))
    power_back = take_rows(batch.power, back)
    power_missed = np.compress(missed, batch.power, axis=0)
    back_by_obj = np.bincount(patches.obj[prim[back]], weights=rowsum(power_back), minlength=patches.n_objects)
    return Tally(
        received=received,
        hit=hit,
        escaped=colsum(power_missed),
        back_faces=colsum(power_back),
        back_by_obj=back_by_obj,
        portal=portal,
        portal_prim=prim[portal] - n,
        portal_t=t[portal],
        landed=landed,
        kept=kept,
        lost=colsum(np.abs(power_back)) + colsum(np.abs(power_missed)),
        received_a=received_a,
        ends=batch if tracer.glazing is not None else None,
    )


def through_panes(tracer: Tracer, batch: RayBatch, prim: np.ndarray, t: np.ndarray, ng: np.ndarray):
    """The ends of ``batch``'s rays in a scene with glass (optics.py; the seed's eq. 1.2): a ray that
    meets a pane leaves (1 - tau(theta)) of its power on it and goes on, from just beyond it in the
    same direction, with tau(theta) of it, through at most MAX_PANES panes.  Returns (prim, t, ng,
    events): one row per power that ends somewhere (a surface, a pane, nothing), ``events`` a
    RayBatch of their directions, powers and halves, for ``trace`` to tally like rays."""
    glazing = tracer.glazing
    assert glazing is not None
    step = TOL.ray_offset * tracer.scale
    origins, dirs, power, half = batch.origins, batch.dirs, batch.power, batch.half
    ends: list[tuple] = []
    for k in range(MAX_PANES + 1):
        pane = glazing.panes(prim)
        if k == MAX_PANES:
            pane[:] = False  # what is left stays on the last pane met
        stop = np.flatnonzero(~pane)
        rows = np.flatnonzero(pane)
        if len(rows):
            d = dirs[rows]
            tau = glazing.crossing(prim[rows], ng[rows], d)
            ends.append((prim[rows], t[rows], ng[rows], d, power[rows] * (1.0 - tau), origins[rows],
                         None if half is None else half[rows]))
        ends.append((prim[stop], t[stop], ng[stop], dirs[stop], power[stop], origins[stop],
                     None if half is None else half[stop]))
        if not len(rows):
            break
        origins = origins[rows] + (t[rows] + step)[:, None] * dirs[rows]
        dirs, power = dirs[rows], power[rows] * tau
        half = None if half is None else half[rows]
        prim, t, ng = tracer.intersect(origins, dirs, normals=True)
    cat = [np.concatenate(column) for column in zip(*[e[:6] for e in ends])]
    halves = None if batch.half is None else np.concatenate([e[6] for e in ends])
    # each end from where its power set out (the batch's origin, or just beyond the last pane):
    # a boundary's crossing point is origin + t dir (a subscene's exact forwarding continues it there)
    events = RayBatch(origins=cat[5], dirs=cat[3], power=cat[4], shooter=np.zeros(len(cat[0]), np.int64),
                      half=halves)
    return cat[0], cat[1], cat[2], events


@dataclass
class Landing:
    """The rows a batch hit on the front, gathered once (``landing``) for ``deposit`` and
    the noise tallies (noise.NoiseTally.commit): at 1.27M patches each gather of the rows
    hit is a cache miss per row, so every table is read once and written once."""

    hit: np.ndarray  #: (k,) distinct rows, sorted (``Tally.hit``)
    received: np.ndarray  #: (k,3) W that arrived (``Tally.received``)
    area: np.ndarray  #: (k,) m^2
    rho: np.ndarray  #: (k,3)
    radiosity: np.ndarray  #: (k,3) W/m^2, B before the deposit
    unshot: np.ndarray  #: (k,3) W/m^2, dB before the deposit
    reflected: np.ndarray  #: (k,3) W, rho * received: what the rows keep
    gain: np.ndarray  #: (k,3) W/m^2, reflected / area: what B and dB gain

    @property
    def unshot_after(self) -> np.ndarray:
        """(k,3) W/m^2: dB after the deposit."""
        return self.unshot + self.gain


def landing(patches: Patches, hit: np.ndarray, received: np.ndarray,
            before: np.ndarray | None = None) -> Landing:
    """Gather what the rows ``hit`` hold and what they keep of ``received`` (k,3) W; O(k).

    ``before``: ``patches.unshot[hit]`` when the caller has it already.
    """
    area = take_rows(patches.area, hit)
    rho = take_rows(patches.rho, hit)
    reflected = rho * received
    return Landing(hit, received, area, rho, take_rows(patches.radiosity, hit),
                   take_rows(patches.unshot, hit) if before is None else before,
                   reflected, reflected / area[:, None])


def deposit(patches: Patches, hit: np.ndarray, received: np.ndarray,
            before: np.ndarray | None = None, land: Landing | None = None) -> np.ndarray:
    """Add received power to B and dB of the patches hit; return the absorbed power (3,) W.

    hit (k,) distinct patch indices, received (k,3) W (``Tally.hit``, ``Tally.received``).
    A patch keeps rho * received as radiosity and unshot radiosity (divided by its
    area) and absorbs the rest.  Cost O(k): only the rows hit are touched, each table
    gathered once and scattered once (``arrays.take_rows/put_rows``).
    ``before``: ``patches.unshot[hit]`` when the caller has it already; ``land``: the
    rows' ``landing`` when the caller has it (then ``before`` is not used).
    """
    if land is None:
        land = landing(patches, hit, received, before)
    put_rows(patches.radiosity, hit, land.radiosity + land.gain)
    put_rows(patches.unshot, hit, land.unshot_after)
    return colsum(received - land.reflected)
