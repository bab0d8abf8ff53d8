"""Daylight: the sky, the sun and the ground outside the model, as light sources (emitters.py).

**The sky** is a luminance over the upper hemisphere of directions, normalised to its horizontal
diffuse illuminance E_hz (``--sky-illuminance``, 10,000 lx by default): E_hz = integral of L cos
theta over the hemisphere, theta from the zenith.  The distributions:

* ``uniform``: L the same everywhere, E_hz / pi;
* ``cie-overcast``: the CIE traditional overcast sky (Moon and Spencer), L = Lz (1 + 2 cos theta) / 3,
  Lz = 9 E_hz / (7 pi); Radiance's ``gensky -c``;
* ``iso:1`` to ``iso:15``: the CIE standard general skies (ISO 15469:2004 / CIE S 011/E:2003),
  L / Lz = phi(theta) f(chi) / (phi(0) f(Z_s)), with the gradation phi(theta) = 1 + a exp(b / cos theta)
  and the indicatrix f(chi) = 1 + c (exp(d chi) - exp(d pi / 2)) + e cos^2 chi, chi the angle to the
  sun and Z_s the sun's zenith angle; ``ISO_SKIES`` gives (a, b, c, d, e) of the fifteen types;
* ``clear``: type 12, the CIE standard clear sky (Radiance's ``gensky +s`` is its formula), with the sun.

**The ground** outside is an infinite plane of reflectance rho_g (``--ground-reflectance``, 0.2)
lit by the unobstructed sky and sun: every direction below the horizon sees its luminance
rho_g (E_hz + E_sun sin alpha) / pi, as Radiance's ground glow.  (The model's own ground, if it has
one, is a surface like any other and hides this one where it lies.)

**The sun** is a parallel beam of direct normal illuminance E_sun (``--sun-illuminance``) from
altitude alpha and azimuth (compass degrees from north, clockwise: east 90), given or computed
from a site, a date and a time (astral, NOAA's solar equations).

How they light the model.  The sky's direct light is an integral over the openings a point sees,
so it has no exact gather: every receiver gathers it (``patch_gather``, DirectPhase.gather_sampled)
with rays from all over it in two independent halves (its noise is in the estimate), half of them
cosine-distributed and half aimed at the openings, which a pilot learns (``Portals``: where the
rays that leave the model cross its bounding box), weighed by both densities (the balance
heuristic).  The books hold the light that lands as the sky's emitted power.  Black surfaces and
the work plane read it with the same estimator at points (``irradiance``, seeded by the run,
``attune``).  With ``--no-direct`` it is shot instead (``rays``): from the bounding box's faces,
face and direction drawn by the flux through each (a table of ``GRID`` equal solid angles); rays
that meet the model's outside are booked there, and most of a small opening's rays are.  The
sun's direct light is exact (a shadow ray a point, through panes times tau), gathered like a
luminaire's.

Frames: dcrad is Y-up inside.  East is the input file's +X (its +Y when the file is X-up) and north
is up x east: for a Z-up file +Y, for a Y-up file -Z, the architectural conventions (Radiance: +X
east, +Y north, +Z up).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import math
from dataclasses import dataclass, field

import numpy as np

from dcrad.errors import ConfigError
from dcrad.estimate.noise import half_mask
from dcrad.outputs.photometry import EFFICACY
from dcrad.transport.emitters import half_weights, visibility
from dcrad.transport.rays import MISS
from dcrad.transport.sampling import cosine_hemisphere, lattice, onb, triangle_points
from dcrad.transport.shoot import RayBatch

__all__ = ["ISO_SKIES", "SKY_NAMES", "SkyModel", "Sky", "Sun", "sun_position", "sun_direction", "frame",
           "daylight_sources", "parse_sky", "RAYS_PER_POINT", "GRID"]

#: (a, b, c, d, e) of the fifteen CIE standard general skies (ISO 15469:2004, CIE S 011/E:2003):
#: six gradations (a, b) and six indicatrices (c, d, e), paired as the standard's table pairs them
_GRADATION = {1: (4.0, -0.70), 2: (1.1, -0.8), 3: (0.0, -1.0), 4: (-1.0, -0.55), 5: (-1.0, -0.32), 6: (-1.0, -0.15)}
_INDICATRIX = {1: (0.0, -1.0, 0.0), 2: (2.0, -1.5, 0.15), 3: (5.0, -2.5, 0.30), 4: (10.0, -3.0, 0.45),
               5: (16.0, -3.0, 0.30), 6: (24.0, -2.8, 0.15)}
_TYPES = {1: (1, 1), 2: (1, 2), 3: (2, 1), 4: (2, 2), 5: (3, 1), 6: (3, 2), 7: (3, 3), 8: (3, 4), 9: (4, 2),
          10: (4, 3), 11: (4, 4), 12: (5, 4), 13: (5, 5), 14: (6, 5), 15: (6, 6)}
ISO_SKIES = {t: _GRADATION[g] + _INDICATRIX[i] for t, (g, i) in _TYPES.items()}
SKY_NAMES = ("uniform", "cie-overcast", "clear", *(f"iso:{t}" for t in ISO_SKIES))

#: the sky's table of directions: GRID[0] bands equal in cos theta over the sphere x GRID[1] in
#: azimuth, all of equal solid angle (Archimedes); the power, the rays' directions and the
#: normalisation read it (the quadrature of the circumsolar peak of type 15 is within 1e-5 at this size)
GRID = (512, 1024)
#: rays a point reads the sky's direct light with (black surfaces, the work plane): RAYS_BUDGET over the
#: points, within RAYS_PER_POINT (at 4,096 a point under a small roof opening reads within 2% of the
#: closed form, at 16,384 within 0.5%: bench_daylight.py); the floor keeps a model's many black patches
#: (a lamp's housing, 35k pane patches) from tracing a thousand rays each
RAYS_BUDGET = 1 << 23
RAYS_PER_POINT = (64, 16384)
#: the accuracy at which the point estimator spends RAYS_BUDGET (``Sky.attune``)
REFERENCE_ACCURACY = 0.02
#: direct normal illuminance of ``--sky clear``'s sun when none is given, lux (a clear day's sun at
#: mid altitudes: 70-100 klx)
CLEAR_SUN_LUX = 80_000.0
#: the portal map's pilot is seeded alike in every run: the same scene learns the same map
PILOT_SEED = 20061


def _indicatrix(chi: np.ndarray, c: float, d: float, e: float) -> np.ndarray:
    return 1.0 + c * (np.exp(d * chi) - math.exp(d * math.pi / 2.0)) + e * np.cos(chi) ** 2


def _gradation(cos_t: np.ndarray, a: float, b: float) -> np.ndarray:
    with np.errstate(divide="ignore", over="ignore"):
        return 1.0 + a * np.exp(b / np.maximum(cos_t, 1e-300))


def parse_sky(name: str) -> str:
    """The sky's canonical name; ConfigError naming the choices for an unknown one."""
    key = str(name).strip().lower()
    if key.startswith("iso:") and key[4:].isdigit():
        key = f"iso:{int(key[4:])}"
    if key not in SKY_NAMES:
        raise ConfigError(f"--sky {name!r}: unknown sky; use uniform, cie-overcast, clear or iso:1 to iso:15")
    return key


