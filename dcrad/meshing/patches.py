"""Structure-of-arrays patch table: the one data structure the solver walks.

A patch is a triangle after meshing.  Every per-patch quantity is a row of an
array; derived geometry (area, normal, centroid) is computed once and cached.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from dcrad.estimate.noise import SHOWN_SLACK
from dcrad.transport.optics import Glazing

__all__ = ["Patches", "triangle_areas", "triangle_normals", "subdivide", "remap_twin"]


def triangle_areas(tri: np.ndarray) -> np.ndarray:
    """tri : (n, 3, 3) float -> (n,) float64 areas."""
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return 0.5 * np.sqrt(np.einsum("ij,ij->i", cross, cross))


def triangle_normals(tri: np.ndarray) -> np.ndarray:
    """tri : (n, 3, 3) float -> (n, 3) unit normals (right-hand rule); zero rows stay zero."""
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.sqrt(np.einsum("ij,ij->i", cross, cross))
    out = np.zeros_like(cross)
    ok = norm > 0
    out[ok] = cross[ok] / norm[ok, None]
    return out


def remap_twin(twin: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """Twins of a table whose row i came from row ``parent[i]`` of one with ``twin``.

    Row i gets the first row whose parent is ``twin[parent[i]]`` (-1 if none): exact
    for rows copied whole, the same surface nearby for clipped pieces.
    """
    parent = np.asarray(parent, np.int64)
    if not len(parent):
        return np.zeros(0, np.int64)
    tp = twin[parent]
    order = np.argsort(parent, kind="stable")
    sorted_parent = parent[order]
    pos = np.minimum(np.searchsorted(sorted_parent, tp), len(parent) - 1)
    ok = (tp >= 0) & (sorted_parent[pos] == tp)
    return np.where(ok, order[pos], -1).astype(np.int64)


def subdivide(vertices: np.ndarray, faces: np.ndarray, max_edge: float):
    """Split triangles until no edge is longer than ``max_edge``.

    Returns ``(vertices (V,3) float64, faces (n,3) int64, index (n,) int64)``
    where ``index`` maps each new face to the face it came from.  Uses
    trimesh's midpoint subdivision, which keeps shared edges watertight.
    """
    import trimesh.remesh  # noqa: PLC0415  lazy: `dcrad jobs/watch` imports this module; trimesh costs 0.5 s

    if max_edge is None or max_edge <= 0 or len(faces) == 0:
        return vertices, faces, np.arange(len(faces), dtype=np.int64)
    v, f, idx = trimesh.remesh.subdivide_to_size(
        vertices, faces, max_edge=float(max_edge), max_iter=64, return_index=True
    )
    return np.asarray(v, np.float64), np.asarray(f, np.int64), np.asarray(idx, np.int64)


@dataclass
class Patches:
    """The patch table.

    ==========  ==========  ===================================================
    field       shape       meaning (units)
    ==========  ==========  ===================================================
    vertices    (V, 3) f8   mesh vertices (m)
    faces       (n, 3) i8   vertex indices of each patch, counter-clockwise
                            seen from the front (normal side)
    rho         (n, 3) f8   diffuse reflectance per RGB channel, in [0, 1)
    emission    (n, 3) f8   emitted exitance E (W/m^2)
    source      (n,)   i8   index of the input triangle this patch came from
    obj         (n,)   i4   index into ``names`` (object / material of origin)
    names       list[str]   object names, for messages and reports
    radiosity   (n, 3) f8   B (W/m^2), starts at E
    unshot      (n, 3) f8   dB (W/m^2), radiosity not yet shot, starts at E
    twin        (n,)   i8   two-sided surfaces: the patch on the other side of
                            the same triangle (reversed winding, listed after
                            the front ones); -1 for one-sided patches.  A ray
                            that hits a patch from behind lands on its twin
                            (shoot.trace)
    cluster     (n,)   i8   small neighbours of one surface that share one B
                            (mesh.clusters: their irradiance is pooled when
                            read, ``pool``); -1 for a patch that stands alone
    glazing     Glazing     panes: which patches transmit, tau_n, index
                            (optics.py); None without glass
    ==========  ==========  ===================================================
    """

    vertices: np.ndarray
    faces: np.ndarray
    rho: np.ndarray
    emission: np.ndarray
    source: np.ndarray
    obj: np.ndarray
    names: list = field(default_factory=list)
    # None (the default) is filled in by __post_init__: the attributes are always arrays
    radiosity: np.ndarray = None  # type: ignore[assignment]
    unshot: np.ndarray = None  # type: ignore[assignment]
    twin: np.ndarray = None  # type: ignore[assignment]
    cluster: np.ndarray = None  # type: ignore[assignment]
    #: light sources that are not patches (emitters.Emitter: point lights, luminaires); one process only
    sources: tuple = ()
    #: the panes among the patches (optics.Glazing: ideal specular transmitters, the seed's eq. 1.2);
    #: None: no glass.  On every path: it travels in ``table_arrays`` to workers, and clipping
    #: (partition.clip) hands each piece its parent's
    glazing: Glazing | None = None
    #: what the mesh's adaptive refinement did (mesh.adapt's dict and its ``seconds``); None: not run
    adapted: dict | None = None

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, np.float64)
        self.faces = np.ascontiguousarray(self.faces, np.int64)
        n = len(self.faces)
        self.rho = np.ascontiguousarray(np.broadcast_to(self.rho, (n, 3)), np.float64)
        self.emission = np.ascontiguousarray(np.broadcast_to(self.emission, (n, 3)), np.float64)
        self.source = np.ascontiguousarray(self.source, np.int64)
        self.obj = np.ascontiguousarray(self.obj, np.int32)
        if self.radiosity is None:
            self.radiosity = self.emission.copy()
        if self.unshot is None:
            self.unshot = self.emission.copy()
        self.twin = np.full(n, -1, np.int64) if self.twin is None else np.ascontiguousarray(self.twin, np.int64)
        self.cluster = (np.full(n, -1, np.int64) if self.cluster is None
                        else np.ascontiguousarray(self.cluster, np.int64))
        self.sources = tuple(self.sources)

    # -- as arrays (a worker's copy) ---------------------------------------------------
    def table_arrays(self) -> dict:
        """The table's own arrays (not B or dB): what ``from_table`` rebuilds it from (its panes too)."""
        out = {"vertices": self.vertices, "faces": self.faces, "rho": self.rho, "emission": self.emission,
               "source": self.source, "obj": self.obj, "twin": self.twin, "cluster": self.cluster}
        if self.glazing is not None:
            out |= {"glazing_mask": self.glazing.mask, "glazing_tau": self.glazing.tau_n,
                    "glazing_ior": self.glazing.ior}
        return out

    @classmethod
    def from_table(cls, arrays: dict, names: list, radiosity: np.ndarray | None = None,
                   unshot: np.ndarray | None = None) -> "Patches":
        """The table of ``table_arrays`` (``twin``, ``cluster`` optional), B and dB given or starting at E."""
        given: dict = {"radiosity": radiosity, "unshot": unshot, "twin": arrays.get("twin"),
                       "cluster": arrays.get("cluster")}
        out = cls(arrays["vertices"], arrays["faces"], arrays["rho"], arrays["emission"], arrays["source"],
                  arrays["obj"], list(names), **{k: v for k, v in given.items() if v is not None})
        if arrays.get("glazing_mask") is not None:
            out.glazing = Glazing(arrays["glazing_mask"], arrays["glazing_tau"], arrays["glazing_ior"])
        return out

    # -- derived geometry (cached) -------------------------------------------------
    def __len__(self) -> int:
        return len(self.faces)

    @cached_property
    def triangles(self) -> np.ndarray:
        """(n, 3, 3) float64 corner positions."""
        return self.vertices[self.faces]

    def corners(self, index=None) -> np.ndarray:
        """(k, 3, 3) float64 corner positions of the rows ``index`` (an index array, mask or
        slice; None: all): the cached ``triangles`` when it is there, else gathered from
        ``vertices`` and ``faces`` without caching them (the same numbers)."""
        cached = self.__dict__.get("triangles")
        if index is None:
            return cached if cached is not None else self.vertices[self.faces]
        return cached[index] if cached is not None else self.vertices[self.faces[index]]

    def release_corners(self) -> None:
        """Forget the cached ``triangles`` (72 bytes a patch: 87 MB at 1.27M patches) once
        the geometry derived from it is cached; ``triangles`` is rebuilt if read again.
        The outputs call this: they read corners a view or a chunk at a time (``corners``)."""
        for derived in ("area", "normal", "centroid", "bounds"):
            getattr(self, derived)
        self.__dict__.pop("triangles", None)

    @cached_property
    def area(self) -> np.ndarray:
        """(n,) float64 patch areas (m^2)."""
        return triangle_areas(self.triangles)

    @cached_property
    def total_area(self) -> float:
        """Sum of the patch areas (m^2)."""
        return float(self.area.sum())

    @cached_property
    def mean_rho(self) -> np.ndarray:
        """(3,) area-weighted mean reflectance (zeros for an empty table)."""
        if self.total_area <= 0:
            return np.zeros(3)
        return (self.rho * self.area[:, None]).sum(axis=0) / self.total_area

    @cached_property
    def normal(self) -> np.ndarray:
        """(n, 3) float64 unit front normals."""
        return triangle_normals(self.triangles)

    @cached_property
    def centroid(self) -> np.ndarray:
        """(n, 3) float64 centroids."""
        return self.triangles.mean(axis=1)

    @cached_property
    def scratch(self) -> np.ndarray:
        """(n,) int32 workspace for ``shoot.compact`` (no meaning between calls; 4 bytes a patch)."""
        return np.zeros(len(self.faces), np.int32)

    @cached_property
    def n_objects(self) -> int:
        """Number of object ids in use (at least 1): the length of per-object tallies."""
        return max(len(self.names), int(self.obj.max(initial=-1)) + 1, 1)

    @cached_property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64 axis-aligned box of the vertices used."""
        if len(self.faces):  # a mask, not np.unique: 1.0 s at 1.27M patches for the same set
            mask = np.zeros(len(self.vertices), bool)
            mask[self.faces.ravel()] = True
            used = self.vertices[mask]
        else:
            used = np.zeros((1, 3))
        return np.stack([used.min(axis=0), used.max(axis=0)])

    @cached_property
    def scale(self) -> float:
        """Length of the box diagonal (m); at least a tiny positive number."""
        return max(float(np.linalg.norm(self.bounds[1] - self.bounds[0])), 1e-30)

    # -- power bookkeeping -----------------------------------------------------------
    def power(self, exitance: np.ndarray) -> np.ndarray:
        """(n, 3) power (W) of a per-patch exitance array."""
        return exitance * self.area[:, None]

    @property
    def emitted_power(self) -> np.ndarray:
        """(3,) total emitted power (W)."""
        return self.power(self.emission).sum(axis=0)

    @property
    def unshot_power(self) -> np.ndarray:
        """(3,) total unshot power (W)."""
        return self.power(self.unshot).sum(axis=0)

    def reset(self) -> None:
        """Start over: B = dB = E, and the clusters as meshed (a run's settling undoes some, on its
        own noise: the next run on the table, a pass or a replica in this process, starts from the
        mesh, as a worker's copy of the table does)."""
        self.radiosity = self.emission.copy()
        self.unshot = self.emission.copy()
        self.restore_clusters()

    def restore_clusters(self) -> None:
        """The clusters as meshed again, whatever a settling undid (``undo_clusters``)."""
        meshed = self.__dict__.get("_meshed_cluster")
        if meshed is not None:
            self.cluster[:] = meshed

    def undo_clusters(self, rows: np.ndarray) -> None:
        """Rows whose cluster a settling undid stand alone (``reset`` puts them back)."""
        if "_meshed_cluster" not in self.__dict__:
            self.__dict__["_meshed_cluster"] = self.cluster.copy()
        self.cluster[rows] = -1

    def subset(self, index: np.ndarray) -> "Patches":
        """A new table with the rows ``index`` (vertices are shared, not copied)."""
        index = np.asarray(index)
        return Patches(
            vertices=self.vertices,
            faces=self.faces[index],
            rho=self.rho[index],
            emission=self.emission[index],
            source=self.source[index],
            obj=self.obj[index],
            names=self.names,
            radiosity=self.radiosity[index].copy(),
            unshot=self.unshot[index].copy(),
            twin=remap_twin(self.twin, np.arange(len(self))[index]),
            cluster=self.cluster[index],
        )

    @property
    def units(self) -> int:
        """The solver's unknowns: patches that stand alone, and one per cluster (what the ray
        density follows, accuracy.rays_for), of those that reflect: a black patch's B is its E
        whatever lands on it (the ice-cream store's 42,856 black patches, panes most of them, are
        no unknowns).  At least 1."""
        reflects = self.rho.any(axis=1)
        alone = int((reflects & (self.cluster < 0)).sum())
        pooled = self.cluster[reflects & (self.cluster >= 0)]
        return max(alone + (len(np.unique(pooled)) if len(pooled) else 0), 1)

    @property
    def read_units(self) -> int:
        """The unknowns as the accuracy target reads them (noise.py, "Which B"): B per input triangle
        side, the elements held within ``SHOWN_SLACK`` of it; the ray density follows these
        (accuracy.rays_for).  A wall of two triangles meshed into 800 elements is two units where
        its elements' noise averages, 800 / SHOWN_SLACK^2 where the elements bind.  At least 1."""
        reflects = self.rho.any(axis=1)
        triangles = len(np.unique(self.reads(per_triangle=True)[reflects])) if reflects.any() else 0
        return max(triangles, math.ceil(self.units / SHOWN_SLACK ** 2), 1)

    def reads(self, per_triangle: bool = False) -> np.ndarray:
        """(n,) i8: the unit each patch's B is read in: its cluster, else the patch itself (an
        element); ``per_triangle``: else its input triangle's side (radiosity.npz's B and B_back)."""
        own = 2 * self.source + self.is_back if per_triangle else np.arange(len(self), dtype=np.int64)
        base = int(own.max()) + 1 if len(own) else 0
        return np.where(self.cluster >= 0, base + self.cluster, own)

    def pool(self) -> None:
        """Clustered patches share one B: the cluster's irradiance, sum A (B - E) / sum A rho per
        channel (the reflected power is kept exactly), times each patch's rho, plus its E."""
        rows = np.flatnonzero(self.cluster >= 0)
        if not len(rows):
            return
        _, c = np.unique(self.cluster[rows], return_inverse=True)
        a = self.area[rows]
        b = self.radiosity[rows]
        e = self.emission[rows]
        rho = self.rho[rows]
        for ch in range(3):
            refl = np.bincount(c, weights=a * (b[:, ch] - e[:, ch]))
            cap = np.bincount(c, weights=a * rho[:, ch])
            h = np.divide(refl, cap, out=np.zeros_like(refl), where=cap > 0)
            self.radiosity[rows, ch] = np.where(cap[c] > 0, e[:, ch] + rho[:, ch] * h[c], b[:, ch])

    @cached_property
    def is_back(self) -> np.ndarray:
        """(n,) bool: the back side of a two-sided triangle (the later of two twins)."""
        return (self.twin >= 0) & (np.arange(len(self)) > self.twin)

    @cached_property
    def two_sided(self) -> bool:
        """True when some patch has a twin (its other side): shoot.trace then maps back hits."""
        return bool((self.twin >= 0).any())

    @property
    def is_grey(self) -> bool:
        """True when every rho and E has equal channels and every light source emits equal power in
        each and every pane passes equal shares (one channel would do: a red light in a grey room
        lights the red channel only)."""
        return bool(
            np.all(self.rho == self.rho[:, :1]) and np.all(self.emission == self.emission[:, :1])
            and all(np.all(p == p[0]) for p in (np.asarray(s.power(), np.float64) for s in self.sources))
            and (self.glazing is None or bool(np.all(self.glazing.tau_n == self.glazing.tau_n[:, :1])))
        )
