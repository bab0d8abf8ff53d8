"""Sampling: low-discrepancy points, triangle and cosine-hemisphere maps, frames.

All maps are vectorised over rows.  Stratification comes from a rank-1
Kronecker lattice (Roberts' R_d sequence) with a Cranley-Patterson random
shift per shooting patch, so every shot is an independent, randomly shifted,
well-stratified point set over (position on the triangle) x (direction).
Where the number of points is fixed in advance (the final gather's directions per
receiver half) a 2-D rank-1 Korobov lattice of exactly that many points
(``rank1_lattice``) is used instead: lower discrepancy than the sequence's first m points.
"""

from __future__ import annotations

import functools

import numpy as np

__all__ = [
    "kronecker_alpha",
    "lattice",
    "korobov_generator",
    "rank1_lattice",
    "triangle_points",
    "concentric_disk",
    "concentric_disk_inverse",
    "cosine_hemisphere",
    "cosine_hemisphere_columns",
    "onb",
]


def kronecker_alpha(dim: int) -> np.ndarray:
    """(dim,) generator of the R_d sequence: 1/phi_d^k, phi_d the root of x^(d+1) = x + 1."""
    phi = 2.0
    for _ in range(64):
        phi = (1.0 + phi) ** (1.0 / (dim + 1))
    return np.mod(1.0 / phi ** np.arange(1, dim + 1), 1.0)


def lattice(index: np.ndarray, shift: np.ndarray, dim: int, dtype=np.float64) -> np.ndarray:
    """Points of a randomly shifted R_d lattice.

    index : (m,) int   point number within its own set (0, 1, 2, ...)
    shift : (m, dim)   random shift of the set the point belongs to
    returns (m, dim) ``dtype`` in [0, 1)
    """
    alpha = kronecker_alpha(dim)
    # (index + 0.5) * alpha keeps the first point away from the lattice origin;
    # the fractional part is taken in float64 (index * alpha needs the digits)
    u = (index[:, None] + 0.5) * alpha[None, :] + shift
    u -= np.floor(u)
    return u.astype(dtype, copy=False)


#: above this many points the generator is searched near the golden sections of m only
KOROBOV_FULL = 2048


