"""The ``b`` pass: per-element sums of one modified Gauss–Newton iteration over a block.

One idea: one fused sweep computing ``g(X + u)``, the residual ``d = f - g(X + u)``,
``g' = g(X + u) - c`` and the per-element sums from which ``b`` and ``Σ r²`` follow for any
brightness correction (:func:`b_sums`, :class:`chunkdic.kernels.blocks.ElementSums`; the algebra is in
:mod:`chunkdic.kernels.jit`), and the paper's plain ``b`` (:func:`b_block`).
"""

from __future__ import annotations

import numpy as np

from . import twins as kernels_numpy
from .blocks import LAGS, ElementSums, core_shape, grad_index, voxel_xi
from .interp import fast_bounds, jit, jit_inline, jit_sums
from .rows import segment_samples, valid_bounds
from .window import element_activity, kernel_setup

__all__ = ["b_block", "b_sums", "element_to_nodes"]


@jit_inline
def _spread(Be, q, a, w, s0z, s0y, s0x, s1z, s1y, s1x):
    """Add ``w`` × the two x-face sums of quantity ``q`` to local nodes ``a`` and ``a + 1``."""
    Be[q, a, 0] += w * s0z
    Be[q, a, 1] += w * s0y
    Be[q, a, 2] += w * s0x
    Be[q, a + 1, 0] += w * s1z
    Be[q, a + 1, 1] += w * s1y
    Be[q, a + 1, 2] += w * s1x


@jit_inline
def _gram_row(Ge, n, sd, sg, sq, sdd, sdg, sgg, sdq, sgq, sqq, zt, yt):
    """Add a row segment to the upper triangle of the element Gram of
    ``v = (d, g', 1, z~, y~, x~)`` (weights ``w``; :func:`_symmetrize` completes it).

    ``sq, sdq, sgq, sqq``: the segment's sums with ``x~``; ``z~ = zt``, ``y~ = yt`` on the row.
    """
    Ge[0, 0] += sdd
    Ge[0, 1] += sdg
    Ge[0, 2] += sd
    Ge[0, 3] += zt * sd
    Ge[0, 4] += yt * sd
    Ge[0, 5] += sdq
    Ge[1, 1] += sgg
    Ge[1, 2] += sg
    Ge[1, 3] += zt * sg
    Ge[1, 4] += yt * sg
    Ge[1, 5] += sgq
    Ge[2, 2] += n
    Ge[2, 3] += zt * n
    Ge[2, 4] += yt * n
    Ge[2, 5] += sq
    Ge[3, 3] += zt * zt * n
    Ge[3, 4] += zt * yt * n
    Ge[3, 5] += zt * sq
    Ge[4, 4] += yt * yt * n
    Ge[4, 5] += yt * sq
    Ge[5, 5] += sqq


@jit
def _symmetrize(G):
    """Copy the upper triangle of every element's Gram onto its lower triangle."""
    for ez in range(G.shape[0]):
        for ey in range(G.shape[1]):
            for ex in range(G.shape[2]):
                for j in range(6):
                    for k in range(j + 1, 6):
                        G[ez, ey, ex, k, j] = G[ez, ey, ex, j, k]


