"""Glazing: the seed's ideal specular transmitter (van Liere, section 1.2, eq. 1.2).

A ray that meets glass goes on in the same direction with its power times tau(theta); the rest
stays on the pane, where the material's diffuse reflectance (MTL ``Kd``) reflects part of it like
any surface's light and the rest is absorbed (the pane's specular reflection, 4-8% near the normal,
is not modelled: it is booked as what the pane keeps).

tau(theta) is that of a plane-parallel pane of refractive index n (MTL ``Ni``, glTF
``KHR_materials_ior``; 1.52 when not given) whose normal-incidence transmittance tau_n (MTL ``Tf``,
glTF ``KHR_materials_transmission``) fixes its internal absorption: per polarisation, with r the
Fresnel reflectance of one face at the angle of incidence and a the internal transmittance along
the refracted path (a = a_n^(1 / cos theta_t)), T = (1 - r)^2 a / (1 - r^2 a^2), the sum of the
pane's multiple internal reflections; tau = (T_s + T_p) / 2.  a_n solves tau(0) = tau_n.  A tau_n
above what index n allows with no absorption at all (0.918 at 1.52: a file's Tf of 0.94) keeps the
angular shape of the clear pane, scaled to tau_n at the normal.  For 6 mm clear float glass
(tau_n 0.8788) this is the CIE 171:2006 polynomial of its cases 5.5 and 5.10 within 0.005 at every
angle to 85 degrees (0.0046 at 85; tests/test_glass.py).
"""

from __future__ import annotations

import numpy as np

__all__ = ["DEFAULT_IOR", "MAX_PANES", "Glazing", "pane_transmittance", "fresnel"]

#: refractive index of glass when the file gives none (soda-lime float glass)
DEFAULT_IOR = 1.52
#: panes a ray goes through at most; what is left after them stays on the last one (a ray between
#: two parallel panes facing each other at grazing incidence would bounce on forever otherwise:
#: it never does here, it goes straight, but a stack of coplanar duplicates could hold it)
MAX_PANES = 16


def fresnel(cos_i: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(r_s, r_p, cos theta_t): the Fresnel reflectances of one air-to-glass face and the cosine of
    the refracted angle, for incidence cosines ``cos_i`` (m,) in [0, 1] and indices ``n`` (m,)."""
    cos_i = np.clip(np.asarray(cos_i, np.float64), 0.0, 1.0)
    n = np.asarray(n, np.float64)
    sin_t = np.sqrt(np.maximum(1.0 - cos_i * cos_i, 0.0)) / n
    cos_t = np.sqrt(np.maximum(1.0 - sin_t * sin_t, 0.0))
    r_s = ((cos_i - n * cos_t) / (cos_i + n * cos_t)) ** 2
    r_p = ((n * cos_i - cos_t) / (n * cos_i + cos_t)) ** 2
    return r_s, r_p, cos_t


def _pane(r: np.ndarray, a: np.ndarray) -> np.ndarray:
    return (1.0 - r) ** 2 * a / np.maximum(1.0 - r * r * a * a, 1e-300)


def _internal(tau_n: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(a_n (k,3), scale (k,3)): the internal transmittance at the normal that gives ``tau_n`` (k,3)
    for indices ``n`` (k,), and the factor a clear pane's curve is scaled by where tau_n is above
    what n allows (else 1)."""
    r0 = ((n - 1.0) / (n + 1.0))[:, None] ** 2
    t = np.asarray(tau_n, np.float64)
    # r0^2 tau a^2 + (1 - r0)^2 a - tau = 0, the positive root
    q = 2.0 * r0 * r0 * t
    root = np.sqrt((1.0 - r0) ** 4 + 4.0 * r0 * r0 * t * t)
    a = np.where(q > 0, (root - (1.0 - r0) ** 2) / np.where(q > 0, q, 1.0), 0.0)
    clear = _pane(r0, np.ones_like(t))
    over = a >= 1.0
    return np.where(over, 1.0, a), np.where(over, t / clear, 1.0)


def pane_transmittance(cos_i: np.ndarray, tau_n: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(m,3) tau(theta) of panes of normal transmittance ``tau_n`` (m,3) and index ``n`` (m,) at
    incidence cosines ``cos_i`` (m,) (either side of the pane: |cos|)."""
    cos_i = np.abs(np.asarray(cos_i, np.float64))
    n = np.asarray(n, np.float64)
    a_n, scale = _internal(tau_n, n)
    r_s, r_p, cos_t = fresnel(cos_i, n)
    a = a_n ** (1.0 / np.maximum(cos_t, 1e-12))[:, None]
    tau = 0.5 * (_pane(r_s[:, None], a) + _pane(r_p[:, None], a)) * scale
    return np.where(cos_i[:, None] > 0.0, tau, 0.0)


class Glazing:
    """Which primitives of a ray tracer are panes, and their optics: ``mask`` (n,) bool, ``tau_n``
    (n,3) normal transmittance, ``ior`` (n,) refractive index (``Patches.glazing``)."""

    def __init__(self, mask: np.ndarray, tau_n: np.ndarray, ior: np.ndarray):
        self.mask = np.asarray(mask, bool)
        self.tau_n = np.asarray(tau_n, np.float64)
        self.ior = np.asarray(ior, np.float64)

    def __len__(self) -> int:
        return len(self.mask)

    def tau(self, prim: np.ndarray, cos_i: np.ndarray) -> np.ndarray:
        """(m,3) tau(theta) of the panes ``prim`` (m,) at incidence cosines ``cos_i`` (m,)."""
        return pane_transmittance(cos_i, self.tau_n[prim], self.ior[prim])

    def panes(self, prim: np.ndarray) -> np.ndarray:
        """(m,) bool: which hits ``prim`` (MISS -1, or primitives past the table: none) are panes."""
        return (prim >= 0) & (prim < len(self.mask)) & self.mask[np.clip(prim, 0, max(len(self.mask) - 1, 0))]

    def crossing(self, prim: np.ndarray, ng: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """(m,3) tau(theta) of the panes ``prim`` met along unit ``dirs`` (m,3), theta from their
        geometric normals ``ng`` (m,3, any length: Embree's), either side."""
        g = np.asarray(ng, np.float64)
        cos = np.abs(np.einsum("ij,ij->i", dirs, g)) / np.maximum(np.linalg.norm(g, axis=1), 1e-300)
        return self.tau(prim, cos)

    def take(self, rows: np.ndarray) -> "Glazing":
        return Glazing(self.mask[rows], self.tau_n[rows], self.ior[rows])