@functools.lru_cache(maxsize=512)
def korobov_generator(m: int) -> int:
    """The generator z of the 2-D rank-1 lattice {(i/m, i z/m mod 1)} of ``m`` points with the
    largest Zaremba index (the least over the dual lattice's nonzero (h1, h2), h1 + h2 z = 0 mod m,
    of max(1, |h1|) max(1, |h2|): the figure of merit of a 2-D lattice rule's discrepancy), among
    the z coprime to m (each coordinate a permutation of the m strata); ties by the longest shortest
    vector on the torus.  At a Fibonacci m it is the Fibonacci lattice (89: 34).  Above
    KOROBOV_FULL points only the z within 512 of m (3 -+ sqrt 5) / 2 are tried (a Fibonacci
    lattice's generator is there)."""
    if m < 3:
        return 1
    if m <= KOROBOV_FULL:
        z = np.arange(1, m)
    else:
        golden = (3.0 - 5.0 ** 0.5) / 2.0
        window = np.arange(-512, 513)
        near = np.concatenate([round(m * golden) + window, round(m * (1 - golden)) + window])
        z = np.unique(near[(near > 0) & (near < m)])
    z = z[np.gcd(z, m) == 1]
    h2 = np.arange(1, m // 2 + 1)
    i = np.arange(1, m)
    a = (np.minimum(i, m - i) / m) ** 2
    key = np.empty(len(z))
    step = max(1, (1 << 20) // m)
    for lo in range(0, len(z), step):
        zz = z[lo:lo + step]
        h1 = np.outer(zz, h2) % m
        h1 = np.minimum(h1, m - h1)
        zaremba = np.minimum((np.maximum(h1, 1) * h2[None, :]).min(axis=1), m)
        b = np.outer(zz, i) % m
        b = np.minimum(b, m - b) / m
        shortest = (a[None, :] + b * b).min(axis=1)  # <= 1/2 < 1: breaks ties only
        key[lo:lo + step] = zaremba + shortest
    return int(z[int(np.argmax(key))])


def rank1_lattice(index: np.ndarray, m: int, shift: np.ndarray) -> np.ndarray:
    """Points of a randomly shifted 2-D rank-1 (Korobov) lattice of exactly ``m`` points.

    index : (M,) int in [0, m)   point number within its own set
    shift : (M, 2)               random shift of the set the point belongs to
    returns (M, 2) float64 in [0, 1): (i/m, i z/m) + shift mod 1, z = ``korobov_generator(m)``.
    A lattice of fixed size has lower discrepancy than the first m points of the R_2 sequence:
    the final gather's sampling noise on Cornell at 164 rays a receiver fell 1.34x in variance
    (0.0102 -> 0.0088 of the reflected light; bench/RESULTS.md).
    """
    z = korobov_generator(int(m))
    index = np.asarray(index, np.int64)
    u = np.empty((len(index), 2))
    u[:, 0] = (index + 0.5) / m + shift[:, 0]
    u[:, 1] = ((index * z) % m + 0.5) / m + shift[:, 1]
    u -= np.floor(u)
    return u


def triangle_points(v0: np.ndarray, v1: np.ndarray, v2: np.ndarray, u: np.ndarray,
                    owner: np.ndarray | None = None) -> np.ndarray:
    """Uniform points on triangles by the square-root map.

    v0, v1, v2 : (m, 3) corners; u : (m, 2) in [0,1)^2 -> (m, 3) points.  ``owner`` (m,): the
    triangle of each point, when v0, v1, v2 are given once per triangle (the edges are then
    formed per triangle, not per point: the same numbers).
    """
    s = np.sqrt(u[:, 0])
    b1 = s * (1.0 - u[:, 1])
    b2 = s * u[:, 1]
    e1, e2 = v1 - v0, v2 - v0
    if owner is not None:
        v0, e1, e2 = v0[owner], e1[owner], e2[owner]
    return v0 + b1[:, None] * e1 + b2[:, None] * e2


def concentric_disk(u: np.ndarray) -> np.ndarray:
    """Shirley-Chiu concentric map of the unit square onto the unit disk.

    u : (m, 2) in [0,1)^2 -> (m, 2) points with x^2 + y^2 <= 1, same dtype as u
    (float32 input keeps the trigonometry in float32, an order of magnitude faster).
    """
    one = u.dtype.type(1)
    a = 2 * u[:, 0] - one
    b = 2 * u[:, 1] - one
    first = np.abs(a) > np.abs(b)
    r = np.where(first, a, b)
    num = np.where(first, b, a)
    den = np.where(r == 0, one, r)
    quarter = u.dtype.type(np.pi / 4)
    phi = np.where(first, quarter * (num / den), 2 * quarter - quarter * (num / den))
    return np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1)


def concentric_disk_inverse(p: np.ndarray) -> np.ndarray:
    """Inverse of :func:`concentric_disk`: (m, 2) disk points -> (m, 2) square points in [0,1]^2."""
    x, y = p[:, 0], p[:, 1]
    r = np.sqrt(x * x + y * y)
    phi = np.arctan2(y, x)  # (-pi, pi]
    # wedge of the square the point came from
    phi = np.where(phi < -np.pi / 4, phi + 2 * np.pi, phi)  # now in [-pi/4, 7pi/4)
    a = np.empty_like(r)
    b = np.empty_like(r)
    w0 = phi < np.pi / 4  # |a| > |b|, a > 0
    w1 = (phi >= np.pi / 4) & (phi < 3 * np.pi / 4)  # b > 0
    w2 = (phi >= 3 * np.pi / 4) & (phi < 5 * np.pi / 4)  # a < 0
    w3 = phi >= 5 * np.pi / 4  # b < 0
    a[w0] = r[w0]
    b[w0] = r[w0] * phi[w0] / (np.pi / 4)
    b[w1] = r[w1]
    a[w1] = -r[w1] * (phi[w1] - np.pi / 2) / (np.pi / 4)
    a[w2] = -r[w2]
    b[w2] = -r[w2] * (phi[w2] - np.pi) / (np.pi / 4)
    b[w3] = -r[w3]
    a[w3] = r[w3] * (phi[w3] - 3 * np.pi / 2) / (np.pi / 4)
    return np.stack([(a + 1.0) * 0.5, (b + 1.0) * 0.5], axis=1)


def cosine_hemisphere(u: np.ndarray) -> np.ndarray:
    """Cosine-distributed directions around +z: (m, 2) in [0,1)^2 -> (m, 3) unit vectors.

    Malley's method on the concentric disk: equal areas of the square map to
    equal projected solid angle, so the square's cells are cosine-weighted bins.
    """
    d = concentric_disk(u)
    z = np.sqrt(np.maximum(0, 1 - np.einsum("ij,ij->i", d, d)))
    return np.column_stack([d, z])


def cosine_hemisphere_columns(u0: np.ndarray, u1: np.ndarray):
    """:func:`cosine_hemisphere` on separate coordinate columns: (m,), (m,) -> x, y, z (m,) each.

    The same map, element for element; contiguous columns keep every step a
    plain vector loop (a (m,2) view's strided columns made it 1.5-3x slower).
    """
    one = u0.dtype.type(1)
    a = 2 * u0 - one
    b = 2 * u1 - one
    first = np.abs(a) > np.abs(b)
    r = np.where(first, a, b)
    num = np.where(first, b, a)
    den = np.where(r == 0, one, r)
    quarter = u0.dtype.type(np.pi / 4)
    ratio = quarter * (num / den)
    phi = np.where(first, ratio, 2 * quarter - ratio)
    x = r * np.cos(phi)
    y = r * np.sin(phi)
    z = np.sqrt(np.maximum(0, one - (x * x + y * y)))
    return x, y, z


def onb(n: np.ndarray):
    """Orthonormal tangent frames (Duff et al. 2017, branchless).

    n : (m, 3) unit normals -> (t (m,3), b (m,3)) with t x b = n
    """
    sign = np.where(n[:, 2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.column_stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]])
    bt = np.column_stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]])
    return t, bt


#: the degree-2 rule of a triangle: barycentric coordinates of three points of weight 1/3 (exact
#: for quadratics: the mean of a smooth field over a triangle from three evaluations)
DEGREE2_RULE = np.array([[2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])