def needs_sun(sky: str) -> bool:
    """Does ``sky``'s luminance depend on where the sun is (an indicatrix other than the flat one)?"""
    if sky == "clear":
        return True
    if sky.startswith("iso:"):
        a, b, c, d, e = ISO_SKIES[int(sky[4:])]
        return c != 0.0 or e != 0.0
    return False


def frame(rotation: np.ndarray, up_axis: str = "y") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(up, east, north) unit vectors in dcrad's internal frame for a file loaded with ``rotation``
    (input -> internal) from up axis ``up_axis``: east is the input's +X (+Y for an X-up file)."""
    r = np.asarray(rotation, np.float64)
    up = np.array([0.0, 1.0, 0.0])
    east = r @ np.array([0.0, 1.0, 0.0] if up_axis.lstrip("-+") == "x" else [1.0, 0.0, 0.0])
    east -= up * (east @ up)
    east /= np.linalg.norm(east)
    return up, east, np.cross(up, east)


def sun_direction(altitude: float, azimuth: float, up: np.ndarray, east: np.ndarray,
                  north: np.ndarray) -> np.ndarray:
    """Unit vector toward the sun at ``altitude`` degrees above the horizon and compass ``azimuth``
    (degrees from north, clockwise seen from above: east 90)."""
    a, z = math.radians(altitude), math.radians(azimuth)
    return math.cos(a) * (math.sin(z) * east + math.cos(z) * north) + math.sin(a) * up


def sun_position(latitude: float, longitude: float, when: _dt.datetime) -> tuple[float, float]:
    """(altitude, azimuth) degrees of the sun's centre seen from a site at ``latitude`` (north +)
    and ``longitude`` (east +) at the aware datetime ``when``, refraction left out (astral's NOAA
    equations); azimuth from north, clockwise."""
    from astral import Observer  # noqa: PLC0415  (only a run given a site and a time needs it)
    from astral.sun import azimuth, elevation  # noqa: PLC0415

    if when.tzinfo is None:
        raise ConfigError(f"--time {when.isoformat()}: give its UTC offset (e.g. 2026-06-21T12:00+01:00)")
    if not (-90.0 <= latitude <= 90.0 and -180.0 <= longitude <= 180.0):
        raise ConfigError(f"--site {latitude:g},{longitude:g}: latitude must be in [-90, 90], longitude in "
                          f"[-180, 180] degrees")
    obs = Observer(latitude=latitude, longitude=longitude, elevation=0.0)
    return float(elevation(obs, when, with_refraction=False)), float(azimuth(obs, when))


