"""Materials and values as scene files give them, checked: reflectance, emission, textures, coordinates.

Both loaders (scene.py's OBJ/MTL, gltf.py's glTF) read a material's colours and textures through
these, so a bad value gets the same one-line error naming the file, the material and the value.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dcrad.errors import SceneValueError
from dcrad.io.texture import read_texture, uv_means

__all__ = [
    "DEFAULT_RHO", "LIST_MOST", "MAX_COORDINATE", "RHO_MAX_TEXTURE", "TextureMap", "check_emission", "check_rho",
    "fmt", "listing", "near", "texture", "textured_rho"
]

#: reflectance of faces without a usable material
DEFAULT_RHO = 0.5
#: most object names listed in one warning
LIST_MOST = 8
#: highest reflectance a texture may give (a white texel is 1.0, which no real surface reflects)
RHO_MAX_TEXTURE = 0.99

#: m: the farthest a vertex may lie from the origin after scaling.  The solver works in the scene's
#: own scale (a Cornell box at 1e30 m solves like one in metres), but squared lengths and areas
#: overflow float64 beyond about 1e150 m (--scale 1e300 failed as "invalid max_edge=inf")
MAX_COORDINATE = 1e100


@dataclass
class TextureMap:
    """A textured material's triangles: their rows in the scene, the factor, the linear image
    and the UV corners (len(rows), 3, 2), kept so patches can take their own UV sub-triangles."""

    rows: np.ndarray
    factor: np.ndarray
    image: np.ndarray
    uv: np.ndarray


def check_rho(values, where: str, text: str, factor: bool = False) -> np.ndarray:
    """A reflectance in [0, 1), or with ``factor`` (it multiplies a texture) in [0, 1]."""
    rho = np.asarray(values, np.float64)[:3]
    problem = (
        "a non-finite channel" if not np.isfinite(rho).all()
        else "a channel > 1" if factor and (rho > 1).any()
        else "a channel >= 1" if not factor and (rho >= 1).any()
        else "a negative channel" if (rho < 0).any() else None
    )
    if problem:
        raise SceneValueError(f"{where}: {text} has {problem}; reflectance must be in [0, 1)")
    return rho


def check_emission(values, where: str, text: str) -> np.ndarray:
    e = np.asarray(values, np.float64)[:3]
    if not np.isfinite(e).all() or (e < 0).any():
        what = "a non-finite" if not np.isfinite(e).all() else "a negative"
        raise SceneValueError(f"{where}: {text} has {what} channel; emission must be finite and >= 0")
    return e


def near(a, b, atol: float, rtol: float = 0.0) -> bool:
    """|a - b| <= atol + rtol * |b| everywhere; NaN counts as near (validated later)."""
    b = np.asarray(b, np.float64)
    return not np.any(np.abs(np.subtract(a, b)) > atol + rtol * np.abs(b))


def fmt(values) -> str:
    return " ".join(repr(float(x)) for x in values)


def listing(names) -> str:
    names = list(dict.fromkeys(names))
    more = f" and {len(names) - LIST_MOST} more" if len(names) > LIST_MOST else ""
    return ", ".join(f"'{n}'" for n in names[:LIST_MOST]) + more


# -- OBJ -----------------------------------------------------------------------------------
def texture(cache: dict, full: str, written: str, where: str, factor: str, warnings: list):
    """The linear image of a texture file (cached), or None with a warning naming it."""
    if full not in cache:
        try:
            cache[full] = read_texture(full)
        except OSError as exc:
            warnings.append(f"{where}: texture '{written}' not usable ({exc}); using the {factor} alone")
            cache[full] = None
    return cache[full]


def textured_rho(factor, image, uv, where: str, written: str, warnings: list) -> np.ndarray:
    """factor (3,) x the texture's mean over each UV triangle (T, 3, 2) -> (T, 3), capped below 1."""
    rho = np.asarray(factor, np.float64)[None, :] * uv_means(image, uv)
    if (rho > RHO_MAX_TEXTURE).any():
        warnings.append(f"{where}: texture '{written}' gives reflectance above {RHO_MAX_TEXTURE} "
                        f"(max {rho.max():.3f}); capped at {RHO_MAX_TEXTURE}")
        rho = np.minimum(rho, RHO_MAX_TEXTURE)
    return rho
