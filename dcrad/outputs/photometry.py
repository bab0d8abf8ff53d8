"""What lighting engineers read: illuminance in lux, luminance, per-surface statistics, false colour.

Radiometric to photometric: dcrad's RGB channels are linear Rec. 709, so the
photometric weight of a radiometric RGB value is its CIE Y (0.2126 R + 0.7152 G +
0.0722 B) times a luminous efficacy of ``EFFICACY`` = 179 lm/W, Radiance's
convention for white light (the efficacy of equal-energy white over the visible
band).  Illuminance E_v = 179 Y(H) lux with H the irradiance (W/m^2 incident);
luminance L_v = 179 Y(B) / pi cd/m^2 (a Lambertian surface of radiosity B).

Irradiance of a patch: the solver deposits rho_j * (power received) on B_j, so
H_j = (B_j - E_j) / rho_j exactly, per channel.  Where a channel's rho is below
``RHO_GATHER`` (black surfaces keep nothing of what they receive, so B tells
nothing), and at the work plane's grid of points facing up (``workplane``), H
is computed from the solution as H = H_direct + H_indirect:

* H_direct, the emitters' light, deterministically (``direct_irradiance``): each
  emitting patch is Lambertian with exitance E, so an emitter seen whole gives
  E F, F the point-to-polygon form factor, exact by Lambert's contour formula
  (lights.py; coplanar neighbours of one object and exitance are one polygon,
  ``lights.light_polygons``; the outline is clipped to the receiver's horizon).
  A patch takes the mean of F over a degree-2 rule of three points (the patch's
  mean irradiance up to the fourth order in its size).  Visibility comes from
  shadow rays, stratified over the receiver and the emitter (``RAYS_PER_POINT``
  a point, spread over its lights by their share of its E F, at most
  ``SHADOW_RAYS`` a light): all unoccluded gives exactly E F, all occluded
  exactly 0; only a pair in which some are and some are not (a penumbra) traces
  more (``PENUMBRA_RAYS`` in all for a light of SHADOW_RAYS) and takes E F times
  the visible share sum G V / sum G (G = cos cos / r^2).
* H_indirect, the reflected light, by ``rays`` cosine-distributed rays (from
  stratified points all over a patch: its mean, as for H_direct) that read B - E
  of what they hit: the emitters' own E is H_direct's, so a bright small
  emitter hit by chance adds no noise.  Where nothing reflects (B = E everywhere,
  an all-black room) no ray is gathered and H is exact.

Why: the gather alone (256 rays reading B, emitters included) is noisy where the
light is direct (a 1 x 1 m panel 3 m above a black floor is hit by about 9 of a
point's 256 rays: 19% rms, 74% at worst, against the closed form) and costs 256
rays a black patch.  The black room of test_photometry_direct with its floor in
0.0085 m squares (442k patches): 113M rays and 67 s before, 7.1M shadow rays and 3.1 s now, within 2e-10
of the closed form (the work plane: 62% -> 2e-15 at its worst point).

Many emitters (a real model can have thousands of emitting triangles, hundreds
of lamps): coplanar emitters of one object and exitance are one polygon (its
outline: a luminous ceiling of 128 patches is 4 edges), and the work per point is
bounded.  Each light gets an importance w per point (or per cell of nearby points
when points x lights is large, ``IMPORTANCE_ENTRIES``), a bound of its unoccluded
E F from the light's bounding sphere, zero exactly where it cannot reach the
point.  With at most ``EXACT_PAIRS`` lights every pair with w > 0 is exact as
above.  Past that, the lights with w >= sum w / EXACT_PAIRS (at most EXACT_PAIRS:
the near ones, most of the light) are exact, and the weaker rest of a point's
lights (the far tail, often behind walls) gets importance-sampled next-event
estimation: at least ``TAIL_RAYS`` shadow rays, each to a light drawn in proportion
to w and a uniform point on it, E A cos cos V / (pi r^2 p) each (unbiased).  Why
not drop pairs by Russian roulette (keep a pair with probability q, weight 1/q):
with 36 equal lamps in view, 8 kept pairs a point left 30% rms noise, and with
225 lamps (an open-plan floor) 64 pairs left 5%: the tail is many small terms, each
all or nothing.  Next-event rays share the tail instead: 0.5% rms there at 80-100
rays a point, 0.7% with 2,250 lights (each lamp a box of 10 triangles), where
every pair exact took 1,350 rays a point.  Form factors are cheap (microseconds a
pair); the shadow rays are what is bounded: outside penumbrae at most
RAYS_PER_POINT + EXACT_PAIRS first rays to a point's exact lights and RAYS_PER_POINT
to its tail, whatever the count of lights (500k black floor patches under 225
lamps: 80 rays a patch, 17 s; under 2,250 emitting triangles: 95, 21 s).
"""

from __future__ import annotations

import math

import numpy as np

from dcrad.arrays import ray_runs
from dcrad.errors import ConfigError
from dcrad.outputs.render import CornerSmoother, tonemap
from dcrad.transport.lights import Lights, form_factors, light_polygons, triangle_lights
from dcrad.transport.rays import MISS, Tracer
from dcrad.transport.sampling import DEGREE2_RULE, cosine_hemisphere, lattice, onb, triangle_points

__all__ = [
    "EFFICACY", "Y_WEIGHTS", "RHO_GATHER", "GATHER_RAYS", "PANE_GATHER_RAYS", "PANE_SKY_RAYS", "RAYS_PER_POINT",
    "SHADOW_RAYS", "PENUMBRA_RAYS",
    "EXACT_PAIRS", "TAIL_RAYS",
    "irradiance", "direct_irradiance", "direct_look", "shown_direct", "LOOK_RAYS", "to_lux", "luminance_cd",
    "surface_groups", "surface_stats", "workplane", "check_workplane", "stats", "false_colour", "legend_scale",
]

