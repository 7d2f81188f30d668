"""What every block kernel shares: the block's core and halo, its elements, the gradient of ``f``.

A block is a box of whole elements read with a one-voxel halo of the reference, clipped at
the volume boundary (docs/architecture.md, "Coordinates and blocks"). These helpers are
used by the numba kernels (:mod:`chunkdic.kernels.jit`) and their NumPy twins
(:mod:`chunkdic.kernels.twins`) alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: lags (voxels along x) of the autocorrelations that estimate the noise correlation, summed on
#: every row of voxels over the pairs that start on the block core's first ``nx - LAGS`` voxels,
#: the same for every lag: whatever the blocks' cut, every row counts, and a lag summed over
#: ``nx - k`` voxels would read less correlation the narrower the blocks; what a block's x end
#: leaves out, ``LAGS`` voxels per row, depends on the cut (docs/engine.md, "Noise correlation")
LAGS = 4

__all__ = ["LAGS", "QUANTITIES", "ElementSums", "core_shape", "elements_of", "check_nodes", "voxel_xi", "grad_index", "gradient_block"]


#: order of the quantities of :class:`ElementSums`: ``d``, ``g'``, ``1``, then the
#: element-centred coordinates ``z~, y~, x~ = ξ - 1/2`` (ξ the local coordinate, 0..1)
QUANTITIES = ("d", "g", "1", "z", "y", "x")


@dataclass
class ElementSums:
    """Per-element sums of one ``b`` pass over a block (see :mod:`chunkdic.kernels.jit`).

    With ``d = f - g(X + u)``, ``g' = g(X + u) - c`` and the element-centred coordinates
    ``q~ = ξ - 1/2`` (in element sizes), ``v = (d, g', 1, z~, y~, x~)`` (:data:`QUANTITIES`).

    Attributes
    ----------
    B : ndarray, shape (ez, ey, ex, 6, 8, 3), float64
        ``B[e, q, a, i] = Σ_{X in e} w N_a ∂_i f v_q``, local node ``a = 4 dz + 2 dy + dx``,
        component ``i`` (z, y, x).
    gram : ndarray, shape (ez, ey, ex, 6, 6), float64
        ``Σ_{X in e} w v vᵀ`` (``gram[e, 2, 2]`` is the element's ``Σ w``).
    n_excluded : int
        Core voxels of weight 0 (``X + u(X)`` outside the usable part of ``g``).
    lags : ndarray, shape (6, LAGS + 1), float64, optional
        Along x, pairs of voxels ``k = 0 … LAGS`` apart in one row (primes: the voxel ``k``
        further): ``Σ w w' Δd²``, ``Σ w w'``, ``Σ w w' 2 Δd Δg'``, ``Σ w w' Δg'²`` with
        ``Δq = q - q'`` for ``k >= 1`` and ``Δq = q`` for ``k = 0`` (the second moments), and
        ``Σ w d``, ``Σ w g'`` in ``[4, 0]``, ``[5, 0]``: the variogram of any residual
        ``d - α g'`` (:func:`chunkdic.method.noise.correlation_factor`).

    ``w`` are the voxel weights: 1 inside the usable part of ``g``, tapering to 0 over
    its last voxel.
    """

    B: np.ndarray
    gram: np.ndarray
    n_excluded: int
    lags: np.ndarray | None = None


def core_shape(f: np.ndarray, lo, hi) -> tuple[int, int, int]:
    """Shape of a block's core given its haloed region and halos (ValueError if malformed)."""
    if f.ndim != 3:
        raise ValueError(f"f must be 3-D, got shape {f.shape}")
    lo = tuple(int(v) for v in lo)
    hi = tuple(int(v) for v in hi)
    if len(lo) != 3 or len(hi) != 3 or any(v not in (0, 1) for v in lo + hi):
        raise ValueError(f"lo and hi must be 3 values in {{0, 1}}, got {lo}, {hi}")
    core = tuple(n - a - b for n, a, b in zip(f.shape, lo, hi))
    if any(n < 1 for n in core):
        raise ValueError(f"f of shape {f.shape} with halo {lo}/{hi} has an empty core")
    return core


def elements_of(core, ell: int) -> tuple[int, int, int]:
    """Elements per axis of a core shape (ValueError unless a multiple of ``ell``)."""
    ell = int(ell)
    if ell < 1 or any(n % ell for n in core):
        raise ValueError(f"core shape {tuple(core)} is not a multiple of ell={ell}")
    return tuple(n // ell for n in core)


def check_nodes(u_nodes: np.ndarray, elems) -> np.ndarray:
    """``u_nodes`` as float64 C-contiguous of shape ``(3, ez+1, ey+1, ex+1)`` (ValueError otherwise)."""
    u_nodes = np.ascontiguousarray(u_nodes, dtype=np.float64)
    want = (3,) + tuple(e + 1 for e in elems)
    if u_nodes.shape != want:
        raise ValueError(f"u_nodes must have shape {want}, got {u_nodes.shape}")
    return u_nodes


def voxel_xi(ell: int) -> np.ndarray:
    """Local coordinate ``(l + 0.5) / ell`` of voxel ``l`` in its element (as mesh.shape_table)."""
    return (np.arange(ell) + 0.5) / ell


def grad_index(n_core: int, lo: int, hi: int):
    """Per core index along one axis: neighbour indices in the padded array and the scale.

    Centred ``(f[i+1] - f[i-1]) * 0.5`` where both neighbours exist in the padded region,
    one-sided ``* 1`` where only one does (true volume boundary), 0 if neither (an axis of
    length 1): exactly ``np.gradient(..., edge_order=1)`` on the whole volume.
    """
    n_pad = n_core + lo + hi
    p = np.arange(n_core) + lo
    im = np.maximum(p - 1, 0)
    ip = np.minimum(p + 1, n_pad - 1)
    span = ip - im
    # 0.5 and 1.0 are exact in float32, so the product equals numpy's division by 2.
    sc = np.where(span == 2, 0.5, np.where(span == 1, 1.0, 0.0)).astype(np.float32)
    return im.astype(np.int64), ip.astype(np.int64), sc


def gradient_block(f: np.ndarray, lo, hi) -> np.ndarray:
    """Centred-difference gradient of the reference over a block core.

    Parameters
    ----------
    f : ndarray, shape (core_z + lo[0] + hi[0], ...), any real dtype, grey levels
        Block region of the reference including its halo.
    lo, hi : tuple of 3 int in {0, 1}
        Halo voxels present before / after the core on each axis; 0 means the core touches
        the volume boundary there.

    Returns
    -------
    grad : ndarray, shape (3, *core_shape), float32, grey levels per voxel
        ``(d_z f, d_y f, d_x f)``, identical to ``np.gradient(volume.astype(np.float32))``
        restricted to the core.

    References
    ----------
    Paper section 3.1: "a simple finite difference scheme is used".

    Examples
    --------
    >>> f = np.arange(64, dtype=np.float32).reshape(4, 4, 4)
    >>> gradient_block(f, (0, 0, 0), (0, 0, 0))[:, 1, 1, 1].tolist()
    [16.0, 4.0, 1.0]
    """
    core = core_shape(f, lo, hi)
    f32 = np.asarray(f, dtype=np.float32)
    out = np.empty((3,) + core, dtype=np.float32)
    for axis in range(3):
        im, ip, sc = grad_index(core[axis], lo[axis], hi[axis])
        sl = [slice(lo[a], lo[a] + core[a]) for a in range(3)]
        sl[axis] = slice(None)
        sub = np.moveaxis(f32[tuple(sl)], axis, 0)
        d = (sub[ip] - sub[im]) * sc[:, None, None]
        out[axis] = np.moveaxis(d, 0, axis)
    return out
