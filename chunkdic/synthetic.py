"""Synthetic specimens: a procedural foam texture and analytic displacement fields.

The texture imitates the paper's polypropylene foam (section 2): closed cells a few voxels
across, grouped in millimetric beads whose skins are thicker and denser. It is evaluated
**point by point** from integer hashes of lattice-cell indices and the seed (a hashed
cellular, "Worley", texture): nothing is stored, any point of an unbounded volume is
evaluated independently, so any chunk of any size is computed on its own and chunks agree
at their borders exactly.

A deformed scan is the reference texture evaluated at the inverted positions:
``g(x) = f(X(x))`` with ``X = field.inverse(x)``, hence ``g(X + u(X)) = f(X)`` up to the
inverse tolerance (1e-12 voxel or better here) and float32 round-off. There is no
interpolation anywhere. Integer output dtypes round the intensities, so with them the
relation holds only up to half a grey level.

The fields (:class:`Field`, :class:`Translation`, :class:`Affine`, :class:`Band`,
:func:`true_displacement`) live in :mod:`chunkdic.fields` and are re-exported here.

Texture (all sizes in level-0 voxels)
-------------------------------------
- *Cells*: one feature point per cubic lattice cell of edge ``cell_size`` (jittered over
  80 % of the cell), Voronoi cells around them. ``cell_size`` is the cube root of the mean
  cell volume. The signed distance of a point ``p`` to the bisector plane of its nearest
  feature ``a`` and another feature ``b`` is ``d_b = (|p-b|^2 - |p-a|^2) / (2 |b-a|)``;
  the wall weight is ``W = 1 - prod_b (1 - phi(d_b))`` with the compact, near-Gaussian
  profile ``phi(d) = (1 - d^2/R^2)^4`` for ``|d| < R`` (C3 at ``R``), ``R`` set from the
  wall full width at half maximum ``wall_width`` (FWHM = 0.798 R). ``W == 1`` on every
  Voronoi face and its derivative across a face vanishes from both sides, so the texture
  is C1 across faces and smooth elsewhere: sub-voxel interpolation sees a smooth, not
  aliased, image.
- *Beads*: the same construction on a coarser lattice (``bead_size``), with thicker walls
  (``skin_width``) and a brighter level (denser skins).
- Grey levels: cell interiors (gas, dark) take a random level per cell, cell walls a level
  per bead, bead skins the brightest level; changes of level happen only under a wall of
  weight 1 (C1 again). A smooth value noise of small amplitude (``noise_size``) keeps cell
  interiors from being flat.

Feature points are looked up in the 3x3x3 lattice neighbourhood of the point (standard
for cellular textures). In rare configurations the true second-nearest feature lies
outside it; the texture is then still a deterministic function of the position (chunks
still agree exactly) but may show a tiny kink there.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
from dataclasses import asdict, dataclass

import numpy as np
from numba import njit

from .errors import InputError
from .fields import Affine, Band, Field, Translation, true_displacement

__all__ = [
    "TextureParams",
    "texture",
    "Field",
    "Translation",
    "Affine",
    "Band",
    "render",
    "as_dask",
    "synthesize",
    "true_displacement",
    "load_field",
    "load_texture",
    "load_specimen",
    "standard_case",
    "warmup",
]

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------- hashing

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLD = np.uint64(0x9E3779B97F4A7C15)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S43 = np.uint64(43)
_S22 = np.uint64(22)
_S1 = np.uint64(1)
_S11 = np.uint64(11)
_MASK21 = np.uint64((1 << 21) - 1)
_INV21 = 1.0 / (1 << 21)
_INV53 = 1.0 / (1 << 53)

# channels of the hash (distinct streams from one seed)
_CH_CELL, _CH_BEAD, _CH_NOISE, _CH_ACQ_REF, _CH_ACQ_DEF = 1, 2, 3, 4, 5
_JITTER = 0.8  # feature points within the central 80 % of their lattice cell
_FWHM_R = 2.0 * math.sqrt(1.0 - 0.5 ** 0.25)  # FWHM / R of the profile (1 - d^2/R^2)^4


@njit(nogil=True, cache=True)
def _mix(h):
    # splitmix64 finaliser
    h = h ^ (h >> _S30)
    h = h * _M1
    h = h ^ (h >> _S27)
    h = h * _M2
    h = h ^ (h >> _S31)
    return h


@njit(nogil=True, cache=True)
def _hash3(i, j, k, key):
    h = _mix(key ^ np.uint64(i))
    h = _mix(h ^ np.uint64(j))
    return _mix(h ^ np.uint64(k))


def _channel_key(seed: int, channel: int) -> np.uint64:
    """64-bit key of one hash stream (NumPy twin of the kernel arithmetic)."""
    mask = (1 << 64) - 1
    h = ((int(seed) & mask) * 0x9E3779B97F4A7C15 + channel * 0xD1B54A32D192ED03) & mask
    for _ in range(2):  # splitmix64 finaliser, twice
        h ^= h >> 30
        h = (h * 0xBF58476D1CE4E5B9) & mask
        h ^= h >> 27
        h = (h * 0x94D049BB133111EB) & mask
        h ^= h >> 31
    return np.uint64(h)


# --------------------------------------------------------------------------- kernels
# Parameter vector ``prm`` (float64):
#  0 inv_cell  1 inv_bead  2 inv_noise  3 cell 1/(4 R^2) (lattice units)  4 bead 1/(4 R^2)
#  5 cell 4 R^2  6 bead 4 R^2  7 noise amplitude
#  8 cell interior low  9 cell interior high  10 wall low  11 wall high  12 skin level
# Keys ``keys`` (uint64): 0 cells, 1 beads, 2 value noise.
_NPRM = 13


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
    h = _hash3(i, j, k, key)
    fz = np.float64((h >> _S43) & _MASK21) * _INV21
    fy = np.float64((h >> _S22) & _MASK21) * _INV21
    fx = np.float64((h >> _S1) & _MASK21) * _INV21
    fc[0, n] = np.float64(i) + 0.5 + jit * (fz - 0.5)
    fc[1, n] = np.float64(j) + 0.5 + jit * (fy - 0.5)
    fc[2, n] = np.float64(k) + 0.5 + jit * (fx - 0.5)
    fh[n] = h


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
    cz = math.floor(qz)
    cy = math.floor(qy)
    cx = math.floor(qx)
    iz = np.int64(cz)
    iy = np.int64(cy)
    ix = np.int64(cx)
    if ckey[3] == 0 or ckey[0] != iz or ckey[1] != iy or ckey[2] != ix:
        if ckey[3] == 1 and ckey[0] == iz and ckey[1] == iy and ckey[2] + 1 == ix:
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
        ckey[0] = iz
        ckey[1] = iy
        ckey[2] = ix
        ckey[3] = 1
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
def _value_noise(qz, qy, qx, key, vc, ckey):
    """Smooth (C2) value noise in [-1, 1] at lattice position q; ``vc`` (8,) cache."""
    cz = math.floor(qz)
    cy = math.floor(qy)
    cx = math.floor(qx)
    iz = np.int64(cz)
    iy = np.int64(cy)
    ix = np.int64(cx)
    if ckey[3] == 0 or ckey[0] != iz or ckey[1] != iy or ckey[2] != ix:
        if ckey[3] == 1 and ckey[0] == iz and ckey[1] == iy and ckey[2] + 1 == ix:
            for m in range(4):  # shift along x: reuse 4 of the 8 corners
                vc[2 * m] = vc[2 * m + 1]
                h = _hash3(iz + m // 2, iy + m % 2, ix + 1, key)
                vc[2 * m + 1] = np.float64(h >> _S11) * _INV53 * 2.0 - 1.0
        else:
            n = 0
            for dz in range(2):
                for dy in range(2):
                    for dx in range(2):
                        h = _hash3(iz + dz, iy + dy, ix + dx, key)
                        vc[n] = np.float64(h >> _S11) * _INV53 * 2.0 - 1.0
                        n += 1
        ckey[0] = iz
        ckey[1] = iy
        ckey[2] = ix
        ckey[3] = 1
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
    return np.float64(_mix(h ^ m) >> _S11) * _INV53


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


def _texture_points(z, y, x, prm, keys, out):
    _texture_kernel(False, 0, 0, 0, 1, 1, z, y, x, prm, keys, out)


def _texture_grid(o0, o1, o2, prm, keys, out):
    _, ny, nx = out.shape
    _texture_kernel(True, int(o0), int(o1), int(o2), int(ny), int(nx), _NO_POINTS,
                    _NO_POINTS, _NO_POINTS, prm, keys, out.reshape(-1))


@njit(nogil=True, cache=True)
def _add_gaussian_noise(out, o0, o1, o2, key, std):
    """Add N(0, std^2) noise hashed from the global voxel index (chunk independent)."""
    nz, ny, nx = out.shape
    for i in range(nz):
        for j in range(ny):
            for k in range(nx):
                h = _hash3(o0 + i, o1 + j, o2 + k, key)
                u1 = (np.float64(h >> _S11) + 0.5) * _INV53
                u2 = np.float64(_mix(h ^ _GOLD) >> _S11) * _INV53
                g = math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)
                out[i, j, k] += std * g


# --------------------------------------------------------------------------- texture API


@dataclass(frozen=True)
class TextureParams:
    """Parameters of the foam texture (sizes in level-0 voxels).

    Parameters
    ----------
    seed : int
        Seed of every hash stream.
    cell_size : float
        Lattice spacing of the cell features = cube root of the mean cell volume.
    bead_size : float
        Same for the beads.
    wall_width : float
        Full width at half maximum of a cell wall profile (voxels).
    skin_width : float
        Full width at half maximum of a bead skin profile (voxels).
    noise_size : float or None
        Lattice spacing of the smooth value noise (default ``cell_size / 2``).
    noise_amplitude : float
        Amplitude of the smooth value noise (texture units, the texture spans ~[0.1, 1]).
    """

    seed: int = 0
    cell_size: float = 8.0
    bead_size: float = 64.0
    wall_width: float = 2.5
    skin_width: float = 4.0
    noise_size: float | None = None
    noise_amplitude: float = 0.04

    def __post_init__(self):
        for name in ("cell_size", "bead_size", "wall_width", "skin_width"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"texture parameter {name} must be a positive number, got {v!r}")
        if self.noise_size is not None and not (self.noise_size > 0):
            raise InputError(f"noise_size must be positive, got {self.noise_size!r}")
        if self.bead_size < 2 * self.cell_size:
            raise InputError(
                f"bead_size ({self.bead_size}) should be at least twice "
                f"cell_size ({self.cell_size})"
            )

    def to_json(self) -> dict:
        return asdict(self)

    def _kernel_args(self) -> tuple[np.ndarray, np.ndarray]:
        # wall profile (1 - d^2/R^2)^4 for |d| < R (compact, C3, near-Gaussian);
        # its full width at half maximum is 0.7981 R
        r_c = self.wall_width / _FWHM_R / self.cell_size  # lattice units
        r_b = self.skin_width / _FWHM_R / self.bead_size
        noise = self.noise_size if self.noise_size is not None else self.cell_size / 2.0
        prm = np.empty(_NPRM)
        prm[0] = 1.0 / self.cell_size
        prm[1] = 1.0 / self.bead_size
        prm[2] = 1.0 / noise
        prm[3] = 1.0 / (4.0 * r_c * r_c)  # d^2/R^2 = num^2 / (4 R^2 sep^2)
        prm[4] = 1.0 / (4.0 * r_b * r_b)
        prm[5] = 4.0 * r_c * r_c
        prm[6] = 4.0 * r_b * r_b
        prm[7] = self.noise_amplitude
        prm[8:13] = (0.08, 0.30, 0.60, 0.80, 0.95)
        keys = np.array(
            [_channel_key(self.seed, c) for c in (_CH_CELL, _CH_BEAD, _CH_NOISE)], np.uint64
        )
        return prm, keys


def _params(seed, cell_size, bead_size, kw) -> TextureParams:
    if isinstance(seed, TextureParams):
        return seed
    return TextureParams(seed=int(seed), cell_size=float(cell_size),
                         bead_size=float(bead_size), **kw)


def texture(z, y, x, *, seed: int = 0, cell_size: float = 8.0, bead_size: float = 64.0,
            **params) -> np.ndarray:
    """Foam texture at arbitrary points.

    Parameters
    ----------
    z, y, x : array_like, broadcastable, float64, level-0 voxels
        Coordinates of the points (voxel ``i`` has its centre at ``i``).
    seed : int or TextureParams
        Seed of the specimen, or a whole :class:`TextureParams` (the other texture
        arguments are then ignored).
    cell_size, bead_size : float, voxels
        Mean cell and bead sizes (see :class:`TextureParams`).
    **params
        Other :class:`TextureParams` fields (``wall_width``, ``skin_width``,
        ``noise_size``, ``noise_amplitude``).

    Returns
    -------
    ndarray, float32, broadcast shape of the coordinates
        Grey levels, roughly in [0.05, 1].

    Examples
    --------
    >>> import numpy as np
    >>> v = texture(np.arange(4.0), 0.0, 0.0, seed=1)
    >>> v.shape, v.dtype
    ((4,), dtype('float32'))
    """
    p = _params(seed, cell_size, bead_size, params)
    zz, yy, xx = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (z, y, x)))
    shape = zz.shape
    prm, keys = p._kernel_args()
    out = np.empty(zz.size, np.float32)
    _texture_points(
        np.ascontiguousarray(zz).ravel(), np.ascontiguousarray(yy).ravel(),
        np.ascontiguousarray(xx).ravel(), prm, keys, out,
    )
    return out.reshape(shape)


# --------------------------------------------------------------------------- rendering

_INT_LO, _INT_HI = 20.0 / 255.0, 235.0 / 255.0  # [0, 1] maps to 20..235 for uint8
_SLAB_POINTS = 1 << 21  # points per batch of a deformed render (bounds the temporaries)


def _check_dtype(dtype) -> np.dtype:
    dt = np.dtype(dtype)
    if dt.kind not in "uif" or dt.itemsize > 8:
        raise InputError(f"unsupported dtype {dtype!r} (use uint8, uint16, float32, ...)")
    return dt


def _quantise(v: np.ndarray, dt: np.dtype) -> np.ndarray:
    if dt.kind == "f":
        return v.astype(dt, copy=False)
    top = float(np.iinfo(dt).max)  # signed types: the positive half only (0 .. max)
    lo, hi = _INT_LO * top, _INT_HI * top
    q = np.rint(lo + v.astype(np.float64) * (hi - lo))
    return np.clip(q, 0, top).astype(dt)


def _shape3(shape, name="shape") -> tuple[int, int, int]:
    if np.isscalar(shape):
        shape = (shape,) * 3
    t = tuple(int(s) for s in shape)
    if len(t) != 3 or any(s < 1 for s in t):
        raise InputError(f"{name} must be 3 positive integers (z, y, x), got {shape!r}")
    return t


def render(shape, *, field: Field | None = None, seed: int = 0, origin=(0, 0, 0),
           which: str = "reference", dtype="float32", cell_size: float = 8.0,
           bead_size: float = 64.0, noise: float = 0.0, **params) -> np.ndarray:
    """Render one box of the reference or deformed scan in memory.

    Parameters
    ----------
    shape : int or tuple of 3 int
        Box shape ``(nz, ny, nx)``.
    field : Field or None
        Displacement field (``None``: no motion).
    seed, cell_size, bead_size, **params
        Texture parameters (see :func:`texture`; ``seed`` may be a
        :class:`TextureParams`).
    origin : tuple of 3 int
        Global voxel index of the box's first voxel.
    which : {"reference", "deformed"}
        ``reference``: ``f(X)``; ``deformed``: ``g(x) = f(field.inverse(x))``.
    dtype : str
        Output dtype; integer dtypes map [0, 1] to 20/255..235/255 of the range, rounded.
    noise : float
        Standard deviation of additive Gaussian acquisition noise in texture units
        (independent in the two scans, hashed from the global voxel index).

    Returns
    -------
    ndarray, shape ``shape``, ``dtype``

    Examples
    --------
    >>> f = render((8, 8, 8), seed=3)
    >>> g = render((8, 8, 8), seed=3, field=Translation((0.5, 0, 0)), which="deformed")
    """
    p = _params(seed, cell_size, bead_size, params)
    shape = _shape3(shape)
    origin = tuple(int(o) for o in origin)
    if len(origin) != 3:
        raise InputError(f"origin must be 3 integers, got {origin!r}")
    if which not in ("reference", "deformed"):
        raise InputError(f"which must be 'reference' or 'deformed', got {which!r}")
    dt = _check_dtype(dtype)
    prm, keys = p._kernel_args()
    out = np.empty(shape, np.float32)
    if which == "reference" or field is None:
        _texture_grid(origin[0], origin[1], origin[2], prm, keys, out)
    else:
        nz, ny, nx = shape
        step = max(1, _SLAB_POINTS // (ny * nx))
        yy = np.arange(ny, dtype=np.float64)[:, None] + origin[1]
        xx = np.arange(nx, dtype=np.float64)[None, :] + origin[2]
        for z0 in range(0, nz, step):
            zz = np.arange(z0, min(nz, z0 + step), dtype=np.float64)[:, None, None] + origin[0]
            X = field.inverse(zz, yy[None], xx[None])
            buf = np.empty(X.shape[1:], np.float32)
            _texture_points(X[0].ravel(), X[1].ravel(), X[2].ravel(), prm, keys, buf.ravel())
            out[z0:z0 + buf.shape[0]] = buf
    if noise:
        acq = _channel_key(p.seed, _CH_ACQ_REF if which == "reference" else _CH_ACQ_DEF)
        _add_gaussian_noise(out, origin[0], origin[1], origin[2], acq, float(noise))
    return _quantise(out, dt)


def warmup() -> None:
    """Compile (or load from Numba's cache) the texture kernels in this process."""
    render((2, 2, 3), field=Translation((0.5, 0.0, 0.0)), which="deformed", noise=0.01)
    render((2, 2, 3))
    Band(width=4.0).inverse(0.0, 0.0, 0.0)


def _render_block(*, field, params, which, out_dtype, noise, origin, block_info=None):
    loc = block_info[None]["array-location"]
    o = tuple(origin[i] + loc[i][0] for i in range(3))
    s = tuple(loc[i][1] - loc[i][0] for i in range(3))
    return render(s, field=field, seed=params, origin=o, which=which, dtype=out_dtype, noise=noise)


def as_dask(shape, *, chunks, field: Field | None = None, seed: int = 0,
            which: str = "reference", dtype="float32", cell_size: float = 8.0,
            bead_size: float = 64.0, noise: float = 0.0, origin=(0, 0, 0), **params):
    """The reference or deformed scan as a lazy Dask array, computed chunk by chunk.

    Same parameters as :func:`render`, plus ``chunks`` (anything
    :func:`dask.array.core.normalize_chunks` accepts). The graph carries only the small
    parameters (field, texture parameters), never arrays; each chunk equals the same box
    of :func:`render` exactly.

    Returns
    -------
    dask.array.Array, shape ``shape``, ``dtype``
    """
    import dask.array as da

    p = _params(seed, cell_size, bead_size, params)
    shape = _shape3(shape)
    dt = _check_dtype(dtype)
    if which not in ("reference", "deformed"):
        raise InputError(f"which must be 'reference' or 'deformed', got {which!r}")
    norm = da.core.normalize_chunks(chunks, shape, dtype=dt)
    return da.map_blocks(
        _render_block, chunks=norm, dtype=dt, meta=np.empty((0, 0, 0), dt),
        name=f"chunkdic-synth-{which}-" + _token(p, field, which, dt, noise, origin, norm),
        field=field, params=p, which=which, out_dtype=dt.name, noise=float(noise),
        origin=tuple(int(o) for o in origin),
    )


def _token(*args) -> str:
    from dask.base import tokenize

    return tokenize(*(repr(a) for a in args))


# --------------------------------------------------------------------------- writer

_SYNTH_ATTR = "synthetic"


def _metadata(field, p: TextureParams, shape, dtype, noise) -> dict:
    return {
        "field": None if field is None else field.to_json(),
        "texture": p.to_json(),
        "seed": p.seed,
        "shape": list(shape),
        "dtype": np.dtype(dtype).name,
        "noise": float(noise),
        "intensity_map": None if np.dtype(dtype).kind == "f" else [_INT_LO, _INT_HI],
    }


SPECIMEN_NAMES = ("foam", "grains", "concrete")
_CT_ONLY = ("angles", "filter", "blur", "rings", "gain", "offset", "drift")


def synthesize(out_dir, shape, *, field: Field | None = None, specimen: str = "foam",
               seed: int = 0, dtype=None, chunks=None, voxel_size=None, unit=None,
               levels: int = 0, overwrite: bool = False, progress=None,
               cell_size: float = 8.0, bead_size: float = 64.0, noise: float | None = None,
               fourier_shift: bool = False, **params) -> dict:
    """Write a synthetic reference/deformed pair ``out_dir/ref.zarr``, ``out_dir/def.zarr``.

    Both scans are written chunk by chunk with :func:`chunkdic.scanwrite.write_scan`. The field
    JSON, seed and specimen parameters go to ``attrs["chunkdic"]["synthetic"]`` of both
    groups and to ``out_dir/field.json`` (written last: its presence marks a complete pair).

    Parameters
    ----------
    out_dir : path
        Output directory (created).
    shape : int or tuple of 3 int
        Scan shape ``(nz, ny, nx)``.
    field : Field or None
        Displacement field (``None``: a pair of identical scans up to ``noise``).
    specimen : {"foam", "grains", "concrete"} or GrainsParams or ConcreteParams
        ``foam`` (default): the smooth procedural foam of this module. ``grains`` /
        ``concrete``: sharp-edged CT-like specimens imaged by simulated CT slice by slice
        (:mod:`chunkdic.microstructure`, :mod:`chunkdic.ctsim`, docs/synthetic.md).
    dtype : str
        Foam: ``uint8`` (default), ``uint16`` or ``float32``; integer grey levels are
        rounded, so ``g(X + u(X)) = f(X)`` holds to half a grey level. CT specimens:
        ``uint16`` (default; phase units ``[-0.5, 1.5]`` over the range) or ``float32``.
    chunks, voxel_size, unit, levels, overwrite, progress
        Passed to ``write_scan``.
    seed, cell_size, bead_size
        Foam texture parameters (see :func:`render`); ``seed`` for every specimen.
    noise : float, optional
        Foam: std of additive Gaussian noise, texture units (default 0). CT specimens:
        std of the reconstruction noise as a fraction of the phase contrast (default 0.02),
        independent in the two scans.
    fourier_shift : bool
        CT specimens: the deformed scan is the stored reference translated by a Fourier
        phase shift of ``field.t`` (a :class:`Translation`; the paper's section 4.2 test).
    **params
        Foam: other :class:`TextureParams` fields. CT specimens: specimen parameters
        (:class:`~chunkdic.microstructure.GrainsParams`, ``ConcreteParams``), imaging
        (``angles``, ``filter``, ``blur``, ``rings``) and the grey-level change of the
        deformed scan (``gain``, ``offset``, ``drift``; :class:`~chunkdic.ctsim.GreyChange`).

    Returns
    -------
    dict
        ``{"reference": path, "deformed": path, "field_json": path, "field": Field,
        "texture": TextureParams or specimen parameters}``.

    Examples
    --------
    Case (c) of docs/synthetic.md, a compression band with a grey-level change:

    >>> from chunkdic.ctpair import standard_field
    >>> fld, _ = standard_field("band", (96, 96, 96))
    >>> synthesize("band", 96, specimen="grains", field=fld, noise=0.02,
    ...            gain=1.1, offset=0.05, drift=0.03)  # doctest: +SKIP
    """
    from . import config

    shape = _shape3(shape)
    if chunks is None:
        chunks = config.get("chunk-size")
    if specimen == "foam":
        bad = sorted(k for k in params if k in _CT_ONLY) + (["fourier_shift"] if fourier_shift else [])
        if bad:
            raise InputError(f"{', '.join(bad)}: only for the CT specimens (grains, concrete)")
        p = _params(seed, cell_size, bead_size, params)
        dt = _check_dtype("uint8" if dtype is None else dtype)
        noise = 0.0 if noise is None else float(noise)
        if not (np.isfinite(noise) and noise >= 0):
            raise InputError(f"noise must be >= 0, got {noise!r}")
        meta = _metadata(field, p, shape, dt, noise)

        def make(which, ref_path, scratch):
            return as_dask(shape, chunks=chunks, field=field, seed=p, which=which, dtype=dt,
                           noise=noise)
    else:
        from .ctpair import CTSpecimen, as_dask_ct, fourier_deformed

        p = CTSpecimen.build(specimen, shape, seed=seed, field=field, dtype=dtype,
                             fourier_shift=fourier_shift, noise=noise, **params)
        dt = np.dtype(p.dtype)
        meta = {"field": None if field is None else field.to_json(), "seed": p.params.seed,
                "shape": list(shape), "dtype": dt.name, "noise": p.imaging.noise,
                **p.metadata()}

        def make(which, ref_path, scratch):
            if which == "deformed" and p.fourier_shift:
                arr, tmp = fourier_deformed(ref_path, os.path.dirname(ref_path), p)
                scratch.append(tmp)
                return arr
            return as_dask_ct(p, which)
    out = _write_pair(out_dir, shape, make, meta, chunks=chunks, voxel_size=voxel_size,
                      unit=unit, levels=levels, overwrite=overwrite, progress=progress)
    return {**out, "field": field, "texture": p if specimen == "foam" else p.params}


def standard_case(out_dir, case: str, shape=128, *, specimen: str = "grains", **kw) -> dict:
    """Write one of the three standard test pairs in one call (docs/synthetic.md).

    ``case``: ``"fourier-shift"`` (the paper's section 4.2 test: deformed = reference
    Fourier-shifted by (0.5, 0.5, 0.5) voxel), ``"shift"`` (the same translation rendered
    from the geometry, independent noise in each scan) or ``"band"`` (compression band at
    mid-height: -8 % peak strain, 6 voxels wide, lateral expansion 0.3). ``kw`` goes to
    :func:`synthesize` (``noise``, ``gain``, ``offset``, ``drift``, ``seed``, ``dtype``,
    specimen and imaging parameters, ...).

    Examples
    --------
    >>> standard_case("band128", "band", 128, noise=0.02, gain=1.1, offset=0.05,
    ...               drift=0.03)  # doctest: +SKIP
    """
    from .ctpair import standard_field

    shape = _shape3(shape)
    fld, fourier = standard_field(case, shape)
    return synthesize(out_dir, shape, field=fld, specimen=specimen, fourier_shift=fourier, **kw)


def _write_pair(out_dir, shape, make, meta, *, chunks, voxel_size, unit, levels, overwrite,
                progress) -> dict:
    """Write ``make(which, ref_path, scratch)`` for both scans, then ``field.json``."""
    from .scanwrite import write_scan

    out_dir = os.fspath(out_dir)
    ref, dfm = os.path.join(out_dir, "ref.zarr"), os.path.join(out_dir, "def.zarr")
    fjson = os.path.join(out_dir, "field.json")
    existing = [q for q in (ref, dfm, fjson) if os.path.exists(q)]
    if existing and not overwrite:
        raise InputError(f"{existing[0]} exists (use overwrite=True / --overwrite)")
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise InputError(f"{out_dir} exists and is not a directory")
    os.makedirs(out_dir, exist_ok=True)
    if os.path.exists(fjson):
        os.remove(fjson)  # the pair is incomplete until field.json is back
    written, scratch = [], []
    try:
        for i, (which, path) in enumerate((("reference", ref), ("deformed", dfm))):
            arr = make(which, ref, scratch)
            log.info("writing %s scan %s, shape %s, %s", which, path, shape, arr.dtype)
            sub = None if progress is None else _sub_progress(progress, i / 2.0, (i + 1) / 2.0)
            written.append(path)
            write_scan(path, arr, voxel_size=voxel_size, unit=unit, chunks=chunks,
                       overwrite=overwrite, levels=levels, progress=sub)
            _set_synthetic_attrs(path, {**meta, "role": which})
        tmp = fjson + ".tmp"
        with open(tmp, "w") as fh:
            json.dump(meta, fh, indent=2)
        os.replace(tmp, fjson)
    except BaseException:
        for path in written:  # leave no half-written pair behind
            shutil.rmtree(path, ignore_errors=True)
        raise
    finally:
        for path in scratch:
            shutil.rmtree(path, ignore_errors=True)
    return {"reference": ref, "deformed": dfm, "field_json": fjson}


def _sub_progress(progress, start: float, end: float):
    def report(frac: float) -> None:
        progress(start + (end - start) * float(frac))

    return report


def _set_synthetic_attrs(path: str, meta: dict) -> None:
    import zarr

    g = zarr.open_group(path, mode="r+")
    ck = dict(g.attrs.get("chunkdic", {}))
    ck[_SYNTH_ATTR] = meta
    g.attrs["chunkdic"] = ck


def load_metadata(path) -> dict:
    """Synthetic metadata of a pair directory (``field.json``) or of one scan group."""
    path = os.fspath(path)
    fj = os.path.join(path, "field.json")
    if os.path.isfile(fj):
        with open(fj) as fh:
            return json.load(fh)
    if os.path.isfile(path) and path.endswith(".json"):
        with open(path) as fh:
            return json.load(fh)
    try:
        import zarr

        g = zarr.open_group(path, mode="r")
        return dict(g.attrs["chunkdic"][_SYNTH_ATTR])
    except Exception as exc:  # noqa: BLE001 - turned into one actionable line
        raise InputError(f"{path} is not a synthetic pair directory or scan ({exc})") from None


def load_field(path) -> Field | None:
    """The displacement field of a synthetic pair (directory, ``field.json`` or scan group).

    Returns ``None`` for a pair written without a field.
    """
    d = load_metadata(path)["field"]
    return None if d is None else Field.from_json(d)


def load_texture(path) -> TextureParams:
    """The texture parameters of a synthetic foam pair (directory, ``field.json`` or scan group)."""
    meta = load_metadata(path)
    if "texture" not in meta:
        raise InputError(f"{path} is a {meta.get('specimen', {}).get('specimen')} pair, not a foam")
    return TextureParams(**meta["texture"])


def load_specimen(path):
    """The specimen of a synthetic pair: :class:`TextureParams` (foam) or the parameters
    of a CT specimen (:class:`~chunkdic.microstructure.GrainsParams`, ``ConcreteParams``)."""
    meta = load_metadata(path)
    if "texture" in meta:
        return TextureParams(**meta["texture"])
    from .microstructure import specimen_params

    return specimen_params(dict(meta["specimen"]))