#: lm/W: luminous efficacy of white light (Radiance's convention)
EFFICACY = 179.0
#: CIE Y of linear Rec. 709 RGB
Y_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])
#: channels with rho below this get their irradiance gathered, not read from B
RHO_GATHER = 1e-3
#: rays per gathered patch or work-plane point for the reflected light
GATHER_RAYS = 256
#: the same for a pane (optics.py): its lux are read by few (light on the glass itself), and its rays
#: cross other panes (the ice-cream store's display cases: 35,456 pane patches made the outputs
#: 11 -> 45 s at 256 rays each); its direct light stays exact
PANE_GATHER_RAYS = 32
#: rays a point of a pane reads the sky's direct light with (a sampled source: sky.Sky.irradiance), not
#: the budget's share (up to 16,384 a point): a pane's own lux is read per surface, over its patches,
#: and its few patches took the whole budget (the peer's office: 10.6 of its 17.9 s)
PANE_SKY_RAYS = 1024
#: first-pass shadow rays of a point, spread over its lights in proportion to their exact
#: unoccluded contribution E F: each light at least one ray and at most SHADOW_RAYS (one light:
#: SHADOW_RAYS; eight equal lights: 8 each; 36: 2 each)
RAYS_PER_POINT = 64
SHADOW_RAYS = 16
#: a pair whose first rays found a penumbra traces this many / SHADOW_RAYS times its first rays
#: in all (128 for a light with 16).  A point in the penumbra of a 1 x 1 m panel
#: (test_photometry_direct): 1.5% rms of the unshadowed value at 64, 0.6% at 128, 0.5% at 256
PENUMBRA_RAYS = 128
#: exact (point, light) pairs a point has at most: with at most this many lights every pair that
#: can exchange light is exact; past it the lights of importance >= 1/EXACT_PAIRS of the point's
#: are, and the rest get next-event estimation (see the module's docstring)
EXACT_PAIRS = 64
#: least next-event rays a receiver traces to its weak lights (past EXACT_PAIRS lights)
TAIL_RAYS = 16
#: (cell, light) importance entries formed for all the points: past this, nearby points share a
#: cell (a point per cell below it); bounds the work for thousands of lights
IMPORTANCE_ENTRIES = 1 << 25
#: entries of one importance block, pair entries of one form-factor block, expected pairs of one
#: block of receivers, shadow rays at once
_BLOCK = 1 << 20  # about 10 arrays of this many float64 at the peak: 80 MB
_FF_BLOCK = 1 << 19
_PAIR_BLOCK = 1 << 18
_RAY_BATCH = 1 << 18
_POINT_RULE = np.array([[1.0, 0.0, 0.0]])


def to_lux(h: np.ndarray) -> np.ndarray:
    """(..., 3) irradiance W/m^2 -> (...) illuminance lux."""
    return EFFICACY * (np.asarray(h, np.float64) @ Y_WEIGHTS)


def luminance_cd(b: np.ndarray) -> np.ndarray:
    """(..., 3) radiosity W/m^2 -> (...) luminance cd/m^2 of a Lambertian surface."""
    return EFFICACY * (np.asarray(b, np.float64) @ Y_WEIGHTS) / math.pi