@jit_sums
def b_kernel(fp, lo0, lo1, lo2, ell, nez, ney, nex, imz, ipz, scz, imy, ipy, scy, imx, ipx,
              scx, xi, u, c0, c1, c2, g, o0, o1, o2, n0, n1, n2, vm_lo, cubic, center, active):
    """One fused sweep: ``g(X + u)``, ``d``, ``g'`` and the per-element sums (ElementSums).

    Elements whose ``active`` is 0 are skipped (their voxels have weight 0 and are not
    counted as excluded)."""
    B = np.zeros((nez, ney, nex, 6, 8, 3))
    G = np.zeros((nez, ney, nex, 6, 6))
    lags = np.zeros((6, LAGS + 1))
    nbad = 0
    gf = g.ravel()
    gs0 = g.shape[1] * g.shape[2]
    gs1 = g.shape[2]
    bounds = valid_bounds(fast_bounds(g.shape, o0, o1, o2, n0, n1, n2, cubic), n0, n1, n2, vm_lo)
    ff = fp.ravel()
    fs0 = fp.shape[1] * fp.shape[2]
    fs1 = fp.shape[2]
    nx = nex * ell
    gbuf = np.empty(ell)
    wt = np.empty(ell)
    # one x-row of f and of its gradient (float32 differences, as gradient_block)
    frow = np.empty((4, nx), dtype=np.float32)
    drow = np.zeros(nx)  # the row's d, g' and weights, for the residual's autocorrelation
    grow = np.zeros(nx)
    wrow = np.zeros(nx)
    for z in range(nez * ell):
        ez = z // ell
        zz = z + lo0
        tz = xi[z - ez * ell]
        X0 = c0 + z
        for y in range(ney * ell):
            ey = y // ell
            yy = y + lo1
            ty = xi[y - ey * ell]
            X1 = c1 + y
            # a row whose elements are all inactive (a mask, the sampled gap) costs nothing
            row_active = False
            for ex in range(nex):
                if active[ez, ey, ex] != 0:
                    row_active = True
                    break
            if not row_active:
                continue
            # flat offsets (unsigned: no wrap-around code) of the rows of f used by d and
            # the centred differences; contiguous loops that LLVM vectorises
            rc = np.uint64(zz * fs0 + yy * fs1 + lo2)
            rzp = np.uint64(ipz[z] * fs0 + yy * fs1 + lo2)
            rzm = np.uint64(imz[z] * fs0 + yy * fs1 + lo2)
            ryp = np.uint64(zz * fs0 + ipy[y] * fs1 + lo2)
            rym = np.uint64(zz * fs0 + imy[y] * fs1 + lo2)
            rx = np.uint64(zz * fs0 + yy * fs1)
            sz = scz[z]
            sy = scy[y]
            for x in range(nx):
                xu = np.uint64(x)
                frow[0, x] = ff[rc + xu]
                frow[1, x] = (ff[rzp + xu] - ff[rzm + xu]) * sz
                frow[2, x] = (ff[ryp + xu] - ff[rym + xu]) * sy
            for x in range(nx):
                frow[3, x] = (ff[rx + np.uint64(ipx[x])] - ff[rx + np.uint64(imx[x])]) * scx[x]
            for ex in range(nex):
                xa = c2 + ex * ell
                if active[ez, ey, ex] == 0:
                    for lx in range(ell):
                        wt[lx] = 0.0
                        wrow[ex * ell + lx] = 0.0
                    continue
                nbad += segment_samples(u, ez, ey, ex, tz, ty, X0, X1, xa, ell, xi, g, gf, gs0, gs1,
                                         o0, o1, o2, n0, n1, n2, vm_lo, bounds, cubic, gbuf, wt)
                # x-face sums (w0 = 1 - xi, w1 = xi) of grad f times d, g', 1 and x~ = xi - 1/2
                d0z = d0y = d0x = d1z = d1y = d1x = 0.0
                g0z = g0y = g0x = g1z = g1y = g1x = 0.0
                e0z = e0y = e0x = e1z = e1y = e1x = 0.0
                q0z = q0y = q0x = q1z = q1y = q1x = 0.0
                n = sd = sg = sq = sdd = sdg = sgg = sdq = sgq = sqq = 0.0
                for lx in range(ell):
                    w = wt[lx]
                    x = ex * ell + lx
                    wrow[x] = w
                    if w == 0.0:
                        continue
                    gv = gbuf[lx]
                    d = np.float64(frow[0, x]) - gv
                    gp = gv - center
                    drow[x] = d
                    grow[x] = gp
                    gz = np.float64(frow[1, x]) * w
                    gy = np.float64(frow[2, x]) * w
                    gx = np.float64(frow[3, x]) * w
                    w1 = xi[lx]
                    w0 = 1.0 - w1
                    q = w1 - 0.5
                    n += w
                    sd += w * d
                    sg += w * gp
                    sq += w * q
                    sdd += w * d * d
                    sdg += w * d * gp
                    sgg += w * gp * gp
                    sdq += w * d * q
                    sgq += w * gp * q
                    sqq += w * q * q
                    e0z += w0 * gz
                    e0y += w0 * gy
                    e0x += w0 * gx
                    e1z += w1 * gz
                    e1y += w1 * gy
                    e1x += w1 * gx
                    d0z += w0 * gz * d
                    d0y += w0 * gy * d
                    d0x += w0 * gx * d
                    d1z += w1 * gz * d
                    d1y += w1 * gy * d
                    d1x += w1 * gx * d
                    g0z += w0 * gz * gp
                    g0y += w0 * gy * gp
                    g0x += w0 * gx * gp
                    g1z += w1 * gz * gp
                    g1y += w1 * gy * gp
                    g1x += w1 * gx * gp
                    q0z += w0 * gz * q
                    q0y += w0 * gy * q
                    q0x += w0 * gx * q
                    q1z += w1 * gz * q
                    q1y += w1 * gy * q
                    q1x += w1 * gx * q
                if n == 0.0:
                    continue
                # the element's Gram of (d, g', 1, z~, y~, x~); z~, y~ are constant on the row
                zt = tz - 0.5
                yt = ty - 0.5
                _gram_row(G[ez, ey, ex], n, sd, sg, sq, sdd, sdg, sgg, sdq, sgq, sqq, zt, yt)
                # spread the row sums over the 4 (dz, dy) node pairs of each x-face
                Be = B[ez, ey, ex]
                for dz in range(2):
                    wz = tz if dz else 1.0 - tz
                    for dy in range(2):
                        w = wz * (ty if dy else 1.0 - ty)
                        a = 4 * dz + 2 * dy
                        _spread(Be, 0, a, w, d0z, d0y, d0x, d1z, d1y, d1x)
                        _spread(Be, 1, a, w, g0z, g0y, g0x, g1z, g1y, g1x)
                        _spread(Be, 2, a, w, e0z, e0y, e0x, e1z, e1y, e1x)
                        _spread(Be, 3, a, w * zt, e0z, e0y, e0x, e1z, e1y, e1x)
                        _spread(Be, 4, a, w * yt, e0z, e0y, e0x, e1z, e1y, e1x)
                        _spread(Be, 5, a, w, q0z, q0y, q0x, q1z, q1y, q1x)
            # variogram of the residual along x (noise correlation estimate, blocks.LAGS), every
            # lag on the same voxels: the client forms that of r = d - α g' from these
            # (blocks.ElementSums.lags). Lag 0 holds the second moments; lags k >= 1 the squared
            # differences of voxels k apart, so that whatever is constant along the row (an
            # offset, a drift along z or y) cancels exactly
            for k in range(LAGS + 1):
                sdd_k = 0.0
                cnt = 0.0
                sdg_k = 0.0
                sgg_k = 0.0
                for x in range(nx - LAGS):
                    ww = wrow[x] * wrow[x + k]
                    if k == 0:
                        dd = drow[x]
                        dg = grow[x]
                    else:
                        dd = drow[x] - drow[x + k]
                        dg = grow[x] - grow[x + k]
                    sdd_k += ww * dd * dd
                    sdg_k += ww * 2.0 * dd * dg
                    sgg_k += ww * dg * dg
                    cnt += ww
                lags[0, k] += sdd_k
                lags[1, k] += cnt
                lags[2, k] += sdg_k
                lags[3, k] += sgg_k
            for x in range(nx):
                lags[4, 0] += wrow[x] * drow[x]
                lags[5, 0] += wrow[x] * grow[x]
    _symmetrize(G)
    return B, G, lags, nbad


