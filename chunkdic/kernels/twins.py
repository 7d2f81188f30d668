"""Plain NumPy/SciPy twins of the numba kernels of :mod:`chunkdic.kernels.jit`: the test oracle.

Written for obviousness, not speed: ``np.gradient`` semantics for ``grad f``,
``scipy.ndimage.map_coordinates`` for the interpolation, ``einsum`` with
:func:`chunkdic.mesh.shape_table` and explicit loops over elements for the sums. They
share nothing with the numba kernels but :mod:`chunkdic.kernels.blocks` (``kernels.b_sums`` etc.
call them with ``impl="numpy"``).
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

from ..mesh import LOCAL_NODES, shape_table
from .blocks import LAGS, ElementSums, gradient_block, voxel_xi


def _stencil_index(offset) -> int:
    return 9 * (offset[0] + 1) + 3 * (offset[1] + 1) + (offset[2] + 1)


def _element_weights(active, elems, ell) -> np.ndarray:
    """Voxel weights of the element activity (1 in active elements, 0 elsewhere)."""
    a = np.ones(elems) if active is None else np.asarray(active, dtype=np.float64)
    return np.repeat(np.repeat(np.repeat(a, ell, axis=0), ell, axis=1), ell, axis=2)


def _lag_pairs(n: int, k: int) -> tuple[slice, slice]:
    """The voxels of a row of ``n`` and those ``k`` further that the lag sums pair: every lag
    starts on the first ``n - LAGS`` (:data:`~chunkdic.kernels.blocks.LAGS`)."""
    return slice(0, n - LAGS), slice(k, n - LAGS + k)


def m_block_numpy(f32, lo, hi, ell, elems, condensed: int, center: float, u_nodes=None, core_origin=None,
                  g_shape=None, margin: int = 0, active=None, with_lags: bool = False):
    """``M`` stencil (optionally minus the brightness Schur complement), min and max of ``f``
    and, ``with_lags``, the sensitivities' lag sums (3, LAGS + 1): ``Σ w ∂_i f(x) w ∂_i f(x + k)``
    along x on every row (:func:`_lag_pairs`).

    With ``u_nodes``, voxels whose ``X + u(X)`` leaves ``[margin, g_shape - 1 - margin]`` are left out.
    """
    grad = gradient_block(f32, lo, hi).astype(np.float64)
    core = f32[lo[0]:lo[0] + grad.shape[1], lo[1]:lo[1] + grad.shape[2], lo[2]:lo[2] + grad.shape[3]]
    weight = _element_weights(active, elems, ell)
    if u_nodes is not None:
        u = nodal_field(u_nodes, ell)
        grids = np.meshgrid(*[np.arange(n) for n in core.shape], indexing="ij")
        pos = np.stack([core_origin[i] + grids[i] + u[i] for i in range(3)])
        weight = weight * taper(pos, g_shape, margin)
    fc = core.astype(np.float64) - center
    W = shape_table(ell).reshape(-1, 8)
    S = np.zeros(tuple(e + 1 for e in elems) + (27, 3, 3))
    for ez, ey, ex in np.ndindex(*elems):
        sl = tuple(slice(e * ell, (e + 1) * ell) for e in (ez, ey, ex))
        G = grad[(slice(None),) + sl].reshape(3, -1)  # (3, ell^3)
        w = weight[sl].reshape(-1)
        # Ke[a, i, b, j] = sum_v w N_a N_b d_i f d_j f   (paper section 3, M_ij)
        Ke = np.einsum("v,va,vb,iv,jv->aibj", w, W, W, G, G, optimize=True)
        if condensed and w.any():
            fv = fc[sl].reshape(-1)
            # columns of the brightness unknowns: (f - c, 1) on the used voxels; per element,
            # eliminated exactly
            Q = np.stack([fv, np.ones_like(fv)], axis=1) if condensed == 2 else np.ones((fv.size, 1))
            C = np.einsum("v,va,iv,vq->aiq", w, W, G, Q)  # (8, 3, q)
            K = Q.T @ (w[:, None] * Q)
            if condensed == 2 and np.linalg.det(K) <= 1e-12 * K[0, 0] * K[1, 1]:
                C, K = C[..., 1:], K[1:, 1:]  # a flat element: offset only
            Ke = Ke - np.einsum("aip,pq,bjq->aibj", C, np.linalg.inv(K), C)
        for a, da in enumerate(LOCAL_NODES):
            for b, db in enumerate(LOCAL_NODES):
                S[ez + da[0], ey + da[1], ex + da[2], _stencil_index(db - da)] += Ke[a, :, b, :]
    out = (S, float(core.min()), float(core.max()))
    if with_lags:
        wg = (weight * grad).reshape(3, -1, grad.shape[-1])  # (3, rows, nx)
        pairs = [_lag_pairs(wg.shape[-1], k) for k in range(LAGS + 1)]
        lags = np.array([[np.sum(wg[i, :, a] * wg[i, :, b]) for a, b in pairs] for i in range(3)])
        out += (lags,)
    return out


def taper(pos: np.ndarray, g_shape, margin: int) -> np.ndarray:
    """Voxel weights: distance (at most 1) inside ``[margin, g_shape - 1 - margin]`` on every axis, else 0."""
    d = np.min(np.stack([np.minimum(pos[i] - margin, g_shape[i] - 1 - margin - pos[i]) for i in range(3)]), axis=0)
    return np.clip(np.nan_to_num(d, nan=-1.0), 0.0, 1.0)


def nodal_field(u_nodes: np.ndarray, ell: int) -> np.ndarray:
    """Trilinear interpolation of the nodal field at every core voxel, shape (3, *core).

    Separable 1-D lerps ``u[k] + xi (u[k+1] - u[k])`` along z, then y, then x: the same
    function as ``sum_a N_a u_a`` (mesh.shape_table) and exact for a uniform field.
    """
    xi = voxel_xi(ell)
    v = u_nodes
    for axis in (1, 2, 3):
        n_el = v.shape[axis] - 1
        k = np.repeat(np.arange(n_el), ell)  # element of each voxel
        t = np.tile(xi, n_el)
        a = np.take(v, k, axis=axis)
        b = np.take(v, k + 1, axis=axis)
        shp = [1, 1, 1, 1]
        shp[axis] = -1
        v = a + t.reshape(shp) * (b - a)
    return v


def warp_numpy(ell, u_nodes, core_origin, core_shape, gw, g_origin, g_shape, interpolation, margin: int = 0):
    """float64 ``g(X+u)``, validity mask and voxel weights (:func:`taper`) with ``map_coordinates``."""
    u = nodal_field(u_nodes, ell)
    grids = np.meshgrid(*[np.arange(n) for n in core_shape], indexing="ij")
    pos = np.stack([core_origin[i] + grids[i] + u[i] for i in range(3)])
    weight = taper(pos, g_shape, margin)
    mask = weight > 0
    out = np.full(core_shape, np.nan)
    if mask.any():
        local = np.stack([pos[i][mask] - g_origin[i] for i in range(3)])
        if interpolation == "cubic":
            # mirror at the window edges = mirror at the volume edges where they coincide;
            # elsewhere the taps stay inside the window (g_window)
            out[mask] = ndi.map_coordinates(gw, local, order=3, mode="mirror", prefilter=False, output=np.float64)
        else:
            out[mask] = ndi.map_coordinates(gw, local, order=1, mode="nearest", output=np.float64)
    return out, mask, weight


def b_sums_numpy(f32, lo, hi, ell, u_nodes, core_origin, gw, g_origin, g_shape, interpolation,
                 center: float, margin: int = 0, active=None) -> ElementSums:
    """Per-element sums of one pass: warp, then each element with the shape table."""
    core = tuple(n - a - b for n, a, b in zip(f32.shape, lo, hi))
    elems = tuple(n // ell for n in core)
    warped, mask, weight = warp_numpy(ell, u_nodes, core_origin, core, gw, g_origin, g_shape, interpolation, margin)
    on = _element_weights(active, elems, ell) > 0
    n_off = int((~on).sum())
    mask, weight = mask & on, weight * on
    fc = f32[lo[0]:lo[0] + core[0], lo[1]:lo[1] + core[1], lo[2]:lo[2] + core[2]].astype(np.float64)
    d = np.where(mask, fc - warped, 0.0)
    gp = np.where(mask, warped - center, 0.0)
    grad = gradient_block(f32, lo, hi).astype(np.float64)
    W = shape_table(ell).reshape(-1, 8)
    q = voxel_xi(ell) - 0.5  # element-centred coordinate of each voxel, element sizes
    qz, qy, qx = np.meshgrid(q, q, q, indexing="ij")
    B = np.zeros(elems + (6, 8, 3))
    gram = np.zeros(elems + (6, 6))
    for e in np.ndindex(*elems):
        sl = tuple(slice(k * ell, (k + 1) * ell) for k in e)
        G = grad[(slice(None),) + sl].reshape(3, -1)
        w = weight[sl].reshape(-1)
        v = np.stack([d[sl].reshape(-1), gp[sl].reshape(-1), np.ones(w.size), qz.reshape(-1), qy.reshape(-1),
                      qx.reshape(-1)])
        B[e] = np.einsum("va,iv,qv->qai", W, G * w, v)
        gram[e] = (v * w) @ v.T
    return ElementSums(B, gram, int(mask.size - mask.sum()) - n_off, residual_lags(d, gp, weight))


def residual_lags(d: np.ndarray, gp: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """The lag sums (6, LAGS + 1) of :class:`~chunkdic.kernels.blocks.ElementSums` on every
    row: pairs of voxels ``k`` apart along x (:func:`_lag_pairs`), weighted ``w w'``."""
    n = d.shape[-1]
    d, gp, w = d.reshape(-1, n), gp.reshape(-1, n), weight.reshape(-1, n)
    lags = np.zeros((6, LAGS + 1))
    for k in range(LAGS + 1):
        a, b = _lag_pairs(n, k)
        ww = w[:, a] * w[:, b]
        dd = d[:, a] - d[:, b] if k else d[:, a]
        dg = gp[:, a] - gp[:, b] if k else gp[:, a]
        lags[:4, k] = [np.sum(ww * dd * dd), np.sum(ww), np.sum(ww * 2.0 * dd * dg), np.sum(ww * dg * dg)]
    lags[4, 0], lags[5, 0] = np.sum(w * d), np.sum(w * gp)
    return lags
