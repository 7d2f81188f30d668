"""Sharp-edged microstructures of CT-like specimens, evaluated point by point.

Two specimens, both made of polydisperse spheres placed by integer hashes (nothing stored,
as for the foam of :mod:`chunkdic.synth.synthetic`), so that any point of an unbounded specimen
is evaluated on its own and any chunk agrees with any other render exactly:

- ``grains`` (:class:`GrainsParams`): a granular material. Bright grains (one grey level
  per grain, small spread) in dark pore space.
- ``concrete`` (:class:`ConcreteParams`): a mid-grey matrix with a fine low-contrast
  texture (unresolved small particles: C2 value noise), bright aggregates and dark pores.

Values are attenuations in *phase units*: the darkest phase (pores, air) is 0 and the
brightest phase (grains, aggregates) 1 on average, so that the phase contrast is 1.

Geometry
--------
Each population of spheres is a Boolean model (overlaps allowed): a lattice of cubic cells
of edge ``L = r_max + 1``, each holding a Poisson number of spheres (mean ``lam``) with
centres uniform in the cell, radii from a lognormal law truncated to
``[r_min, r_max]`` (inverse CDF) and a grey level uniform in ``level +- spread``. That is a
homogeneous Poisson process: the expected volume fraction of the union is
``1 - exp(-lam / L^3 * 4/3 pi E[r^3])``; the parameters give the fraction and ``lam``
follows. A point sees only the spheres of the 27 cells around its cell
(:mod:`chunkdic.synth.boolean` has the kernels).

Texture scale
-------------
``texture_scale`` multiplies every size of a specimen (radii of each population, the
concrete matrix's texture lattice) and leaves its fractions and grey levels alone: the
same material seen at a finer or coarser binning, with the same voxel-sized edges, noise
and reconstruction. The autocorrelation length of the scans grows in proportion (about 6
voxels at 1; docs/synthetic.md, "Texture scale", has the measured statistics) while the
texture per element falls: sizes of 4 to 32 voxels cover fine granular scans to
cementitious and rock scans whose large inclusions carry little inner texture.

Partial volume (analytic, no supersampling)
-------------------------------------------
A voxel's value is the fraction of the voxel (unit cube centred on the point) inside the
phase, computed for the boundary's tangent plane: with ``s`` the signed distance to the
nearest sphere surface and ``n`` its normal, the fraction is ``P(n.U < -s)`` for ``U``
uniform in the cube, the CDF of a sum of three uniforms of widths ``|n_i|``
(:func:`chunkdic.synth.boolean.cube_fraction`, exact for a plane). For a sphere the tangent plane lies outside
the surface; averaged over positions this overestimates the volume by exactly
``pi r / 3`` (``integral = 4/3 pi (r^3 + r/4)``), so the spheres are drawn with an
effective radius solving ``r_e^3 + r_e/4 = r^3`` and the voxel sum of an isolated sphere
equals its volume (measured: within 0.13 voxel^3 for r in [3, 10], against pi r / 3 >= 3.1
without the correction). Per voxel the planar rule differs from the exact fraction by the
surface's sag over the voxel, at most ~``3/(8 r)`` of a voxel (measured max 0.012, RMS
0.004 over the edge voxels at r = 3.2, against 16^3 supersampling). Where two spheres meet, the
fraction is ``f1 + f2 - f1 f2`` of the two nearest (exact for perpendicular planes);
the grey level between two overlapping grains is blended over one voxel the same way.

Deformed specimens are evaluated at ``X = field.inverse(x)``: the phase at the material
point, never an interpolation of the reference. The ramp width stays one reference voxel
(an error of order strain x 1 voxel in the edge width, none in the edge position).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from numba import njit

from ..errors import InputError
from .boolean import (
    build_table,
    hash3,
    mean_r3,
    phase_at,
    population_vector,
    stream_key,
)

__all__ = [
    "GrainsParams",
    "ConcreteParams",
    "SPECIMENS",
    "specimen_params",
    "phantom",
    "render_phantom",
    "spheres",
]

# hash channels (distinct streams from one seed); ctsim uses 31..
CH_GRAINS, CH_AGGREGATES, CH_PORES, CH_TEXTURE = 21, 22, 23, 24
_S11 = np.uint64(11)
#: the factor ``texture_scale`` may take (module docstring, "Texture scale")
TEXTURE_SCALE_RANGE = (0.25, 16.0)
_INV53 = 1.0 / (1 << 53)


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class Population:
    """One population of spheres: volume fraction of the union and radius law (voxels)."""

    fraction: float
    median: float
    sigma: float
    r_min: float
    r_max: float

    def check(self, name: str) -> None:
        if not (0.0 <= self.fraction < 1.0):
            raise InputError(f"{name} fraction must lie in [0, 1), got {self.fraction!r}")
        if not (0.5 <= self.r_min <= self.median <= self.r_max <= 200.0):
            raise InputError(f"{name} radii need 0.5 <= r_min <= median <= r_max <= 200, got "
                             f"{self.r_min!r}, {self.median!r}, {self.r_max!r}")
        if not (0.0 <= self.sigma <= 2.0):
            raise InputError(f"{name} radius sigma must lie in [0, 2], got {self.sigma!r}")

    def scaled(self, factor: float) -> "Population":
        """The same population with every radius multiplied by ``factor`` (same volume fraction)."""
        return Population(self.fraction, self.median * factor, self.sigma, self.r_min * factor,
                          self.r_max * factor)

    def mean_r3(self) -> float:
        """``E[r^3]`` of the truncated lognormal law, voxels^3."""
        return mean_r3(self.median, self.sigma, self.r_min, self.r_max)

    def vector(self, level: float, spread: float) -> np.ndarray:
        """Kernel vector (:func:`chunkdic.synth.boolean.population_vector`)."""
        return population_vector(self.fraction, self.median, self.sigma, self.r_min,
                                 self.r_max, level, spread)


def _check_scale(scale: float) -> None:
    lo, hi = TEXTURE_SCALE_RANGE
    if not (lo <= scale <= hi):
        raise InputError(f"texture_scale must lie in [{lo:g}, {hi:g}], got {scale!r}")


def _finite(obj, names):
    for n in names:
        v = getattr(obj, n)
        try:
            f = float(v)
        except (TypeError, ValueError):
            f = float("nan")
        if isinstance(v, bool) or not np.isfinite(f):
            raise InputError(f"{n} must be a finite number, got {v!r}")
        object.__setattr__(obj, n, f)


@dataclass(frozen=True)
class GrainsParams:
    """Granular specimen: overlapping polydisperse grains (bright) in pore space (dark).

    Parameters (sizes in voxels)
    ----------------------------
    seed : int
    solid_fraction : float
        Expected volume fraction of the grains (union of the spheres), default 0.6.
    radius_median, radius_sigma, radius_min, radius_max : float
        Lognormal radius law (median, sigma of ``ln r``) truncated to ``[min, max]``;
        default 5, 0.35, 3, 10.
    grain_level, grain_spread : float
        Mean grey level of the grains (phase units) and half-width of the uniform
        per-grain variation; default 1.0, 0.05.
    pore_level : float
        Grey level of the pore space, default 0.
    texture_scale : float
        Factor applied to every size above (module docstring, "Texture scale"), default 1.
    """

    seed: int = 0
    solid_fraction: float = 0.6
    radius_median: float = 5.0
    radius_sigma: float = 0.35
    radius_min: float = 3.0
    radius_max: float = 10.0
    grain_level: float = 1.0
    grain_spread: float = 0.05
    pore_level: float = 0.0
    texture_scale: float = 1.0

    kind = "grains"

    def __post_init__(self):
        object.__setattr__(self, "seed", int(self.seed))
        _finite(self, [n for n in self.__dataclass_fields__ if n != "seed"])
        _check_scale(self.texture_scale)
        self.grains.check("grain")
        if not (0.0 <= self.grain_spread < 0.5):
            raise InputError(f"grain_spread must lie in [0, 0.5), got {self.grain_spread!r}")

    @property
    def grains(self) -> Population:
        """The grains as drawn (radii times :attr:`texture_scale`)."""
        return Population(self.solid_fraction, self.radius_median, self.radius_sigma,
                          self.radius_min, self.radius_max).scaled(self.texture_scale)

    def to_json(self) -> dict:
        return {"specimen": self.kind, **asdict(self)}

    def _kernel_args(self):
        pops = np.stack([self.grains.vector(self.grain_level, self.grain_spread),
                         Population(0.0, 1.0, 0.0, 1.0, 1.0).vector(0.0, 0.0)])
        keys = np.array([stream_key(self.seed, CH_GRAINS), stream_key(self.seed, CH_PORES),
                         stream_key(self.seed, CH_TEXTURE)], np.uint64)
        prm = np.array([0, self.pore_level, 0.0, 0.0, 1.0], np.float64)
        return pops, keys, prm


@dataclass(frozen=True)
class ConcreteParams:
    """Cementitious specimen: matrix (mid grey, fine texture), aggregates (bright), pores.

    Parameters (sizes in voxels)
    ----------------------------
    seed : int
    aggregate_fraction : float
        Expected volume fraction of the aggregates before the pores are cut, default 0.4.
    aggregate_median, aggregate_sigma, aggregate_min, aggregate_max : float
        Aggregate radius law, default 6, 0.4, 3.5, 14.
    pore_fraction : float
        Expected volume fraction of the pores (they cut through everything), default 0.04.
    pore_median, pore_sigma, pore_min, pore_max : float
        Pore radius law, default 2, 0.35, 1, 5.
    matrix_level, aggregate_level, aggregate_spread, pore_level : float
        Grey levels (phase units), default 0.5, 1.0, 0.05, 0.0.
    texture_contrast, texture_size : float
        Amplitude (peak, phase units) and lattice spacing (voxels) of the matrix's C2
        value noise, default 0.08 (std ~0.025) and 2.
    texture_scale : float
        Factor applied to every size above (radii of aggregates and pores, the matrix
        texture's lattice; module docstring, "Texture scale"), default 1.
    """

    seed: int = 0
    aggregate_fraction: float = 0.4
    aggregate_median: float = 6.0
    aggregate_sigma: float = 0.4
    aggregate_min: float = 3.5
    aggregate_max: float = 14.0
    pore_fraction: float = 0.04
    pore_median: float = 2.0
    pore_sigma: float = 0.35
    pore_min: float = 1.0
    pore_max: float = 5.0
    matrix_level: float = 0.5
    aggregate_level: float = 1.0
    aggregate_spread: float = 0.05
    pore_level: float = 0.0
    texture_contrast: float = 0.08
    texture_size: float = 2.0
    texture_scale: float = 1.0

    kind = "concrete"

    def __post_init__(self):
        object.__setattr__(self, "seed", int(self.seed))
        _finite(self, [n for n in self.__dataclass_fields__ if n != "seed"])
        _check_scale(self.texture_scale)
        self.aggregates.check("aggregate")
        self.pores.check("pore")
        if not (0.0 <= self.aggregate_spread < 0.5):
            raise InputError(f"aggregate_spread must lie in [0, 0.5), got {self.aggregate_spread!r}")
        if not (self.texture_contrast >= 0.0 and self.texture_size * self.texture_scale >= 0.5):
            raise InputError("texture_contrast must be >= 0 and texture_size >= 0.5 voxel")

    @property
    def aggregates(self) -> Population:
        """The aggregates as drawn (radii times :attr:`texture_scale`)."""
        return Population(self.aggregate_fraction, self.aggregate_median, self.aggregate_sigma,
                          self.aggregate_min, self.aggregate_max).scaled(self.texture_scale)

    @property
    def pores(self) -> Population:
        """The pores as drawn (radii times :attr:`texture_scale`)."""
        return Population(self.pore_fraction, self.pore_median, self.pore_sigma,
                          self.pore_min, self.pore_max).scaled(self.texture_scale)

    def to_json(self) -> dict:
        return {"specimen": self.kind, **asdict(self)}

    def _kernel_args(self):
        pops = np.stack([self.aggregates.vector(self.aggregate_level, self.aggregate_spread),
                         self.pores.vector(self.pore_level, 0.0)])
        keys = np.array([stream_key(self.seed, CH_AGGREGATES), stream_key(self.seed, CH_PORES),
                         stream_key(self.seed, CH_TEXTURE)], np.uint64)
        prm = np.array([1, self.pore_level, self.matrix_level, self.texture_contrast,
                        1.0 / (self.texture_size * self.texture_scale)], np.float64)
        return pops, keys, prm


SPECIMENS = {"grains": GrainsParams, "concrete": ConcreteParams}


def specimen_params(specimen, seed: int = 0, **params):
    """Parameters of a CT specimen by name (``"grains"``, ``"concrete"``) or as given.

    ``specimen`` may already be a :class:`GrainsParams` / :class:`ConcreteParams`
    (``seed`` and ``params`` are then ignored). Unknown names or parameters raise
    :class:`~chunkdic.errors.InputError`.
    """
    if isinstance(specimen, (GrainsParams, ConcreteParams)):
        return specimen
    if isinstance(specimen, dict):
        d = dict(specimen)
        return specimen_params(d.pop("specimen"), **d)
    cls = SPECIMENS.get(specimen)
    if cls is None:
        raise InputError(f"unknown specimen {specimen!r} (known: foam, {', '.join(SPECIMENS)})")
    bad = sorted(set(params) - set(cls.__dataclass_fields__))
    if bad:
        raise InputError(f"unknown {specimen} parameter(s) {bad} (known: "
                         f"{', '.join(n for n in cls.__dataclass_fields__ if n != 'seed')})")
    return cls(seed=seed, **params)


# --------------------------------------------------------------------------- kernels


@njit(nogil=True, cache=True)
def _fade(t):
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


@njit(nogil=True, cache=True)
def _value_noise(qz, qy, qx, key):
    """C2 value noise in [-1, 1] on the unit lattice."""
    cz, cy, cx = math.floor(qz), math.floor(qy), math.floor(qx)
    iz, iy, ix = np.int64(cz), np.int64(cy), np.int64(cx)
    tz, ty, tx = _fade(qz - cz), _fade(qy - cy), _fade(qx - cx)
    v = 0.0
    for dz in range(2):
        wz = tz if dz else 1.0 - tz
        for dy in range(2):
            wy = ty if dy else 1.0 - ty
            for dx in range(2):
                wx = tx if dx else 1.0 - tx
                h = hash3(iz + dz, iy + dy, ix + dx, key)
                v += wz * wy * wx * (np.float64(h >> _S11) * _INV53 * 2.0 - 1.0)
    return v


@njit(nogil=True, cache=True)
def _phantom_kernel(qz, qy, qx, pops, keys, prm, out):
    """Phase values at the points q (1-D float64 arrays) into out (1-D float32).

    prm: 0 kind (0 grains, 1 concrete), 1 pore level, 2 matrix level, 3 texture
    amplitude, 4 1/texture size.
    """
    n = qz.size
    if n == 0:
        return
    lo0, hi0 = qz.min(), qz.max()
    lo1, hi1 = qy.min(), qy.max()
    lo2, hi2 = qx.min(), qx.max()
    c0a, da, sa, spa = build_table(pops[0], keys[0], lo0, lo1, lo2, hi0, hi1, hi2)
    c0b, db, sb, spb = build_table(pops[1], keys[1], lo0, lo1, lo2, hi0, hi1, hi2)
    La, Lb = pops[0, 0], pops[1, 0]
    concrete = prm[0] == 1.0
    for i in range(n):
        z, y, x = qz[i], qy[i], qx[i]
        fa, ga = phase_at(z, y, x, La, c0a, da, sa, spa)
        if concrete:
            fp, gp = phase_at(z, y, x, Lb, c0b, db, sb, spb)
            m = prm[2]
            if prm[3] != 0.0:
                m += prm[3] * _value_noise(z * prm[4], y * prm[4], x * prm[4], keys[2])
            v = (1.0 - fp) * (fa * ga + (1.0 - fa) * m) + fp * prm[1]
        else:
            v = fa * ga + (1.0 - fa) * prm[1]
        out[i] = v


# --------------------------------------------------------------------------- public API

_GROUP = 32.0  # points are evaluated in groups of 32^3-voxel boxes (bounded sphere tables)


def phantom(params, z, y, x) -> np.ndarray:
    """Noise-free phase values (attenuation, phase units) at arbitrary points.

    Parameters
    ----------
    params : GrainsParams or ConcreteParams
    z, y, x : array_like, broadcastable, float64, voxels
        Positions (voxel ``i`` has its centre at ``i``).

    Returns
    -------
    ndarray, float32, broadcast shape
        0 in pores, ~1 in grains/aggregates; partial-volume values at the edges.

    Examples
    --------
    >>> v = phantom(GrainsParams(seed=1), [0.0, 5.0], 0.0, 0.0)
    >>> v.dtype
    dtype('float32')
    """
    zz, yy, xx = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (z, y, x)))
    shape = zz.shape
    q = np.stack([zz.ravel(), yy.ravel(), xx.ravel()])
    out = np.empty(q.shape[1], np.float32)
    if q.shape[1] == 0:
        return out.reshape(shape)
    # group far-apart points so that each sphere table stays small; values do not depend
    # on the grouping (pure functions of the point)
    cells = np.floor(q / _GROUP).astype(np.int64)
    _, inv = np.unique(cells, axis=1, return_inverse=True)
    order = np.argsort(inv.ravel(), kind="stable")
    bounds = np.flatnonzero(np.diff(inv.ravel()[order])) + 1
    pops, keys, prm = params._kernel_args()
    for idx in np.split(order, bounds):
        buf = np.empty(idx.size, np.float32)
        _phantom_kernel(q[0, idx], q[1, idx], q[2, idx], pops, keys, prm, buf)
        out[idx] = buf
    return out.reshape(shape)


def render_phantom(params, shape, *, origin=(0, 0, 0), field=None) -> np.ndarray:
    """Noise-free phase map of a box, reference or deformed (``g(x) = phase(X(x))``).

    Parameters
    ----------
    params : GrainsParams or ConcreteParams
    shape : tuple of 3 int
        ``(nz, ny, nx)``.
    origin : tuple of 3 int
        Global voxel index of the first voxel.
    field : chunkdic.synth.fields.Field or None
        Deformation; the value at ``x`` is the phase at ``X = field.inverse(x)``.

    Returns
    -------
    ndarray, shape ``shape``, float32, phase units
    """
    nz, ny, nx = (int(s) for s in shape)
    pops, keys, prm = params._kernel_args()
    out = np.empty((nz, ny, nx), np.float32)
    yy = np.arange(ny, dtype=np.float64)[:, None] + origin[1]
    xx = np.arange(nx, dtype=np.float64)[None, :] + origin[2]
    for k in range(nz):
        z = float(origin[0] + k)
        if field is None:
            q = np.broadcast_arrays(np.full((ny, nx), z), yy, xx)
        else:
            q = field.inverse(z, yy, xx)
        _phantom_kernel(np.ascontiguousarray(q[0]).ravel(), np.ascontiguousarray(q[1]).ravel(),
                        np.ascontiguousarray(q[2]).ravel(), pops, keys, prm, out[k].reshape(-1))
    return out


def spheres(params, population: str, lo, hi) -> dict:
    """The spheres of one population whose lattice cells meet the box ``[lo, hi]``.

    For tests and figures. ``population``: ``"grains"`` (GrainsParams),
    ``"aggregates"`` or ``"pores"`` (ConcreteParams).

    Returns
    -------
    dict
        ``center`` (n, 3) float64 voxels ``(z, y, x)``, ``radius`` (n,) the drawn radius,
        ``effective_radius`` (n,), ``grey`` (n,), ``cell`` (float, lattice edge) and
        ``intensity`` (spheres per voxel^3).
    """
    pops, keys, _ = params._kernel_args()
    i = {"grains": 0, "aggregates": 0, "pores": 1}.get(population)
    if i is None or (population == "grains") != isinstance(params, GrainsParams):
        raise InputError(f"population {population!r} does not belong to {params.kind}")
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    _, _, _, sph = build_table(pops[i], keys[i], *lo, *hi)
    return {"center": sph[:, :3].copy(), "radius": sph[:, 5].copy(),
            "effective_radius": sph[:, 3].copy(), "grey": sph[:, 4].copy(),
            "cell": float(pops[i, 0]), "intensity": float(pops[i, 1] / pops[i, 0] ** 3)}