def b_sums(f: np.ndarray, lo, hi, ell: int, u_nodes: np.ndarray, core_origin, g: np.ndarray,
           g_origin, g_shape, *, interpolation: str = "cubic", impl: str = "numba",
           prefiltered: bool = False, center: float = 0.0, margin: int = 0,
           active: np.ndarray | None = None) -> ElementSums:
    """Per-element sums of one modified Gauss–Newton pass over a block (module docstring).

    Parameters
    ----------
    f : ndarray, shape (core + lo + hi), any real dtype, grey levels
        Block region of the (prepared) reference with its one-voxel halo.
    lo, hi : tuple of 3 int in {0, 1}
    ell : int
        Element edge, voxels; the core shape must be a multiple of it.
    u_nodes : ndarray, shape (3, ez+1, ey+1, ex+1), float64, voxels
        Current nodal displacement over the block's nodes, components (z, y, x).
    core_origin : tuple of 3 int
        Absolute level index of the first core voxel.
    g : ndarray, 3-D, grey levels
        Window of the deformed level starting at ``g_origin`` covering :func:`g_window`:
        raw samples, or (``prefiltered``) the prepared float32 samples / B-spline
        coefficients of :mod:`chunkdic.passes.prefilter`.
    g_origin, g_shape : tuple of 3 int
        Window origin; shape of the whole deformed level.
    interpolation : {"linear", "cubic"}, keyword-only
    impl : {"numba", "numpy"}, keyword-only
    prefiltered : bool, keyword-only
        ``g`` is already what the interpolation reads (no per-window cubic prefilter here).
    center : float, keyword-only
        Centring constant ``c`` of ``g' = g(X+u) - c`` (grey levels; the level's mid-range).
    margin : int, keyword-only
        A voxel is valid when ``margin <= X_i + u_i <= g_shape_i - 1 - margin`` on every axis;
        the data beyond still serve the interpolation and its prefilter (the engine
        excludes where the low-pass of ``g`` is not exact, :func:`chunkdic.passes.prefilter.face_margin`).
    active : ndarray, shape (ez, ey, ex), uint8, keyword-only, optional
        0 for the elements left out (:mod:`chunkdic.passes.masks`): no sums, not counted as
        excluded. Default all 1.

    Returns
    -------
    ElementSums

    References
    ----------
    Paper section 3 (``b_i``) and 3.1 (modified Gauss-Newton, trilinear interpolation).
    """
    core = core_shape(f, lo, hi)
    st = kernel_setup(ell, u_nodes, core_origin, core, g, g_origin, g_shape, interpolation, impl, prefiltered, margin)
    ell = int(ell)
    lo = tuple(int(v) for v in lo)
    hi = tuple(int(v) for v in hi)
    active = element_activity(active, st.elems)
    if st.gw is None:
        n_off = int(np.sum(active == 0)) * ell**3
        return ElementSums(np.zeros(st.elems + (6, 8, 3)), np.zeros(st.elems + (6, 6)), int(np.prod(core)) - n_off,
                           np.zeros((6, LAGS + 1)))
    f32 = np.ascontiguousarray(f, dtype=np.float32)
    if impl == "numpy":
        return kernels_numpy.b_sums_numpy(f32, lo, hi, ell, st.u_nodes, st.core_origin, st.gw, st.g_origin,
                                          st.g_shape, interpolation, float(center), int(margin), active)
    idx = [grad_index(core[a], lo[a], hi[a]) for a in range(3)]
    B, gram, lags, nbad = b_kernel(f32, lo[0], lo[1], lo[2], ell, *st.elems, *idx[0], *idx[1], *idx[2],
                             voxel_xi(ell), st.u_nodes, *st.core_origin, st.gw, *st.g_origin, *st.g_shape,
                             float(margin), interpolation == "cubic", float(center), active)
    return ElementSums(B, gram, int(nbad), lags)


