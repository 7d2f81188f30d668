"""Boolean model of polydisperse spheres from integer hashes, with analytic partial volume.

The geometric engine of the CT-like specimens (:mod:`chunkdic.synth.microstructure`). Nothing is
stored: the spheres of a lattice cell are a pure function of the cell index and a stream
key, so any point of an unbounded specimen is evaluated on its own and any two renders
agree exactly.

A *population* is described by a float64 vector ``pop`` (:func:`population_vector`):
``L`` (cell edge, voxels), ``lam`` (mean number of spheres per cell), ``mu``, ``sigma``
(lognormal law of the radius), ``Phi(a)``, ``Phi(b)`` (its CDF at the truncation bounds),
``level``, ``spread`` (per-sphere grey level, uniform in ``level +- spread``). Each cell
holds a Poisson(``lam``) number of spheres with centres uniform in the cell: a homogeneous
Poisson process. A point sees the spheres of the 27 cells around its own: with ``L = r_max + 1`` that
holds every sphere whose surface is within one voxel of the point; spheres are considered
up to ``sqrt(3)`` voxel from their surface (:func:`phase_at`).

Partial volume: :func:`cube_fraction` (exact for a plane) applied to the nearest sphere's
tangent plane at the signed distance to its *effective radius* ``r_e`` with
``r_e^3 + r_e/4 = r^3`` (see :mod:`chunkdic.synth.microstructure`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["mix64", "hash3", "stream_key", "population_vector", "build_table", "phase_at",
           "cube_fraction", "unit_cube_fraction"]

# --------------------------------------------------------------------------- hashing

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLD = np.uint64(0x9E3779B97F4A7C15)
_C_RAD = np.uint64(0xD6E8FEB86659FD93)
_C_GREY = np.uint64(0xA0761D6478BD642F)
_S30, _S27, _S31 = np.uint64(30), np.uint64(27), np.uint64(31)
_S43, _S22, _S1, _S11 = np.uint64(43), np.uint64(22), np.uint64(1), np.uint64(11)
_MASK21 = np.uint64((1 << 21) - 1)
_INV21 = 1.0 / (1 << 21)
_INV53 = 1.0 / (1 << 53)

_MAXCOUNT = 24  # spheres per cell at most (P(more) < 1e-20 for the defaults)
_HALF_DIAG = 0.5 * math.sqrt(3.0)
_REACH = math.sqrt(3.0)


@njit(nogil=True, cache=True)
def mix64(h):
    """splitmix64 finaliser of a uint64."""
    h = h ^ (h >> _S30)
    h = h * _M1
    h = h ^ (h >> _S27)
    h = h * _M2
    return h ^ (h >> _S31)


@njit(nogil=True, cache=True)
def hash3(i, j, k, key):
    """64-bit hash of three integers and a stream key."""
    h = mix64(key ^ np.uint64(i))
    h = mix64(h ^ np.uint64(j))
    return mix64(h ^ np.uint64(k))


def stream_key(seed: int, channel: int) -> np.uint64:
    """Key of one hash stream of a seed (pure Python, same arithmetic as :func:`mix64`)."""
    mask = (1 << 64) - 1
    h = ((int(seed) & mask) * 0x9E3779B97F4A7C15 + channel * 0xD1B54A32D192ED03) & mask
    for _ in range(2):
        h ^= h >> 30
        h = (h * 0xBF58476D1CE4E5B9) & mask
        h ^= h >> 27
        h = (h * 0x94D049BB133111EB) & mask
        h ^= h >> 31
    return np.uint64(h)




def _phi(x: float) -> float:
    return 0.5 * math.erfc(-x / math.sqrt(2.0))


def population_vector(fraction, median, sigma, r_min, r_max, level, spread) -> np.ndarray:
    """Kernel vector of a population whose union fills ``fraction`` of space on average.

    ``lam = -ln(1 - fraction) / (4/3 pi E[r^3]) * L^3`` (Boolean model), ``L = r_max + 1``.
    """
    L = r_max + 1.0
    ev = 4.0 / 3.0 * math.pi * mean_r3(median, sigma, r_min, r_max)
    lam = -math.log1p(-fraction) / ev * L ** 3
    mu, s = math.log(median), sigma
    if s > 0:
        pa, pb = _phi((math.log(r_min) - mu) / s), _phi((math.log(r_max) - mu) / s)
    else:
        pa, pb = 0.5, 0.5
    return np.array([L, lam, mu, s, pa, pb, level, spread], np.float64)


def mean_r3(median, sigma, r_min, r_max) -> float:
    """``E[r^3]`` of the lognormal law truncated to ``[r_min, r_max]``, voxels^3."""
    mu, s = math.log(median), sigma
    if s == 0.0:
        return median ** 3
    a, b = (math.log(r_min) - mu) / s, (math.log(r_max) - mu) / s
    return math.exp(3 * mu + 4.5 * s * s) * (_phi(b - 3 * s) - _phi(a - 3 * s)) / (_phi(b) - _phi(a))


# --------------------------------------------------------------------------- kernels


@njit(nogil=True, cache=True)
def _ndtri(p):
    """Inverse standard normal CDF (Acklam's approximation + one Halley step, ~1e-15)."""
    if p <= 1e-300:
        p = 1e-300
    if p >= 1.0 - 1e-16:
        p = 1.0 - 1e-16
    if p < 0.02425 or p > 0.97575:
        q = math.sqrt(-2.0 * math.log(min(p, 1.0 - p)))
        x = (((((-7.784894002430293e-03 * q - 3.223964580411365e-01) * q - 2.400758277161838e+00)
               * q - 2.549732539343734e+00) * q + 4.374664141464968e+00) * q + 2.938163982698783e+00) / \
            ((((7.784695709041462e-03 * q + 3.224671290700398e-01) * q + 2.445134137142996e+00)
              * q + 3.754408661907416e+00) * q + 1.0)
        if p > 0.5:
            x = -x
    else:
        q = p - 0.5
        r = q * q
        x = (((((-3.969683028665376e+01 * r + 2.209460984245205e+02) * r - 2.759285104469687e+02)
               * r + 1.383577518672690e+02) * r - 3.066479806614716e+01) * r + 2.506628277459239e+00) * q / \
            (((((-5.447609879822406e+01 * r + 1.615858368580409e+02) * r - 1.556989798598866e+02)
               * r + 6.680131188771972e+01) * r - 1.328068155288572e+01) * r + 1.0)
    e = 0.5 * math.erfc(-x / math.sqrt(2.0)) - p
    u = e * math.sqrt(2.0 * math.pi) * math.exp(0.5 * x * x)
    return x - u / (1.0 + 0.5 * x * u)


@njit(nogil=True, cache=True)
def _sphere_count(h, lam):
    # Poisson(lam) by inverse CDF from 53 bits of h
    u = np.float64(h >> _S11) * _INV53
    p = math.exp(-lam)
    cdf = p
    k = 0
    while u > cdf and k < _MAXCOUNT:
        k += 1
        p *= lam / k
        cdf += p
    return k


@njit(nogil=True, cache=True)
def _sphere(pop, cz, cy, cx, h0, m, out):
    """Sphere ``m`` of cell ``(cz, cy, cx)``: centre (3), effective radius, grey, radius."""
    L = pop[0]
    h = mix64(h0 ^ (np.uint64(m + 1) * _GOLD))
    out[0] = (np.float64(cz) + np.float64((h >> _S43) & _MASK21) * _INV21) * L
    out[1] = (np.float64(cy) + np.float64((h >> _S22) & _MASK21) * _INV21) * L
    out[2] = (np.float64(cx) + np.float64((h >> _S1) & _MASK21) * _INV21) * L
    hr = mix64(h ^ _C_RAD)
    if pop[3] > 0.0:
        u = pop[4] + (pop[5] - pop[4]) * (np.float64(hr >> _S11) * _INV53)
        r = math.exp(pop[2] + pop[3] * _ndtri(u))
    else:
        r = math.exp(pop[2])
    # effective radius: r_e^3 + r_e / 4 = r^3 (module docstring), Newton from r - 1/(12 r)
    re = r - 1.0 / (12.0 * r)
    for _ in range(4):
        re -= (re * re * re + 0.25 * re - r * r * r) / (3.0 * re * re + 0.25)
    out[3] = re
    hg = mix64(hr ^ _C_GREY)
    out[4] = pop[6] + pop[7] * (2.0 * (np.float64(hg >> _S11) * _INV53) - 1.0)
    out[5] = r


@njit(nogil=True, cache=True)
def build_table(pop, key, lo0, lo1, lo2, hi0, hi1, hi2):
    """Spheres of the cells covering the box [lo, hi] plus one cell: (origin, dims, start, sph)."""
    L = pop[0]
    c0 = np.empty(3, np.int64)
    dims = np.empty(3, np.int64)
    c0[0] = np.int64(math.floor(lo0 / L)) - 1
    c0[1] = np.int64(math.floor(lo1 / L)) - 1
    c0[2] = np.int64(math.floor(lo2 / L)) - 1
    dims[0] = np.int64(math.floor(hi0 / L)) + 2 - c0[0]
    dims[1] = np.int64(math.floor(hi1 / L)) + 2 - c0[1]
    dims[2] = np.int64(math.floor(hi2 / L)) + 2 - c0[2]
    n = dims[0] * dims[1] * dims[2]
    start = np.zeros(n + 1, np.int64)
    for a in range(dims[0]):
        for b in range(dims[1]):
            for c in range(dims[2]):
                i = (a * dims[1] + b) * dims[2] + c
                k = 0
                if pop[1] > 0.0:
                    k = _sphere_count(hash3(c0[0] + a, c0[1] + b, c0[2] + c, key), pop[1])
                start[i + 1] = start[i] + k
    sph = np.empty((start[n], 6), np.float64)
    for a in range(dims[0]):
        for b in range(dims[1]):
            for c in range(dims[2]):
                i = (a * dims[1] + b) * dims[2] + c
                if start[i + 1] > start[i]:
                    h0 = hash3(c0[0] + a, c0[1] + b, c0[2] + c, key)
                    for m in range(start[i + 1] - start[i]):
                        _sphere(pop, c0[0] + a, c0[1] + b, c0[2] + c, h0, m, sph[start[i] + m])
    return c0, dims, start, sph


@njit(nogil=True, cache=True, inline="always")
def _cube(a):
    return a * a * a if a > 0.0 else 0.0


@njit(nogil=True, cache=True, inline="always")
def _cdf3(x, w1, w2, w3):
    # P(V1 + V2 + V3 <= x), V_i uniform on [0, w_i], w1 >= w2 >= w3 > 0, 0 < x <= W/2
    t = x * x * x - _cube(x - w1) - _cube(x - w2) - _cube(x - w3)
    t += _cube(x - w1 - w2) + _cube(x - w1 - w3) + _cube(x - w2 - w3)
    return t / (6.0 * w1 * w2 * w3)


@njit(nogil=True, cache=True, inline="always")
def _cdf2(x, w1, w2):
    a = x - w1
    b = x - w2
    c = x - w1 - w2
    t = x * x - (a * a if a > 0.0 else 0.0) - (b * b if b > 0.0 else 0.0)
    t += c * c if c > 0.0 else 0.0
    return t / (2.0 * w1 * w2)


@njit(nogil=True, cache=True)
def unit_cube_fraction(s, nz, ny, nx):
    """Fraction of the unit cube centred at 0 where ``s + n.u < 0`` (``n`` unit)."""
    a, b, c = abs(nz), abs(ny), abs(nx)
    w1 = max(a, max(b, c))
    w3 = min(a, min(b, c))
    w2 = a + b + c - w1 - w3
    W = w1 + w2 + w3
    x = 0.5 * W - s  # P(S <= x), S = sum of uniforms on [0, w_i]
    if x <= 0.0:
        return 0.0
    if x >= W:
        return 1.0
    flip = x > 0.5 * W
    if flip:
        x = W - x  # symmetry keeps the arguments small (less cancellation)
    if w3 > 1e-4:
        v = _cdf3(x, w1, w2, w3)
    elif w2 > 1e-4:
        v = _cdf2(x, w1, w2)  # the third uniform changes the CDF by O(w3^2)
    else:
        v = x / w1
    return 1.0 - v if flip else v


@njit(nogil=True, cache=True, inline="always")
def _nearest2(qz, qy, qx, L, c0, dims, start, sph):
    """Two spheres of least signed distance (< sqrt 3) around q: (s1, i1, s2, i2), -1 if none."""
    iz = np.int64(math.floor(qz / L)) - c0[0]
    iy = np.int64(math.floor(qy / L)) - c0[1]
    ix = np.int64(math.floor(qx / L)) - c0[2]
    # spheres farther than sqrt(3) voxel do not touch the voxel nor its grey blending
    s1 = _REACH
    s2 = _REACH
    i1 = -1
    i2 = -1
    for dz in range(-1, 2):
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                cell = ((iz + dz) * dims[1] + iy + dy) * dims[2] + ix + dx
                for k in range(start[cell], start[cell + 1]):
                    a = qz - sph[k, 0]
                    b = qy - sph[k, 1]
                    c = qx - sph[k, 2]
                    d2 = a * a + b * b + c * c
                    lim = s2 + sph[k, 3]  # the sphere matters only if d < lim
                    if lim <= 0.0 or d2 >= lim * lim:
                        continue
                    sd = math.sqrt(d2) - sph[k, 3]
                    if sd < s1:
                        s2, i2 = s1, i1
                        s1, i1 = sd, k
                    elif sd < s2:
                        s2, i2 = sd, k
    return s1, i1, s2, i2


@njit(nogil=True, cache=True, inline="always")
def _frac_of(qz, qy, qx, sd, k, sph):
    if sd >= _HALF_DIAG:
        return 0.0
    if sd <= -_HALF_DIAG:
        return 1.0
    a = qz - sph[k, 0]
    b = qy - sph[k, 1]
    c = qx - sph[k, 2]
    d = math.sqrt(a * a + b * b + c * c)
    if d == 0.0:
        return 1.0
    return unit_cube_fraction(sd, a / d, b / d, c / d)


@njit(nogil=True, cache=True, inline="always")
def phase_at(qz, qy, qx, L, c0, dims, start, sph):
    """(occupied fraction, blended grey level) of one population at q."""
    s1, i1, s2, i2 = _nearest2(qz, qy, qx, L, c0, dims, start, sph)
    if i1 < 0:
        return 0.0, 0.0
    f1 = _frac_of(qz, qy, qx, s1, i1, sph)
    grey = sph[i1, 4]
    if i2 < 0:
        return f1, grey
    f2 = _frac_of(qz, qy, qx, s2, i2, sph)
    h = 0.5 * (s2 - s1)  # ~ distance to the interface between the two spheres
    if h < _HALF_DIAG:
        a = sph[i2, 0] - sph[i1, 0]
        b = sph[i2, 1] - sph[i1, 1]
        c = sph[i2, 2] - sph[i1, 2]
        d = math.sqrt(a * a + b * b + c * c)
        if d > 0.0:
            w2 = 1.0 - unit_cube_fraction(-h, a / d, b / d, c / d)  # sphere 2's side of the interface
            grey = (1.0 - w2) * grey + w2 * sph[i2, 4]
    return f1 + f2 - f1 * f2, grey


@njit(nogil=True, cache=True)
def _cube_fraction_many(s, n, out):
    for i in range(s.size):
        out[i] = unit_cube_fraction(s[i], n[0, i], n[1, i], n[2, i])


def cube_fraction(s, n) -> np.ndarray:
    """Fraction of a unit voxel inside a plane (the partial-volume rule).

    Parameters
    ----------
    s : array_like, float64, voxels
        Signed distance from the voxel centre to the plane (positive: centre outside).
    n : array_like, shape (3, ...), float64
        Unit normal pointing outside, components ``(z, y, x)``.

    Returns
    -------
    ndarray, float64, shape of ``s``
    """
    s = np.asarray(s, np.float64)
    n = np.asarray(n, np.float64)
    if n.ndim == 1:
        n = n.reshape(3, *([1] * s.ndim))
    n = np.broadcast_to(n, (3, *s.shape)).reshape(3, -1)
    out = np.empty(s.size)
    _cube_fraction_many(np.ascontiguousarray(s).ravel(), np.ascontiguousarray(n), out)
    return out.reshape(s.shape)
