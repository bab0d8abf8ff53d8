"""Luminaires from photometric files (IES LM-63, EULUMDAT), placed by a luminaire schedule.

A luminaire is a point source (``emitters.PointSource``) at its photometric centre whose intensity
is the file's candela table, turned into the scene by its aim and rotation:

* **The file** is parsed by ``photompy`` (IES LM-63 1995, 2002 and 2019 through ``IESFile``; the
  EULUMDAT header through ``LDTHeader``).  What photompy 0.3.1 lacks is written here, each piece
  saying what it replaces: the EULUMDAT intensity block (photompy reads as many C angles as stored
  planes and relabels Isym 3's planes, so a symmetric real file is misread), the expansion of
  symmetric tables (photompy's ``expanded()`` mirrors by adding 90/180 degrees, right only for
  evenly spaced planes, and leaves no plane at 360 to interpolate across), the ballast factor it
  ignores, TILT=INCLUDE applied at the installed tilt, and files of LM-63-1986/1991 (no version
  line photompy accepts).  Type B photometry (floodlights) is read onto a fine type C web in the
  frame Radiance's ies2rad reads it in (``type_b_web``; checked against ies2rad + rtrace).  Type A
  photometry, TILT=<file>, IES files of 90-270 lateral symmetry and EULUMDAT files of several lamp
  sets are refused by name, not guessed at.
* **The distribution** (``Distribution``): candela over (gamma, C), gamma the vertical angle from
  the photometric nadir, C the horizontal angle, expanded to the whole sphere and interpolated
  bilinearly in (gamma, C); zero outside the measured vertical angles (a 0-90 table emits nothing
  upward).  Its flux is the exact integral of that interpolant, so the lumens the solver emits are
  those of the table as it is read, to round-off.
* **The frame** (``Luminaire``): the nadir (gamma 0) points along ``aim``; C0 lies along the scene
  file's +X axis made perpendicular to the aim (its +Y when the aim is within 2.6 degrees of +-X),
  turned by ``rotation`` degrees about the aim; C increases counter-clockwise seen from above
  (looking along the aim), C90 = C0 x aim (CIE and LM-63 type C).  I_world(d) = I_file(R^T d).
* **The schedule** (``load_schedule``): JSON, positions and aims in the scene file's own
  coordinates and units (``scale`` and the up axis apply as to the scene's vertices).

Light: a white luminaire of I candela is I / 179 W/sr in each channel (photometry.EFFICACY;
the Y weights sum to 1, so lux read back are the candela's).  Rays sample the cells of the table
by their exact flux, so no ray is wasted where the table is dark, and each half of a batch carries
exactly half the power, so the ledger closes with the file's lumens in it.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dcrad.errors import ConfigError
from dcrad.estimate.noise import half_mask
from dcrad.outputs.photometry import EFFICACY, Y_WEIGHTS
from dcrad.transport.emitters import PointSource, half_weights, visibility
from dcrad.transport.gltf_lights import extension_lights, placements, unique_name
from dcrad.transport.rays import Tracer
from dcrad.transport.sampling import lattice
from dcrad.transport.shoot import RayBatch

__all__ = ["Distribution", "Photometric", "Luminaire", "read_photometric", "load_schedule", "report_section",
           "summary_lines", "SCHEDULE_KEYS"]

#: the keys a schedule entry may have
SCHEDULE_KEYS = ("file", "position", "aim", "rotation", "multiplier", "name")
#: a schedule position may lie this share of the scene's diagonal outside its bounding box (a
#: luminaire's photometric centre sits on or just off a ceiling)
POSITION_PAD = 0.01
#: angles (degrees) closer than this are one angle (mirrored planes of a symmetric file)
_ANGLE_EPS = 1e-9


# -- the distribution ----------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Distribution:
    """Candela ``cd`` (K, G) over horizontal angles ``c`` (K,) degrees, 0 to 360 both included (the
    360 plane a copy of the 0 one, so C interpolates across it), and vertical angles ``gamma`` (G,)
    degrees, strictly increasing within [0, 180].  Zero outside [gamma[0], gamma[-1]]."""

    c: np.ndarray
    gamma: np.ndarray
    cd: np.ndarray

    @staticmethod
    def expand(c_deg, gamma_deg, cd, symmetry: str) -> "Distribution":
        """The whole sphere's table from the planes a file stores (``c_deg`` (k,), ``cd`` (k, G)):
        ``symmetry`` "none" (0 to 360, or 0 up to its last plane), "axial" (one plane),
        "c0-c180" (planes 0-180, I(C) = I(360 - C)), "c90-c270" (planes 90-270, I(C) = I(180 - C))
        or "quadrant" (planes 0-90, both).  Mirrored planes are placed at their own mirrored
        angles, so unevenly spaced planes stay where they were measured (photompy's ``expanded``
        adds 180 or 90 degrees to each plane, which puts them elsewhere unless evenly spaced)."""
        c = np.asarray(c_deg, np.float64).reshape(-1)
        v = np.asarray(cd, np.float64).reshape(len(c), -1)
        if symmetry == "axial":
            c, v = np.zeros(1), v[:1]
        elif symmetry == "c0-c180":
            c, v = np.concatenate([c, 360.0 - c]), np.concatenate([v, v])
        elif symmetry == "c90-c270":
            c, v = np.concatenate([c, 180.0 - c]), np.concatenate([v, v])
        elif symmetry == "quadrant":
            c, v = np.concatenate([c, 180.0 - c, 180.0 + c, 360.0 - c]), np.concatenate([v, v, v, v])
        elif symmetry != "none":
            raise ValueError(f"unknown symmetry {symmetry!r}")
        c = np.mod(np.round(c, 9), 360.0)
        c, first = np.unique(c, return_index=True)  # a mirrored plane on itself (0, 90, 180) once
        v = v[first]
        # the 360 plane is the 0 plane: C wraps
        return Distribution(np.append(c, 360.0), np.asarray(gamma_deg, np.float64).copy(), np.vstack([v, v[:1]]))

    def __post_init__(self) -> None:
        if self.c[0] != 0.0 or self.c[-1] != 360.0 or not (np.diff(self.c) > 0).all():
            raise ValueError("horizontal angles must increase from 0 to 360")
        if len(self.gamma) < 2 or not (np.diff(self.gamma) > 0).all():
            raise ValueError("vertical angles must be at least two, increasing")
        if self.cd.shape != (len(self.c), len(self.gamma)):
            raise ValueError(f"candela table {self.cd.shape} is not {len(self.c)} x {len(self.gamma)}")

    def at(self, gamma_deg: np.ndarray, c_deg: np.ndarray) -> np.ndarray:
        """(m,) candela at vertical angles ``gamma_deg`` and horizontal angles ``c_deg`` (any
        value: taken modulo 360), bilinear in (gamma, C); 0 outside the measured vertical angles."""
        g = np.asarray(gamma_deg, np.float64)
        out = bilinear(self.c, self.gamma, self.cd, np.mod(np.asarray(c_deg, np.float64), 360.0), g)
        inside = (g >= self.gamma[0] - _ANGLE_EPS) & (g <= self.gamma[-1] + _ANGLE_EPS)
        return np.where(inside, out, 0.0)

    def cells(self) -> tuple[np.ndarray, np.ndarray]:
        """(flux (K-1, G-1) lm, solid angle (K-1, G-1) sr) of each cell between neighbouring planes
        and vertical angles: the exact integrals of the bilinear interpolant, I sin(gamma) over
        the cell (linear in C: the trapezoid; linear in gamma times sin: in closed form)."""
        a, b = np.radians(self.gamma[:-1]), np.radians(self.gamma[1:])
        width = b - a
        band = np.cos(a) - np.cos(b)  # the integral of sin over [a, b]
        # integrals of t sin and (1 - t) sin, t = (gamma - a) / (b - a)
        w1 = (np.sin(b) - np.sin(a) - width * np.cos(b)) / width
        w0 = band - w1
        dc = np.radians(np.diff(self.c))
        v = self.cd
        flux = 0.5 * dc[:, None] * (w0[None, :] * (v[:-1, :-1] + v[1:, :-1]) + w1[None, :] * (v[:-1, 1:] + v[1:, 1:]))
        return flux, dc[:, None] * band[None, :]

    def flux(self) -> float:
        """lm: the integral of the interpolated intensity over the sphere (exact)."""
        return float(self.cells()[0].sum())

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(gamma (n,) rad, C (n,) rad, ratio (n,)) of ``n`` directions: cells chosen by their flux
        (systematic sampling: each cell gets its share of the rays to within one), uniform in solid
        angle within a cell (a shifted 2-D lattice); ratio = I Omega_cell / flux_cell, whose mean
        is 1 in every cell, so rays of power ratio x P / n carry the distribution unbiased."""
        flux, omega = self.cells()
        flat = flux.reshape(-1)
        cdf = np.cumsum(flat)
        cdf /= cdf[-1]
        cdf[-1] = 1.0
        cell = np.minimum(np.searchsorted(cdf, (np.arange(n) + rng.random()) / n, side="right"), len(flat) - 1)
        ci, gi = np.divmod(cell, flux.shape[1])
        u = lattice(np.arange(n), np.repeat(rng.random((1, 2)), n, axis=0), 2)
        ga, gb = np.radians(self.gamma[gi]), np.radians(self.gamma[gi + 1])
        cos_g = np.cos(ga) + u[:, 0] * (np.cos(gb) - np.cos(ga))
        gamma = np.arccos(np.clip(cos_g, -1.0, 1.0))
        c = np.radians(self.c[ci] + u[:, 1] * (self.c[ci + 1] - self.c[ci]))
        ratio = self.at(np.degrees(gamma), np.degrees(c)) * omega.reshape(-1)[cell] / flat[cell]
        return gamma, c, ratio