def _gather(patches, tracer: Tracer, origins: np.ndarray, normals: np.ndarray, rays: int,
            seed: int, values: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Cosine-gathered irradiance (k,3) facing ``normals`` of ``values`` (n,3) of what the rays
    hit (None: zeros, only the second result is wanted), and the fraction of rays that met a
    one-sided surface from behind (k,) (a point inside a wall sees only backs).

    ``origins``: points (k,3), or triangles (k,3,3) whose mean irradiance is wanted: the rays
    then start at stratified points all over the triangle (a 4-D lattice: direction, position),
    lifted off it and pulled in from its edges by the ray offset (``_inward``)."""
    k = len(origins)
    if k == 0:
        return np.zeros((0, 3)), np.zeros(0)
    rng = np.random.default_rng(seed)
    owner = np.repeat(np.arange(k), rays)
    dims = 2 if origins.ndim == 2 else 4
    u = lattice(np.tile(np.arange(rays), k), np.repeat(rng.random((k, dims)), rays, axis=0), dims)
    t, b = onb(normals)
    frames = np.stack([t, b, normals], axis=1)
    d = np.einsum("mi,mij->mj", cosine_hemisphere(u[:, :2]), frames[owner])
    if dims == 2:
        start = origins[owner]
    else:
        off = 2e-6 * patches.scale
        start = triangle_points(origins[:, 0], origins[:, 1], origins[:, 2], u[:, 2:], owner)
        start = _inward(start, origins.mean(axis=1)[owner], off) + off * normals[owner]
    prim, _, _, tau = tracer.through(start, d)  # beyond glass, read times its tau
    n = len(patches)
    hit = (prim != MISS) & (prim < n)
    p = np.where(hit, prim, 0)
    behind = hit & (np.einsum("ij,ij->i", d, patches.normal[p]) > 0)
    twin = patches.twin[p]
    p = np.where(behind & (twin >= 0), twin, p)
    lost = behind & (twin < 0)
    if values is None:
        h = np.zeros((k, 3))
    else:
        seen = np.where((hit & ~lost)[:, None], values[p], 0.0) * tau
        h = np.stack([np.bincount(owner, weights=seen[:, c], minlength=k) for c in range(3)], axis=1) / rays
    return h, np.bincount(owner, weights=lost.astype(np.float64), minlength=k) / rays


def _reflected(patches) -> np.ndarray | None:
    """B - E (n,3), or None when nothing reflects (B = E everywhere: no indirect light to gather)."""
    refl = patches.radiosity - patches.emission
    return refl if np.any(refl != 0.0) else None


def irradiance(patches, tracer: Tracer | None = None, rays: int = GATHER_RAYS, seed: int = 0):
    """(H (n,3) W/m^2 incident on each patch, gathered (n,) bool: patches whose H was gathered).

    H of a gathered patch is its mean over the patch: the direct part exactly (a degree-2 rule
    and shadow rays over the patch, ``direct_irradiance``), the reflected part from ``rays``
    rays from stratified points all over it (a pane's from PANE_GATHER_RAYS; none when nothing
    reflects)."""
    rho = patches.rho
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.where(rho >= RHO_GATHER, (patches.radiosity - patches.emission) / rho, 0.0)
    gathered = np.any(rho < RHO_GATHER, axis=1)
    idx = np.flatnonzero(gathered)
    if len(idx):
        tracer = tracer or Tracer.mesh(patches)
        tri = patches.corners(idx)
        nrm = patches.normal[idx]
        panes = np.zeros(len(idx), bool) if patches.glazing is None else patches.glazing.mask[idx]
        g = np.zeros((len(idx), 3))
        for rows, sky in ((np.flatnonzero(~panes), None), (np.flatnonzero(panes), PANE_SKY_RAYS)):
            if len(rows):
                g[rows] = direct_irradiance(patches, tracer, tri[rows], nrm[rows], seed=seed, sampled_rays=sky)[0]
        refl = _reflected(patches)
        if refl is not None:
            for rows, n in ((np.flatnonzero(~panes), rays), (np.flatnonzero(panes), PANE_GATHER_RAYS)):
                if len(rows) == len(idx):
                    g += _gather(patches, tracer, tri, nrm, n, seed, refl)[0]
                elif len(rows):
                    g[rows] += _gather(patches, tracer, tri[rows], nrm[rows], n, seed, refl)[0]
        low = rho[idx] < RHO_GATHER
        h[idx] = np.where(low, g, h[idx])
    return np.maximum(h, 0.0), gathered


# -- the direct light ------------------------------------------------------------------------
class _Emitters:
    """The emitting patches as lights (``lights.light_polygons``; per triangle past its limit), with
    what the pairs need: each light's loops, bounding sphere, importance weight and a sampler."""

    def __init__(self, patches):
        self.patches = patches
        em = np.flatnonzero(patches.emission.any(axis=1) & (patches.area > 0))
        self.emitters = em
        power = patches.emission[em] * patches.area[em, None]
        lights = light_polygons(patches, em, power) if len(em) else None
        if lights is None and len(em):
            lights = triangle_lights(patches, em, power)
        self.lights: Lights | None = lights
        if lights is None:
            return
        n_l = len(lights)
        # loops of each light: a run of ``n_loops`` rows of ``loop_rows`` from ``loop_start``
        self.loop_rows = np.argsort(lights.loop_light, kind="stable")
        self.n_loops = np.bincount(lights.loop_light, minlength=n_l)
        self.loop_start = np.cumsum(self.n_loops) - self.n_loops
        # area centroid (in the light's plane) and the radius of a sphere about it holding the light
        a = patches.area[em]
        cen = patches.centroid[em]
        self.centre = np.stack([np.bincount(lights.of_emitter, weights=a * cen[:, j], minlength=n_l)
                                for j in range(3)], axis=1) / lights.area[:, None]
        reach = np.linalg.norm(lights.loops - self.centre[lights.loop_light][:, None, :], axis=2).max(axis=1)
        self.radius = np.zeros(n_l)
        np.maximum.at(self.radius, lights.loop_light, reach)
        self.radius *= 1.0 + 1e-9
        self.lum = lights.exitance @ Y_WEIGHTS  # Y of the exitance
        self.weight = self.lum * lights.area  # Y of the power
        # a triangle of a light by area: emitters in light order, keyed light + share before it
        self.order = np.argsort(lights.of_emitter, kind="stable")
        per = np.bincount(lights.of_emitter, minlength=n_l)
        self.first = np.cumsum(per) - per
        self.last = self.first + per - 1
        lt = lights.of_emitter[self.order]
        self.share = a[self.order] / lights.area[lt]
        before = np.cumsum(self.share) - self.share
        self.key = lt + (before - before[self.first][lt])
        self.para = lights.parallelogram if lights.parallelogram is not None else np.zeros(n_l, bool)
        self.corner = lights.corner if lights.corner is not None else np.zeros((n_l, 3))
        self.edges = lights.edges if lights.edges is not None else np.zeros((n_l, 2, 3))

    def __len__(self) -> int:
        return 0 if self.lights is None else len(self.lights)

    def importance(self, xc: np.ndarray, nc: np.ndarray, rc: np.ndarray, spread: np.ndarray) -> np.ndarray:
        """(c,L) importance w of each light for cells of points within ``rc`` (c,) of ``xc`` (c,3),
        facing within ``spread`` (c,) of ``nc`` (c,3): Y(power) x bounds of the two cosines over
        (rmin^2 + A) pi, rmin the least distance between the cell's and the light's spheres.  Zero
        exactly where no point of the cell can exchange light with the light: every point of the
        light below every horizon of the cell (n_x . (y - x) <= n . d + R + r_c + s |y - x|), or
        the cell behind the light's plane (n_L . (x - y) <= -n_L . d + r_c); so no pair with F > 0
        has w = 0 (no light is lost, and w is a valid density to sample lights by)."""
        assert self.lights is not None
        d = self.centre[None, :, :] - xc[:, None, :]  # (c,L,3)
        r = np.sqrt((d * d).sum(axis=2))
        reach = self.radius[None, :] + rc[:, None]
        rmin = np.maximum(r - reach, 0.0)
        up = (d * nc[:, None, :]).sum(axis=2) + reach + spread[:, None] * (r + reach)
        facing = -(d * self.lights.normal[None, :, :]).sum(axis=2) + rc[:, None]
        den = np.maximum(rmin, 1e-300)
        cos_x = np.clip(up / den, 0.0, 1.0)
        cos_l = np.clip(facing / den, 0.0, 1.0)
        return self.weight[None, :] * cos_x * cos_l / (math.pi * (rmin * rmin + self.lights.area[None, :]))

    def form_factor(self, corners: np.ndarray, normals: np.ndarray, rec: np.ndarray, light: np.ndarray,
                    rule: np.ndarray) -> np.ndarray:
        """(P,) unoccluded form factor from receiver ``rec`` (its ``rule``'s points' mean) to ``light``,
        exact (Lambert's formula over each loop of the light, clipped to the horizon)."""
        assert self.lights is not None
        lights = self.lights
        out = np.zeros(len(rec))
        per = self.n_loops[light]
        owner = np.repeat(np.arange(len(rec)), per)
        loop = self.loop_rows[self.loop_start[light][owner] + np.arange(len(owner))
                              - np.repeat(np.cumsum(per) - per, per)]
        step = max(1, _FF_BLOCK // (len(rule) * (lights.loops.shape[1] + 1)))
        for a in range(0, len(owner), step):
            o, lp = owner[a:a + step], loop[a:a + step]
            r = rec[o]
            x = np.einsum("qk,ekj->eqj", rule, corners[r])
            f = form_factors(x, normals[r], lights.loops[lp], lights.normal[lights.loop_light[lp]])
            out += np.bincount(o, weights=f.mean(axis=1), minlength=len(rec))
        return np.maximum(out, 0.0)

    def points(self, lt: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(m,3) points on lights ``lt`` (m,) from ``u`` (m,2): a parallelogram light as a whole,
        else a triangle of it by area from u0, the rest of u0 within that triangle's share and
        u1 then a point on it (the 2-D stratification of u spread over the whole light: a
        separate dimension for the triangle left an L-shaped panel's penumbra 2.7x the
        variance); and (m,3) the centre of the parallelogram or triangle each is on."""
        y = np.empty((len(lt), 3))
        mid = np.empty((len(lt), 3))
        para = self.para[lt]
        f = np.flatnonzero(para)
        lf = lt[f]
        y[f] = self.corner[lf] + u[f, 0:1] * self.edges[lf, 0] + u[f, 1:2] * self.edges[lf, 1]
        mid[f] = self.corner[lf] + 0.5 * (self.edges[lf, 0] + self.edges[lf, 1])
        t = np.flatnonzero(~para)
        if len(t):
            lk = lt[t]
            pos = lk + u[t, 0]
            pick = np.clip(np.searchsorted(self.key, pos, side="right") - 1, self.first[lk], self.last[lk])
            rest = np.clip((pos - self.key[pick]) / self.share[pick], 0.0, 1.0 - 1e-12)
            e = self.emitters[self.order[pick]]
            g = self.patches.faces[e]
            v = self.patches.vertices
            y[t] = triangle_points(v[g[:, 0]], v[g[:, 1]], v[g[:, 2]], np.stack([rest, u[t, 1]], axis=1))
            mid[t] = self.patches.centroid[e]
        return y, mid

    def segments(self, tracer: Tracer, tri: np.ndarray, nrm: np.ndarray, local: np.ndarray, lt: np.ndarray,
                 u: np.ndarray, offset: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Shadow rays from points of receivers ``tri`` (h,3,3) facing ``nrm`` (h,3) (ray j from
        receiver local[j], at u[j, 3:5]) to points of lights ``lt`` (m,) (at u[j, 0:2]): (rays above
        both horizons (q,) of the m, their cos cos / r^2 (q,), visible (q,) bool)."""
        assert self.lights is not None
        x = triangle_points(tri[:, 0], tri[:, 1], tri[:, 2], u[:, 3:5], local)
        nx = nrm[local]
        y, mid = self.points(lt, u[:, 0:2])
        ny = self.lights.normal[lt]
        d = y - x
        r2 = np.einsum("ij,ij->i", d, d)
        dist = np.sqrt(np.maximum(r2, 1e-300))
        cx = np.einsum("ij,ij->i", nx, d) / dist
        cy = -np.einsum("ij,ij->i", ny, d) / dist
        ok = np.flatnonzero((cx > 0) & (cy > 0))
        g = cx[ok] * cy[ok] / r2[ok]
        # the ends lifted off their surfaces and pulled towards their triangle's centre by the
        # offset: a point on an edge where two surfaces meet (a floor at a wall) is on the other
        # surface too, in Embree's float32, and would hit it
        origin = _inward(x[ok], tri.mean(axis=1)[local[ok]], offset) + offset * nx[ok]
        end = _inward(y[ok], mid[ok], offset) + offset * ny[ok]
        return ok, g, tracer.visible(origin, end - origin, np.ones(len(ok)))

    def shadow(self, tracer: Tracer, corners: np.ndarray, normals: np.ndarray, rec: np.ndarray,
               light: np.ndarray, shift: np.ndarray, first: np.ndarray, counts: np.ndarray,
               offset: float) -> tuple[np.ndarray, int]:
        """Shadow rays number first[j] .. first[j] + counts[j] - 1 of pair j's shifted 5-D lattice
        (0-1 on the light, 3-4 on the receiver: R_5's projections there stratify well in 2-D; R_4's
        first two, whose generators differ by about 1/8, left 6x the penumbra's variance) from
        ``rec[j]`` to ``light[j]``: ((4,P) sums of G V, G, V, 1 over its rays above both horizons,
        rays traced)."""
        out = np.zeros((4, len(rec)))
        traced = 0
        for lo, hi, local, index in ray_runs(counts, _RAY_BATCH):
            u = lattice(first[lo:hi][local] + index, shift[lo:hi][local], 5)
            ok, g, seen = self.segments(tracer, corners[rec[lo:hi]], normals[rec[lo:hi]], local,
                                        light[lo:hi][local], u, offset)
            traced += len(ok)
            at = local[ok]
            for row, wgt in enumerate((g * seen, g, seen.astype(np.float64), None)):
                out[row, lo:hi] += np.bincount(at, weights=wgt, minlength=hi - lo)
        return out, traced

    def tail(self, tracer: Tracer, corners: np.ndarray, normals: np.ndarray, rec: np.ndarray, run: np.ndarray,
             n: np.ndarray, cdf: np.ndarray, at: np.ndarray, lights: np.ndarray, prob: np.ndarray,
             rng: np.random.Generator, offset: float) -> tuple[np.ndarray, int]:
        """Next-event estimation of the weak lights: receiver ``rec[j]`` traces n[j] rays, each to a
        light drawn from run ``run[j]`` of ``cdf`` (keys: run + cumulative probability before the
        entry; run i is entries at[i] .. at[i+1]-1 of ``lights``, ``prob``) by u2 of a 5-D
        lattice, a uniform point on it;
        each ray adds E A cos cos V / (pi r^2 p) / n.  Unbiased: p > 0 wherever the light can reach
        (``importance``).  ((P,3) H, rays traced)."""
        assert self.lights is not None
        out = np.zeros((len(rec), 3))
        shift = rng.random((len(rec), 5))
        traced = 0
        for lo, hi, local, index in ray_runs(n, _RAY_BATCH):
            c = n[lo:hi]
            u = lattice(index, shift[lo:hi][local], 5)
            r = run[lo:hi][local]
            pick = np.clip(np.searchsorted(cdf, r + u[:, 2], side="right") - 1, at[r], at[r + 1] - 1)
            lt = lights[pick]
            ok, g, seen = self.segments(tracer, corners[rec[lo:hi]], normals[rec[lo:hi]], local, lt, u, offset)
            traced += len(ok)
            lk = lt[ok]
            val = (g * seen * self.lights.area[lk] / (math.pi * prob[pick[ok]] * c[local[ok]]))[:, None] \
                * self.lights.exitance[lk]
            for ch in range(3):
                out[lo:hi, ch] += np.bincount(local[ok], weights=val[:, ch], minlength=hi - lo)
        return out, traced


def _inward(x: np.ndarray, centre: np.ndarray, by: float) -> np.ndarray:
    """Points x (m,3) moved ``by`` towards ``centre`` (m,3) (to it when closer)."""
    d = centre - x
    n = np.sqrt(np.einsum("ij,ij->i", d, d))
    return x + d * (np.minimum(by, n) / np.where(n > 0, n, 1.0))[:, None]


def _cells(x: np.ndarray, nrm: np.ndarray, rad: np.ndarray, most: int):
    """Cells of nearby points facing alike, at most ``most`` (a point per cell when they fit):
    (order (k,) points by cell, start (C,), count (C,), centre (C,3), mean normal (C,3), radius
    (C,) holding the points' own ``rad``, spread (C,) the largest |n - mean|)."""
    k = len(x)
    if k <= most:
        one = np.arange(k)
        return one, one, np.ones(k, np.int64), x, nrm, rad, np.zeros(k)
    axis = np.abs(nrm).argmax(axis=1)
    face = 2 * axis + (nrm[np.arange(k), axis] < 0)
    lo = x.min(axis=0)
    size = max(float(np.linalg.norm(x.max(axis=0) - lo)), 1e-300) / math.sqrt(most)
    while True:  # a grid fine enough for about ``most`` cells on surfaces, coarser until it fits
        idx = np.floor((x - lo) / size).astype(np.int64)
        dims = idx.max(axis=0) + 1
        key = ((idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]) * 6 + face
        _, inv, count = np.unique(key, return_inverse=True, return_counts=True)
        if len(count) <= most:
            break
        size *= 1.5
    inv = np.asarray(inv).reshape(-1)
    n_c = len(count)
    order = np.argsort(inv, kind="stable")
    start = np.cumsum(count) - count
    centre = np.stack([np.bincount(inv, weights=x[:, j], minlength=n_c) for j in range(3)], axis=1) / count[:, None]
    radius = np.zeros(n_c)
    np.maximum.at(radius, inv, np.linalg.norm(x - centre[inv], axis=1) + rad)
    mean = np.stack([np.bincount(inv, weights=nrm[:, j], minlength=n_c) for j in range(3)], axis=1)
    mean = mean / np.maximum(np.linalg.norm(mean, axis=1), 1e-300)[:, None]
    spread = np.zeros(n_c)
    np.maximum.at(spread, inv, np.linalg.norm(nrm - mean[inv], axis=1))
    return order, start, count, centre, mean, radius * (1.0 + 1e-9), spread * (1.0 + 1e-9)


def direct_irradiance(patches, tracer: Tracer, corners: np.ndarray, normals: np.ndarray, seed: int = 0,
                      emitters: _Emitters | None = None, rays: tuple[int, int, int, int] | None = None,
                      sampled_rays: int | None = None) -> tuple[np.ndarray, int]:
    """(H_direct (k,3) W/m^2, shadow rays traced) at receivers facing ``normals`` (k,3): triangles
    ``corners`` (k,3,3) (H is the mean over the triangle) or points (k,3).  The emitting patches'
    light (``_patch_direct``) and the light sources' that are not patches (emitters.Emitter: exact,
    at the rule's points).  ``rays``: (RAYS_PER_POINT, SHADOW_RAYS, PENUMBRA_RAYS, IMPORTANCE_ENTRIES)
    for a coarser look (the mesh's refinement reads where the light varies, not its value to 1%).
    ``sampled_rays``: rays a point for the sources without an exact form (the sky; None: their own
    budget)."""
    out, traced = _patch_direct(patches, tracer, corners, normals, seed, emitters, rays)
    sources = patches.sources
    if not sources or len(out) == 0:
        return out, traced
    corners = np.asarray(corners, np.float64)
    normals = np.asarray(normals, np.float64)
    if corners.ndim == 2:
        points, weights = corners[:, None, :], np.ones(1)
    else:
        rule = DEGREE2_RULE
        points, weights = np.einsum("rc,kcx->krx", rule, corners), np.full(len(rule), 1 / len(rule))
    k, r = points.shape[:2]
    at = points.reshape(-1, 3)
    facing = np.repeat(normals, r, axis=0)
    offset = 2e-6 * patches.scale
    for source in sources:
        if rays is not None and not getattr(source, "exact", True):
            continue  # a coarse look asks where the light varies sharply: the sky's does not
        if sampled_rays is not None and not getattr(source, "exact", True):
            h = source.irradiance(at, facing, tracer, offset, rays=sampled_rays).reshape(k, r, 3)
        else:
            h = source.irradiance(at, facing, tracer, offset).reshape(k, r, 3)
        out += np.einsum("r,krc->kc", weights, h)
        traced += len(at)
    return out, traced


#: the mesh's look at the direct light (mesh.adapt): shadow rays a point, at most a light, in a penumbra
#: a light, and (cell, light) importance entries (IMPORTANCE_ENTRIES): it asks where the light varies,
#: not its value to 1% (the ice-cream store's many lamps: the importance took 6.1 of the look's 8.0 s)
LOOK_RAYS = (8, 4, 16, 1 << 21)


def direct_look(patches):
    """``look(points, normals)`` -> (CIE Y of the direct irradiance there, shadow rays): what
    mesh.adapt reads, with LOOK_RAYS, on a tracer of ``patches`` built once."""
    tracer = Tracer.mesh(patches)
    emitters = _Emitters(patches)

    def look(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, int]:
        h, rays = direct_irradiance(patches, tracer, points, normals, emitters=emitters, rays=LOOK_RAYS)
        return h @ Y_WEIGHTS, rays

    return look


def shown_direct(patches, rows: np.ndarray, points: int, seed: int = 5) -> dict:
    """The direct light as the pictures show it, against the exact one, at ``points`` area-sampled
    points of the patches ``rows`` (each facing its patch's front): what mesh.adapt is measured by
    (bench/bench_adapt.py, tests/test_adapt.py).  Each patch takes its exact mean direct light
    (``direct_irradiance`` over the triangle), smoothed over corners as the pictures are
    (render.CornerSmoother) and interpolated; CIE Y, W/m^2.  Returns ``shown`` (k,), ``flat`` (k,:
    the patch's mean, unsmoothed), ``exact`` (k,) and ``at`` (k,3)."""
    tracer = Tracer.mesh(patches)
    rows = np.asarray(rows)
    tri = patches.triangles
    mean = np.zeros(len(patches))
    h, _ = direct_irradiance(patches, tracer, tri[rows], patches.normal[rows], seed=seed)
    mean[rows] = h @ Y_WEIGHTS
    corner = CornerSmoother(patches).apply(mean[:, None])[:, :, 0]
    rng = np.random.default_rng(seed)
    area = patches.area[rows]
    pick = rows[rng.choice(len(rows), points, p=area / area.sum())]
    uv = rng.random((points, 2))
    s = np.sqrt(uv[:, 0])
    bc = np.stack([1 - s, s * (1 - uv[:, 1]), s * uv[:, 1]], axis=1)  # triangle_points' square-root map
    at = np.einsum("kc,kcx->kx", bc, tri[pick])
    exact = direct_irradiance(patches, tracer, at, patches.normal[pick], seed=seed + 1)[0] @ Y_WEIGHTS
    return {"shown": (bc * corner[pick]).sum(axis=1), "flat": mean[pick], "exact": exact, "at": at}


def _patch_direct(patches, tracer: Tracer, corners: np.ndarray, normals: np.ndarray, seed: int = 0,
                  emitters: _Emitters | None = None, budget: tuple[int, int, int, int] | None = None
                  ) -> tuple[np.ndarray, int]:
    """(H_direct (k,3) W/m^2 from the emitting patches, shadow rays traced) at receivers facing
    ``normals`` (k,3): triangles ``corners`` (k,3,3) (H is the mean over the triangle: F by a
    degree-2 rule, shadow rays from stratified points of it) or points (k,3).

    Per (receiver, strong light) pair (``_Emitters``; every light when there are at most
    EXACT_PAIRS): the exact unoccluded form factor F, then stratified shadow rays, RAYS_PER_POINT
    a receiver over its lights by their share of its E F (at least 1 and at most SHADOW_RAYS a
    light).  All unoccluded: E F exactly; all occluded: 0; some of each (a penumbra):
    PENUMBRA_RAYS / SHADOW_RAYS times the first rays in all and E F sum G V / sum G.  The weak
    lights of a receiver (past EXACT_PAIRS lights): next-event estimation, TAIL_RAYS or more.
    Receivers in chunks: memory is bounded by _BLOCK, _FF_BLOCK, _PAIR_BLOCK and _RAY_BATCH
    whatever the counts.  ``budget``: (RAYS_PER_POINT, SHADOW_RAYS, PENUMBRA_RAYS, IMPORTANCE_ENTRIES)
    other than these."""
    per_point, per_light, penumbra, entries = budget if budget is not None else \
        (RAYS_PER_POINT, SHADOW_RAYS, PENUMBRA_RAYS, IMPORTANCE_ENTRIES)
    corners = np.asarray(corners, np.float64)
    normals = np.asarray(normals, np.float64)
    if corners.ndim == 2:  # points: a triangle of three equal corners, one rule point
        corners, rule = np.repeat(corners[:, None, :], 3, axis=1), _POINT_RULE
    else:
        rule = DEGREE2_RULE
    k = len(corners)
    out = np.zeros((k, 3))
    src = emitters if emitters is not None else _Emitters(patches)
    if src.lights is None or k == 0:
        return out, 0
    lights = src.lights
    n_l = len(src)
    rng = np.random.default_rng(seed + 2)
    offset = 2e-6 * patches.scale
    centroid = corners.mean(axis=1)
    rad = np.linalg.norm(corners - centroid[:, None, :], axis=2).max(axis=1)
    order, start, count, xc, nc, rc, spread = _cells(centroid, normals, rad, max(1, entries // n_l))
    ends = np.cumsum(count)
    per_chunk = max(1, _PAIR_BLOCK // min(n_l, EXACT_PAIRS))  # receivers at once
    rays = 0
    c0 = 0
    while c0 < len(count):
        # cells of at most _BLOCK importance entries and about _PAIR_BLOCK pairs at once
        c1 = min(len(count), c0 + max(1, _BLOCK // n_l),
                 max(c0 + 1, int(np.searchsorted(ends, (ends[c0 - 1] if c0 else 0) + per_chunk, side="right"))))
        w = src.importance(xc[c0:c1], nc[c0:c1], rc[c0:c1], spread[c0:c1])
        total = w.sum(axis=1, keepdims=True)
        strong = (w > 0) & ((EXACT_PAIRS * w >= total) if n_l > EXACT_PAIRS else True)
        # the strong lights: every receiver of the cell, exact
        ci, li = np.nonzero(strong)
        cell = c0 + ci
        per = count[cell]
        rows = np.repeat(np.arange(len(cell)), per)
        rec = order[start[cell][rows] + np.arange(len(rows)) - np.repeat(np.cumsum(per) - per, per)]
        light = li[rows]
        del rows
        ff = src.form_factor(corners, normals, rec, light, rule)
        live = np.flatnonzero(ff > 0)
        rec, light, ff = rec[live], light[live], ff[live]
        # the first rays: RAYS_PER_POINT over the receiver's lights by their share of its E F
        part = ff * src.lum[light]
        whole = np.bincount(rec, weights=part, minlength=k)[rec]
        n0 = np.clip(np.rint(per_point * part / np.where(whole > 0, whole, 1.0)), 1, per_light).astype(np.int64)
        shift = rng.random((len(rec), 5))
        sums, traced = src.shadow(tracer, corners, normals, rec, light, shift, np.zeros(len(rec), np.int64), n0, offset)
        rays += traced
        # a penumbra (or no ray above both horizons yet): PENUMBRA_RAYS / SHADOW_RAYS times as many
        more = np.flatnonzero(((sums[2] > 0) & (sums[2] < sums[3])) | (sums[3] == 0))
        if len(more):
            extra = n0[more] * (penumbra // per_light - 1)
            add, traced = src.shadow(tracer, corners, normals, rec[more], light[more], shift[more], n0[more], extra,
                                     offset)
            sums[:, more] += add
            rays += traced
        share = np.where(sums[1] > 0, sums[0] / np.where(sums[1] > 0, sums[1], 1.0), 1.0)
        got = (ff * share)[:, None] * lights.exitance[light]
        for ch in range(3):
            out[:, ch] += np.bincount(rec, weights=got[:, ch], minlength=k)
        del rec, light, ff, part, whole, n0, shift, sums, share, got
        # the weak lights of each cell (past EXACT_PAIRS): drawn in proportion to w, per receiver
        weak = (w > 0) & ~strong
        if weak.any():
            ci, li = np.nonzero(weak)  # by cell, then light
            wt = w[ci, li]
            used, run_of, n_run = np.unique(ci, return_inverse=True, return_counts=True)
            run_of = np.asarray(run_of).reshape(-1)
            w_run = np.bincount(run_of, weights=wt)
            at = np.concatenate([[0], np.cumsum(n_run)])
            prob = wt / w_run[run_of]
            before = np.cumsum(prob) - prob  # (normalised first: runs of very different w stay exact)
            cdf = run_of + (before - before[at[:-1]][run_of])
            # rays by the weak lights' share of the cell's w, at least TAIL_RAYS
            cell = c0 + used
            n_cell = np.clip(np.rint(per_point * w_run / total[used, 0]), min(TAIL_RAYS, per_point), per_point)
            per = count[cell]
            rows = np.repeat(np.arange(len(cell)), per)
            rec = order[start[cell][rows] + np.arange(len(rows)) - np.repeat(np.cumsum(per) - per, per)]
            got, traced = src.tail(tracer, corners, normals, rec, rows, n_cell[rows].astype(np.int64), cdf, at, li,
                                   prob, rng, offset)
            rays += traced
            for ch in range(3):
                out[:, ch] += np.bincount(rec, weights=got[:, ch], minlength=k)
        del w
        c0 = c1
    return out, rays


def surface_groups(patches, lux: np.ndarray | None = None) -> tuple[list[str], np.ndarray]:
    """(names, group (n,) int): one group per object, per material when objects are unnamed
    (OBJ's "default").  Two-sided surfaces: of each triangle's two sides the one with more
    ``lux`` counts for the object (the room side, whatever the winding), the other for
    "name (other side)"; without ``lux`` the back side is the other one."""
    labels = []
    for full in patches.names:
        obj, _, mat = full.rpartition("/")
        labels.append(mat if obj in ("", "default") else obj)
    labels = labels or ["scene"]
    unique = list(dict.fromkeys(labels))
    of_obj = np.array([unique.index(x) for x in labels], np.int64)
    other = patches.is_back.copy()
    pair = np.flatnonzero(patches.twin >= 0)
    if lux is not None and len(pair):
        mine, theirs = lux[pair], lux[patches.twin[pair]]
        other[pair] = (mine < theirs) | ((mine == theirs) & patches.is_back[pair])
    code = of_obj[np.clip(patches.obj, 0, len(labels) - 1)] + len(unique) * other
    used, group = np.unique(code, return_inverse=True)
    names = [unique[c % len(unique)] + (" (other side)" if c >= len(unique) else "") for c in used]
    return names, group.reshape(-1)


def stats(lux: np.ndarray, area: np.ndarray | None = None) -> dict:
    """E_avg (area-weighted), E_min, E_max (lux) and uniformity E_min / E_avg of some values."""
    lux = np.asarray(lux, np.float64)
    if not lux.size:
        return {"E_avg_lux": 0.0, "E_min_lux": 0.0, "E_max_lux": 0.0, "uniformity": 0.0}
    w = np.ones_like(lux) if area is None else np.asarray(area, np.float64)
    return _stats_of((lux * w).sum(), w.sum(), lux.mean(), lux.min(), lux.max())


def _stats_of(weighted, weight, mean, lo, hi) -> dict:
    """``stats`` from its sums: sum of lux x weight, sum of weight, plain mean, min and max."""
    avg = float(weighted / weight) if weight > 0 else float(mean)
    return {"E_avg_lux": avg, "E_min_lux": float(lo), "E_max_lux": float(hi),
            "uniformity": float(lo) / avg if avg > 0 else 0.0}


def surface_stats(patches, lux: np.ndarray) -> list[dict]:
    """``photometry.surfaces``: one entry per surface group (see surface_groups), as ``stats`` of
    its patches.  One pass over the patches for all groups (a mask per group was 2.6 s of the
    20x20 office's 6.1 s of outputs: hundreds of groups x 1.27M patches)."""
    names, group = surface_groups(patches, lux)
    lux = np.asarray(lux, np.float64)
    lum = luminance_cd(patches.radiosity)
    a = np.asarray(patches.area, np.float64)
    m = len(names)
    count = np.bincount(group, minlength=m)
    area = np.bincount(group, a, m)
    lux_a, lum_a, lux_sum = np.bincount(group, lux * a, m), np.bincount(group, lum * a, m), np.bincount(group, lux, m)
    order = np.argsort(group, kind="stable")
    used = np.flatnonzero(count)
    starts = (np.cumsum(count) - count)[used]
    lo, hi = np.full(m, 0.0), np.full(m, 0.0)
    lo[used] = np.minimum.reduceat(lux[order], starts)
    hi[used] = np.maximum.reduceat(lux[order], starts)
    return [{"name": names[g], "area_m2": float(area[g]),
             **_stats_of(lux_a[g], area[g], lux_sum[g] / count[g], lo[g], hi[g]),
             "L_avg_cd_m2": float(lum_a[g] / area[g]) if area[g] > 0 else 0.0} for g in used]


def check_workplane(height: float, patches) -> None:
    """ConfigError unless a work plane ``height`` m above the floor is inside the scene's box
    (0: none): above it every grid point looks at the outside, and the grid is empty."""
    top = float(patches.bounds[1][1] - patches.bounds[0][1]) if len(patches) else 0.0
    if not (math.isfinite(height) and 0.0 <= height < max(top, 1e-300)) and height != 0.0:
        raise ConfigError(f"--workplane {height:g} m: must be at least 0 and below the scene's height above its "
                          f"floor, {top:.4g} m (0: no work plane)")


def workplane(patches, height: float, spacing: float | None = None, tracer: Tracer | None = None,
              rays: int = GATHER_RAYS, seed: int = 0, border: float | None = None) -> dict:
    """Illuminance on a horizontal grid ``height`` m above the floor (the bottom of the box), facing up.

    At each point H = H_direct (exact, ``direct_irradiance``) + the reflected light gathered by
    ``rays`` rays reading B - E; the rays are traced even where nothing reflects, to find the
    points inside solids (below).  ``spacing`` default: the box's larger horizontal extent / 64.  Left out: points
    closer than ``border`` (default 0.5 m, EN 12464-1's border zone, at most a tenth of
    the smaller horizontal extent) to a surface along +-X or +-Z (walls, furniture; this
    also drops points inside them), and points that see mostly one-sided surfaces from
    behind (inside solids, outside the building).  Returns {"points" (k,3), "lux" (k,),
    and the statistics}.
    """
    lo, hi = patches.bounds
    ext = hi - lo
    spacing = spacing or max(ext[0], ext[2]) / 64.0
    xs = np.arange(lo[0] + 0.5 * spacing, hi[0], spacing)
    zs = np.arange(lo[2] + 0.5 * spacing, hi[2], spacing)
    xx, zz = np.meshgrid(xs, zs)
    pts = np.stack([xx.ravel(), np.full(xx.size, lo[1] + height), zz.ravel()], axis=1)
    tracer = tracer or Tracer.mesh(patches)
    border = min(0.5, 0.1 * min(ext[0], ext[2])) if border is None else border
    near = np.zeros(len(pts), bool)
    for d in ([1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0], [0, 0, -1.0]):
        prim, t = tracer.intersect(pts, np.broadcast_to(np.array(d), pts.shape).copy())
        near |= (prim != MISS) & (t < border)
    pts = pts[~near]
    up = np.broadcast_to(np.array([0.0, 1.0, 0.0]), pts.shape).copy()
    h, lost = _gather(patches, tracer, pts, up, rays, seed, _reflected(patches))
    keep = lost < 0.5
    h = h[keep] + direct_irradiance(patches, tracer, pts[keep], up[keep], seed=seed)[0]
    lux = to_lux(np.maximum(h, 0.0))
    out = {"height_m": float(height), "spacing_m": float(spacing), "border_m": float(border),
           "points": pts[keep], "lux": lux, "n_points": int(keep.sum()), **stats(lux)}
    rooms = workplane_rooms(pts[keep], lux, spacing, tracer)
    if len(rooms) > 1:
        out["rooms"] = rooms
    return out


#: a room of the work plane has at least this many grid points (smaller pieces are niches, gaps)
ROOM_POINTS = 4


def workplane_rooms(points: np.ndarray, lux: np.ndarray, spacing: float, tracer: Tracer) -> list[dict]:
    """The work plane's grid split where walls part it: neighbouring grid points (along X or Z) are
    in one room when the segment between them is clear, and rooms are the connected sets (labels
    spread to the smallest of each clear pair until nothing changes: at most the grid's diameter of
    vectorised steps).  Per room of ROOM_POINTS points or more, largest first: its points, area
    (m^2, a grid cell a point), centre (the solver's frame) and E avg/min/max and uniformity U0 =
    Emin / Eavg (EN 12464-1 reads these per room)."""
    k = len(points)
    if k == 0:
        return []
    ix = np.round((points[:, 0] - points[:, 0].min()) / spacing).astype(np.int64)
    iz = np.round((points[:, 2] - points[:, 2].min()) / spacing).astype(np.int64)
    width = int(ix.max()) + 2
    key = iz * width + ix
    order = np.argsort(key)
    pairs = []
    for step in (1, width):  # the next point along X, along Z
        at = np.searchsorted(key[order], key + step)
        found = at < k
        found[found] = key[order][at[found]] == key[found] + step
        pairs.append(np.stack([np.flatnonzero(found), order[at[found]]], axis=1))
    pair = np.concatenate(pairs)
    if len(pair):
        a, b = points[pair[:, 0]], points[pair[:, 1]]
        pair = pair[~tracer.occluded(a, b - a, np.ones(len(pair)))]
    label = np.arange(k)
    while len(pair):
        low = np.minimum(label[pair[:, 0]], label[pair[:, 1]])
        new = label.copy()
        np.minimum.at(new, pair[:, 0], low)
        np.minimum.at(new, pair[:, 1], low)
        new = new[new]  # follow the chain one more step
        if np.array_equal(new, label):
            break
        label = new
    rooms = []
    for r in np.unique(label):
        members = np.flatnonzero(label == r)
        if len(members) < ROOM_POINTS:
            continue
        rooms.append({"n_points": int(len(members)), "area_m2": float(len(members) * spacing * spacing),
                      "centre": points[members].mean(axis=0).tolist(), **stats(lux[members])})
    return sorted(rooms, key=lambda room: -room["area_m2"])


# -- false colour -----------------------------------------------------------------------------
#: colour map stops (linear RGB), low to high: dark blue, blue, cyan, green, yellow, orange, red
_STOPS = np.array([[0.0, 0.0, 0.25], [0.0, 0.1, 1.0], [0.0, 0.8, 1.0], [0.0, 0.8, 0.1],
                   [1.0, 1.0, 0.0], [1.0, 0.45, 0.0], [0.8, 0.0, 0.0]])


def colour_map(x: np.ndarray) -> np.ndarray:
    """(...) values in [0, 1] -> (..., 3) linear RGB along _STOPS."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0) * (len(_STOPS) - 1)
    i = np.minimum(np.floor(x).astype(np.int64), len(_STOPS) - 2)
    f = (x - i)[..., None]
    return _STOPS[i] * (1 - f) + _STOPS[i + 1] * f


def legend_scale(lux: np.ndarray, area: np.ndarray) -> float:
    """Top of the false-colour scale: a round number (1, 1.5, 2, 2.5, 3, 4, 5, 6, 7.5 x 10^k)
    at or above the area-weighted 99th percentile of the values."""
    ok = lux > 0
    if not ok.any():
        return 1.0
    order = np.argsort(lux[ok])
    cum = np.cumsum(area[ok][order])
    top = float(lux[ok][order][min(int(np.searchsorted(cum, 0.99 * cum[-1])), len(cum) - 1)])
    k = 10.0 ** math.floor(math.log10(top))
    return next(m * k for m in (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.5, 10.0) if m * k >= top * (1 - 1e-12))


def false_colour(value: np.ndarray, front: np.ndarray, back: np.ndarray, top: float,
                 legend_width: int = 110, ticks: int = 6, unit: str = "lux") -> np.ndarray:
    """(H, W) lux, front-hit and back-hit coverage -> (H, W + legend_width, 3) uint8 sRGB image.

    Pixels: the colour map of value / top where surfaces face the camera, grey where a
    one-sided surface is seen from behind, black for nothing.  At the right a colour bar
    (top at the top) with ``ticks`` labels in ``unit``, drawn with OpenImageIO's text renderer.
    """
    import OpenImageIO as oiio  # noqa: PLC0415  lazy: `dcrad jobs/watch` imports this module and must not load OpenImageIO

    h, w = value.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = np.where(front > 0, value / np.where(front > 0, front, 1.0), 0.0)
    img = np.zeros((h, w + legend_width, 3))
    img[:, :w] = colour_map(mean / top) * front[..., None] + 0.35 * back[..., None]
    img[:, w:] = 0.08
    bar_x0, bar_x1 = w + 10, w + 34
    y0, y1 = 20, h - 20
    ys = np.arange(y0, y1)
    img[y0:y1, bar_x0:bar_x1] = colour_map(1.0 - (ys - y0) / max(y1 - 1 - y0, 1))[:, None, :]
    buf = oiio.ImageBuf(oiio.ImageSpec(w + legend_width, h, 3, oiio.FLOAT))
    buf.set_pixels(oiio.ROI(0, w + legend_width, 0, h, 0, 1, 0, 3), img.astype(np.float32))
    size = max(10, min(16, h // 20))
    for i in range(ticks):
        frac = i / (ticks - 1)
        y = int(round(y1 - 1 - frac * (y1 - 1 - y0)))
        oiio.ImageBufAlgo.fill(buf, (1.0, 1.0, 1.0), oiio.ROI(bar_x1, bar_x1 + 6, y, y + 1))
        label = f"{frac * top:.4g}"
        oiio.ImageBufAlgo.render_text(buf, bar_x1 + 9, y + size // 3, label, size, "", (1.0, 1.0, 1.0))
    oiio.ImageBufAlgo.render_text(buf, w + 8, 14, unit, size, "", (1.0, 1.0, 1.0))
    out = np.asarray(buf.get_pixels(oiio.FLOAT)).reshape(h, w + legend_width, 3)
    return tonemap(out, exposure=1.0)
