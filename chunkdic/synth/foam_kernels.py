"""Numba kernels of the procedural foam texture: hashing, cellular walls, value noise.

One idea: the arithmetic that evaluates the foam texture of :mod:`chunkdic.synth.foam` at a point
from integer hashes of lattice-cell indices and the seed (nothing stored; any point
independently). :mod:`chunkdic.synth.foam` packs the parameters (:class:`~chunkdic.synth.foam.TextureParams`)
and calls :func:`texture_points` / :func:`texture_grid`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# the hash streams are boolean.py's (splitmix64): one implementation for both specimens
from .boolean import hash3, mix64
from .boolean import stream_key as channel_key

__all__ = ["CH_ACQ_DEF", "CH_ACQ_REF", "CH_BEAD", "CH_CELL", "CH_NOISE", "FWHM_R", "NPRM", "add_gaussian_noise",
           "channel_key", "texture_grid", "texture_points"]

# --------------------------------------------------------------------------- hashing

_GOLD = np.uint64(0x9E3779B97F4A7C15)
_S43 = np.uint64(43)
_S22 = np.uint64(22)
_S1 = np.uint64(1)
_S11 = np.uint64(11)
_MASK21 = np.uint64((1 << 21) - 1)
_INV21 = 1.0 / (1 << 21)
_INV53 = 1.0 / (1 << 53)

# channels of the hash (distinct streams from one seed)
CH_CELL, CH_BEAD, CH_NOISE, CH_ACQ_REF, CH_ACQ_DEF = 1, 2, 3, 4, 5
_JITTER = 0.8  # feature points within the central 80 % of their lattice cell
FWHM_R = 2.0 * math.sqrt(1.0 - 0.5 ** 0.25)  # FWHM / R of the profile (1 - d^2/R^2)^4


# --------------------------------------------------------------------------- kernels
# Parameter vector ``prm`` (float64):
#  0 inv_cell  1 inv_bead  2 inv_noise  3 cell 1/(4 R^2) (lattice units)  4 bead 1/(4 R^2)
#  5 cell 4 R^2  6 bead 4 R^2  7 noise amplitude
#  8 cell interior low  9 cell interior high  10 wall low  11 wall high  12 skin level
# Keys ``keys`` (uint64): 0 cells, 1 beads, 2 value noise.
NPRM = 13


@njit(nogil=True, cache=True, inline="always", fastmath={"nnan", "ninf", "nsz"})
def _min_value(work, n):
    # min of work[0, :n]; min is exact in any order, so these flags (which let LLVM
    # vectorise) change nothing
    m = np.inf
    for i in range(n):
        m = min(m, work[0, i])
    return m


@njit(nogil=True, cache=True, inline="always")
def _feature(fc, fh, n, i, j, k, key, jit):
    h = hash3(i, j, k, key)
    fz = np.float64((h >> _S43) & _MASK21) * _INV21
    fy = np.float64((h >> _S22) & _MASK21) * _INV21
    fx = np.float64((h >> _S1) & _MASK21) * _INV21
    fc[0, n] = np.float64(i) + 0.5 + jit * (fz - 0.5)
    fc[1, n] = np.float64(j) + 0.5 + jit * (fy - 0.5)
    fc[2, n] = np.float64(k) + 0.5 + jit * (fx - 0.5)
    fh[n] = h


@njit(nogil=True, cache=True, inline="always")
def _cell_lookup(qz, qy, qx, ckey):
    """The lattice cell of ``q`` and what a per-cell cache keyed by ``ckey`` holds for it.

    Returns ``(cz, cy, cx, iz, iy, ix, state)``: the floored coordinates (float and int)
    and ``state`` 0 when the cache is this cell's, 1 when it is the previous cell's along x
    (the caller shifts it and fills one face), 2 when it must be filled anew.
    """
    cz = math.floor(qz)
    cy = math.floor(qy)
    cx = math.floor(qx)
    iz = np.int64(cz)
    iy = np.int64(cy)
    ix = np.int64(cx)
    state = 0
    if ckey[3] == 0 or ckey[0] != iz or ckey[1] != iy or ckey[2] != ix:
        state = 1 if ckey[3] == 1 and ckey[0] == iz and ckey[1] == iy and ckey[2] + 1 == ix else 2
        ckey[0] = iz
        ckey[1] = iy
        ckey[2] = ix
        ckey[3] = 1
    return cz, cy, cx, iz, iy, ix, state


@njit(nogil=True, cache=True, inline="always")
def _worley_wall(qz, qy, qx, key, jit, inv4r2, lim, fc, fh, work, ckey):
    """Wall weight at lattice position q, and the hash of the nearest feature's cell.

    Caches (per kernel call), none of which changes the value (a function of q alone):

    - ``fc`` (3, 32), ``fh`` (32,): coordinates and hashes of the features of the 27
      lattice cells around the lattice cell of q (``ckey[0:3]``), refilled when that cell
      changes (shifted when it moves by +1 along x);
    - ``work[1]``: squared separations from the nearest feature ``ckey[4]``;
    - ``work[2, 0:4]``: a ball (centre, squared radius) around a point where the weight
      was 0: the planes of the nearest feature are 1-Lipschitz in position, so inside the
      ball every plane stays farther than R (weight exactly 0) and the nearest feature
      stays the same (``ckey[5]``). It is only used within the same lattice cell.
    """
    cz, cy, cx, iz, iy, ix, state = _cell_lookup(qz, qy, qx, ckey)
    if state != 0:
        if state == 1:
            for m in range(9):  # shift along x: reuse 18 of the 27 features
                b = 3 * m
                for r in range(3):
                    fc[r, b] = fc[r, b + 1]
                    fc[r, b + 1] = fc[r, b + 2]
                fh[b] = fh[b + 1]
                fh[b + 1] = fh[b + 2]
                _feature(fc, fh, b + 2, iz + m // 3 - 1, iy + m % 3 - 1, ix + 1, key, jit)
        else:
            n = 0
            for dz in range(-1, 2):
                for dy in range(-1, 2):
                    for dx in range(-1, 2):
                        _feature(fc, fh, n, iz + dz, iy + dy, ix + dx, key, jit)
                        n += 1
        ckey[4] = -1  # separations not computed
        work[2, 3] = -1.0  # no ball
    elif work[2, 3] > 0.0:
        a = qz - work[2, 0]
        b = qy - work[2, 1]
        c = qx - work[2, 2]
        if a * a + b * b + c * c < work[2, 3]:
            return 0.0, fh[ckey[5]]
    for n in range(27):
        a = qz - fc[0, n]
        b = qy - fc[1, n]
        c = qx - fc[2, n]
        work[0, n] = a * a + b * b + c * c
    best = _min_value(work, 27)
    ia = 0
    while work[0, ia] != best:
        ia += 1
    if ckey[4] != ia:
        az = fc[0, ia]
        ay = fc[1, ia]
        ax = fc[2, ia]
        for n in range(27):
            a = fc[0, n] - az
            b = fc[1, n] - ay
            c = fc[2, n] - ax
            work[1, n] = a * a + b * b + c * c
        ckey[4] = ia
    prod = 1.0
    for n in range(27):
        # distance to the bisector of (a, n): d = (d2[n] - best) / (2 sep); the profile
        # (1 - d^2/R^2)^4 vanishes beyond d = R, i.e. for num^2 >= 4 R^2 sep^2
        num = work[0, n] - best
        if n == ia or num * num >= lim * work[1, n]:
            continue
        t = 1.0 - num * num * inv4r2 / work[1, n]
        t = t * t
        prod *= 1.0 - t * t
    if prod == 1.0:
        # no wall here: the nearest bisector is at dmin > R; record the ball of radius
        # dmin - R (less a margin far above round-off) where the weight stays 0
        dmin2 = np.inf
        for n in range(27):
            if n != ia:
                num = work[0, n] - best
                dmin2 = min(dmin2, num * num / (4.0 * work[1, n]))
        rad = math.sqrt(dmin2) - 0.5 * math.sqrt(lim) - 1e-7
        if rad > 0.0:
            work[2, 0] = qz
            work[2, 1] = qy
            work[2, 2] = qx
            work[2, 3] = rad * rad
            ckey[5] = ia
        else:
            work[2, 3] = -1.0
    return 1.0 - prod, fh[ia]


@njit(nogil=True, cache=True)
def _fade(t):
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


@njit(nogil=True, cache=True, inline="always")
def _signed_unit(h):
    """A 64-bit hash as a float in [-1, 1)."""
    return np.float64(h >> _S11) * _INV53 * 2.0 - 1.0


@njit(nogil=True, cache=True, inline="always")
def _value_noise(qz, qy, qx, key, vc, ckey):
    """Smooth (C2) value noise in [-1, 1] at lattice position q; ``vc`` (8,) cache."""
    cz, cy, cx, iz, iy, ix, state = _cell_lookup(qz, qy, qx, ckey)
    if state == 1:
        for m in range(4):  # shift along x: reuse 4 of the 8 corners
            vc[2 * m] = vc[2 * m + 1]
            vc[2 * m + 1] = _signed_unit(hash3(iz + m // 2, iy + m % 2, ix + 1, key))
    elif state == 2:
        n = 0
        for dz in range(2):
            for dy in range(2):
                for dx in range(2):
                    vc[n] = _signed_unit(hash3(iz + dz, iy + dy, ix + dx, key))
                    n += 1
    tz = _fade(qz - cz)
    ty = _fade(qy - cy)
    tx = _fade(qx - cx)
    v00 = vc[0] + tx * (vc[1] - vc[0])
    v01 = vc[2] + tx * (vc[3] - vc[2])
    v10 = vc[4] + tx * (vc[5] - vc[4])
    v11 = vc[6] + tx * (vc[7] - vc[6])
    v0 = v00 + ty * (v01 - v00)
    v1 = v10 + ty * (v11 - v10)
    return v0 + tz * (v1 - v0)


@njit(nogil=True, cache=True)
def _unit(h, m):
    # a second float in [0, 1) derived from a feature hash
    return np.float64(mix64(h ^ m) >> _S11) * _INV53


@njit(nogil=True, cache=True, inline="always")
def _point(z, y, x, prm, keys, c_fp, c_fh, c_d2, c_key, b_fp, b_fh, b_d2, b_key, n_vc, n_key):
    wc, hc = _worley_wall(
        z * prm[0], y * prm[0], x * prm[0], keys[0], _JITTER, prm[3], prm[5],
        c_fp, c_fh, c_d2, c_key,
    )
    wb, hb = _worley_wall(
        z * prm[1], y * prm[1], x * prm[1], keys[1], _JITTER, prm[4], prm[6],
        b_fp, b_fh, b_d2, b_key,
    )
    interior = prm[8] + (prm[9] - prm[8]) * _unit(hc, _GOLD)
    wall = prm[10] + (prm[11] - prm[10]) * _unit(hb, _GOLD)
    v = (1.0 - wb) * ((1.0 - wc) * interior + wc * wall) + wb * prm[12]
    if prm[7] != 0.0:
        v += prm[7] * _value_noise(z * prm[2], y * prm[2], x * prm[2], keys[2], n_vc, n_key)
    return v


@njit(nogil=True, cache=True)
def _texture_kernel(grid, o0, o1, o2, ny, nx, z, y, x, prm, keys, out):
    """Texture into ``out`` (1-D float32).

    ``grid``: the C-ordered grid of ``out.size`` voxels starting at global voxel
    ``(o0, o1, o2)`` with rows of ``nx`` and planes of ``ny * nx`` (``z, y, x`` unused);
    otherwise the points ``(z[i], y[i], x[i])``. One call site of ``_point`` (inlined)
    serves both, which halves the compile time.
    """
    c_fp = np.empty((3, 32))
    c_fh = np.empty(32, np.uint64)
    c_d2 = np.empty((3, 32))
    c_key = np.zeros(6, np.int64)
    b_fp = np.empty((3, 32))
    b_fh = np.empty(32, np.uint64)
    b_d2 = np.empty((3, 32))
    b_key = np.zeros(6, np.int64)
    n_vc = np.empty(8)
    n_key = np.zeros(4, np.int64)
    i = o0
    j = o1
    k = o2
    for t in range(out.size):
        if grid:
            pz = np.float64(i)
            py = np.float64(j)
            px = np.float64(k)
            k += 1
            if k == o2 + nx:
                k = o2
                j += 1
                if j == o1 + ny:
                    j = o1
                    i += 1
        else:
            pz = z[t]
            py = y[t]
            px = x[t]
        out[t] = _point(pz, py, px, prm, keys, c_fp, c_fh, c_d2, c_key,
                        b_fp, b_fh, b_d2, b_key, n_vc, n_key)


_NO_POINTS = np.empty(0)


def texture_points(z, y, x, prm, keys, out):
    """Texture at the points ``(z[i], y[i], x[i])`` (1-D float64) into ``out`` (1-D float32)."""
    _texture_kernel(False, 0, 0, 0, 1, 1, z, y, x, prm, keys, out)


def texture_grid(o0, o1, o2, prm, keys, out):
    """Texture over the voxel grid of ``out`` (3-D float32) whose first voxel is ``(o0, o1, o2)``."""
    _, ny, nx = out.shape
    _texture_kernel(True, int(o0), int(o1), int(o2), int(ny), int(nx), _NO_POINTS,
                    _NO_POINTS, _NO_POINTS, prm, keys, out.reshape(-1))


@njit(nogil=True, cache=True)
def add_gaussian_noise(out, o0, o1, o2, key, std):
    """Add N(0, std^2) noise hashed from the global voxel index (chunk independent)."""
    nz, ny, nx = out.shape
    for i in range(nz):
        for j in range(ny):
            for k in range(nx):
                h = hash3(o0 + i, o1 + j, o2 + k, key)
                u1 = (np.float64(h >> _S11) + 0.5) * _INV53
                u2 = np.float64(mix64(h ^ _GOLD) >> _S11) * _INV53
                g = math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)
                out[i, j, k] += std * g
