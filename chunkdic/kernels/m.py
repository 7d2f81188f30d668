"""The ``M`` pass: a block's contribution to the C8 matrix as a nodal 27-point stencil.

One idea: the element tensor moments of ``grad f`` (and, for the brightness models, the
couplings that condense ``M``), swept once over the block in raster order, and their
scatter into the stencil (:func:`m_block`). The factorisation that makes it fast is
described in :mod:`chunkdic.kernels.jit` ("Why the numba kernels are fast").
"""

from __future__ import annotations

import numpy as np

from . import twins as kernels_numpy
from .blocks import (
    LAGS,
    check_nodes,
    core_shape,
    elements_of,
    grad_index,
    voxel_xi,
)
from .interp import jit, jit_sums, lerp, segment_inside
from .rows import row_field, taper
from .window import IMPLEMENTATIONS, check_choice, element_activity

__all__ = ["CONDENSED", "cell_couplings", "m_block"]

#: brightness models whose element moments condense ``M`` (see :func:`m_block`)
CONDENSED = {"none": 0, "global": 0, "drift": 1, "element": 2}

# Index of the symmetric gradient product d_i f d_j f in the 6-vector G_c.
_SYM = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]], dtype=np.int64)


@jit_sums
def m_kernel(fp, lo0, lo1, lo2, ell, nez, ney, nex, imz, ipz, scz, imy, ipy, scy, imx, ipx,
              scx, psi, xi, center, u, c0, c1, c2, n0, n1, n2, vm_lo, masked, active):
    """Element tensor moments T, element brightness couplings C and moments K; min / max.

    ``C[e, q, a, i] = Σ N_a d_i f q`` for ``q = (f - center, 1, z~, y~, x~)`` and
    ``K[e] = (n, Σ(f - c), Σ(f - c)², Σ z~, Σ y~, Σ x~, Σ z~z~, z~y~, z~x~, y~y~, y~x~, x~x~)``
    (``z~ = ξ - 1/2``: the voxel's coordinate from its element's centre, elements): what the
    Schur complement of a brightness model needs (:func:`_assemble_stencil` for per-element
    unknowns, :func:`cell_couplings` for affine offsets per cell of elements). With
    ``masked``, voxels whose ``X + u(X)`` leaves ``[vm_lo, n - 1 - vm_lo]`` are left out of
    T, C and K, and so are the elements whose ``active`` is 0 (min / max keep every core voxel).
    """
    nx = nex * ell
    T = np.zeros((nez, ney, nex, 3, 3, 3, 6))
    C = np.zeros((nez, ney, nex, 5, 8, 3))
    K = np.zeros((nez, ney, nex, 12))
    lags = np.zeros((3, LAGS + 1))
    prod = np.empty((9, nx))
    vm = np.ones(nx)
    fmin = np.inf
    fmax = -np.inf
    for z in range(nez * ell):
        ez = z // ell
        lz = z - ez * ell
        zz = z + lo0
        tz = xi[lz]
        for y in range(ney * ell):
            ey = y // ell
            ly = y - ey * ell
            yy = y + lo1
            ty = xi[ly]
            zp, zm, sz = ipz[z], imz[z], scz[z]
            yp, ym, sy = ipy[y], imy[y], scy[y]
            for ex in range(nex):
                if active[ez, ey, ex] == 0:
                    for lx in range(ell):
                        vm[ex * ell + lx] = 0.0
                    continue
                if not masked:
                    for lx in range(ell):
                        vm[ex * ell + lx] = 1.0
                    continue
                if masked:
                    uz0, uz1 = row_field(u, 0, ez, ey, ex, tz, ty)
                    uy0, uy1 = row_field(u, 1, ez, ey, ex, tz, ty)
                    ux0, ux1 = row_field(u, 2, ez, ey, ex, tz, ty)
                    xa = c2 + ex * ell
                    lo_in = vm_lo + 1.0  # weight 1 at least one voxel inside the usable part
                    if (segment_inside(c0 + z, c0 + z, uz0, uz1, xi[0], xi[ell - 1], lo_in, n0 - 1.0 - lo_in)
                            and segment_inside(c1 + y, c1 + y, uy0, uy1, xi[0], xi[ell - 1], lo_in, n1 - 1.0 - lo_in)
                            and segment_inside(xa, xa + ell - 1, ux0, ux1, xi[0], xi[ell - 1], lo_in,
                                               n2 - 1.0 - lo_in)):
                        for lx in range(ell):
                            vm[ex * ell + lx] = 1.0
                        continue
                    for lx in range(ell):
                        tx = xi[lx]
                        p0 = c0 + z + lerp(uz0, uz1, tx)
                        p1 = c1 + y + lerp(uy0, uy1, tx)
                        p2 = c2 + ex * ell + lx + lerp(ux0, ux1, tx)
                        vm[ex * ell + lx] = taper(p0, p1, p2, n0, n1, n2, vm_lo)
            # pass 1 over the row: gradient (float32, as gradient_block) and its products
            for x in range(nx):
                xx = x + lo2
                v = fp[zz, yy, xx]
                if v < fmin:
                    fmin = v
                if v > fmax:
                    fmax = v
                # a weight w on every voxel's squared residual (the b passes' taper)
                w = vm[x]
                gz = np.float64((fp[zp, yy, xx] - fp[zm, yy, xx]) * sz)
                gy = np.float64((fp[zz, yp, xx] - fp[zz, ym, xx]) * sy)
                gx = np.float64((fp[zz, yy, ipx[x]] - fp[zz, yy, imx[x]]) * scx[x])
                prod[0, x] = w * gz * gz
                prod[1, x] = w * gz * gy
                prod[2, x] = w * gz * gx
                prod[3, x] = w * gy * gy
                prod[4, x] = w * gy * gx
                prod[5, x] = w * gx * gx
                prod[6, x] = w * gz
                prod[7, x] = w * gy
                prod[8, x] = w * gx
            # autocorrelation of the gradient along x (noise correlation estimate, LAGS), every
            # lag on the same voxels
            for i in range(3):
                for k in range(LAGS + 1):
                    acc = 0.0
                    for x in range(nx - LAGS):
                        acc += prod[6 + i, x] * prod[6 + i, x + k]
                    lags[i, k] += acc
            # pass 2: per element, reduce the row against psi_px, then spread over pz, py
            for ex in range(nex):
                x0 = ex * ell
                for c in range(6):
                    s0 = 0.0
                    s1 = 0.0
                    s2 = 0.0
                    for lx in range(ell):
                        p = prod[c, x0 + lx]
                        s0 += psi[0, lx] * p
                        s1 += psi[1, lx] * p
                        s2 += psi[2, lx] * p
                    for pz in range(3):
                        for py in range(3):
                            w = psi[pz, lz] * psi[py, ly]
                            T[ez, ey, ex, pz, py, 0, c] += w * s0
                            T[ez, ey, ex, pz, py, 1, c] += w * s1
                            T[ez, ey, ex, pz, py, 2, c] += w * s2
                # brightness couplings: x-face sums of grad f, grad f (f - c) and grad f x~
                # (the row's z~, y~ are constants: they multiply its sums when spread)
                cz = tz - 0.5
                cy = ty - 0.5
                k0 = 0.0
                k1 = 0.0
                k2 = 0.0
                kx1 = 0.0
                kx2 = 0.0
                for i in range(3):
                    a0 = 0.0
                    a1 = 0.0
                    b0 = 0.0
                    b1 = 0.0
                    m0 = 0.0
                    m1 = 0.0
                    for lx in range(ell):
                        gi = prod[6 + i, x0 + lx]
                        fv = np.float64(fp[zz, yy, x0 + lx + lo2]) - center
                        w1 = xi[lx]
                        w0 = 1.0 - w1
                        cx = w1 - 0.5
                        a0 += w0 * gi * fv
                        a1 += w1 * gi * fv
                        b0 += w0 * gi
                        b1 += w1 * gi
                        m0 += w0 * gi * cx
                        m1 += w1 * gi * cx
                        if i == 0:
                            w = vm[x0 + lx]
                            k0 += w
                            k1 += w * fv
                            k2 += w * fv * fv
                            kx1 += w * cx
                            kx2 += w * cx * cx
                    for dz in range(2):
                        wz = tz if dz else 1.0 - tz
                        for dy in range(2):
                            w = wz * (ty if dy else 1.0 - ty)
                            a = 4 * dz + 2 * dy
                            C[ez, ey, ex, 0, a, i] += w * a0
                            C[ez, ey, ex, 0, a + 1, i] += w * a1
                            C[ez, ey, ex, 1, a, i] += w * b0
                            C[ez, ey, ex, 1, a + 1, i] += w * b1
                            C[ez, ey, ex, 2, a, i] += w * cz * b0
                            C[ez, ey, ex, 2, a + 1, i] += w * cz * b1
                            C[ez, ey, ex, 3, a, i] += w * cy * b0
                            C[ez, ey, ex, 3, a + 1, i] += w * cy * b1
                            C[ez, ey, ex, 4, a, i] += w * m0
                            C[ez, ey, ex, 4, a + 1, i] += w * m1
                K[ez, ey, ex, 0] += k0
                K[ez, ey, ex, 1] += k1
                K[ez, ey, ex, 2] += k2
                K[ez, ey, ex, 3] += cz * k0
                K[ez, ey, ex, 4] += cy * k0
                K[ez, ey, ex, 5] += kx1
                K[ez, ey, ex, 6] += cz * cz * k0
                K[ez, ey, ex, 7] += cz * cy * k0
                K[ez, ey, ex, 8] += cz * kx1
                K[ez, ey, ex, 9] += cy * cy * k0
                K[ez, ey, ex, 10] += cy * kx1
                K[ez, ey, ex, 11] += kx2
    return T, C, K, lags, fmin, fmax