def bilinear(rows: np.ndarray, cols: np.ndarray, table: np.ndarray, r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``table`` (R, C) over increasing ``rows`` and ``cols`` interpolated bilinearly at (``r``, ``c``),
    clamped to the edges; one row (R = 1): the same along ``rows``."""
    ri = np.clip(np.searchsorted(rows, r, side="right") - 1, 0, max(len(rows) - 2, 0))
    ci = np.clip(np.searchsorted(cols, c, side="right") - 1, 0, len(cols) - 2)
    if len(rows) > 1:
        u, r1 = np.clip((r - rows[ri]) / (rows[ri + 1] - rows[ri]), 0.0, 1.0), ri + 1
    else:
        u, r1 = np.zeros(np.shape(r)), ri
    t = np.clip((c - cols[ci]) / (cols[ci + 1] - cols[ci]), 0.0, 1.0)
    return ((1 - u) * ((1 - t) * table[ri, ci] + t * table[ri, ci + 1])
            + u * ((1 - t) * table[r1, ci] + t * table[r1, ci + 1]))


# -- photometric files ----------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Photometric:
    """One photometric file as read: its ``distribution`` (candela with the file's own multipliers
    and ballast factor applied), a ``label`` saying what it is, the rated ``lamp_lumens`` (None for
    absolute photometry), the ``input_watts`` (None when the file gives none), the luminous
    opening (``opening_m`` width, length, height in metres and ``opening_shape``: a flat rectangle or
    disc lights its near field from all over it, ``Luminaire.irradiance``; any other shape is a point
    at the photometric centre) and the TILT=INCLUDE table
    (``tilt``: (angles deg, factors), or None)."""

    file: str
    label: str
    distribution: Distribution
    lamp_lumens: float | None
    input_watts: float | None
    opening_m: tuple[float, float, float]
    opening_shape: str
    tilt: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def lumens(self) -> float:
        """lm the table emits (the luminaire's flux, at the schedule's multiplier 1 and no tilt)."""
        return self.distribution.flux()

    def tilt_factor(self, tilt_deg: float) -> float:
        """The TILT=INCLUDE multiplying factor at a luminaire tilt of ``tilt_deg`` (1 without a table)."""
        if self.tilt is None:
            return 1.0
        return float(np.interp(tilt_deg, self.tilt[0], self.tilt[1]))


def _check_table(path: str, gamma: np.ndarray, cd: np.ndarray) -> None:
    """ConfigError naming ``path`` for candela a luminaire cannot emit or angles out of range."""
    if not np.isfinite(cd).all():
        raise ConfigError(f"{path}: non-finite candela value(s) in the table")
    if (cd < 0).any():
        raise ConfigError(f"{path}: negative candela value(s) in the table (least {float(cd.min()):g} cd)")
    if not (cd > 0).any():
        raise ConfigError(f"{path}: every candela value is 0: the luminaire emits nothing")
    if len(gamma) < 2 or not (np.diff(gamma) > 0).all() or gamma[0] < 0 or gamma[-1] > 180:
        raise ConfigError(f"{path}: vertical angles {gamma.tolist()[:6]}...: need at least two, increasing, "
                          f"within 0-180 degrees")


def _ies_text(path: str, raw: bytes) -> tuple[str, str]:
    """(text photompy can read, the LM-63 version).  Files are often Latin-1 (photompy decodes
    UTF-8 only); LM-63-1986 files have no version line and LM-63-1991 ones start ``IESNA91``, which
    photompy refuses: their numbers are laid out as in 1995, so they are read as 1995."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    if "TILT=" not in text.upper():
        raise ConfigError(f"{path}: not an IES LM-63 file: no TILT= line (empty, truncated or another format)")
    first, _, rest = text.lstrip("\ufeff").partition("\n")
    head = first.strip().upper()
    for version in ("LM-63-2019", "LM-63-2002", "LM-63-1995"):
        if head.startswith(("IES:", "IESNA:")) and head.endswith(version):
            return text, version
    if head.startswith("IESNA91"):
        return "IESNA:LM-63-1995\n" + rest, "LM-63-1991"
    return "IESNA:LM-63-1995\n" + text, "LM-63-1986"


#: the type C web a type B table is read onto: (gamma step, C step) in degrees
TYPE_B_WEB = (0.5, 1.0)


def type_b_web(horiz: np.ndarray, vert: np.ndarray, table: np.ndarray) -> Distribution:
    """A type B table (candela ``table`` (H, V) over horizontal angles ``horiz`` and vertical angles
    ``vert``, degrees, the beam centre at H = V = 0) as a type C Distribution on a TYPE_B_WEB grid.
    The luminaire's frame is type C's (nadir = the beam centre, C0, C90 = C0 x nadir), and a
    direction e reads V = atan2(e.C0, e.nadir) and H = atan2(-e.C90, e.nadir), as Radiance's ies2rad
    and source.cal read type B (``srcB_vert``, ``srcB_horiz``; an asymmetric file lights a plane as
    `ies2rad` + `rtrace` do to 1e-3, tests/test_luminaires.py); bilinear in (H, V), 0 outside the
    table (the back hemisphere)."""
    gamma = np.arange(0.0, 180.0 + 1e-9, TYPE_B_WEB[0])
    c = np.arange(0.0, 360.0 + 1e-9, TYPE_B_WEB[1])
    cc, gg = np.meshgrid(np.radians(c), np.radians(gamma), indexing="ij")
    x, y, z = np.sin(gg) * np.cos(cc), np.sin(gg) * np.sin(cc), np.cos(gg)
    v, h = np.degrees(np.arctan2(x, z)), np.degrees(np.arctan2(-y, z))
    cd = bilinear(horiz, vert, table, h, v)  # one horizontal plane: the same every way
    eps = 1e-9
    inside = (v >= vert[0] - eps) & (v <= vert[-1] + eps) & (h >= horiz[0] - eps) & (h <= horiz[-1] + eps)
    return Distribution(c, gamma, np.where(inside, cd, 0.0))


def _read_ies(path: str, raw: bytes) -> Photometric:
    import photompy  # noqa: PLC0415  lazy: only a run with luminaires needs it (and matplotlib, which it imports)
    from photompy.exceptions import IESDataError  # noqa: PLC0415
    from photompy.photometry import LampSymmetry, PhotometricType  # noqa: PLC0415
    from photompy.tilt import TiltData  # noqa: PLC0415

    text, version = _ies_text(path, raw)
    try:
        ies = photompy.IESFile.read(text)
    except Exception as exc:  # anything photompy raises on this file is the file's fault: say which file
        if isinstance(exc, IESDataError) and "malformed" in str(exc):  # photompy's words for a first plane not at 0
            raise ConfigError(f"{path}: type C horizontal angles must start at 0 (files of 90-270 lateral "
                              f"symmetry are not read)") from None
        raise ConfigError(f"{path}: malformed or truncated IES LM-63 file ({type(exc).__name__}: {exc})") from None
    hdr, phot = ies.header, ies.photometry
    if hdr.photometric_type not in (PhotometricType.C, PhotometricType.B):
        raise ConfigError(f"{path}: type {hdr.photometric_type.name} photometry is not supported (type C, the "
                          f"nadir-based C-gamma system of interior and most area luminaires, and type B, "
                          f"floodlights' horizontal polar axis)")
    tilt = None
    if isinstance(hdr.tilt, TiltData):
        if not (np.isfinite(hdr.tilt.factors).all() and (hdr.tilt.factors >= 0).all()
                and (np.diff(hdr.tilt.angles) > 0).all()):
            raise ConfigError(f"{path}: TILT=INCLUDE table has non-increasing angles or bad factors")
        tilt = (hdr.tilt.angles.copy(), hdr.tilt.factors.copy())
    elif hdr.tilt != "NONE":
        raise ConfigError(f"{path}: TILT={hdr.tilt} (tilt factors in another file) is not supported: use "
                          f"TILT=NONE or TILT=INCLUDE")
    # photompy applies the candela multiplier but not the ballast factor, nor LM-63-1995's (and
    # earlier) ballast-lamp photometric factor in the place 2002 calls future use and 2019 the
    # file generation type (not a factor)
    factor = hdr.ballast_factor
    if version in ("LM-63-1986", "LM-63-1991", "LM-63-1995"):
        factor *= hdr.future_use
    if not (math.isfinite(factor) and factor > 0):
        raise ConfigError(f"{path}: ballast factor {factor:g} must be a finite number > 0")
    if hdr.photometric_type == PhotometricType.B:
        try:
            web = phot.expanded()  # photompy mirrors a symmetric type B table (V 0-90, H 0-90 or one plane)
        except (NotImplementedError, ValueError) as exc:
            raise ConfigError(f"{path}: type B table not read ({exc})") from None
        vert, horiz = np.asarray(web.thetas, np.float64), np.asarray(web.phis, np.float64)
        table = np.asarray(web.values, np.float64) * factor
        _check_table(path, vert + 90.0, table)  # its values (its angles -90 to 90: checked below)
        if not (len(vert) >= 2 and (np.diff(vert) > 0).all() and (np.diff(horiz) > 0).all()
                and vert[0] >= -90 and vert[-1] <= 90 and horiz[0] >= -90 and horiz[-1] <= 90):
            raise ConfigError(f"{path}: type B angles must increase within -90 to 90 degrees")
        opening = hdr.luminous_opening
        return Photometric(path, f"IES {version}, type B (horizontal polar axis), on a type C web of "
                                 f"{TYPE_B_WEB[0]:g} x {TYPE_B_WEB[1]:g} degrees" + (", TILT=INCLUDE" if tilt else ""),
                           type_b_web(horiz, vert, table),
                           hdr.lumens_per_lamp * hdr.num_lamps if hdr.lumens_per_lamp > 0 else None,
                           hdr.input_watts if hdr.input_watts > 0 else None,
                           (float(opening.width), float(opening.length), float(opening.height)),
                           opening.shape.name.lower(), tilt)
    gamma, cd = np.asarray(phot.thetas, np.float64), np.asarray(phot.values, np.float64) * factor
    _check_table(path, gamma, cd)
    symmetry = {LampSymmetry.AXIAL: "axial", LampSymmetry.QUAD: "quadrant", LampSymmetry.HALF: "c0-c180",
                LampSymmetry.NONE: "none"}.get(phot.symmetry)
    phis = np.asarray(phot.phis, np.float64)
    if symmetry is None or not (np.diff(phis) > 0).all() or phis[-1] > 360:
        raise ConfigError(f"{path}: horizontal angles {phis[0]:g} to {phis[-1]:g}: type C needs 0, 0-90, 0-180 or "
                          f"0-360, increasing")
    described = {"axial": "axially symmetric", "quadrant": "quadrant symmetric (0-90)",
                 "c0-c180": "symmetric about C0-C180 (0-180)", "none": "full (0-360)"}[symmetry]
    opening = hdr.luminous_opening
    lumens = hdr.lumens_per_lamp * hdr.num_lamps if hdr.lumens_per_lamp > 0 else None
    return Photometric(path, f"IES {version}, type C, {described}" + (", TILT=INCLUDE" if tilt else ""),
                       Distribution.expand(phis, gamma, cd, symmetry), lumens,
                       hdr.input_watts if hdr.input_watts > 0 else None,
                       (float(opening.width), float(opening.length), float(opening.height)),
                       opening.shape.name.lower(), tilt)


#: a line that is one number with a decimal comma (EULUMDAT files written in some locales)
_DECIMAL_COMMA = re.compile(r"^[+-]?\d*,\d+([eE][+-]?\d+)?$")


def _read_ldt(path: str, raw: bytes) -> Photometric:
    from photompy.ldt import LDTHeader  # noqa: PLC0415  lazy: only a run with luminaires needs it

    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    # photompy's float() reads no decimal commas: a line that is one such number gets a point
    lines = [ln.strip() for ln in text.replace("\r\n", "\n").replace("\r", "\n").split("\n")]
    lines = [ln.replace(",", ".") if _DECIMAL_COMMA.match(ln) else ln for ln in lines]
    try:
        hdr, start = LDTHeader.from_lines(lines, strict=True)
    except Exception as exc:  # anything photompy raises on this header is the file's fault
        raise ConfigError(f"{path}: malformed or truncated EULUMDAT header ({type(exc).__name__}: {exc})") from None
    isym, mc, ng = hdr.symmetry, hdr.mc, hdr.ng
    if isym not in (0, 1, 2, 3, 4):
        raise ConfigError(f"{path}: symmetry indicator Isym {isym} is not 0-4")
    if mc < 1 or ng < 2:
        raise ConfigError(f"{path}: Mc {mc} C planes and Ng {ng} gamma angles: need Mc >= 1, Ng >= 2")
    if hdr.num_lamp_sets != 1 or len(hdr.lamps) != 1:
        raise ConfigError(f"{path}: {hdr.num_lamp_sets} lamp sets: which one the intensities are for is not "
                          f"defined; give a file with one")
    # The intensity block, read here: EULUMDAT lists all Mc C angles whatever the symmetry, then the
    # Ng gamma angles, then only the stored planes (Isym 1: one; 2 and 3: Mc/2 + 1; 4: Mc/4 + 1;
    # Isym 3's from C90 to C270).  photompy 0.3.1 reads as many C angles as stored planes and
    # relabels Isym 3's planes by 270 degrees, so it misreads every symmetric file but Mc = 1.
    planes = {0: mc, 1: 1, 2: mc // 2 + 1, 3: mc // 2 + 1, 4: mc // 4 + 1}[isym]
    tokens = [ln for ln in lines[start:] if ln]
    need = mc + ng + planes * ng
    if len(tokens) != need:
        raise ConfigError(f"{path}: {len(tokens)} numbers after the header where EULUMDAT with Mc {mc}, Ng {ng}, "
                          f"Isym {isym} has {need} ({'truncated' if len(tokens) < need else 'extra values'})")
    try:
        nums = np.array([float(t) for t in tokens])
    except ValueError as exc:
        raise ConfigError(f"{path}: malformed EULUMDAT data ({exc})") from None
    c_all, gamma = nums[:mc], nums[mc:mc + ng]
    if not (np.isfinite(c_all).all() and c_all[0] == 0 and (np.diff(c_all) > 0).all() and c_all[-1] < 360):
        raise ConfigError(f"{path}: C angles must increase from 0 to below 360")
    first = int(np.searchsorted(c_all, 90.0)) if isym == 3 else 0
    stored = c_all[first:first + planes] if isym != 1 else np.zeros(1)
    span = {0: (0.0, 360.0), 1: (0.0, 0.0), 2: (0.0, 180.0), 3: (90.0, 270.0), 4: (0.0, 90.0)}[isym]
    if len(stored) != planes or stored[0] != span[0] or (isym in (2, 3, 4) and stored[-1] != span[1]):
        raise ConfigError(f"{path}: the C angles do not hold the planes Isym {isym} stores ({span[0]:g} to "
                          f"{span[1]:g} degrees)")
    lamp = hdr.lamps[0]
    if not (math.isfinite(lamp.total_flux) and lamp.total_flux > 0):
        raise ConfigError(f"{path}: lamp flux {lamp.total_flux:g} lm must be > 0 (the intensities are cd per 1000 lm "
                          f"of it)")
    cf = hdr.conversion_factor if hdr.conversion_factor not in (0.0, 1.0) else 1.0
    cd = nums[mc + ng:].reshape(planes, ng) * (lamp.total_flux / 1000.0) * cf
    _check_table(path, gamma, cd)
    symmetry = {0: "none", 1: "axial", 2: "c0-c180", 3: "c90-c270", 4: "quadrant"}[isym]
    described = {0: "no symmetry", 1: "axially symmetric", 2: "symmetric about C0-C180",
                 3: "symmetric about C90-C270", 4: "symmetric about C0-C180 and C90-C270"}[isym]
    ll, lw = hdr.luminous_length / 1000.0, hdr.luminous_width / 1000.0
    shape = "point" if ll <= 0 else ("disc" if lw <= 0 else "rectangle")
    label = f"EULUMDAT, Isym {isym} ({described})" + (f", measured at {hdr.tilt:g} degrees tilt" if hdr.tilt else "")
    return Photometric(path, label, Distribution.expand(stored, gamma, cd, symmetry),
                       None if lamp.num_lamps < 0 else float(lamp.total_flux),
                       float(lamp.wattage) if lamp.wattage > 0 else None,
                       (lw if lw > 0 else ll, ll, hdr.luminous_height_c0 / 1000.0), shape)


def read_photometric(path: str | os.PathLike) -> Photometric:
    """Read an .ies (IES LM-63) or .ldt (EULUMDAT) file; ConfigError naming it and the problem."""
    path = os.fspath(path)
    suffix = Path(path).suffix.lower()
    if suffix not in (".ies", ".ldt"):
        raise ConfigError(f"{path}: not a photometric file (.ies or .ldt)")
    try:
        import photompy  # noqa: F401, PLC0415  lazy: it imports matplotlib; the container image leaves both out
    except ImportError:
        raise ConfigError(f"{path}: reading photometric files needs photompy (pip install photompy), not installed "
                          f"here (the container image leaves it out)") from None
    try:
        raw = Path(path).read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such photometric file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    return _read_ies(path, raw) if suffix == ".ies" else _read_ldt(path, raw)


def read_ies_bytes(label: str, raw: bytes) -> Photometric:
    """An IES LM-63 profile given as bytes (a glTF file's embedded one); ConfigError naming ``label``."""
    try:
        import photompy  # noqa: F401, PLC0415  lazy, as in read_photometric
    except ImportError:
        raise ConfigError(f"{label}: reading photometric files needs photompy (pip install photompy), not "
                          f"installed here") from None
    return _read_ies(label, raw)


# -- the luminaire -------------------------------------------------------------------------------

#: a flat luminous opening's near field, (distance in opening sizes, grid side n) nearest first: a
#: point within the first distance is lit by an 8 x 8 grid of points on the opening, within the
#: second by 4 x 4, beyond by the photometric centre alone.  Under a Lambertian square the centre
#: alone reads E 33% high at one size, 8% at two, 1.3% at five; the grids' worst at each tier's edge
#: is about 0.3% (a size away: 8 x 8 0.30%, 4 x 4 1.2%; beyond 2.7 sizes 4 x 4 under 0.25%; beyond
#: 14 sizes the centre under 0.25%)
NEAR_FIELD = ((2.7, 8), (14.0, 4))

def default_c0(aim: np.ndarray) -> np.ndarray:
    """The C0 reference of a luminaire aimed along unit ``aim`` (the scene file's frame): the file's
    +X made perpendicular to the aim, or its +Y when the aim is within 2.6 degrees of +-X."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(aim[0]) < 0.999 else np.array([0.0, 1.0, 0.0])
    ref = ref - (ref @ aim) * aim
    return ref / np.linalg.norm(ref)


@dataclass(kw_only=True)
class Luminaire(PointSource):
    """A photometric file's luminaire at ``position`` (m, the solver's frame), its nadir along unit
    ``aim`` and its C0 plane along unit ``c0`` (both the solver's frame, c0 perpendicular to aim),
    its candela times ``multiplier`` (the schedule's) and the TILT=INCLUDE factor at its tilt.
    ``placed``: the schedule entry as given (file coordinates), for the report."""

    photometric: Photometric
    aim: np.ndarray = field(default_factory=lambda: np.array([0.0, -1.0, 0.0]))
    c0: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    multiplier: float = 1.0
    placed: dict = field(default_factory=dict)
    #: linear RGB per-channel factor (glTF EXT_lights_ies' ``color``); white by default
    color: np.ndarray = field(default_factory=lambda: np.ones(3))

    def __post_init__(self) -> None:
        self.color = np.asarray(self.color, np.float64).reshape(3)
        self.aim = np.asarray(self.aim, np.float64).reshape(3)
        self.aim = self.aim / np.linalg.norm(self.aim)
        c0 = np.asarray(self.c0, np.float64).reshape(3)
        c0 = c0 - (c0 @ self.aim) * self.aim
        if not np.linalg.norm(c0) > 1e-9:
            raise ConfigError(f"{self.name}: its C0 direction lies along its aim")
        self.c0 = c0 / np.linalg.norm(c0)
        self.c90 = np.cross(self.c0, self.aim)
        # the tilt of the aim from straight down (the solver's -Y), for TILT=INCLUDE
        self.tilt_deg = math.degrees(math.acos(min(1.0, max(-1.0, -float(self.aim[1])))))
        self.scale = self.multiplier * self.photometric.tilt_factor(self.tilt_deg)
        self.intensity = self.watts_per_sr
        super().__post_init__()

    @property
    def lumens(self) -> float:
        """lm it emits: the table's flux times the multiplier and tilt factor (and the luminance Y of
        its colour, 1 for white)."""
        y = 1.0 if (self.color == 1.0).all() else float(Y_WEIGHTS @ self.color)  # white: exactly the table's
        return self.photometric.lumens * self.scale * y

    def to_wire(self) -> dict:
        """What rebuilds it on a worker (``from_wire``; source_wire.py): JSON-able, every float exact
        (its frame and scale as computed here, so a worker's copy is this one to the bit)."""
        ph = self.photometric
        dist = ph.distribution
        return {"name": self.name, "position": self.position.tolist(), "aim": self.aim.tolist(),
                "c0": self.c0.tolist(), "multiplier": self.multiplier, "scale": self.scale, "placed": self.placed,
                "color": self.color.tolist(),
                "photometric": {"file": ph.file, "label": ph.label, "lamp_lumens": ph.lamp_lumens,
                                "input_watts": ph.input_watts, "opening_m": list(ph.opening_m),
                                "opening_shape": ph.opening_shape,
                                "tilt": None if ph.tilt is None else [ph.tilt[0].tolist(), ph.tilt[1].tolist()],
                                "c": dist.c.tolist(), "gamma": dist.gamma.tolist(), "cd": dist.cd.tolist()}}

    @classmethod
    def from_wire(cls, d: dict) -> "Luminaire":
        ph = d["photometric"]
        tilt = None if ph["tilt"] is None else (np.array(ph["tilt"][0], np.float64),
                                                np.array(ph["tilt"][1], np.float64))
        photometric = Photometric(str(ph["file"]), str(ph["label"]),
                                  Distribution(np.array(ph["c"], np.float64), np.array(ph["gamma"], np.float64),
                                               np.array(ph["cd"], np.float64)),
                                  ph["lamp_lumens"], ph["input_watts"], tuple(ph["opening_m"]),
                                  str(ph["opening_shape"]), tilt)
        lum = cls(position=np.array(d["position"], np.float64), name=str(d["name"]), photometric=photometric,
                  aim=np.array(d["aim"], np.float64), c0=np.array(d["c0"], np.float64),
                  multiplier=float(d["multiplier"]), placed=dict(d["placed"]),
                  color=np.array(d.get("color", [1.0, 1.0, 1.0]), np.float64))
        # the frame and scale as the coordinator computed them, not normalised again (bit for bit)
        lum.aim, lum.c0 = np.array(d["aim"], np.float64), np.array(d["c0"], np.float64)
        lum.c90 = np.cross(lum.c0, lum.aim)
        lum.scale = float(d["scale"])
        return lum

    def candela(self, dirs: np.ndarray) -> np.ndarray:
        """(m,) cd toward unit ``dirs`` (m,3) of the solver's frame: the file's table at the
        direction's (gamma, C) in the luminaire's frame."""
        d = np.asarray(dirs, np.float64)
        z, x, y = d @ self.aim, d @ self.c0, d @ self.c90
        gamma = np.degrees(np.arctan2(np.hypot(x, y), z))
        c = np.degrees(np.arctan2(y, x))
        return self.photometric.distribution.at(gamma, c) * self.scale

    @property
    def opening(self) -> tuple[str, float, float]:
        """(shape, length along C0, width along C90) of the luminous opening as modelled: "rectangle"
        or "disc" (its diameter both) when the file gives a flat one, else "point" (0, 0): LM-63 and
        EULUMDAT give the length along the C0-C180 plane and the width along C90-C270."""
        w, ln, h = (abs(float(v)) for v in self.photometric.opening_m)
        shape = self.photometric.opening_shape
        if shape in ("rectangular", "rectangle") and w > 0 and ln > 0 and h == 0:
            return "rectangle", ln, w
        if shape in ("circular", "disc") and w > 0 and h == 0:
            return "disc", w, w
        return "point", 0.0, 0.0

    def opening_grid(self, n: int) -> np.ndarray:
        """(n*n, 3) offsets from the position of n x n points spread evenly over the opening, in the
        solver's frame (cell centres of a rectangle; a disc's points on equal-area rings, sunflower)."""
        shape, ln, w = self.opening
        if shape == "rectangle":
            t = (np.arange(n) + 0.5) / n - 0.5
            u, v = np.meshgrid(t * ln, t * w, indexing="ij")
        else:
            k = np.arange(n * n) + 0.5
            rad, ang = 0.5 * ln * np.sqrt(k / (n * n)), k * math.pi * (3.0 - math.sqrt(5.0))
            u, v = rad * np.cos(ang), rad * np.sin(ang)
        return u.reshape(-1, 1) * self.c0 + v.reshape(-1, 1) * self.c90

    def irradiance(self, points: np.ndarray, normals: np.ndarray, tracer, offset: float) -> np.ndarray:
        """I cos / d^2 from the photometric centre (PointSource's, exact for a point opening); within
        the near field of a flat opening (``NEAR_FIELD``), the mean over an n x n grid of points on
        the opening of I(direction) cos / d^2 instead, times the centre's visibility (its shadow ray,
        or the panes' transmittance): the opening's extent, not its penumbra."""
        shape, ln, w = self.opening
        if shape == "point":
            return super().irradiance(points, normals, tracer, offset)
        pts, nrm = np.asarray(points, np.float64), np.asarray(normals, np.float64)
        r = np.linalg.norm(self.position - pts, axis=1)
        size = max(ln, w)
        tier = np.full(len(pts), -1)  # the NEAR_FIELD tier of each point (-1: the centre alone)
        for k, (sizes, _) in reversed(list(enumerate(NEAR_FIELD))):
            tier[(r <= sizes * size) & (r > offset)] = k
        out = np.zeros((len(pts), 3))
        far = np.flatnonzero(tier < 0)
        if len(far):
            out[far] = super().irradiance(pts[far], nrm[far], tracer, offset)
        for k, (_, n) in enumerate(NEAR_FIELD):
            rows = np.flatnonzero(tier == k)
            if not len(rows):
                continue
            toward = (self.position - pts[rows]) / r[rows, None]
            seen = visibility(tracer, pts[rows] + offset * toward, toward, r[rows] - 2.0 * offset)
            got = np.zeros((len(rows), 3))
            grid = self.opening_grid(n)
            for g in grid:
                d = self.position + g - pts[rows]
                dist = np.linalg.norm(d, axis=1)
                cos = np.einsum("ij,ij->i", d, nrm[rows]) / dist
                lit = cos > 0
                got[lit] += self.intensity_at(-d[lit] / dist[lit, None]) * (cos[lit] / dist[lit] ** 2)[:, None]
            out[rows] = got / len(grid) * seen
        return out

    def watts_per_sr(self, dirs: np.ndarray) -> np.ndarray:
        """(m,3) W/sr per channel: I / 179 lm/W times its colour (white: the same in each)."""
        return (self.candela(dirs) / EFFICACY)[:, None] * self.color[None, :]

    def power(self) -> np.ndarray:
        """(3,) W: the table's exact flux (lm) / 179 times its colour, per channel."""
        return self.photometric.lumens * self.scale / EFFICACY * self.color

    def rays(self, n: int, rng: np.random.Generator) -> RayBatch:
        """``n`` rays from the position, sampled by the table (``Distribution.sample``), each half
        carrying exactly half the power (the ledger books ``power()`` and closes to round-off)."""
        half = half_mask(np.array([n]), rng)
        gamma, c, weight = np.empty(n), np.empty(n), np.empty(n)
        split = 0 < int(half.sum()) < n  # one ray (either half) carries it all
        for which in (True, False):
            rows = np.flatnonzero(half == which)
            if len(rows):
                gamma[rows], c[rows], weight[rows] = self.photometric.distribution.sample(len(rows), rng)
        s = np.sin(gamma)
        dirs = ((s * np.cos(c))[:, None] * self.c0 + (s * np.sin(c))[:, None] * self.c90
                + np.cos(gamma)[:, None] * self.aim)
        dirs /= np.linalg.norm(dirs, axis=1)[:, None]
        power = half_weights(weight, half)[:, None] * self.power()[None, :]
        origins = np.broadcast_to(self.position, (n, 3)).copy()
        shape, ln, w = self.opening
        if shape != "point":  # from anywhere on the opening (its luminance the same all over it)
            u, v = rng.random(n), rng.random(n)
            if shape == "rectangle":
                a, b = (u - 0.5) * ln, (v - 0.5) * w
            else:
                a, b = 0.5 * ln * np.sqrt(u) * np.cos(2 * math.pi * v), 0.5 * ln * np.sqrt(u) * np.sin(2 * math.pi * v)
            origins += a[:, None] * self.c0 + b[:, None] * self.c90
        return RayBatch(origins=origins, dirs=dirs, power=power, shooter=np.zeros(n, np.int64),
                        half=half if split else None)


# -- the schedule --------------------------------------------------------------------------------

def _vector(value, what: str) -> np.ndarray:
    """Three finite numbers, or ValueError saying what is wrong."""
    if not (isinstance(value, list | tuple) and len(value) == 3
            and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)):
        raise ValueError(f"{what} must be [x, y, z], three numbers, not {json.dumps(value)[:60]}")
    v = np.array(value, np.float64)
    if not np.isfinite(v).all():
        raise ValueError(f"{what} {v.tolist()} must be finite")
    return v


def _number(value, what: str) -> float:
    if not isinstance(value, int | float) or isinstance(value, bool) or not math.isfinite(value):
        raise ValueError(f"{what} must be a finite number, not {json.dumps(value)[:60]}")
    return float(value)


def load_schedule(path: str | os.PathLike, scene, scale: float = 1.0) -> list[Luminaire]:
    """The luminaires of a schedule: a JSON object or a list of objects with ``file`` (the .ies or
    .ldt, relative to the JSON file), ``position`` [x, y, z] and optionally ``aim`` [x, y, z] (the
    nadir's direction; default straight down), ``rotation`` (degrees of C0 about the aim),
    ``multiplier`` (> 0: dimming or lumen scaling) and ``name``.  Positions and aims are in the
    scene file's coordinates and units, as its vertices: times ``scale``, turned by the scene's up
    axis (``scene.rotation``).  ConfigError naming the file and the problem for anything else."""
    path = os.fspath(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such luminaire schedule") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot be read ({exc})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    entries = [data] if isinstance(data, dict) else data
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise ConfigError(f"{path}: a luminaire schedule is a JSON object or a list of objects")
    if not entries:
        raise ConfigError(f"{path}: the schedule holds no luminaires")
    rotation = np.asarray(scene.rotation, np.float64)
    tri = scene.vertices[scene.faces[scene.valid]].reshape(-1, 3)
    lo, hi = tri.min(axis=0), tri.max(axis=0)
    pad = POSITION_PAD * float(np.linalg.norm(hi - lo)) + 1e-12 * float(np.abs(tri).max())
    down = rotation.T @ np.array([0.0, -1.0, 0.0])  # straight down, in the file's frame
    files: dict[str, Photometric] = {}
    out = []
    for i, entry in enumerate(entries):
        name = entry.get("name")
        where = f"{path}: luminaire {i + 1}" + (f" ({name})" if isinstance(name, str) and name else "")
        try:
            unknown = sorted(set(entry) - set(SCHEDULE_KEYS))
            if unknown:
                raise ValueError(f"unknown key(s) {', '.join(map(repr, unknown))}; the keys are "
                                 f"{', '.join(SCHEDULE_KEYS)}")
            if not isinstance(entry.get("file"), str) or not entry["file"]:
                raise ValueError("needs \"file\": the .ies or .ldt, relative to the schedule")
            if "position" not in entry:
                raise ValueError("needs \"position\": [x, y, z] in the scene file's coordinates")
            if name is not None and not isinstance(name, str):
                raise ValueError(f"name must be a string, not {json.dumps(name)[:60]}")
            position = _vector(entry["position"], "position")
            aim = _vector(entry["aim"], "aim") if "aim" in entry else down
            if not np.linalg.norm(aim) > 0:
                raise ValueError("aim [0, 0, 0] has no direction")
            aim = aim / np.linalg.norm(aim)
            turn = math.radians(_number(entry.get("rotation", 0.0), "rotation"))
            multiplier = _number(entry.get("multiplier", 1.0), "multiplier")
            if not multiplier > 0:
                raise ValueError(f"multiplier {multiplier:g} must be > 0")
        except ValueError as exc:
            raise ConfigError(f"{where}: {exc}") from None
        at = rotation @ (position * scale)
        if ((at < lo - pad) | (at > hi + pad)).any():
            corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
            box = corners @ rotation / scale  # the box in the file's frame and units
            raise ConfigError(f"{where}: position {position.tolist()} lies outside the scene, whose bounding box "
                              f"in the file's coordinates is {box.min(axis=0).tolist()} to {box.max(axis=0).tolist()}")
        file = os.path.join(os.path.dirname(path), entry["file"])
        try:
            if file not in files:
                files[file] = read_photometric(file)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None
        c0 = default_c0(aim)
        c0 = math.cos(turn) * c0 + math.sin(turn) * np.cross(c0, aim)  # C0 turned towards C90
        placed = {"file": entry["file"], "position": position.tolist(), "aim": aim.tolist(),
                  "rotation_deg": math.degrees(turn), "multiplier": multiplier}
        out.append(Luminaire(at, name=name or f"{Path(entry['file']).name} #{i + 1}", photometric=files[file],
                             aim=rotation @ aim, c0=rotation @ c0, multiplier=multiplier, placed=placed))
    return out


# -- the report ----------------------------------------------------------------------------------

def report_section(patches, grid: dict | None = None, tracer=None) -> dict | None:
    """report.json's ``luminaires`` (None when the run has none): per photometric file its count,
    lumens and watts; with a work-plane ``grid`` (``photometry.workplane``, its points kept) the
    installation's utilisation factor, and per file the share of its flux that reaches the grid
    directly (exact: one shadow ray a point, ``tracer`` the scene's Embree scene)."""
    lums = [s for s in patches.sources if isinstance(s, Luminaire)]
    if not lums:
        return None
    if grid is not None and tracer is None:
        tracer = Tracer.mesh(patches)
    types: dict[str, list[Luminaire]] = {}
    for lum in lums:
        types.setdefault(lum.photometric.file, []).append(lum)
    total = sum(lum.lumens for lum in lums)
    points = grid["points"] if grid is not None else np.zeros((0, 3))
    area = grid["spacing_m"] ** 2 if grid is not None else 0.0  # each grid point stands for one cell
    up = np.broadcast_to(np.array([0.0, 1.0, 0.0]), points.shape).copy()
    entries = []
    for file, group in types.items():
        ph = group[0].photometric
        lumens = sum(lum.lumens for lum in group)
        entry = {"file": Path(file).name, "type": ph.label, "count": len(group), "lumens_each": ph.lumens,
                 "lumens": lumens, "lamp_lumens": ph.lamp_lumens, "input_watts_each": ph.input_watts,
                 "input_watts": None if ph.input_watts is None else ph.input_watts * len(group),
                 "opening_m": list(ph.opening_m), "opening_shape": ph.opening_shape,
                 "opening_modelled": group[0].opening[0]}
        if len(points):
            h = np.sum([lum.irradiance(points, up, tracer, 2e-6 * patches.scale)[:, 0] for lum in group], axis=0)
            entry["workplane_direct_share"] = float((EFFICACY * h).sum() * area / lumens)
        entries.append(entry)
    section: dict = {"count": len(lums), "lumens": total,
                     "input_watts": sum(e["input_watts"] or 0.0 for e in entries) or None, "types": entries}
    if grid is not None and len(points):
        # the work plane's flux is the luminaires' alone only when nothing else lights the scene
        lit_by_others = bool((patches.emission > 0).any()) or len(lums) < len(patches.sources)
        section["workplane_area_m2"] = area * len(points)
        section["utilisation_factor"] = None if lit_by_others else float(np.sum(grid["lux"]) * area / total)
        section["method"] = (
            "lumens: the exact integral of each file's interpolated candela table (its multiplier and ballast "
            "factor applied) times the schedule's multiplier; utilisation factor: sum of E x cell area over the "
            "work-plane grid (the border zone left out) / the luminaires' lumens, direct and reflected light of "
            "the whole installation (per file it cannot be told apart from one solve; null when emitting surfaces "
            "or other light sources light the scene too); workplane_direct_share: the share of a file's lumens "
            "reaching the grid directly")
    return section


def summary_lines(section: dict | None) -> list[str]:
    """A short table of report.json's ``luminaires`` for the command's last lines."""
    if not section:
        return []
    lines = []
    for t in section["types"]:
        watts = f", {t['input_watts_each']:g} W each" if t["input_watts_each"] else ""
        direct = (f", {100 * t['workplane_direct_share']:.1f}% of it directly on the work plane"
                  if "workplane_direct_share" in t else "")
        lines.append(f"  {t['count']:>3} x {t['file']:<24} {t['lumens_each']:>9,.0f} lm each{watts}; "
                     f"{t['lumens']:,.0f} lm{direct}")
    uf = section.get("utilisation_factor")
    head = f"{section['count']} luminaire(s), {section['lumens']:,.0f} lm" + (
        f", utilisation factor {uf:.3f} on the work plane" if uf is not None else "")
    return [head, *lines]


# -- glTF EXT_lights_ies ---------------------------------------------------------------------------

#: the glTF extension that places IES light profiles at nodes
IES_EXTENSION = "EXT_lights_ies"
IES_MIME = "application/x-ies-lm-63"


def read_gltf_ies(header: dict, path: str, scale: float, nodes, warnings: list, view_bytes) -> list[dict]:
    """The IES light profiles the glTF ``header``'s nodes place (``EXT_lights_ies``), in the file's
    frame times ``scale``: [{"kind": "ies", "name", "position", "aim", "c0", "photometric",
    "multiplier", "color", "placed"}].  Per the extension, a profile's nadir (vertical angle 0) is
    the node's local -Z and its C0 plane the local X/Z plane (C0 toward +X, C90 toward +Y); a
    profile is a file next to the scene (``uri``), a data URI, or a buffer view
    (``view_bytes(index)``).  ``multiplier`` scales it and ``color`` (linear RGB in [0, 1]) tints it
    per channel.  ``nodes``: (index, node, world 4x4).  Anything malformed: SceneError naming
    ``path`` and the light."""
    import base64  # noqa: PLC0415

    from dcrad.errors import SceneFormatError, SceneValueError  # noqa: PLC0415
    from dcrad.io.objfile import inside_folder  # noqa: PLC0415

    profiles = extension_lights(header, path, IES_EXTENSION)
    read: dict[int, Photometric] = {}

    def profile(index: int, where: str) -> Photometric:
        if index in read:
            return read[index]
        item = profiles[index]
        if not isinstance(item, dict):
            raise SceneFormatError(f"{where}: its profile is not a JSON object")
        uri, view = item.get("uri"), item.get("bufferView")
        try:
            if isinstance(uri, str) and uri.startswith("data:"):
                label, raw = f"{path}: {IES_EXTENSION} light {index} (embedded)", base64.b64decode(uri.split(",", 1)[1])
            elif isinstance(uri, str) and uri:
                folder = os.path.dirname(os.path.abspath(path))
                file = inside_folder(folder, uri, path, f"{IES_EXTENSION} light {index}")
                label, raw = file, Path(file).read_bytes()
            elif isinstance(view, int) and not isinstance(view, bool):
                if item.get("mimeType") != IES_MIME:
                    raise SceneFormatError(f"{where}: a profile in bufferView {view} needs mimeType '{IES_MIME}'")
                label, raw = f"{path}: {IES_EXTENSION} light {index} (bufferView {view})", view_bytes(view)
            else:
                raise SceneFormatError(f"{where}: its profile has neither a 'uri' nor a 'bufferView'")
        except (OSError, ValueError, IndexError, KeyError, TypeError) as exc:
            raise SceneFormatError(f"{where}: its profile cannot be read ({exc})") from None
        try:
            read[index] = read_ies_bytes(label, raw)
        except ConfigError as exc:
            raise SceneValueError(str(exc)) from None
        return read[index]

    out: list[dict] = []
    names: set[str] = set()
    for node_name, index, ref, world in placements(nodes, path, IES_EXTENSION, len(profiles)):
        label = profiles[index].get("name") if isinstance(profiles[index], dict) else None
        label = label if isinstance(label, str) and label else node_name
        where = f"{path}: {IES_EXTENSION} light {index} ('{label}', node '{node_name}')"
        mult = ref.get("multiplier", 1.0)
        if isinstance(mult, bool) or not isinstance(mult, int | float) or not (math.isfinite(mult) and mult >= 0):
            raise SceneValueError(f"{where}: multiplier {mult!r} must be a finite number >= 0")
        color = ref.get("color", [1.0, 1.0, 1.0])
        if not (isinstance(color, list) and len(color) == 3
                and all(isinstance(c, int | float) and not isinstance(c, bool) for c in color)
                and all(math.isfinite(c) and 0.0 <= c <= 1.0 for c in color)):
            raise SceneValueError(f"{where}: color {color!r} must be three numbers in [0, 1] (linear RGB)")
        world = np.asarray(world, np.float64)
        position = world[:3, 3] * scale
        aim, c0 = world[:3, :3] @ np.array([0.0, 0.0, -1.0]), world[:3, :3] @ np.array([1.0, 0.0, 0.0])
        if not (np.isfinite(position).all() and np.linalg.norm(aim) > 0 and np.linalg.norm(np.cross(aim, c0)) > 0):
            raise SceneValueError(f"{where}: its node's transform is not finite or has no direction")
        ph = profile(index, where)
        if mult == 0 or not max(color) > 0:
            warnings.append(f"{where} emits nothing (multiplier {mult:g}, color {color}); left out")
            continue
        name = unique_name(f"glTF IES light '{label}'", names)
        placed = {"name": label, "node": node_name, "type": "ies", "light": index,
                  "position": (position / scale).tolist(), "aim": (aim / np.linalg.norm(aim)).tolist(),
                  "multiplier": float(mult), "color": [float(c) for c in color]}
        out.append({"kind": "ies", "name": name, "position": position, "aim": aim, "c0": c0, "photometric": ph,
                    "multiplier": float(mult), "color": np.array(color, np.float64), "placed": placed})
    return out
