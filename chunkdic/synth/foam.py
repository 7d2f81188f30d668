"""The procedural foam texture: its parameters, point evaluation and renders (in memory, Dask).

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

The fields (:class:`~chunkdic.synth.fields.Field`, ...) live in :mod:`chunkdic.synth.fields`; the numba
kernels in :mod:`chunkdic.synth.foam_kernels`; synthetic pairs on disk in :mod:`chunkdic.synth.synthetic`.

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

from dataclasses import asdict, dataclass

import numpy as np

from ..errors import InputError
from .fields import Band, Field, Translation
from .foam_kernels import (
    CH_ACQ_DEF,
    CH_ACQ_REF,
    CH_BEAD,
    CH_CELL,
    CH_NOISE,
    FWHM_R,
    NPRM,
    add_gaussian_noise,
    channel_key,
    texture_grid,
    texture_points,
)

__all__ = [
    "TextureParams",
    "texture",
    "render",
    "as_dask",
    "warmup",
]

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
        r_c = self.wall_width / FWHM_R / self.cell_size  # lattice units
        r_b = self.skin_width / FWHM_R / self.bead_size
        noise = self.noise_size if self.noise_size is not None else self.cell_size / 2.0
        prm = np.empty(NPRM)
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
            [channel_key(self.seed, c) for c in (CH_CELL, CH_BEAD, CH_NOISE)], np.uint64
        )
        return prm, keys


def texture_params(seed, cell_size, bead_size, kw) -> TextureParams:
    """``seed`` if it is a :class:`TextureParams`, else the parameters built from the arguments."""
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
    p = texture_params(seed, cell_size, bead_size, params)
    zz, yy, xx = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (z, y, x)))
    shape = zz.shape
    prm, keys = p._kernel_args()
    out = np.empty(zz.size, np.float32)
    texture_points(
        np.ascontiguousarray(zz).ravel(), np.ascontiguousarray(yy).ravel(),
        np.ascontiguousarray(xx).ravel(), prm, keys, out,
    )
    return out.reshape(shape)


# --------------------------------------------------------------------------- rendering

INT_LO, INT_HI = 20.0 / 255.0, 235.0 / 255.0  # [0, 1] maps to 20..235 for uint8
_SLAB_POINTS = 1 << 21  # points per batch of a deformed render (bounds the temporaries)


def check_dtype(dtype) -> np.dtype:
    """The output dtype, refused (InputError) unless an integer or float type of at most 8 bytes."""
    dt = np.dtype(dtype)
    if dt.kind not in "uif" or dt.itemsize > 8:
        raise InputError(f"unsupported dtype {dtype!r} (use uint8, uint16, float32, ...)")
    return dt


def _quantise(v: np.ndarray, dt: np.dtype) -> np.ndarray:
    if dt.kind == "f":
        return v.astype(dt, copy=False)
    top = float(np.iinfo(dt).max)  # signed types: the positive half only (0 .. max)
    lo, hi = INT_LO * top, INT_HI * top
    q = np.rint(lo + v.astype(np.float64) * (hi - lo))
    return np.clip(q, 0, top).astype(dt)


def shape3(shape, name="shape") -> tuple[int, int, int]:
    """A scan shape as 3 positive ints (a scalar means a cube); InputError otherwise."""
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
    p = texture_params(seed, cell_size, bead_size, params)
    shape = shape3(shape)
    origin = tuple(int(o) for o in origin)
    if len(origin) != 3:
        raise InputError(f"origin must be 3 integers, got {origin!r}")
    if which not in ("reference", "deformed"):
        raise InputError(f"which must be 'reference' or 'deformed', got {which!r}")
    dt = check_dtype(dtype)
    prm, keys = p._kernel_args()
    out = np.empty(shape, np.float32)
    if which == "reference" or field is None:
        texture_grid(origin[0], origin[1], origin[2], prm, keys, out)
    else:
        nz, ny, nx = shape
        step = max(1, _SLAB_POINTS // (ny * nx))
        yy = np.arange(ny, dtype=np.float64)[:, None] + origin[1]
        xx = np.arange(nx, dtype=np.float64)[None, :] + origin[2]
        for z0 in range(0, nz, step):
            zz = np.arange(z0, min(nz, z0 + step), dtype=np.float64)[:, None, None] + origin[0]
            X = field.inverse(zz, yy[None], xx[None])
            buf = np.empty(X.shape[1:], np.float32)
            texture_points(X[0].ravel(), X[1].ravel(), X[2].ravel(), prm, keys, buf.ravel())
            out[z0:z0 + buf.shape[0]] = buf
    if noise:
        acq = channel_key(p.seed, CH_ACQ_REF if which == "reference" else CH_ACQ_DEF)
        add_gaussian_noise(out, origin[0], origin[1], origin[2], acq, float(noise))
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

    p = texture_params(seed, cell_size, bead_size, params)
    shape = shape3(shape)
    dt = check_dtype(dtype)
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