def b_block(f: np.ndarray, lo, hi, ell: int, u_nodes: np.ndarray, core_origin, g: np.ndarray,
            g_origin, g_shape, *, interpolation: str = "cubic", impl: str = "numba",
            prefiltered: bool = False):
    """The paper's ``b`` over a block: no brightness correction (``r = f - g(X + u)``).

    Same parameters as :func:`b_sums`. Returns ``(b, ssr, n_valid, n_excluded)``: ``b``
    of shape (ez+1, ey+1, ex+1, 3), float64, grey levels² / voxel; ``ssr = Σ w r²`` over the
    valid voxels (weights ``w``, see :class:`ElementSums`); valid and excluded voxel counts
    (they add up to the core size).

    Examples
    --------
    Identical images and a zero field give a zero right-hand side; the voxels of the
    volume's outer layer sit where the weight tapers to zero (:func:`chunkdic.kernels.rows.taper`), so they are
    counted as excluded (216 valid of 512):

    >>> from chunkdic.kernels.window import g_window
    >>> vol = np.random.default_rng(0).random((8, 8, 8)).astype(np.float32)
    >>> u = np.zeros((3, 3, 3, 3))
    >>> win = g_window((0, 0, 0), (8, 8, 8), u, vol.shape, interpolation="linear")
    >>> b, ssr, n_valid, n_excluded = b_block(
    ...     vol, (0, 0, 0), (0, 0, 0), 4, u, (0, 0, 0), vol[win],
    ...     tuple(s.start for s in win), vol.shape, interpolation="linear")
    >>> bool(np.all(b == 0)), float(ssr), int(n_valid), int(n_excluded)
    (True, 0.0, 216, 296)
    """
    sums = b_sums(f, lo, hi, ell, u_nodes, core_origin, g, g_origin, g_shape, interpolation=interpolation,
                  impl=impl, prefiltered=prefiltered)
    b = element_to_nodes(sums.B[..., 0, :, :])
    n_core = int(np.prod(core_shape(f, lo, hi)))
    return b, float(sums.gram[..., 0, 0].sum()), n_core - sums.n_excluded, sums.n_excluded


@jit
def _element_to_nodes(E):
    nez, ney, nex = E.shape[0], E.shape[1], E.shape[2]
    out = np.zeros((nez + 1, ney + 1, nex + 1, 3))
    for ez in range(nez):
        for ey in range(ney):
            for ex in range(nex):
                for a in range(8):
                    for i in range(3):
                        out[ez + (a >> 2), ey + ((a >> 1) & 1), ex + (a & 1), i] += E[ez, ey, ex, a, i]
    return out


def element_to_nodes(E: np.ndarray) -> np.ndarray:
    """Add per-element local-node values ``E (ez, ey, ex, 8, 3)`` into nodal ``(ez+1, ey+1, ex+1, 3)``."""
    return _element_to_nodes(np.ascontiguousarray(E, dtype=np.float64))
