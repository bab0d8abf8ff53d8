"""The solver's elements, chosen from the scene's light, not from the file's triangulation.

A modeller's triangulation says nothing about how fast the light varies: a long wall is two
triangles, a chair ten thousand slivers.  So the element size comes from the scene's own light
scale, the mean free path of its rays (``light_scale``: cosine rays from random points of the
surfaces, the mean distance to what they hit; in a closed convex room it is Cauchy's 4V/S),
divided by ``PATHS_PER_ELEMENT``.  It is the same for a building of 400 rooms as for one room,
and the same for a file triangulated finely or coarsely.  Where the direct light varies across an
element (shadow edges, near lamps) ``adapt`` splits it further, as lighting programs subdivide.

Meshing (``refine``) only splits: a triangle larger than the element is bisected across its
longest edge until it is not; triangles already smaller are kept whole (their neighbours of the
same surface share their light through ``clusters``, which groups them, see scene.Scene.patches).
Bisection, not trimesh's 4-way midpoint split, because a 4-way split of a 3 m sliver splits its
1 cm edges too (a sliver into 256 patches); bisection halves only the long edge.
"""

from __future__ import annotations

import numpy as np

from dcrad.meshing.patches import triangle_areas, triangle_normals

__all__ = ["light_scale", "element_size", "refine", "adapt", "near_lamps", "estimate_elements", "clusters", "mesh_note",
           "mesh_table", "PATHS_PER_ELEMENT", "SCALE_RAYS", "ADAPT_CONTRAST", "ADAPT_LEVELS", "ADAPT_FINEST",
           "ADAPT_SHARE", "ADAPT_MOST"]

#: element size = mean free path / PATHS_PER_ELEMENT (the office's rooms, 1.6 m: 0.32 m; Cornell 0.05 m).
#: The base mesh is coarser where the light is smooth because ``adapt`` splits it where it is not: a
#: sixth of the free path, unrefined, showed the direct light worse with more rays on the built-in
#: scenes and the corpus (bench/bench_adapt.py, RESULTS.md)
PATHS_PER_ELEMENT = 5.0
#: rays traced to measure the mean free path (its standard error is about 1/sqrt of this: 0.8%)
SCALE_RAYS = 1 << 14
#: a triangle is split while its area exceeds AREA_SHARE * size^2 (and its longest edge the size),
#: or while its longest edge exceeds SLIVER_EDGES * size whatever its area (a long sliver still
#: sees light vary along its length)
AREA_SHARE = 0.6
SLIVER_EDGES = 4.0
#: adaptive refinement (``adapt``): an element is split where the direct light across its corners
#: differs by more than ADAPT_CONTRAST of the light there (its corners' mean direct light plus the
#: room's mean reflected light, which fills shadows and lifts what the eye compares against)
ADAPT_CONTRAST = 0.3
#: at most this many rounds of splitting (each halves an element), and never an element whose
#: longest edge is under the element size / ADAPT_FINEST
ADAPT_LEVELS = 3
ADAPT_FINEST = 4.0
#: the refinement adds at most this share of the elements' summed light (``adapt``: what the accuracy
#: plan pays rays for), the most visible error per ray first
ADAPT_SHARE = 0.3
#: past this many elements the mesh is not refined: the look costs about 20 us a corner (the 20 x 20
#: office's 1.1M elements: 83 s, most of its meshing), which a larger scene's coarser pictures do not pay for
ADAPT_MOST = 400_000
#: corners are looked at this far toward the element's centroid (a corner on a wall's foot would
#: otherwise start its shadow rays on the wall)
_INSET = 0.05