@dataclass
class SkyModel:
    """The luminance outside: ``sky`` (a name of SKY_NAMES), ``diffuse_lux`` E_hz, the sun toward
    ``sun`` (unit, internal frame; None: no position) with ``sun_lux`` direct normal illuminance
    (0: no sun), the ``ground`` reflectance, and ``up``."""

    sky: str
    diffuse_lux: float = 10_000.0
    sun: np.ndarray | None = None
    sun_lux: float = 0.0
    ground: float = 0.2
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))

    def __post_init__(self) -> None:
        self.sky = parse_sky(self.sky)
        self.up = np.asarray(self.up, np.float64)
        if not (math.isfinite(self.diffuse_lux) and self.diffuse_lux > 0):
            raise ConfigError(f"--sky-illuminance {self.diffuse_lux:g}: must be a finite illuminance > 0 lux")
        if not (math.isfinite(self.sun_lux) and self.sun_lux >= 0):
            raise ConfigError(f"--sun-illuminance {self.sun_lux:g}: must be a finite illuminance >= 0 lux")
        if not (math.isfinite(self.ground) and 0.0 <= self.ground < 1.0):
            raise ConfigError(f"--ground-reflectance {self.ground:g}: must be in [0, 1)")
        if self.sun is not None:
            self.sun = np.asarray(self.sun, np.float64)
            if float(self.sun @ self.up) <= 0.0:
                alt = math.degrees(math.asin(max(-1.0, min(1.0, float(self.sun @ self.up)))))
                raise ConfigError(f"the sun is {-alt:.2f} degrees below the horizon: --sky {self.sky} with a sun "
                                  f"needs it above (altitude > 0)")
        if needs_sun(self.sky) and self.sun is None:
            raise ConfigError(f"--sky {self.sky} needs the sun's position: give --sun-altitude and --sun-azimuth, "
                              f"or --site and --time")
        if self.sun_lux > 0 and self.sun is None:
            raise ConfigError("--sun-illuminance needs the sun's position: give --sun-altitude and --sun-azimuth, "
                              "or --site and --time")
        self._norm: float | None = None

    # -- luminance --------------------------------------------------------------------------
    def _relative(self, s: np.ndarray) -> np.ndarray:
        """(m,) the sky's luminance toward unit sky directions ``s`` (m,3) up to a constant (0 below
        the horizon)."""
        cos_t = s @ self.up
        up = cos_t > 0
        if self.sky == "uniform":
            rel = np.ones(len(s))
        elif self.sky == "cie-overcast":
            rel = 1.0 + 2.0 * cos_t
        else:
            a, b, c, d, e = ISO_SKIES[12 if self.sky == "clear" else int(self.sky[4:])]
            rel = _gradation(cos_t, a, b)
            if c != 0.0 or e != 0.0:
                chi = np.arccos(np.clip(s @ self.sun, -1.0, 1.0))
                rel = rel * _indicatrix(chi, c, d, e)
        return np.where(up, rel, 0.0)

    def _normaliser(self) -> float:
        """W/m^2/sr per unit of ``_relative``: E_hz / 179 over the grid's integral of rel cos."""
        if self._norm is None:
            s, omega = grid_directions()
            cos_t = np.maximum(s @ self.up, 0.0)
            integral = float((self._relative(s) * cos_t).sum() * omega)
            self._norm = self.diffuse_lux / EFFICACY / integral
        return self._norm

    def zenith(self) -> float:
        """Lz, cd/m^2: the sky's luminance at the zenith."""
        return float(self._relative(self.up[None, :])[0]) * self._normaliser() * EFFICACY

    def sun_horizontal(self) -> float:
        """W/m^2 the sun puts on an unobstructed horizontal plane."""
        if self.sun is None or self.sun_lux <= 0:
            return 0.0
        return self.sun_lux / EFFICACY * float(self.sun @ self.up)

    def ground_radiance(self) -> float:
        """W/m^2/sr of the ground outside (Lambertian, lit by the unobstructed sky and sun)."""
        return self.ground * (self.diffuse_lux / EFFICACY + self.sun_horizontal()) / math.pi

    def radiance(self, s: np.ndarray) -> np.ndarray:
        """(m,) W/m^2/sr per channel (the light is white) seen toward unit directions ``s`` (m,3):
        the sky above the horizon, the ground below it."""
        s = np.asarray(s, np.float64)
        return np.where(s @ self.up > 0, self._relative(s) * self._normaliser(), self.ground_radiance())

    def horizontal_lux(self) -> float:
        """E_hz: the unobstructed horizontal illuminance of the sky alone (the daylight factor's
        denominator)."""
        return self.diffuse_lux

    def describe(self) -> dict:
        out = {"sky": self.sky, "horizontal_diffuse_lux": self.diffuse_lux, "zenith_cd_m2": self.zenith(),
               "ground_reflectance": self.ground, "ground_cd_m2": self.ground_radiance() * EFFICACY}
        if self.sun is not None:
            alt = math.degrees(math.asin(float(np.clip(self.sun @ self.up, -1.0, 1.0))))
            out |= {"sun_altitude_deg": alt, "sun_direct_normal_lux": self.sun_lux}
        return out


def grid_directions() -> tuple[np.ndarray, float]:
    """((GRID[0] * GRID[1], 3) the centres of the direction table's cells, their solid angle); the
    table's cells are equal in cos of the polar angle about +Y (dcrad's up) and in azimuth."""
    nz, nphi = GRID
    z = -1.0 + (np.arange(nz) + 0.5) * (2.0 / nz)
    phi = (np.arange(nphi) + 0.5) * (2.0 * math.pi / nphi)
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(np.maximum(1.0 - zz * zz, 0.0))
    s = np.stack([r * np.cos(pp), zz, r * np.sin(pp)], axis=-1).reshape(-1, 3)
    return s, 4.0 * math.pi / (nz * nphi)