@jit
def _assemble_stencil(T, C, K, sym, condensed):
    """Scatter element moments into the block's nodal 27-point stencil.

    ``condensed`` 0: plain ``M``; 1: minus the Schur complement of a per-element offset
    (``C1 C1ᵀ / n``); 2: of a per-element gain and offset (``[Cf C1] K⁻¹ [Cf C1]ᵀ``).
    """
    nez, ney, nex = T.shape[0], T.shape[1], T.shape[2]
    S = np.zeros((nez + 1, ney + 1, nex + 1, 27, 3, 3))
    inv = np.zeros((2, 2))
    for ez in range(nez):
        for ey in range(ney):
            for ex in range(nex):
                n, s1, s2 = K[ez, ey, ex, 0], K[ez, ey, ex, 1], K[ez, ey, ex, 2]
                inv[:, :] = 0.0
                if condensed == 1 and n > 0:
                    inv[1, 1] = 1.0 / n
                elif condensed == 2 and n > 0:
                    det = s2 * n - s1 * s1
                    if det > 1e-12 * s2 * n:
                        inv[0, 0] = n / det
                        inv[0, 1] = -s1 / det
                        inv[1, 0] = -s1 / det
                        inv[1, 1] = s2 / det
                    else:  # a flat element: offset only
                        inv[1, 1] = 1.0 / n
                for a in range(8):
                    az = a >> 2
                    ay = (a >> 1) & 1
                    ax = a & 1
                    for b in range(8):
                        bz = b >> 2
                        by = (b >> 1) & 1
                        bx = b & 1
                        k = 9 * (bz - az + 1) + 3 * (by - ay + 1) + (bx - ax + 1)
                        for i in range(3):
                            for j in range(3):
                                v = T[ez, ey, ex, az + bz, ay + by, ax + bx, sym[i, j]]
                                if condensed:
                                    for p in range(2):
                                        for q in range(2):
                                            v -= C[ez, ey, ex, p, a, i] * inv[p, q] * C[ez, ey, ex, q, b, j]
                                S[ez + az, ey + ay, ex + ax, k, i, j] += v
    return S


