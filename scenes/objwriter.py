"""Tiny Wavefront OBJ + MTL writer shared by the built-in scene generators.

Conventions (shared by every generator in :mod:`scenes`):

* units are metres, +Y is up;
* triangles only (``f a b c``, 1-based indices), counter-clockwise seen from
  the FRONT side, so the right-hand normal ``(v1 - v0) x (v2 - v0)`` points
  to where light is received / emitted;
* MTL ``Kd r g b`` is the diffuse reflectance (each channel in ``[0, 1)``),
  ``Ke r g b`` the emitted exitance in W/m^2 (written for emitters only);
* the OBJ starts with ``mtllib <stem>.mtl`` (bare file name, same folder), each
  object is ``o NAME`` + ``usemtl MATERIAL`` + its faces; names are unique.

Zero-area triangles are rejected at insertion time, so a generator cannot
silently emit degenerate geometry.  Output is deterministic: the same calls
give byte-identical files.
"""

from __future__ import annotations

import math
import pathlib
from dataclasses import dataclass, field

import numpy as np

__all__ = ["ObjWriter", "BOX_FACES", "rgb"]

#: Face keys accepted by :meth:`ObjWriter.add_box` ``skip_faces``.
#: ``-y``/``bottom`` and ``+y``/``top`` are synonyms.
BOX_FACES = ("-x", "+x", "-y", "+y", "-z", "+z")
_ALIASES = {"bottom": "-y", "top": "+y"}
_AREA_EPS = 1e-12  # m^2; triangles smaller than this are refused


def _cross(u, v) -> tuple[float, float, float]:
    """u x v of two 3-vectors (np.cross costs 60 us a call: most of writing the 8x8 office)."""
    return (float(u[1] * v[2] - u[2] * v[1]), float(u[2] * v[0] - u[0] * v[2]), float(u[0] * v[1] - u[1] * v[0]))


def rgb(value) -> tuple[float, float, float]:
    """Scalar or 3-sequence -> tuple of three floats."""
    arr = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,))
    return (float(arr[0]), float(arr[1]), float(arr[2]))


def _fmt(x: float) -> str:
    """Shortest round-trip text for a float, rounded to 1e-12 (snaps float noise) and without ``-0.0``."""
    return repr(round(float(x), 12) + 0.0)


@dataclass
class _Object:
    name: str
    material: str
    vertices: list = field(default_factory=list)  # list of (x, y, z) tuples
    index: dict = field(default_factory=dict)  # rounded vertex -> local index
    faces: list = field(default_factory=list)  # list of (a, b, c) local indices


