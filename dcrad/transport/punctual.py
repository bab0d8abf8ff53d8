"""Point and spot lights of a glTF file (``KHR_lights_punctual``) as light sources of the run.

A glTF node that refers to a light (``extensions.KHR_lights_punctual.light``) places it: the
light sits at the node's world position and, a spot, points along the node's local -Z turned by
its world rotation (the node's scale moves it but leaves its cone alone, as the extension says).
``scene.load_scene`` reads them with the geometry (``read_gltf``) and turns them into the solver's
frame with it (``sources``: times ``scale``, turned by the up axis), so they are ``Scene.sources``
and every run that meshes the scene lights with them (``Scene.patches``).

* **Light.** ``intensity`` is candela (the extension's unit for point and spot lights), the
  luminous intensity of the light's ``color`` (linear RGB): I / 179 x color / Y(color) W/sr per
  channel (photometry.EFFICACY and Y_WEIGHTS), so the lux read back are the candela's whatever the
  colour, and a red light lights the red channel only.
* **Spot falloff.** Full intensity inside ``innerConeAngle``, none outside ``outerConeAngle``, and
  between them the extension's reference falloff (its README, "Inner and Outer Cone Angles"; the
  Khronos glTF sample renderer uses the same): t = (cos a - cos outer) / (cos inner - cos outer),
  I = I0 t^2.  Its flux is exact: 2 pi I0 ((1 - cos inner) + (cos inner - cos outer) / 3).
* **Left out, and said so.** ``range`` (a renderer's cut-off: the light follows the inverse square
  law everywhere here), directional lights (a sun at infinity: not a point source), and lights
  that emit nothing (intensity 0 or a black colour) each leave a warning.  Bad values (non-finite
  or negative intensity or colour, cone angles outside 0 <= inner < outer <= pi/2, an unknown type,
  a node naming a light the file lacks) are one error naming the file and the light.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from dcrad.errors import SceneFormatError, SceneValueError
from dcrad.outputs.photometry import EFFICACY, Y_WEIGHTS
from dcrad.transport.emitters import PointSource, half_lattice, half_weights
from dcrad.transport.gltf_lights import extension_lights, placements, unique_name
from dcrad.transport.shoot import RayBatch

__all__ = ["PunctualLight", "SpotLight", "read_gltf", "sources", "report_section", "summary_lines", "EXTENSION"]

EXTENSION = "KHR_lights_punctual"
#: the extension's default outer cone angle of a spot (radians)
DEFAULT_OUTER = math.pi / 4.0


def watts_per_sr(candela: float, color: np.ndarray) -> np.ndarray:
    """(3,) W/sr of a light of ``candela`` cd in linear RGB ``color`` (Y(color) > 0): its luminous
    intensity stays ``candela`` at 179 lm/W whatever the colour."""
    return candela / EFFICACY * np.asarray(color, np.float64) / float(Y_WEIGHTS @ color)


@dataclass(kw_only=True)
class PunctualLight(PointSource):
    """A glTF point light at ``position`` (m, the solver's frame): ``candela`` cd of linear RGB
    ``color`` the same every way.  ``placed``: the light as the file gives it (its frame and units),
    for the report."""

    candela: float = 1.0
    color: np.ndarray = field(default_factory=lambda: np.ones(3))
    placed: dict = field(default_factory=dict)

    kind = "point"

    def __post_init__(self) -> None:
        self.color = np.asarray(self.color, np.float64).reshape(3)
        self.peak = watts_per_sr(self.candela, self.color)
        self.intensity = self.peak
        super().__post_init__()

    @property
    def lumens(self) -> float:
        """lm it emits."""
        return 4.0 * math.pi * self.candela

    def to_wire(self) -> dict:
        """What rebuilds it on a worker (``from_wire``; source_wire.py), JSON-able and exact."""
        return {"name": self.name, "position": self.position.tolist(), "candela": self.candela,
                "color": self.color.tolist(), "placed": self.placed}

    @classmethod
    def from_wire(cls, d: dict) -> "PunctualLight":
        return cls(position=np.array(d["position"], np.float64), name=str(d["name"]), candela=float(d["candela"]),
                   color=np.array(d["color"], np.float64), placed=dict(d["placed"]))

    def power(self) -> np.ndarray:
        return 4.0 * math.pi * self.peak


@dataclass(kw_only=True)
class SpotLight(PunctualLight):
    """A glTF spot light: ``candela`` cd along unit ``axis`` (the solver's frame) out to ``inner``
    radians from it, none beyond ``outer``, the extension's falloff between (module doc)."""

    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, -1.0, 0.0]))
    inner: float = 0.0
    outer: float = DEFAULT_OUTER

    kind = "spot"

    def __post_init__(self) -> None:
        self.axis = np.asarray(self.axis, np.float64).reshape(3)
        self.axis = self.axis / np.linalg.norm(self.axis)
        self.cos_inner, self.cos_outer = math.cos(self.inner), math.cos(self.outer)
        super().__post_init__()
        self.intensity = self.spot_intensity

    def to_wire(self) -> dict:
        return super().to_wire() | {"axis": self.axis.tolist(), "inner": self.inner, "outer": self.outer}

    @classmethod
    def from_wire(cls, d: dict) -> "SpotLight":
        spot = cls(position=np.array(d["position"], np.float64), name=str(d["name"]), candela=float(d["candela"]),
                   color=np.array(d["color"], np.float64), placed=dict(d["placed"]),
                   axis=np.array(d["axis"], np.float64), inner=float(d["inner"]), outer=float(d["outer"]))
        spot.axis = np.array(d["axis"], np.float64)  # as the coordinator normalised it (bit for bit)
        return spot

    def falloff(self, cos: np.ndarray) -> np.ndarray:
        """(m,) share of the peak intensity at angles of cosine ``cos`` (m,) from the axis."""
        t = np.clip((np.asarray(cos, np.float64) - self.cos_outer) / (self.cos_inner - self.cos_outer), 0.0, 1.0)
        return t * t

    def spot_intensity(self, dirs: np.ndarray) -> np.ndarray:
        """(m,3) W/sr toward unit ``dirs`` (m,3)."""
        return self.falloff(np.asarray(dirs, np.float64) @ self.axis)[:, None] * self.peak[None, :]

    @property
    def lumens(self) -> float:
        return 2.0 * math.pi * self.candela * self._cap

    @property
    def _cap(self) -> float:
        """The cone's solid angle weighted by the falloff (sr): the flux over the peak intensity."""
        return (1.0 - self.cos_inner) + (self.cos_inner - self.cos_outer) / 3.0

    def power(self) -> np.ndarray:
        return 2.0 * math.pi * self._cap * self.peak

    def rays(self, n: int, rng: np.random.Generator) -> RayBatch:
        """``n`` rays over the outer cone only (uniform in solid angle, stratified, each half from
        its own shifted lattice), each carrying its direction's share of the intensity, each half
        exactly half the power (the ledger books ``power()`` and closes to round-off)."""
        u, half = half_lattice(n, rng)
        split = 0 < int(half.sum()) < n  # one ray (either half) carries it all
        cos = 1.0 - u[:, 0] * (1.0 - self.cos_outer)
        sin = np.sqrt(np.maximum(1.0 - cos * cos, 0.0))
        phi = 2.0 * math.pi * u[:, 1]
        a = np.array([1.0, 0.0, 0.0]) if abs(self.axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        t = np.cross(self.axis, a)
        t /= np.linalg.norm(t)
        b = np.cross(self.axis, t)
        dirs = ((sin * np.cos(phi))[:, None] * t + (sin * np.sin(phi))[:, None] * b
                + cos[:, None] * self.axis[None, :])
        power = half_weights(self.falloff(cos), half)[:, None] * self.power()[None, :]
        origins = np.broadcast_to(self.position, (n, 3)).copy()
        return RayBatch(origins=origins, dirs=dirs, power=power, shooter=np.zeros(n, np.int64),
                        half=half if split else None)


# -- reading ---------------------------------------------------------------------------------------

def _number(value, default: float) -> float:
    if value is None:
        return default
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError
    return float(value)


def read_gltf(header: dict, path: str, scale: float, nodes: Iterable, warnings: list) -> list[dict]:
    """The point and spot lights the glTF ``header`` places, in the file's frame times ``scale``:
    [{"name", "kind", "position", "axis", "candela", "color", "inner", "outer", "placed"}].
    ``nodes``: (index, node, world 4x4) of the default scene's nodes, depth-first.  Directional lights,
    ``range`` and dark lights leave warnings (module doc); bad lights raise a SceneError naming
    ``path`` and the light."""
    lights = extension_lights(header, path, EXTENSION)
    out: list[dict] = []
    names: set[str] = set()
    for node_name, index, _, world in placements(nodes, path, EXTENSION, len(lights)):
        light = lights[index]
        if not isinstance(light, dict):
            raise SceneFormatError(f"{path}: {EXTENSION} light {index} is not a JSON object")
        label = light.get("name") if isinstance(light.get("name"), str) and light.get("name") else node_name
        where = f"{path}: {EXTENSION} light {index} ('{label}', node '{node_name}')"
        kind = light.get("type")
        if kind == "directional":
            warnings.append(f"{where} is a directional light: dcrad lights with point and spot lights only (a sun "
                            f"at infinity is not a point source), so it lights nothing in this run")
            continue
        if kind not in ("point", "spot"):
            raise SceneFormatError(f"{where}: type {kind!r} is not one of point, spot, directional")
        try:
            candela = _number(light.get("intensity"), 1.0)
        except ValueError:
            raise SceneValueError(f"{where}: intensity {light.get('intensity')!r} is not a number") from None
        if not (math.isfinite(candela) and candela >= 0):
            raise SceneValueError(f"{where}: intensity {candela!r} cd must be finite and >= 0")
        color = light.get("color", [1.0, 1.0, 1.0])
        if not (isinstance(color, list) and len(color) == 3
                and all(isinstance(c, int | float) and not isinstance(c, bool) for c in color)):
            raise SceneValueError(f"{where}: color {color!r} is not three numbers (linear RGB)")
        rgb = np.array(color, np.float64)
        if not (np.isfinite(rgb).all() and (rgb >= 0).all()):
            raise SceneValueError(f"{where}: color {rgb.tolist()} must be finite and >= 0 in every channel")
        inner, outer = 0.0, DEFAULT_OUTER
        if kind == "spot":
            spot = light.get("spot", {})
            if not isinstance(spot, dict):
                raise SceneFormatError(f"{where}: 'spot' is not a JSON object")
            try:
                inner = _number(spot.get("innerConeAngle"), 0.0)
                outer = _number(spot.get("outerConeAngle"), DEFAULT_OUTER)
            except ValueError:
                raise SceneValueError(f"{where}: innerConeAngle {spot.get('innerConeAngle')!r} and outerConeAngle "
                                      f"{spot.get('outerConeAngle')!r} must be numbers (radians)") from None
            if not (math.isfinite(inner) and math.isfinite(outer) and 0.0 <= inner < outer <= math.pi / 2):
                raise SceneValueError(f"{where}: innerConeAngle {inner!r} and outerConeAngle {outer!r} must satisfy "
                                      f"0 <= inner < outer <= pi/2 (radians)")
        world = np.asarray(world, np.float64)
        position = world[:3, 3] * scale
        axis = world[:3, :3] @ np.array([0.0, 0.0, -1.0])
        norm = float(np.linalg.norm(axis))
        if not (np.isfinite(position).all() and math.isfinite(norm) and norm > 0):
            raise SceneValueError(f"{where}: its node's transform is not finite or has no direction")
        axis = axis / norm
        if "range" in light:
            warnings.append(f"{where}: range {light['range']!r} ignored: its light follows the inverse square law "
                            f"at every distance")
        if candela == 0 or not float(Y_WEIGHTS @ rgb) > 0:
            warnings.append(f"{where} emits nothing (intensity {candela:g} cd, color {rgb.tolist()}); left out")
            continue
        name = unique_name(f"glTF {kind} light '{label}'", names)
        placed = {"name": label, "node": node_name, "type": kind, "light": index,
                  "position": (position / scale).tolist(), "intensity_cd": candela, "color": rgb.tolist()}
        if kind == "spot":
            placed |= {"direction": axis.tolist(), "inner_cone_deg": math.degrees(inner),
                       "outer_cone_deg": math.degrees(outer)}
        if "range" in light:
            placed["range_ignored"] = light["range"]
        out.append({"name": name, "kind": kind, "position": position, "axis": axis, "candela": candela,
                    "color": rgb, "inner": inner, "outer": outer, "placed": placed})
    return out


def sources(lights: list[dict], rotation: np.ndarray) -> tuple:
    """The ``read_gltf`` lights (and ``luminaires.read_gltf_ies``' profiles) as light sources in the
    solver's frame (``rotation``: the scene's up axis, file -> solver)."""
    rotation = np.asarray(rotation, np.float64)
    out: list = []
    for lt in lights:
        at = rotation @ lt["position"]
        if lt["kind"] == "ies":  # EXT_lights_ies: a luminaire of the profile (luminaires.read_gltf_ies)
            from dcrad.transport.luminaires import Luminaire  # noqa: PLC0415  lazy: it imports photometric reading

            out.append(Luminaire(position=at, name=lt["name"], photometric=lt["photometric"],
                                 aim=rotation @ lt["aim"], c0=rotation @ lt["c0"], multiplier=lt["multiplier"],
                                 color=lt["color"], placed=lt["placed"]))
            continue
        common = {"name": lt["name"], "candela": lt["candela"], "color": lt["color"], "placed": lt["placed"]}
        if lt["kind"] == "spot":
            out.append(SpotLight(at, axis=rotation @ lt["axis"], inner=lt["inner"], outer=lt["outer"], **common))
        else:
            out.append(PunctualLight(at, **common))
    return tuple(out)


# -- the report ------------------------------------------------------------------------------------

def report_section(all_sources) -> dict | None:
    """report.json's ``gltf_lights`` (None when the run has none): each light as the file places it,
    its lumens, and the total."""
    lights = [s for s in all_sources if isinstance(s, PunctualLight)]
    if not lights:
        return None
    return {
        "count": len(lights), "lumens": float(sum(lt.lumens for lt in lights)),
        "lights": [{**lt.placed, "lumens": lt.lumens, "watts_per_sr": lt.peak.tolist()} for lt in lights],
        "method": "KHR_lights_punctual point and spot lights, positions and directions in the file's frame and "
                  "units; intensity (cd) is the luminous intensity of the light's colour, I / 179 lm/W x color / "
                  "Y(color) W/sr per channel; a spot's falloff between its cone angles is the extension's "
                  "reference ((cos a - cos outer) / (cos inner - cos outer))^2; range is not applied",
    }


def summary_lines(section: dict | None) -> list[str]:
    """The command's line for report.json's ``gltf_lights``."""
    if not section:
        return []
    kinds = [lt["type"] for lt in section["lights"]]
    parts = ", ".join(f"{kinds.count(k)} {k}" for k in ("point", "spot") if k in kinds)
    return [f"{section['count']} glTF light(s) ({parts}), {section['lumens']:,.0f} lm"]