#: eigenvalues of a cell's offset Gram matrix below this fraction of its largest are dropped
#: (a thin cell at a mask's edge does not fix its slopes; the ``b`` pass's pseudo-inverse,
#: :func:`chunkdic.method.brightness._reduce_cells`, uses the same cut)
CELL_RCOND = 1e-12


def _cell_gram(K: np.ndarray, o: tuple) -> np.ndarray:
    """``Σ w q qᵀ`` for ``q = (1, z, y, x)`` centred on the cell, per element: (ez, ey, ex, 4, 4).

    ``K``: the element moments of :func:`m_kernel` (centred on the element); ``o``: the
    element centres' offsets from their cell's centre per axis (elements), broadcastable."""
    n = K[..., 0]
    m1 = [K[..., 3] + o[0] * n, K[..., 4] + o[1] * n, K[..., 5] + o[2] * n]
    raw2 = {(0, 0): 6, (0, 1): 7, (0, 2): 8, (1, 1): 9, (1, 2): 10, (2, 2): 11}
    D = np.empty(K.shape[:3] + (4, 4))
    D[..., 0, 0] = n
    for a in range(3):
        D[..., 0, a + 1] = D[..., a + 1, 0] = m1[a]
    for (a, b), j in raw2.items():
        # Σ (q_a + o_a)(q_b + o_b) = Σ q_a q_b + o_b Σ q_a + o_a Σ q_b + o_a o_b n
        v = K[..., j] + o[b] * K[..., 3 + a] + o[a] * K[..., 3 + b] + o[a] * o[b] * n
        D[..., a + 1, b + 1] = D[..., b + 1, a + 1] = v
    return D


