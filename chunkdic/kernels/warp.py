"""The warp: the corrected deformed image ``g(X + u(X))`` over a block core.

One idea: the same segment loop as the ``b`` pass (:func:`chunkdic.kernels.rows.segment_samples`)
writing the interpolated values and the validity mask instead of sums (:func:`warp_block`).
"""

from __future__ import annotations

import numpy as np

from . import twins as kernels_numpy
from .blocks import voxel_xi
from .interp import fast_bounds, jit
from .rows import segment_samples, valid_bounds
from .window import kernel_setup

__all__ = ["warp_block"]


@jit
def _warp_kernel(ell, nez, ney, nex, xi, u, c0, c1, c2, g, o0, o1, o2, n0, n1, n2, vm_lo, cubic):
    """``g(X + u(X))`` over the core (float32, NaN where invalid) and the validity mask."""
    out = np.empty((nez * ell, ney * ell, nex * ell), dtype=np.float32)
    mask = np.zeros((nez * ell, ney * ell, nex * ell), dtype=np.bool_)
    gf = g.ravel()
    gs0 = g.shape[1] * g.shape[2]
    gs1 = g.shape[2]
    bounds = valid_bounds(fast_bounds(g.shape, o0, o1, o2, n0, n1, n2, cubic), n0, n1, n2, vm_lo)
    gbuf = np.empty(ell)
    wt = np.empty(ell)
    for z in range(nez * ell):
        ez = z // ell
        tz = xi[z - ez * ell]
        for y in range(ney * ell):
            ey = y // ell
            ty = xi[y - ey * ell]
            for ex in range(nex):
                segment_samples(u, ez, ey, ex, tz, ty, c0 + z, c1 + y, c2 + ex * ell, ell, xi, g, gf,
                                 gs0, gs1, o0, o1, o2, n0, n1, n2, vm_lo, bounds, cubic, gbuf, wt)
                for lx in range(ell):
                    x = ex * ell + lx
                    mask[z, y, x] = wt[lx] > 0.0
                    out[z, y, x] = gbuf[lx] if wt[lx] > 0.0 else np.nan
    return out, mask


def warp_block(ell: int, u_nodes: np.ndarray, core_origin, core_shape, g: np.ndarray,
               g_origin, g_shape, *, interpolation: str = "cubic", impl: str = "numba",
               prefiltered: bool = False, margin: int = 0):
    """The corrected deformed image ``g(X + u(X))`` over a block core.

    Parameters
    ----------
    ell : int
        Element edge, voxels.
    u_nodes : ndarray, shape (3, ez+1, ey+1, ex+1), float64, voxels
    core_origin, core_shape : tuple of 3 int
        Absolute level index of the first core voxel; ``(ez*ell, ey*ell, ex*ell)``.
    g : ndarray, 3-D, grey levels
        Window of the deformed level (see :func:`b_sums`).
    g_origin, g_shape : tuple of 3 int
    interpolation : {"linear", "cubic"}, keyword-only
    impl : {"numba", "numpy"}, keyword-only
    prefiltered : bool, keyword-only
    margin : int, keyword-only
        See :func:`b_sums`.

    Returns
    -------
    warped : ndarray, shape core_shape, float32, grey levels
        ``g(X + u(X))``; NaN where invalid.
    valid : ndarray, shape core_shape, bool
        ``0 <= X_i + u_i <= g_shape_i - 1`` on every axis.

    References
    ----------
    Paper section 3 ("the deformed image is corrected") and 3.1 (trilinear interpolation).
    """
    core = tuple(int(v) for v in core_shape)
    st = kernel_setup(ell, u_nodes, core_origin, core, g, g_origin, g_shape, interpolation, impl, prefiltered, margin)
    if st.gw is None:
        return np.full(core, np.nan, dtype=np.float32), np.zeros(core, bool)
    if impl == "numpy":
        out, mask, _ = kernels_numpy.warp_numpy(int(ell), st.u_nodes, st.core_origin, core, st.gw, st.g_origin,
                                                st.g_shape, interpolation, int(margin))
        return out.astype(np.float32), mask
    return _warp_kernel(int(ell), *st.elems, voxel_xi(int(ell)), st.u_nodes, *st.core_origin, st.gw,
                        *st.g_origin, *st.g_shape, float(margin), interpolation == "cubic")