def light_scale(vertices: np.ndarray, faces: np.ndarray, seed: int = 0) -> tuple[float, float]:
    """(mean free path m, share of rays that hit something): cosine rays from area-sampled points
    on both sides of the triangles, the mean distance to their first hit (misses left out: the
    sky or the outside of a model are not a length of its rooms).  With no hit at all (a lone
    plane), the box diagonal / 2."""
    from dcrad.transport.rays import Tracer  # noqa: PLC0415  embreex is imported on first use
    from dcrad.transport.sampling import cosine_hemisphere, onb, triangle_points  # noqa: PLC0415

    tri = vertices[faces]
    area = triangle_areas(tri)
    if len(faces) == 0 or not area.sum() > 0:
        return 0.0, 0.0
    lo, hi = tri.reshape(-1, 3).min(axis=0), tri.reshape(-1, 3).max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(faces), SCALE_RAYS, p=area / area.sum())
    normal = triangle_normals(tri[pick]) * np.where(rng.random(SCALE_RAYS) < 0.5, 1.0, -1.0)[:, None]
    origin = triangle_points(tri[pick, 0], tri[pick, 1], tri[pick, 2], rng.random((SCALE_RAYS, 2)))
    t, b = onb(normal)
    local = cosine_hemisphere(rng.random((SCALE_RAYS, 2)))
    dirs = local[:, :1] * t + local[:, 1:2] * b + local[:, 2:3] * normal
    tracer = Tracer(None, vertices=vertices, faces=faces)
    prim, dist = tracer.intersect(origin + 1e-6 * diag * normal, dirs)
    hit = np.isfinite(dist) & (prim >= 0) & (dist > 1e-6 * diag)
    if not hit.any():
        return 0.5 * diag, 0.0
    return float(dist[hit].mean()), float(hit.mean())


def element_size(vertices: np.ndarray, faces: np.ndarray) -> tuple[float, str]:
    """The automatic element size (m) and the report's sentence on how it was found."""
    mfp, seen = light_scale(vertices, faces)
    if mfp <= 0:
        return 0.0, "no surface with area: one element per triangle"
    size = mfp / PATHS_PER_ELEMENT
    return size, (f"element size {size:.3g} m: the rays' mean free path {mfp:.3g} m (measured with {SCALE_RAYS} "
                  f"rays, {seen:.0%} of them hit a surface) / {PATHS_PER_ELEMENT:g}; larger triangles split, "
                  f"smaller ones kept whole (mesh.py)")


def _edges(tri: np.ndarray) -> np.ndarray:
    """(m, 3) edge lengths of (m,3,3) triangles: edge k joins corners k and k+1."""
    return np.linalg.norm(np.roll(tri, -1, axis=1) - tri, axis=2)