class ObjWriter:
    """Collects materials and named objects, then writes ``<stem>.obj/.mtl``.

    Typical use::

        w = ObjWriter()
        w.material("white", kd=0.73)
        w.begin("floor", "white")
        w.add_quad((0, 0, 0), (0, 0, 1), (1, 0, 1), (1, 0, 0))   # faces +y
        w.write(folder, "scene")
    """

    def __init__(self) -> None:
        self.materials: dict[str, tuple[tuple, tuple | None]] = {}
        self.objects: list[_Object] = []
        self._names: set[str] = set()

    # -- materials / objects ---------------------------------------------------------
    def material(self, name: str, kd, ke=None) -> str:
        """Declare material ``name`` with reflectance ``kd`` (scalar or RGB, each in
        [0, 1)) and optional exitance ``ke`` (W/m^2, scalar or RGB, >= 0)."""
        kd3 = rgb(kd)
        if not all(0.0 <= c < 1.0 for c in kd3):
            raise ValueError(f"material {name!r}: Kd {kd3} must be in [0, 1)")
        ke3 = None
        if ke is not None:
            ke3 = rgb(ke)
            if not all(c >= 0.0 and np.isfinite(c) for c in ke3):
                raise ValueError(f"material {name!r}: Ke {ke3} must be finite and >= 0")
        if name in self.materials and self.materials[name] != (kd3, ke3):
            raise ValueError(f"material {name!r} redefined differently")
        self.materials[name] = (kd3, ke3)
        return name

    def begin(self, name: str, material: str) -> None:
        """Start a new object; following ``add_*`` calls go into it."""
        if name in self._names:
            raise ValueError(f"duplicate object name {name!r}")
        if material not in self.materials:
            raise ValueError(f"object {name!r}: unknown material {material!r}")
        if not name or any(c.isspace() for c in name):
            raise ValueError(f"bad object name {name!r}")
        self._names.add(name)
        self.objects.append(_Object(name, material))

    # -- geometry --------------------------------------------------------------------
    def _vertex(self, p) -> int:
        obj = self.objects[-1]
        key = tuple(round(float(c), 12) + 0.0 for c in p)
        idx = obj.index.get(key)
        if idx is None:
            idx = obj.index[key] = len(obj.vertices)
            obj.vertices.append(key)
        return idx

    def add_tri(self, p0, p1, p2) -> None:
        """Add one triangle, counter-clockwise seen from its front side."""
        if not self.objects:
            raise RuntimeError("call begin() before adding geometry")
        a, b, c = (np.asarray(p, np.float64) for p in (p0, p1, p2))
        n = _cross(b - a, c - a)
        if 0.5 * math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]) <= _AREA_EPS:
            raise ValueError(f"zero-area triangle in {self.objects[-1].name!r}: {p0} {p1} {p2}")
        self.objects[-1].faces.append((self._vertex(a), self._vertex(b), self._vertex(c)))

    def add_quad(self, p0, p1, p2, p3, *, facing=None) -> None:
        """Add the quad p0-p1-p2-p3 (counter-clockwise from the front) as the
        triangles (p0, p1, p2) and (p0, p2, p3).

        If ``facing`` (a direction) is given, the winding is reversed when the
        quad's normal points away from it, so callers need not care about order.
        """
        pts = [np.asarray(p, np.float64) for p in (p0, p1, p2, p3)]
        if facing is not None:
            n = _cross(pts[2] - pts[0], pts[3] - pts[1])
            if n[0] * facing[0] + n[1] * facing[1] + n[2] * facing[2] < 0.0:
                pts = pts[::-1]
        self.add_tri(pts[0], pts[1], pts[2])
        self.add_tri(pts[0], pts[2], pts[3])

    def add_rect(self, axis: int, value: float, lo, hi, facing: int) -> None:
        """Axis-aligned rectangle in the plane ``coord[axis] == value``.

        ``lo``/``hi`` are the two remaining coordinates' bounds, in increasing axis
        order (e.g. for axis=1: (x, z)).  ``facing`` is +1 or -1: the side along
        ``axis`` that the front normal points to.
        """
        u, v = [k for k in range(3) if k != axis]
        corners = []
        for cu, cv in ((lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])):
            p = [0.0, 0.0, 0.0]
            p[axis], p[u], p[v] = value, cu, cv
            corners.append(p)
        normal = [0.0, 0.0, 0.0]
        normal[axis] = float(facing)
        self.add_quad(*corners, facing=normal)

    def add_box(self, lo, hi, outward: bool = True, skip_faces=()) -> None:
        """Axis-aligned box ``lo``..``hi`` (m) with normals outward (solid object)
        or inward (room / enclosure).  ``skip_faces`` names faces to omit, from
        :data:`BOX_FACES` (``"bottom"``/``"top"`` accepted for ``-y``/``+y``)."""
        lo = np.asarray(lo, np.float64)
        hi = np.asarray(hi, np.float64)
        if np.any(hi <= lo):
            raise ValueError(f"empty box {lo} .. {hi}")
        skip = {_ALIASES.get(s, s) for s in skip_faces}
        bad = skip - set(BOX_FACES)
        if bad:
            raise ValueError(f"unknown box faces {sorted(bad)}; use {BOX_FACES}")
        sign = 1 if outward else -1
        for axis in range(3):
            u, v = [k for k in range(3) if k != axis]
            for side, key in ((-1, "-"), (1, "+")):
                if key + "xyz"[axis] in skip:
                    continue
                value = lo[axis] if side < 0 else hi[axis]
                self.add_rect(axis, value, (lo[u], lo[v]), (hi[u], hi[v]), side * sign)

    # -- output ----------------------------------------------------------------------
    @property
    def triangle_count(self) -> int:
        return sum(len(o.faces) for o in self.objects)

    def write(self, folder, stem: str) -> pathlib.Path:
        """Write ``<folder>/<stem>.obj`` and ``.mtl`` (folder created); return the OBJ path."""
        folder = pathlib.Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        mtl = [f"# {stem}.mtl: Kd = diffuse reflectance, Ke = emitted exitance (W/m^2)"]
        for name, (kd, ke) in self.materials.items():
            mtl.append(f"newmtl {name}")
            mtl.append("Kd " + " ".join(_fmt(c) for c in kd))
            if ke is not None and any(ke):
                mtl.append("Ke " + " ".join(_fmt(c) for c in ke))
            mtl.append("")
        obj = [f"mtllib {stem}.mtl", f"# {stem}: metres, +Y up, CCW front faces"]
        base = 1
        for o in self.objects:
            if not o.faces:
                raise ValueError(f"object {o.name!r} has no faces")
            obj.append(f"o {o.name}")
            obj.extend("v " + " ".join(_fmt(c) for c in p) for p in o.vertices)
            obj.append(f"usemtl {o.material}")
            obj.extend(f"f {a + base} {b + base} {c + base}" for a, b, c in o.faces)
            base += len(o.vertices)
        (folder / f"{stem}.mtl").write_text("\n".join(mtl) + "\n", encoding="ascii")
        path = folder / f"{stem}.obj"
        path.write_text("\n".join(obj) + "\n", encoding="ascii")
        return path