def _cell_directions(cell: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Unit directions uniform (in solid angle) within the table's cells ``cell`` (m,), from ``u`` (m,2)."""
    nz, nphi = GRID
    iz, ip = cell // nphi, cell % nphi
    z = -1.0 + (iz + u[:, 0]) * (2.0 / nz)
    phi = (ip + u[:, 1]) * (2.0 * math.pi / nphi)
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    return np.stack([r * np.cos(phi), z, r * np.sin(phi)], axis=1)


class _Box:
    """The model's bounding box, a little grown, and its six faces (outward normals, areas)."""

    def __init__(self, lo, hi):
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi >= lo).all()):
            raise ConfigError("daylight: the model has no finite extent to light")
        grow = 1e-4 * float(np.linalg.norm(hi - lo)) + 1e-6
        self.lo, self.hi = lo - grow, hi + grow
        ext = self.hi - self.lo
        self.normals = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], np.float64)
        self.areas = np.array([ext[1] * ext[2]] * 2 + [ext[0] * ext[2]] * 2 + [ext[0] * ext[1]] * 2)
        self.reach = 2.0 * float(np.linalg.norm(ext))

    def points(self, face: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Points on the faces ``face`` (m,) at ``u`` (m,2) in [0,1)^2 of the face's two other axes
        (``_OTHER``): uniform for uniform ``u``."""
        axis = face // 2
        other = _OTHER[axis]
        rows = np.arange(len(face))
        ext = self.hi - self.lo
        out = np.empty((len(face), 3))
        for j in range(2):
            out[rows, other[:, j]] = self.lo[other[:, j]] + ext[other[:, j]] * u[:, j]
        out[rows, axis] = np.where(face % 2 == 1, self.hi[axis], self.lo[axis])
        return out


#: the two axes a face of the box spans, by the axis it faces along
_OTHER = np.array([[1, 2], [0, 2], [0, 1]])


def _halves(n: int, rng: np.random.Generator) -> np.ndarray | None:
    half = half_mask(np.array([n]), rng)
    return half if 0 < int(half.sum()) < n else None


#: cells along each side of a bounding-box face in the portal map (``Portals``)
PORTAL_CELLS = 64
#: pilot rays a receiver (at most PILOT_RAYS_MAX in all) the portal map is learnt from
PILOT_RAYS, PILOT_RAYS_MAX = 32, 1 << 21
#: cells the map's reached cells are grown by, each way (the pilot misses an opening's edges, and a
#: grazing line of sight leaves the box a few cells past the opening it went through)
GROW_CELLS = 2


def _edge_mask(c: int, axis: int, step: int) -> np.ndarray:
    """(1,c,c) 0 on the row ``np.roll`` wraps around to, else 1."""
    m = np.ones((1, c, c))
    idx = 0 if step > 0 else c - 1
    if axis == 1:
        m[:, idx, :] = 0.0
    else:
        m[:, :, idx] = 0.0
    return m


class Portals:
    """Where the light from outside comes in, learnt: a map over the bounding box's faces of where
    the rays that leave the model from its receivers cross them, weighted by the radiance they read
    (an opening in the roof is a patch of the top face; a window, the region of a face its lines of
    sight reach).  A gather aims half its rays at the map and half cosine-distributed, each weighed
    by both densities (the balance heuristic, Veach's multi-sample MIS): unbiased whatever the map
    holds, and where the map is right most rays go through the openings."""

    def __init__(self, box: _Box, cells: int = PORTAL_CELLS):
        self.box = box
        self.cells = cells
        self.weight = np.zeros(6 * cells * cells)
        self.count = np.zeros(6 * cells * cells)
        self.cdf: np.ndarray | None = None
        ext = box.hi - box.lo
        #: (6,) each face's cell area
        self.cell_area = np.array([ext[_OTHER[f // 2, 0]] * ext[_OTHER[f // 2, 1]] for f in range(6)]) / cells ** 2

    def exit(self, x: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(face (m,), cell (m,), t (m,)): where rays from ``x`` (inside the box) along unit ``d`` leave it."""
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = np.where(d > 0, self.box.hi, self.box.lo)
            t_axis = np.where(d != 0, (bound - x) / d, np.inf)
        axis = np.argmin(t_axis, axis=1)
        rows = np.arange(len(x))
        t = np.maximum(t_axis[rows, axis], 0.0)
        face = 2 * axis + (d[rows, axis] > 0)
        q = x + t[:, None] * d
        o = _OTHER[axis]
        ext = self.box.hi - self.box.lo
        c = self.cells
        i = np.clip(((q[rows, o[:, 0]] - self.box.lo[o[:, 0]]) / ext[o[:, 0]] * c).astype(np.int64), 0, c - 1)
        j = np.clip(((q[rows, o[:, 1]] - self.box.lo[o[:, 1]]) / ext[o[:, 1]] * c).astype(np.int64), 0, c - 1)
        return face, (face * c + i) * c + j, t

    def learn(self, x: np.ndarray, d: np.ndarray, weight: np.ndarray) -> None:
        """Add escaping rays (from ``x`` along ``d``, reading ``weight``) to the map: a cell's weight is
        the mean radiance its rays read, over the cells they reached grown by GROW_CELLS (the
        pilot's counts a cell are a few: weighing by them left 50% noise on a ray aimed at a roof
        opening; the neighbours cover the edges of an opening the pilot's rays missed)."""
        c = self.cells
        if len(x):
            _, cell, _ = self.exit(x, d)
            self.weight += np.bincount(cell, weights=weight, minlength=len(self.weight))
            self.count += np.bincount(cell, minlength=len(self.weight))
        mean = np.where(self.count > 0, self.weight / np.maximum(self.count, 1), 0.0).reshape(6, c, c)
        grown = mean
        for _ in range(GROW_CELLS):
            wider = grown.copy()
            for axis in (1, 2):
                for step in (1, -1):
                    wider = np.maximum(wider, np.roll(grown, step, axis=axis) * _edge_mask(c, axis, step))
            grown = wider
        flat = grown.ravel()
        total = float(flat.sum())
        self.cdf = np.cumsum(flat) / total if total > 0 else None

    def sample(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Unit directions from ``x`` (m,3) toward points of the map drawn by its weights (``u`` (m,3))."""
        assert self.cdf is not None
        cell = np.minimum(np.searchsorted(self.cdf, u[:, 0], side="right"), len(self.cdf) - 1)
        c = self.cells
        face, rest = cell // (c * c), cell % (c * c)
        i, j = rest // c, rest % c
        q = self.box.points(face, np.column_stack([(i + u[:, 1]) / c, (j + u[:, 2]) / c]))
        d = q - x
        return d / np.maximum(np.linalg.norm(d, axis=1), 1e-300)[:, None]

    def pdf(self, x: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(m,) the solid-angle density ``sample`` draws unit ``d`` from ``x`` with."""
        assert self.cdf is not None
        face, cell, t = self.exit(x, d)
        p = np.diff(self.cdf, prepend=0.0)[cell]
        cos_q = np.abs(d[np.arange(len(d)), face // 2])
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(cos_q > 0, p / self.cell_area[face] * t * t / cos_q, 0.0)


class Sky:
    """The sky and the ground outside as one light source (module doc): ``model`` (SkyModel) lighting
    the model inside the bounding box ``lo``..``hi`` (internal frame)."""

    #: its direct light is an integral over what a point sees of the sky: sampled, never exact
    exact = False
    #: it lights the model from outside (report.py: what escapes or meets back faces is no mistake)
    outside = True

    def __init__(self, model: SkyModel, lo, hi, name: str = "sky"):
        self.model = model
        self.box = _Box(lo, hi)
        self._box_given = (np.asarray(lo, np.float64), np.asarray(hi, np.float64))
        self.name = name
        self._table: tuple[np.ndarray, np.ndarray, float] | None = None
        #: where its light comes in (learnt on the first gather; None: not yet)
        self.portals: Portals | None = None
        self.pilot_mean = 0.0
        #: the run's seed and its accuracy's share of the point estimator's budget (``attune``)
        self.seed, self.quality = 0, 1.0

    def _flux(self) -> tuple[np.ndarray, np.ndarray, float]:
        """(cumulative joint weights over (face, cell) (6 * cells,), the cells' radiance (cells,), total W per
        channel): the flux in through each face from each cell of directions."""
        if self._table is None:
            s, omega = grid_directions()
            rad = self.model.radiance(s)
            # light from sky direction s travels along -s: it enters a face whose outward normal n has s.n > 0
            w = np.maximum(self.box.normals @ s.T, 0.0) * rad[None, :] * omega * self.box.areas[:, None]
            total = float(w.sum())
            self._table = (np.cumsum(w.ravel()) / max(total, 1e-300), rad, total)
        return self._table

    def power(self) -> np.ndarray:
        """(3,) W: all the light the sky and the ground send in through the box's faces."""
        return np.full(3, self._flux()[2])

    def rays(self, n: int, rng: np.random.Generator) -> RayBatch:
        """``n`` rays in through the box's faces: face and cell of directions drawn by their flux, the
        direction uniform in the cell, the point uniform on the face; each ray's share weighs its own
        radiance and cosine against its cell's (half_weights: each half carries exactly half)."""
        cdf, rad, _ = self._flux()
        u = rng.random((n, 5))
        joint = np.minimum(np.searchsorted(cdf, u[:, 0] * cdf[-1], side="right"), len(cdf) - 1)
        ncell = len(rad)
        face, cell = joint // ncell, joint % ncell
        s = _cell_directions(cell, u[:, 1:3])
        cos = np.einsum("ij,ij->i", s, self.box.normals[face])
        cell_s = _cell_directions(cell, np.full((n, 2), 0.5))
        cell_cos = np.einsum("ij,ij->i", cell_s, self.box.normals[face])
        with np.errstate(divide="ignore", invalid="ignore"):
            weight = np.where(rad[cell] * cell_cos > 0, self.model.radiance(s) * np.maximum(cos, 0.0)
                              / (rad[cell] * cell_cos), 0.0)
        half = _halves(n, rng)
        share = half_weights(weight, half if half is not None else np.ones(n, bool))
        origins = self.box.points(face, u[:, 3:5])
        power = share[:, None] * self.power()[None, :]
        return RayBatch(origins=origins, dirs=-s, power=power, shooter=np.zeros(n, np.int64), half=half)

    def learn(self, points: np.ndarray, normals: np.ndarray, tracer, offset: float) -> None:
        """Learn the portal map (``Portals``) once, from PILOT_RAYS cosine rays a point (at most
        PILOT_RAYS_MAX in all, the points taken evenly) that leave the model."""
        if self.portals is not None:
            return
        self.portals = Portals(self.box)
        m = len(points)
        if m == 0:
            return
        # few points (a work plane's, a test's) take more rays each: the map wants about as many in all
        per = int(min(max(PILOT_RAYS, PILOT_RAYS_MAX // (8 * m)), 4096))
        take = np.arange(0, m, max(1, (m * per) // PILOT_RAYS_MAX))
        x, n = points[take], normals[take]
        rng = np.random.default_rng(PILOT_SEED)
        owner = np.repeat(np.arange(len(x)), per)
        u = lattice(np.tile(np.arange(per), len(x)), np.repeat(rng.random((len(x), 2)), per, axis=0), 2)
        t, b = onb(n)
        d = np.einsum("mi,mij->mj", cosine_hemisphere(u), np.stack([t, b, n], axis=1)[owner])
        start = x[owner] + offset * n[owner]
        prim, _, _, tau = tracer.through(start, d)
        out = np.flatnonzero(prim == MISS)
        read = self.model.radiance(d[out]) * tau[out].mean(axis=1)
        self.portals.learn(start[out], d[out], read)
        #: W/m^2, the pilot's mean irradiance over its points (``pilot``)
        self.pilot_mean = math.pi * float(read.sum()) / max(len(owner), 1)

    def attune(self, seed: int, accuracy: float) -> None:
        """Read the points of this run's outputs (``irradiance``) with its ``seed`` (another seed:
        other rays, so that a reference run is independent of the run it checks) and a budget of
        RAYS_BUDGET x (REFERENCE_ACCURACY / ``accuracy``)^2 rays: a run asked for 1% reads its work
        plane with 4x the rays of one at 2%."""
        self.seed = int(seed)
        if accuracy > 0 and math.isfinite(accuracy):
            self.quality = max(1.0, (REFERENCE_ACCURACY / accuracy) ** 2)

    def pilot(self, points: np.ndarray, normals: np.ndarray, tracer, offset: float) -> float:
        """W/m^2: about the mean irradiance of sky and ground over ``points`` (the portal map's pilot,
        learnt from them when it has not been yet): what sets how many rays the gather takes."""
        self.learn(points, normals, tracer, offset)
        return self.pilot_mean

    def _read(self, x: np.ndarray, n: np.ndarray, u: np.ndarray, cosine: np.ndarray, share: np.ndarray,
              tracer) -> np.ndarray:
        """(m,3) each ray's estimate of the irradiance at ``x`` (m,3, off the surface) facing ``n``: rays
        ``cosine`` (m,) bool cosine-distributed from ``u[:, :2]``, the others toward the portal map from
        ``u[:, 2:5]``; f / (s p_cos + (1 - s) p_portal), s = ``share`` (m,) the cosine rays' share of
        their point's (the balance heuristic: an odd count's one more cosine ray than aimed ones, read
        as a half, biased a side-lit room's sky light 4% low at 8 to 15 rays a receiver), or pi L tau
        where the map is empty (every ray cosine)."""
        portals = self.portals if self.portals is not None and self.portals.cdf is not None else None
        t, b = onb(n)
        d = np.einsum("mi,mij->mj", cosine_hemisphere(u[:, :2]), np.stack([t, b, n], axis=1))
        if portals is None:
            prim, _, _, tau = tracer.through(x, d)
            return np.where(prim == MISS, math.pi * self.model.radiance(d), 0.0)[:, None] * tau
        aim = np.flatnonzero(~cosine)
        if len(aim):
            d[aim] = portals.sample(x[aim], u[aim, 2:5])
        cos = np.einsum("ij,ij->i", d, n)
        prim, _, _, tau = tracer.through(x, d)
        mix = share * np.maximum(cos, 0.0) / math.pi + (1.0 - share) * portals.pdf(x, d)
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where((prim == MISS) & (cos > 0) & (mix > 0), self.model.radiance(d) * cos / mix, 0.0)
        return f[:, None] * tau

    def irradiance(self, points: np.ndarray, normals: np.ndarray, tracer, offset: float,
                   rays: int | None = None) -> np.ndarray:
        """(m,3) W/m^2 of sky and ground on ``points`` facing ``normals``: ``rays`` a point (None:
        RAYS_BUDGET over the points, within RAYS_PER_POINT, an even number; a 5-D
        lattice shifted at random per point, seeded by the points: the same points read the same),
        half cosine-distributed and half aimed at the portal map (learnt from these points when it
        has not been yet), reading the radiance outside where they leave the model, times the panes'
        tau on the way."""
        points = np.asarray(points, np.float64)
        normals = np.asarray(normals, np.float64)
        m = len(points)
        out = np.zeros((m, 3))
        if m == 0:
            return out
        self.learn(points, normals, tracer, offset)
        if rays is None:
            budget = RAYS_BUDGET * self.quality
            rays = int(min(max(budget // m, RAYS_PER_POINT[0]), RAYS_PER_POINT[1])) & ~1
        rng = np.random.default_rng([self.seed, _seed(points)])
        shift = rng.random((m, 5))
        chunk = max(1, (1 << 20) // rays)
        for lo in range(0, m, chunk):
            rows = np.arange(lo, min(m, lo + chunk))
            owner = np.repeat(rows, rays)
            j = np.tile(np.arange(rays), len(rows))
            u = lattice(j // 2, shift[owner], 5)
            x = points[owner] + offset * normals[owner]
            seen = self._read(x, normals[owner], u, j % 2 == 0, np.full(len(j), ((rays + 1) // 2) / rays), tracer)
            for c in range(3):
                out[rows, c] = np.bincount(owner - lo, weights=seen[:, c], minlength=len(rows)) / rays
        return out

    def patch_gather(self, corners: np.ndarray, normals: np.ndarray, counts: np.ndarray, tracer, offset: float,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Two independent estimates (h_a, h_b), (k,3) W/m^2 each, of the sky's and ground's mean
        irradiance over each triangle ``corners`` (k,3,3) facing ``normals`` (k,3): ``counts`` (k,)
        rays each, from a 7-D lattice (direction both ways, point on the triangle) shifted at random
        per triangle and per half (the two halves of noise.py: their difference is the gather's
        noise); the portal map is learnt from the triangles' centres first."""
        k = len(corners)
        centre = corners.mean(axis=1)
        self.learn(centre, normals, tracer, offset)
        total = int(counts.sum())
        owner_all = np.repeat(np.arange(k), counts)
        index_all = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
        share = ((counts + 1) // 2) / np.maximum(counts, 1)  # the even rays are cosine-distributed
        out = []
        for _ in range(2):
            shift = rng.random((k, 7))
            h = np.zeros((k, 3))
            for lo in range(0, total, 1 << 20):
                owner = owner_all[lo:lo + (1 << 20)]
                j = index_all[lo:lo + (1 << 20)]
                u = lattice(j // 2, shift[owner], 7)
                x = triangle_points(corners[:, 0], corners[:, 1], corners[:, 2], u[:, 5:], owner)
                x += (centre[owner] - x) * 1e-6 + offset * normals[owner]  # off the edges and the surface
                seen = self._read(x, normals[owner], u, j % 2 == 0, share[owner], tracer)
                for c in range(3):
                    h[:, c] += np.bincount(owner, weights=seen[:, c], minlength=k)
            out.append(h / np.maximum(counts, 1)[:, None])
        return out[0], out[1]

    def to_wire(self) -> dict:
        m = self.model
        return {"name": self.name, "sky": m.sky, "diffuse_lux": m.diffuse_lux,
                "sun": None if m.sun is None else m.sun.tolist(), "sun_lux": m.sun_lux, "ground": m.ground,
                "up": m.up.tolist(), "lo": self._box_given[0].tolist(), "hi": self._box_given[1].tolist()}

    @classmethod
    def from_wire(cls, d: dict) -> "Sky":
        model = SkyModel(d["sky"], float(d["diffuse_lux"]), None if d["sun"] is None else np.array(d["sun"]),
                         float(d["sun_lux"]), float(d["ground"]), np.array(d["up"]))
        return cls(model, np.array(d["lo"]), np.array(d["hi"]), name=str(d["name"]))


def _seed(points: np.ndarray) -> int:
    head = np.ascontiguousarray(points[: min(len(points), 64)]).tobytes()
    return int(np.frombuffer(head, np.uint8).sum()) + len(points)


class Sun:
    """The sun: a parallel beam of ``lux`` direct normal illuminance toward unit ``direction`` (toward
    the sun, internal frame), lighting the model inside the box ``lo``..``hi``.  Its direct light is
    exact: E_n cos theta where a shadow ray toward the sun leaves the model (through panes: times tau)."""

    exact = True
    outside = True

    def __init__(self, direction, lux: float, lo, hi, name: str = "sun"):
        self.direction = np.asarray(direction, np.float64)
        self.direction = self.direction / np.linalg.norm(self.direction)
        self.lux = float(lux)
        self.box = _Box(lo, hi)
        self._box_given = (np.asarray(lo, np.float64), np.asarray(hi, np.float64))
        self.name = name

    def normal_irradiance(self) -> float:
        """W/m^2 per channel on a plane facing the sun."""
        return self.lux / EFFICACY

    def _faces(self) -> np.ndarray:
        return np.maximum(self.box.normals @ self.direction, 0.0) * self.box.areas

    def power(self) -> np.ndarray:
        return np.full(3, self.normal_irradiance() * float(self._faces().sum()))

    def rays(self, n: int, rng: np.random.Generator) -> RayBatch:
        """``n`` parallel rays in through the faces that see the sun, uniform over their projected area."""
        w = self._faces()
        u = rng.random((n, 3))
        face = np.minimum(np.searchsorted(np.cumsum(w) / w.sum(), u[:, 0], side="right"), 5)
        half = _halves(n, rng)
        share = half_weights(np.ones(n), half if half is not None else np.ones(n, bool))
        return RayBatch(origins=self.box.points(face, u[:, 1:3]), dirs=np.repeat(-self.direction[None, :], n, axis=0),
                        power=share[:, None] * self.power()[None, :], shooter=np.zeros(n, np.int64), half=half)

    def irradiance(self, points: np.ndarray, normals: np.ndarray, tracer, offset: float) -> np.ndarray:
        points = np.asarray(points, np.float64)
        cos = np.asarray(normals, np.float64) @ self.direction
        out = np.zeros((len(points), 3))
        lit = np.flatnonzero(cos > 0)
        if not len(lit):
            return out
        toward = np.repeat(self.direction[None, :], len(lit), axis=0)
        seen = visibility(tracer, points[lit] + offset * toward, toward, np.full(len(lit), self.box.reach))
        out[lit] = self.normal_irradiance() * cos[lit, None] * seen
        return out

    def to_wire(self) -> dict:
        return {"name": self.name, "direction": self.direction.tolist(), "lux": self.lux,
                "lo": self._box_given[0].tolist(), "hi": self._box_given[1].tolist()}

    @classmethod
    def from_wire(cls, d: dict) -> "Sun":
        return cls(np.array(d["direction"]), float(d["lux"]), np.array(d["lo"]), np.array(d["hi"]),
                   name=str(d["name"]))


@dataclass
class DaylightSpec:
    """What the flags ask for (``--sky`` and its companions); ``sources(scene)`` builds the emitters."""

    sky: str
    diffuse_lux: float = 10_000.0
    sun_altitude: float | None = None
    sun_azimuth: float | None = None
    site: tuple[float, float] | None = None
    time: _dt.datetime | None = None
    sun_lux: float | None = None
    ground: float = 0.2

    def __post_init__(self) -> None:
        self.sky = parse_sky(self.sky)
        given = (self.sun_altitude is not None) + (self.sun_azimuth is not None)
        if given == 1:
            raise ConfigError("--sun-altitude and --sun-azimuth go together: give both")
        if given and (self.site is not None or self.time is not None):
            raise ConfigError("the sun's position: give --sun-altitude/--sun-azimuth or --site/--time, not both")
        if (self.site is None) != (self.time is None):
            raise ConfigError("--site and --time go together: give both to place the sun")
        for name, v in (("--sun-altitude", self.sun_altitude), ("--sun-azimuth", self.sun_azimuth)):
            if v is not None and not math.isfinite(v):
                raise ConfigError(f"{name} {v}: not a finite number of degrees")
        if self.sun_altitude is not None and not (-90.0 <= self.sun_altitude <= 90.0):
            raise ConfigError(f"--sun-altitude {self.sun_altitude:g}: must be in [-90, 90] degrees")
        positioned = given or self.site is not None
        if self.sun_lux is not None and self.sun_lux > 0 and self.sky in ("uniform", "cie-overcast"):
            raise ConfigError(f"--sun-illuminance does not apply to --sky {self.sky} (an overcast or uniform sky "
                              f"has no sun); use --sky clear or iso:N")
        if positioned and not needs_sun(self.sky) and not (self.sun_lux or 0) > 0:
            raise ConfigError(f"the sun's position does not apply to --sky {self.sky}, whose luminance does not "
                              f"depend on the sun, without --sun-illuminance")

    def to_json(self) -> str:
        """The spec as JSON (the service's JobSpec.daylight); ``from_json`` reads it back."""
        import json  # noqa: PLC0415

        d = dataclasses.asdict(self)
        d["time"] = None if self.time is None else self.time.isoformat()
        return json.dumps(d)

    @classmethod
    def from_json(cls, text: str) -> "DaylightSpec":
        import json  # noqa: PLC0415

        try:
            d = json.loads(text)
            d["time"] = None if d.get("time") is None else _dt.datetime.fromisoformat(d["time"])
            d["site"] = None if d.get("site") is None else tuple(d["site"])
            return cls(**d)
        except (ValueError, TypeError, KeyError) as exc:
            raise ConfigError(f"the job's daylight settings cannot be read: {exc}") from None

    def check(self) -> None:
        """Every value read and the sun placed (ConfigError else), before the scene is loaded."""
        self.model(np.eye(3), "y")

    def altitude_azimuth(self) -> tuple[float, float] | None:
        if self.sun_altitude is not None and self.sun_azimuth is not None:
            return self.sun_altitude, self.sun_azimuth
        if self.site is not None and self.time is not None:
            return sun_position(self.site[0], self.site[1], self.time)
        return None

    def model(self, rotation: np.ndarray, up_axis: str = "y") -> SkyModel:
        up, east, north = frame(rotation, up_axis)
        pos = self.altitude_azimuth()
        sun = None if pos is None else sun_direction(pos[0], pos[1], up, east, north)
        if pos is not None and pos[0] <= 0 and (needs_sun(self.sky) or (self.sun_lux or 0) > 0):
            raise ConfigError(f"the sun is {-pos[0]:.2f} degrees below the horizon (altitude {pos[0]:.2f}): "
                              f"--sky {self.sky} needs it above")
        lux = self.sun_lux if self.sun_lux is not None else (CLEAR_SUN_LUX if self.sky == "clear" else 0.0)
        keep = sun if (needs_sun(self.sky) or lux > 0) else None
        return SkyModel(self.sky, self.diffuse_lux, keep, lux, self.ground, up)


def daylight_sources(spec: DaylightSpec, scene) -> tuple:
    """The Sky (and the Sun when it shines) lighting ``scene`` (its valid triangles' box)."""
    model = spec.model(scene.rotation, scene.up)
    tri = scene.vertices[scene.faces[scene.valid]].reshape(-1, 3)
    if not len(tri):
        raise ConfigError("daylight: the scene has no valid triangles to light")
    lo, hi = tri.min(axis=0), tri.max(axis=0)
    out: list = [Sky(model, lo, hi)]
    if model.sun is not None and model.sun_lux > 0:
        out.append(Sun(model.sun, model.sun_lux, lo, hi))
    return tuple(out)