def _key(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """An undirected edge's key from its two vertex indices (vertex counts stay far below 2^31)."""
    return np.minimum(a, b) * np.int64(1 << 31) + np.maximum(a, b)


def _split_mask(tri: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """(split (m,) bool, longest edge index (m,)): which triangles ``refine`` bisects, and where
    (edge k joins corners k and k+1)."""
    edges = _edges(tri)
    k = edges.argmax(axis=1)
    longest = edges[np.arange(len(tri)), k]
    area = triangle_areas(tri)
    split = (longest > size) & ((area > AREA_SHARE * size * size) | (longest > SLIVER_EDGES * size))
    return split, k


def refine(vertices: np.ndarray, faces: np.ndarray, size: float, max_levels: int = 40):
    """Bisect triangles across their longest edge until none is larger than the element ``size``.

    Returns (vertices (V,3) f8, faces (n,3) i8, index (n,) i8: the input face of each).  An edge
    split by both of its triangles gets one midpoint (the pieces share it, as the renderer's
    vertex colours need); winding is kept.  ``size`` <= 0: the input as it is.
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    index = np.arange(len(faces), dtype=np.int64)
    if not size > 0 or len(faces) == 0:
        return vertices, faces, index
    verts = [vertices]
    edges = _SplitEdges(len(vertices))
    done_f, done_i = [], []
    for _ in range(max_levels):
        all_v = np.concatenate(verts) if len(verts) > 1 else verts[0]
        verts = [all_v]
        split, k = _split_mask(all_v[faces], size)
        done_f.append(faces[~split])
        done_i.append(index[~split])
        if not split.any():
            break
        faces, index, fresh = edges.bisect(all_v, faces[split], k[split], index[split])
        verts.append(fresh)
    else:  # pragma: no cover - 40 halvings of an edge: 1e12 elements, refused before meshing
        done_f.append(faces)
        done_i.append(index)
    faces, index = _close(np.concatenate(done_f), np.concatenate(done_i), edges.keys, edges.mids)
    order = np.argsort(index, kind="stable")  # patches of one input triangle together, in file order
    return np.concatenate(verts), faces[order], index[order]


class _SplitEdges:
    """The edges bisected so far (sorted keys, ``_key``) and the vertex index of each one's midpoint:
    an edge split by both of its triangles, in one step or two, gets one midpoint."""

    def __init__(self, n_verts: int):
        self.n_verts = n_verts
        self.keys = np.zeros(0, np.int64)
        self.mids = np.zeros(0, np.int64)

    def bisect(self, vertices: np.ndarray, f: np.ndarray, kk: np.ndarray, idx: np.ndarray):
        """Split faces ``f`` across their edge ``kk`` (edge k joins corners k and k+1): (the two
        halves of each, winding kept (2m,3), their input faces (2m,), the new midpoints (j,3), which
        take the next vertex indices)."""
        rows = np.arange(len(f))
        a, b, c = f[rows, kk], f[rows, (kk + 1) % 3], f[rows, (kk + 2) % 3]
        key = _key(a, b)
        uniq, inv = np.unique(key, return_inverse=True)
        keys, mids = self.keys, self.mids
        pos = np.searchsorted(keys, uniq)
        known = (pos < len(keys)) & (keys[np.minimum(pos, len(keys) - 1)] == uniq) if len(keys) else \
            np.zeros(len(uniq), bool)
        mid_of = np.empty(len(uniq), np.int64)
        mid_of[known] = mids[pos[known]]
        fresh = np.flatnonzero(~known)
        mid_of[fresh] = self.n_verts + np.arange(len(fresh))
        first = np.zeros(len(uniq), np.int64)
        first[inv] = np.arange(len(key))  # a triangle that splits each new edge: its corners give the midpoint
        points = 0.5 * (vertices[a[first[fresh]]] + vertices[b[first[fresh]]])
        self.n_verts += len(fresh)
        order = np.argsort(np.concatenate([keys, uniq[fresh]]), kind="stable")
        self.keys = np.concatenate([keys, uniq[fresh]])[order]
        self.mids = np.concatenate([mids, mid_of[fresh]])[order]
        m = mid_of[inv]
        return (np.concatenate([np.stack([a, m, c], axis=1), np.stack([m, b, c], axis=1)]),
                np.concatenate([idx, idx]), points)


def adapt(vertices: np.ndarray, faces: np.ndarray, index: np.ndarray, look, size: float, fixed: np.ndarray,
          two_sided: np.ndarray | None = None, reflect: float = 0.5):
    """Split the elements across which the direct light varies fast (shadow edges, near lamps), as
    lighting programs subdivide adaptively: a mesh from ``refine`` -> (vertices, faces, index as
    ``refine`` returns them, and a dict of what was done: ``split`` elements split because of their
    light, ``added`` elements in all, ``levels``, ``points`` looked at, ``rays`` traced).

    ``look(points (k,3), normals (k,3))`` -> ((k,) the direct light's luminance there, rays traced).
    Each element's three corners (moved ``_INSET`` toward its centroid) are looked at facing its
    normal (and its back for the input triangles ``two_sided``); an element is split across its
    longest edge where their spread exceeds ADAPT_CONTRAST x (their mean + the room's reflected
    light: the mean direct light x ``reflect`` / (1 - reflect), the integrating sphere's share), up
    to ADAPT_LEVELS rounds, each looking at the new elements only, and never below size /
    ADAPT_FINEST; the neighbours of a split element take its midpoint (no hanging vertex).  Input
    triangles ``fixed`` (emitters, panes, clustered triangles) are not looked at, nor split as a
    neighbour's closure.  The splits' light adds up to at most ADAPT_SHARE of the light of the
    elements looked at (a split costs rays as the light on it), the largest area x contrast^2 /
    light first."""
    done = {"split": 0, "added": 0, "levels": 0, "points": 0, "rays": 0}
    vertices = np.asarray(vertices, np.float64)
    n0 = len(faces)
    if not size > 0 or not n0:
        return vertices, faces, index, done
    # one vertex per position: a file's neighbours often repeat their shared corners (one object
    # each, or OBJ groups), and a split must give its neighbour across the edge the midpoint too (a
    # T-junction leaks light in float32: the two-sided Cornell box lost 5e-8 W on its back faces)
    vertices, weld = np.unique(vertices, axis=0, return_inverse=True)
    faces = weld.reshape(-1)[faces]
    room = None  # the light the spreads are compared against, from the first look
    budget = 0.0  # the noise weight the new elements may add (see below)
    edges = _SplitEdges(len(vertices))
    test = np.ones(n0, bool)
    for level in range(ADAPT_LEVELS):
        tri = vertices[faces]
        lengths = _edges(tri)
        test &= ~fixed[index] & (lengths.max(axis=1) > size / ADAPT_FINEST)
        # an element is split across its longest edge and its neighbour there takes the midpoint: not
        # when that neighbour is fixed (a lamp, a pane, a clustered triangle stays as it is)
        held = faces[fixed[index]]
        if len(held):
            longest = lengths.argmax(axis=1)
            r = np.arange(len(faces))
            test &= ~np.isin(_key(faces[r, longest], faces[r, (longest + 1) % 3]),
                             _key(held, np.roll(held, -1, axis=1)).ravel())
        rows = np.flatnonzero(test)
        if not len(rows):
            break
        spread, level_of = _spreads(tri[rows], look, two_sided is not None and two_sided[index[rows]], done)
        area = triangle_areas(tri[rows])
        if room is None:
            direct = float((level_of * area).sum() / max(area.sum(), 1e-300))
            room = direct * reflect / max(1.0 - reflect, 1e-3)
            if not direct > 0:
                break
            # An element's shot light is noisy as its light (a patch's variance ~ B / hits, hits ~ area:
            # the area-weighted noise sums B over the unknowns), so a split costs rays in proportion to
            # the light there: the budget is ADAPT_SHARE of the summed light of the elements looked at
            # (the unknowns but for the clusters, which count once, and the lamps: not every element,
            # which a model of many clustered slivers would make many times larger), not of their
            # count; the bright ones near lamps cost the most.
            budget = ADAPT_SHARE * float((level_of + room).sum())
        light = level_of + room
        contrast = np.divide(spread, light, out=np.zeros_like(spread), where=light > 0)
        over = contrast > ADAPT_CONTRAST
        if not over.any() or budget <= 0:
            break
        # the most visible error (area x contrast^2, the picture's squared relative error) per ray first
        first = np.argsort(-(area[over] * contrast[over] ** 2 / light[over]), kind="stable")  # light > 0 there
        cand = rows[over][first]
        cost = 2.0 * light[over][first]  # itself and about one neighbour split to close it
        pick = np.sort(cand[:max(1, int(np.searchsorted(np.cumsum(cost), budget, side="right")))])
        keep = np.ones(len(faces), bool)
        keep[pick] = False
        halves, idx, fresh = edges.bisect(vertices, faces[pick], lengths[pick].argmax(axis=1), index[pick])
        vertices = np.concatenate([vertices, fresh])
        faces, index = _close(np.concatenate([faces[keep], halves]), np.concatenate([index[keep], idx]),
                              edges.keys, edges.mids)
        test = np.asarray((faces >= len(vertices) - len(fresh)).any(axis=1), bool)  # new ones carry a new midpoint
        done["split"] += len(pick)
        done["levels"] = level + 1
        budget -= float(cost[:len(pick)].sum())
    done["added"] = len(faces) - n0
    order = np.argsort(index, kind="stable")
    return vertices, faces[order], index[order], done


def _spreads(tri: np.ndarray, look, back: np.ndarray | bool, done: dict) -> tuple[np.ndarray, np.ndarray]:
    """(spread, mean) of the direct light over the inset corners of (m,3,3) triangles ``tri``, on
    their front and, where ``back``, their back (the larger spread of the two sides)."""
    centre = tri.mean(axis=1, keepdims=True)
    points = (tri + _INSET * (centre - tri)).reshape(-1, 3)
    normal = triangle_normals(tri)
    sides = [(np.arange(len(tri)), 1.0)]
    back = np.flatnonzero(back) if np.ndim(back) else np.zeros(0, np.int64)
    if len(back):
        sides.append((back, -1.0))
    spread = np.zeros(len(tri))
    mean = np.zeros(len(tri))
    for rows, sign in sides:
        at = (3 * rows[:, None] + np.arange(3)).ravel()
        y, rays = look(points[at], np.repeat(sign * normal[rows], 3, axis=0))
        y = np.asarray(y, np.float64).reshape(-1, 3)
        done["points"] += len(at)
        done["rays"] += int(rays)
        s = y.max(axis=1) - y.min(axis=1)
        bigger = s > spread[rows]
        spread[rows] = np.where(bigger, s, spread[rows])
        mean[rows] = np.where(bigger, y.mean(axis=1), mean[rows])
    return spread, mean


def _close(faces: np.ndarray, index: np.ndarray, keys: np.ndarray, mids: np.ndarray):
    """Split every face at the midpoints its neighbours put on its edges (no hanging vertices).

    Without this a triangle next to a bisected one keeps the whole edge while the neighbour's
    pieces meet at its midpoint: in float32 the two sides of the seam differ and a ray can slip
    through the crack (the two-sided Cornell box lost 3e-7 W through its walls)."""
    if not len(keys):
        return faces, index
    for _ in range(64):
        ek = _key(faces, np.roll(faces, -1, axis=1))  # (m, 3): edge k joins corners k and k+1
        pos = np.minimum(np.searchsorted(keys, ek), len(keys) - 1)
        hang = keys[pos] == ek  # (m, 3): this edge has a midpoint
        todo = np.flatnonzero(hang.any(axis=1))
        if not len(todo):
            break
        f = faces[todo]
        k = hang[todo].argmax(axis=1)
        rows = np.arange(len(todo))
        a, b, c = f[rows, k], f[rows, (k + 1) % 3], f[rows, (k + 2) % 3]
        m = mids[pos[todo, k]]
        keep = np.ones(len(faces), bool)
        keep[todo] = False
        faces = np.concatenate([faces[keep], np.stack([a, m, c], axis=1), np.stack([m, b, c], axis=1)])
        index = np.concatenate([index[keep], index[todo], index[todo]])
    return faces, index


def estimate_elements(triangles: np.ndarray, size: float) -> int:
    """About how many elements ``refine`` makes of (n,3,3) ``triangles``, before meshing (the memory
    check): each split halves the area, so a triangle larger than the element becomes about
    2^ceil(log2(area / (AREA_SHARE size^2))) of them; slivers by their length."""
    if len(triangles) == 0 or not size > 0:
        return len(triangles)
    area = triangle_areas(triangles)
    longest = _edges(triangles).max(axis=1)
    by_area = np.where(longest > size, np.ceil(np.log2(np.maximum(area / (AREA_SHARE * size * size), 1.0))), 0)
    by_length = np.ceil(np.log2(np.maximum(longest / (SLIVER_EDGES * size), 1.0)))
    levels = np.minimum(np.maximum(by_area, by_length), 60)
    return int(np.sum(2.0 ** levels))


def mesh_note(size: float, how: str | None, table: list[dict], adapted: dict | None = None) -> str:
    """The report's line on the mesh: the size and how it was chosen (``how`` None: --patch-size),
    the totals of ``mesh_table`` (triangles split into how many elements, kept whole, grouped into
    how many clusters) and what the adaptive refinement did (``adapted``: Patches.adapted)."""
    total = {k: sum(r[k] for r in table) for k in ("triangles", "split", "split_into", "kept_whole", "clustered",
                                                   "clusters", "elements")}
    chosen = how if how is not None else f"element size {size:.4g} m (--patch-size)"
    if adapted is None:
        refined = ("no adaptive refinement (--patch-size: the mesh is the size asked for)" if how is None
                   else "no adaptive refinement (no light to follow)")
    elif adapted.get("skipped"):
        refined = f"no adaptive refinement: {adapted['skipped']}"
    else:
        refined = (f"adaptive refinement: {adapted['split']} elements split where the direct light varies across "
                   f"them (shadow edges, near lamps) in {adapted['levels']} round(s), {adapted['added']} elements "
                   f"added ({adapted['points']} points looked at with {adapted['rays']} shadow rays; mesh.adapt; "
                   "its seconds are report.json's mesh.refined)")
    return (f"mesh: {chosen}; {total['triangles']} input triangles -> {total['elements']} elements: "
            f"{total['split']} split into {total['split_into']}, {total['kept_whole']} kept whole, of which "
            f"{total['clustered']} grouped into {total['clusters']} clusters that share one B (small neighbours "
            f"of one surface facing alike); {total['elements'] - total['clustered']} elements alone; {refined}")


def _lamp_cells(triangles: np.ndarray, size: float) -> np.ndarray:
    """(k, 3) cells of the element grid within one cell of a point of the emitting ``triangles``
    (corners and a barycentric grid at the element size over each)."""
    if not len(triangles):
        return np.zeros((0, 3), np.int64)
    longest = _edges(triangles).max(axis=1)
    pts = [triangles.reshape(-1, 3)]
    for steps in np.unique(np.minimum(np.ceil(longest / size), 64).astype(np.int64)):
        sel = triangles[np.ceil(np.minimum(longest / size, 64)).astype(np.int64) == steps]
        i, j = np.meshgrid(np.arange(steps + 1), np.arange(steps + 1), indexing="ij")
        keep = i + j <= steps
        u, v = i[keep] / max(steps, 1), j[keep] / max(steps, 1)
        pts.append((sel[:, None, 0] + u[None, :, None] * (sel[:, None, 1] - sel[:, None, 0])
                    + v[None, :, None] * (sel[:, None, 2] - sel[:, None, 0])).reshape(-1, 3))
    cells = np.unique(np.floor(np.concatenate(pts) / size).astype(np.int64), axis=0)
    near = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    return np.unique((cells[:, None, :] + near[None]).reshape(-1, 3), axis=0)


def near_lamps(cells: np.ndarray, lamps: np.ndarray, size: float) -> np.ndarray:
    """(k,) bool: which of the element-grid ``cells`` (k,3) (floor(point / size)) lie within a cell
    of the emitting triangles ``lamps`` (m,3,3): where the light varies fastest (``clusters`` groups
    nothing there; bench/bench_adapt.py leaves fixtures out by it)."""
    lit = _lamp_cells(lamps, size)
    _, inv = np.unique(np.concatenate([lit, cells]), axis=0, return_inverse=True)
    inv = inv.ravel()
    return np.isin(inv[len(lit):], inv[:len(lit)])


def clusters(triangles: np.ndarray, obj: np.ndarray, whole: np.ndarray, size: float,
             emits: np.ndarray | None = None) -> np.ndarray:
    """(T,) i8: the cluster of each input triangle that ``refine`` kept whole, -1 for the rest.

    Small triangles of one object and material (``obj``), facing alike (their normals in one of 26
    directions: the cube's faces, edges and corners, about 27 degrees either way) and whose
    centroids fall in one cell of the element size share a cluster: a chair's ten thousand slivers
    become a few elements, as hierarchical radiosity groups them.  A cluster of one is none.
    Nothing near a lamp is grouped (``emits`` (T,) bool: the emitting triangles; within a cell of
    one), nor the lamps themselves: there the light varies fastest, and the small bright
    reflectors of a fixture differ two-fold (office2's lamp trough: pooled, 7% of the reflected
    light's RMS per input triangle).
    Their B is the cluster's (Patches.pool), and the ray density and the error estimate count one
    unknown per cluster (Patches.units, Patches.reads)."""
    out = np.full(len(triangles), -1, np.int64)
    rows = np.flatnonzero(whole)
    if not len(rows) or not size > 0:
        return out
    tri = triangles[rows]
    n = triangle_normals(tri)
    biggest = np.maximum(np.abs(n).max(axis=1, keepdims=True), 1e-300)
    direction = np.rint(n / biggest * 0.99).astype(np.int64) + 1  # each axis -1, 0, 1 -> 0..2
    cell = np.floor(tri.mean(axis=1) / size).astype(np.int64)
    key = np.concatenate([obj[rows, None].astype(np.int64), cell, direction], axis=1)
    _, group, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    group = group.ravel()
    shared = count[group] > 1
    if emits is not None and emits.any():
        shared &= ~emits[rows]
        shared &= ~near_lamps(cell, triangles[emits], size)
    _, out[rows[shared]] = np.unique(group[shared], return_inverse=True)
    return out


def mesh_table(names: list, obj: np.ndarray, source: np.ndarray, cluster: np.ndarray, n_input: int,
               extra: np.ndarray | None = None) -> list[dict]:
    """Per object (report.json's ``mesh.objects``): its input triangles, how many were split and
    into how many elements, how many were kept whole and into how many clusters those were grouped,
    and how many elements the adaptive refinement added (``extra``: per input triangle, Patches.adapted).
    ``obj``/``source``/``cluster``: the front patches' (a cluster lies in one object)."""
    k = max(len(names), int(obj.max()) + 1 if len(obj) else 0)
    pieces = np.bincount(source, minlength=n_input)
    first = np.zeros(n_input, np.int64)
    first[source[::-1]] = obj[::-1]  # each input triangle's object, from one of its patches
    seen = pieces > 0

    def per_obj(where: np.ndarray, of: np.ndarray, weights=None) -> np.ndarray:
        return np.bincount(of[where], weights=None if weights is None else weights[where], minlength=k)

    split = per_obj(seen & (pieces > 1), first)
    grouped = cluster >= 0
    ids = np.unique(cluster[grouped])
    c_obj = np.zeros(len(ids), np.int64)
    c_obj[np.searchsorted(ids, cluster[grouped])] = obj[grouped]
    columns = {"triangles": per_obj(seen, first), "split": split,
               "split_into": per_obj(seen & (pieces > 1), first, pieces.astype(np.float64)),
               "elements": np.bincount(obj, minlength=k), "kept_whole": per_obj(seen & (pieces == 1), first),
               "clustered": np.bincount(obj[grouped], minlength=k), "clusters": np.bincount(c_obj, minlength=k),
               "refined": per_obj(seen, first, None if extra is None else np.asarray(extra, np.float64))
               if extra is not None else np.zeros(k, np.int64)}
    rows = [{"name": names[int(o)], **{key: int(col[o]) for key, col in columns.items()}}
            for o in np.flatnonzero(columns["elements"])]
    return sorted(rows, key=lambda r: -r["elements"])