def cell_couplings(C: np.ndarray, K: np.ndarray, k: int) -> np.ndarray:
    """The Schur complement of affine brightness offsets per cell of ``k³`` elements, factored.

    The ``drift`` model with cells (:mod:`chunkdic.method.brightness`) eliminates, per cell,
    an offset ``a + b·(X - X_c)`` at every pass (variable projection). The Gauss–Newton
    matrix of the field is then ``M - Σ_c V_c D_c⁻¹ V_cᵀ``, ``V_c[(n, i), q] = Σ w N_n ∂_i f q``
    and ``D_c = Σ w q qᵀ`` over the cell's voxels, ``q = (1, z, y, x)``. That term couples every
    node of a cell with every other, beyond ``M``'s 27-node stencil, so it is kept as
    ``W_c = V_c D_c^{-1/2}`` (``Σ_c W_c W_cᵀ`` is the complement) and applied next to the
    stencil in the client's solve (:func:`chunkdic.solve.stencil.subtract_cells`). Left out,
    the steps fell short in the directions the offsets absorb: at 512³, ℓ = 16, cells of 2³
    elements, Gauss–Newton contracted by ×0.11-0.2 per pass instead of the ×0.04-0.07 of one
    offset per element (docs/engine.md, "Brightness").

    Parameters
    ----------
    C : ndarray, shape (ez, ey, ex, 5, 8, 3), float64
        :func:`m_kernel`'s element couplings (rows 1-4: ``q = 1, z~, y~, x~`` centred on the element).
    K : ndarray, shape (ez, ey, ex, 12), float64
        Its element moments.
    k : int
        Elements per side of a cell; the block's first element starts a cell (the last
        cells may be partial).

    Returns
    -------
    W : ndarray, shape (cz, cy, cx, k+1, k+1, k+1, 3, 4), float32, grey levels / voxel
        Per cell, over its nodes (zero beyond the block's), ``W_c`` with ``W_c W_cᵀ = V_c D_c⁺ V_cᵀ``.
    """
    k = int(k)
    elems = C.shape[:3]
    cells = tuple(-(-n // k) for n in elems)
    pad = [(0, c * k - n) for c, n in zip(cells, elems)]
    Cp = np.pad(C[..., 1:, :, :], pad + [(0, 0)] * 3)
    Kp = np.pad(K, pad + [(0, 0)])
    # the offsets of the elements from their (whole) cell's centre: any centre spans the same
    # affine functions, as the b pass's (which centres a partial cell on itself)
    o = tuple(np.tile(np.arange(k) - (k - 1) / 2.0, c).reshape([-1 if a == ax else 1 for a in range(3)])
              for ax, c in enumerate(cells))
    V = Cp.copy()
    for a in range(3):
        V[..., a + 1, :, :] += o[a][..., None, None] * Cp[..., 0, :, :]
    D = _cell_gram(Kp, o).reshape(cells[0], k, cells[1], k, cells[2], k, 4, 4).sum(axis=(1, 3, 5))
    Vc = np.zeros(cells + (k + 1, k + 1, k + 1, 3, 4))
    Vb = V.reshape(cells[0], k, cells[1], k, cells[2], k, 4, 8, 3)
    for node in range(8):
        dz, dy, dx = node >> 2, (node >> 1) & 1, node & 1
        # (cz, k, cy, k, cx, k, 4, 3) -> (cz, cy, cx, k, k, k, 3, 4)
        Vc[:, :, :, dz:dz + k, dy:dy + k, dx:dx + k] += Vb[..., node, :].transpose(0, 2, 4, 1, 3, 5, 7, 6)
    lam, U = np.linalg.eigh(D)
    keep = lam > CELL_RCOND * np.maximum(lam[..., -1:], 0.0)
    scale = np.where(keep, 1.0 / np.sqrt(np.where(keep, lam, 1.0)), 0.0)
    root = U * scale[..., None, :]  # D⁺ = root rootᵀ
    return np.einsum("zyxnmlip,zyxpq->zyxnmliq", Vc, root).astype(np.float32)


def m_block(f: np.ndarray, lo, hi, ell: int, *, impl: str = "numba", grey: str = "none",
            center: float = 0.0, u_nodes: np.ndarray | None = None, core_origin=None, g_shape=None,
            margin: int = 0, with_lags: bool = False, active: np.ndarray | None = None, cell: int = 1):
    """Block contribution to the C8 matrix ``M`` as a nodal 27-point stencil.

    Parameters
    ----------
    f : ndarray, shape (core_z + lo[0] + hi[0], ...), any real dtype, grey levels
        Block region of the (prepared) reference including its one-voxel halo (see
        :func:`gradient_block`). Converted to float32.
    lo, hi : tuple of 3 int in {0, 1}
        Halo voxels before / after the core per axis (0 at the volume boundary).
    ell : int
        Element edge, voxels. The core shape must be a multiple of ``ell``.
    impl : {"numba", "numpy"}, keyword-only
        Fused kernel or its NumPy twin (test oracle).
    grey : {"none", "global", "drift", "element"}, keyword-only
        Brightness model (:mod:`chunkdic.method.brightness`). ``drift`` and ``element`` have
        per-element brightness unknowns, eliminated exactly (variable projection), so the
        Gauss–Newton matrix is ``M`` minus their Schur complement per element, with ``f``
        standing for ``g(X + u)`` as in the rest of the modified Gauss–Newton.
    center : float, keyword-only
        Centring constant ``c`` of the brightness sums (grey levels).
    u_nodes, core_origin, g_shape : keyword-only, optional
        The level's starting field over the block's nodes (3, ez+1, ey+1, ex+1), the
        block's first core voxel and the shape of ``g``: voxels whose ``X + u(X)`` leaves
        ``g`` are left out of ``M``, as the ``b`` passes leave them out, so that ``M``
        matches ``b`` where the field maps part of the ROI outside ``g`` (without it,
        nodes of partly excluded elements converge very slowly).
    margin : int, keyword-only
        Positions within ``margin`` voxels of a face of ``g`` count as outside (see
        :func:`b_sums`).
    active : ndarray, shape (ez, ey, ex), uint8, keyword-only, optional
        0 for the elements left out (:mod:`chunkdic.passes.masks`); default all 1.
    with_lags : bool, keyword-only
        Also return ``lags`` (3, LAGS + 1): ``Σ w ∂_i f(x) w ∂_i f(x + k)`` along x, the
        autocorrelation of the sensitivities that estimates the noise correlation
        (:func:`chunkdic.method.noise.correlation_factor`).
    cell : int, keyword-only
        With ``grey="drift"``: elements per side of the cells sharing one affine offset
        (:func:`chunkdic.method.brightness.offset_cell`, the block's first element starting a
        cell). Above 1 the stencil is ``M`` itself and the offsets' Schur complement comes
        apart, as :func:`cell_couplings` (it reaches across the cell, beyond the stencil).
        numba only.

    Returns
    -------
    S : ndarray, shape (ez+1, ey+1, ex+1, 27, 3, 3), float64, grey levels^2
        ``S[n, k, i, j] = M[(n, i), (n + off_k, j)]`` with ``off_k`` from
        :data:`chunkdic.mesh.STENCIL_OFFSETS`, ``M_(a,i),(b,j) = sum_X N_a N_b d_i f d_j f``
        over the core voxels (minus the condensation); entries whose column node leaves the
        block are 0. Symmetric: ``S[n, k, i, j] == S[n + off_k, 26 - k, j, i]``.
    fmin, fmax : float
        Extreme grey levels of the core voxels (for the matching gap normalisation).
    lags : ndarray, shape (3, LAGS + 1), float64
        With ``with_lags``.
    cells : ndarray, shape (cz, cy, cx, cell+1, cell+1, cell+1, 3, 4), float32
        With ``cell`` > 1 and ``grey="drift"``: :func:`cell_couplings`.

    References
    ----------
    Paper section 3, linear system ``M_ij a_j = b_i``; section 3.1 (``M`` is built once
    from the reference).
    """
    check_choice(impl, IMPLEMENTATIONS, "impl")
    check_choice(grey, tuple(CONDENSED), "grey")
    core = core_shape(f, lo, hi)
    elems = elements_of(core, ell)
    f32 = np.ascontiguousarray(f, dtype=np.float32)
    lo = tuple(int(v) for v in lo)
    hi = tuple(int(v) for v in hi)
    masked = u_nodes is not None
    u = check_nodes(u_nodes if masked else np.zeros((3,) + tuple(e + 1 for e in elems)), elems)
    origin = tuple(int(v) for v in core_origin) if masked else (0, 0, 0)
    shape = tuple(int(v) for v in g_shape) if masked else (1, 1, 1)
    active = element_activity(active, elems)
    if impl == "numpy":
        if grey == "drift" and int(cell) > 1:
            raise ValueError("the brightness cells' couplings have no NumPy twin (impl='numba')")
        return kernels_numpy.m_block_numpy(f32, lo, hi, int(ell), elems, CONDENSED[grey], float(center),
                                           u if masked else None, origin, shape, int(margin), active, with_lags)
    ell = int(ell)
    idx = [grad_index(core[a], lo[a], hi[a]) for a in range(3)]
    xi = voxel_xi(ell)
    psi = np.stack([(1.0 - xi) ** 2, xi * (1.0 - xi), xi**2])  # psi_p, p = d_a + d_b
    T, C, K, lags, fmin, fmax = m_kernel(f32, lo[0], lo[1], lo[2], ell, *elems, *idx[0], *idx[1], *idx[2],
                                          psi, xi, float(center), u, *origin, *shape, float(margin), masked,
                                          active)
    cells = grey == "drift" and int(cell) > 1
    out = (_assemble_stencil(T, C, K, _SYM, 0 if cells else CONDENSED[grey]), float(fmin), float(fmax))
    if with_lags:
        out += (lags,)
    if cells:
        out += (cell_couplings(C, K, int(cell)),)
    return out
