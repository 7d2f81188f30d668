"""Primitives of the stencil CG: the half-stencil matrix-vector product, block-Jacobi, vector kernels.

Shared by the CG of :mod:`chunkdic.solve.cg` and the V-cycle of
:mod:`chunkdic.solve.multigrid`, which both build on them (and neither on the other's
internals). Numba kernels, serial and ``nogil`` as every kernel of the package.
"""

from __future__ import annotations

import numba
import numpy as np

from ..mesh import STENCIL_OFFSETS
from .penalty import add_weighted

#: index of the node itself in the 27-point stencil
CENTRE = 13
#: the stored half of the stencil: entries 13 (the node) to 26; entry ``26 - k`` of the
#: neighbour ``n + off_k`` is the transpose of entry ``k`` of node ``n``
HALF_OFFSETS = STENCIL_OFFSETS[CENTRE:]


def half_stencil(full: np.ndarray) -> np.ndarray:
    """The stored half ``S[..., 13:, :, :]`` of a full (…, 27, 3, 3) stencil (a view)."""
    return full[..., CENTRE:, :, :]


# reassociated sums (LLVM vectorises the 3x3 products; the flags of kernels.interp.jit_sums,
# which solve may not import): 12 % faster at 64³ nodes, the same product to 1e-15 relative (docs/engine.md, "Reassociated sums in the kernels")
@numba.njit(nogil=True, cache=True, fastmath={"reassoc", "contract"})
def half_matvec(H, x, y):
    """y = M x from the half stencil H (nz, ny, nx, 14, 3, 3)."""
    nz, ny, nx = x.shape[:3]
    y[:] = 0.0
    for z in range(nz):
        for yy in range(ny):
            for xx in range(nx):
                s = H[z, yy, xx, 0]
                c0, c1, c2 = x[z, yy, xx, 0], x[z, yy, xx, 1], x[z, yy, xx, 2]
                y[z, yy, xx, 0] += s[0, 0] * c0 + s[0, 1] * c1 + s[0, 2] * c2
                y[z, yy, xx, 1] += s[1, 0] * c0 + s[1, 1] * c1 + s[1, 2] * c2
                y[z, yy, xx, 2] += s[2, 0] * c0 + s[2, 1] * c1 + s[2, 2] * c2
                for h in range(1, 14):
                    k = h + 13
                    z2 = z + k // 9 - 1
                    y2 = yy + (k // 3) % 3 - 1
                    x2 = xx + k % 3 - 1
                    if z2 < 0 or z2 >= nz or y2 < 0 or y2 >= ny or x2 < 0 or x2 >= nx:
                        continue
                    s = H[z, yy, xx, h]
                    v0, v1, v2 = x[z2, y2, x2, 0], x[z2, y2, x2, 1], x[z2, y2, x2, 2]
                    y[z, yy, xx, 0] += s[0, 0] * v0 + s[0, 1] * v1 + s[0, 2] * v2
                    y[z, yy, xx, 1] += s[1, 0] * v0 + s[1, 1] * v1 + s[1, 2] * v2
                    y[z, yy, xx, 2] += s[2, 0] * v0 + s[2, 1] * v1 + s[2, 2] * v2
                    # the transposed entry of the neighbour
                    y[z2, y2, x2, 0] += s[0, 0] * c0 + s[1, 0] * c1 + s[2, 0] * c2
                    y[z2, y2, x2, 1] += s[0, 1] * c0 + s[1, 1] * c1 + s[2, 1] * c2
                    y[z2, y2, x2, 2] += s[0, 2] * c0 + s[1, 2] * c1 + s[2, 2] * c2


def stencil_matvec(H: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``y = M x`` for the half stencil ``H`` (nz, ny, nx, 14, 3, 3) and ``x`` (nz, ny, nx, 3)."""
    y = np.empty(x.shape, dtype=np.float64)
    half_matvec(H, np.ascontiguousarray(x, dtype=np.float64), y)
    return y


def rigid_restriction(H: np.ndarray) -> np.ndarray:
    """``Σ_ij M_ij`` (3, 3): ``M`` restricted to uniform translations (``Σ_a N_a = 1``)."""
    centre = H[..., 0, :, :].sum(axis=(0, 1, 2), dtype=np.float64)
    off = H[..., 1:, :, :].sum(axis=(0, 1, 2, 3), dtype=np.float64)
    return centre + off + off.T


@numba.njit(nogil=True, cache=True)
def block_jacobi(Binv, r, z):
    nz, ny, nx = r.shape[:3]
    for i in range(nz):
        for j in range(ny):
            for k in range(nx):
                for a in range(3):
                    z[i, j, k, a] = (Binv[i, j, k, a, 0] * r[i, j, k, 0] + Binv[i, j, k, a, 1] * r[i, j, k, 1]
                                     + Binv[i, j, k, a, 2] * r[i, j, k, 2])


@numba.njit(nogil=True, cache=True)
def block_jacobi_step(Binv, r, x, theta):
    """``x += (Binv r) / θ`` node by node: :func:`block_jacobi` and the step in one loop, the
    same operations in the same order, without a vector for ``Binv r`` (the V-cycle's
    degree-1 smoother, :mod:`chunkdic.solve.multigrid`)."""
    nz, ny, nx = r.shape[:3]
    for i in range(nz):
        for j in range(ny):
            for k in range(nx):
                for a in range(3):
                    s = (Binv[i, j, k, a, 0] * r[i, j, k, 0] + Binv[i, j, k, a, 1] * r[i, j, k, 1]
                         + Binv[i, j, k, a, 2] * r[i, j, k, 2])
                    x[i, j, k, a] += s / theta


@numba.njit(nogil=True, cache=True)
def _solve_block(H, Rd, iz, iy, ix, lam, i, j, k, r0, r1, r2):
    """``D⁻¹ r`` at node (i, j, k) for ``D = M_ii + λ R_ii``: ``M_ii`` the node's diagonal
    block in the half stencil ``H`` (float32, read as float64), ``R_ii`` the class block
    ``Rd[iz[i], iy[j], ix[k]]`` (:meth:`~chunkdic.solve.regularizer.Regularizer.diagonal_blocks`).
    Cholesky on the lower triangle (``D`` symmetric positive definite), float64."""
    a, b, c = iz[i], iy[j], ix[k]
    s = H[i, j, k, 0]
    d00 = s[0, 0] + lam * Rd[a, b, c, 0, 0]
    d10 = s[1, 0] + lam * Rd[a, b, c, 1, 0]
    d20 = s[2, 0] + lam * Rd[a, b, c, 2, 0]
    d11 = s[1, 1] + lam * Rd[a, b, c, 1, 1]
    d21 = s[2, 1] + lam * Rd[a, b, c, 2, 1]
    d22 = s[2, 2] + lam * Rd[a, b, c, 2, 2]
    l00 = np.sqrt(d00)
    l10 = d10 / l00
    l20 = d20 / l00
    l11 = np.sqrt(d11 - l10 * l10)
    l21 = (d21 - l20 * l10) / l11
    l22 = np.sqrt(d22 - l20 * l20 - l21 * l21)
    y0 = r0 / l00
    y1 = (r1 - l10 * y0) / l11
    y2 = (r2 - l20 * y0 - l21 * y1) / l22
    z2 = y2 / l22
    z1 = (y1 - l21 * z2) / l11
    z0 = (y0 - l10 * z1 - l20 * z2) / l00
    return z0, z1, z2


@numba.njit(nogil=True, cache=True)
def block_solve(H, Rd, iz, iy, ix, lam, r, z):
    """``z = D⁻¹ r`` node by node, ``D`` the 3×3 diagonal blocks of ``M + λ R`` formed on the fly
    (:func:`_solve_block`): block-Jacobi without a stored inverse (72 B per node in float64,
    150 MB at 128³ nodes; docs/distributed.md)."""
    nz, ny, nx = r.shape[:3]
    for i in range(nz):
        for j in range(ny):
            for k in range(nx):
                z0, z1, z2 = _solve_block(H, Rd, iz, iy, ix, lam, i, j, k, r[i, j, k, 0], r[i, j, k, 1],
                                          r[i, j, k, 2])
                z[i, j, k, 0], z[i, j, k, 1], z[i, j, k, 2] = z0, z1, z2


@numba.njit(nogil=True, cache=True)
def block_solve_step(H, Rd, iz, iy, ix, lam, r, x, theta):
    """``x += D⁻¹ r / θ`` (:func:`block_solve` and the V-cycle's damped step in one loop)."""
    nz, ny, nx = r.shape[:3]
    for i in range(nz):
        for j in range(ny):
            for k in range(nx):
                z0, z1, z2 = _solve_block(H, Rd, iz, iy, ix, lam, i, j, k, r[i, j, k, 0], r[i, j, k, 1],
                                          r[i, j, k, 2])
                x[i, j, k, 0] += z0 / theta
                x[i, j, k, 1] += z1 / theta
                x[i, j, k, 2] += z2 / theta


def subtract_cells(W: np.ndarray, k: int, x: np.ndarray, y: np.ndarray) -> None:
    """``y -= Σ_c W_c W_cᵀ x`` over the mesh's cells (:func:`chunkdic.kernels.m.cell_couplings` gathered for the
    whole mesh: ``W`` (cz, cy, cx, k+1, k+1, k+1, 3, 4)), ``x``, ``y`` (nz, ny, nx, 3) float64."""
    if W.shape[0]:
        _subtract_cells(W, int(k), x, y)


@numba.njit(nogil=True, cache=True)
def _subtract_cells(W, k, x, y):
    nz, ny, nx = x.shape[0], x.shape[1], x.shape[2]
    t = np.empty(4)
    for c0 in range(W.shape[0]):
        for c1 in range(W.shape[1]):
            for c2 in range(W.shape[2]):
                t[:] = 0.0
                for a in range(min(k + 1, nz - c0 * k)):
                    for b in range(min(k + 1, ny - c1 * k)):
                        for c in range(min(k + 1, nx - c2 * k)):
                            for i in range(3):
                                v = x[c0 * k + a, c1 * k + b, c2 * k + c, i]
                                for p in range(4):
                                    t[p] += W[c0, c1, c2, a, b, c, i, p] * v
                for a in range(min(k + 1, nz - c0 * k)):
                    for b in range(min(k + 1, ny - c1 * k)):
                        for c in range(min(k + 1, nx - c2 * k)):
                            for i in range(3):
                                s = 0.0
                                for p in range(4):
                                    s += W[c0, c1, c2, a, b, c, i, p] * t[p]
                                y[c0 * k + a, c1 * k + b, c2 * k + c, i] -= s


def no_diagonal(nodes_shape) -> tuple:
    """``(Rd, iz, iy, ix)`` of a zero ``R_ii`` on a mesh of ``nodes_shape`` nodes (:func:`block_solve`
    without regularisation: every node of class 0)."""
    return (np.zeros((1, 1, 1, 3, 3)), *(np.zeros(int(n), np.int64) for n in nodes_shape))


@numba.njit(nogil=True, cache=True)
def pcg_block_jacobi(H, Rd, iz, iy, ix, b, x, rtol, maxiter, code, Ke, Kf, sw, ew, freed, lam, cells, cell,
                     overwrite_b=False):
    """Preconditioned conjugate gradients on ``M + λ R``, x updated in place; -1 if not converged.

    Written out (rather than scipy's ``cg``) so that its vector operations are plain
    loops: on a busy machine, multithreaded BLAS calls on these small vectors cost more
    than the whole stencil product. The vector operations run on flat views through
    :func:`dot` and :func:`axpy`: written as 4-D array expressions they took numba 41 s
    to compile (the first run's largest single wait), as flat loops under a second.

    ``λ R`` comes from :func:`chunkdic.solve.penalty.add_weighted`, compiled into this
    function's Numba cache: a change of ``R`` (the Tikhonov Hessian, say) is seen here
    only once this file changes too or the cache is cleared (docs/architecture.md,
    development notes). ``freed``: the Tikhonov terms the robust reweighting left out
    (:attr:`~chunkdic.solve.regularizer.Regularizer.freed`; the block-Jacobi blocks ``Rd``
    stay the plain penalty's). ``cells``, ``cell``: the brightness cells' Schur complement
    (:func:`subtract_cells`; no cell: ``cells`` of length 0). ``overwrite_b``: ``b`` becomes
    the residual (changed on return).
    """
    bnorm = np.sqrt(dot(b.reshape(-1), b.reshape(-1)))
    r = b if overwrite_b else b.copy()  # x starts at zero
    z = np.empty_like(b)
    q = np.empty_like(b)
    rf, zf, qf, xf = r.reshape(-1), z.reshape(-1), q.reshape(-1), x.reshape(-1)
    block_solve(H, Rd, iz, iy, ix, lam, r, z)
    p = z.copy()
    pf = p.reshape(-1)
    rz = dot(rf, zf)
    if bnorm == 0.0:
        return 0
    for it in range(1, maxiter + 1):
        half_matvec(H, p, q)
        if cells.shape[0]:
            _subtract_cells(cells, cell, p, q)
        if code != 0:
            add_weighted(code, Ke, Kf, sw, ew, freed, lam, p, q)
        alpha = rz / dot(pf, qf)
        axpy(alpha, pf, xf)
        axpy(-alpha, qf, rf)
        if np.sqrt(dot(rf, rf)) <= rtol * bnorm:
            return it
        block_solve(H, Rd, iz, iy, ix, lam, r, z)
        rz_new = dot(rf, zf)
        beta = rz_new / rz
        for k in range(pf.size):  # p = z + β p
            pf[k] = zf[k] + beta * pf[k]
        rz = rz_new
    return -1


def pcg(matvec, precondition, b, x, rtol, maxiter, overwrite_b: bool = False) -> int:
    """:func:`pcg_block_jacobi` with any symmetric positive definite preconditioner.

    ``matvec(p, out)`` writes ``A p`` into ``out``, ``precondition(r, out)`` the
    preconditioned residual: both into this function's vectors, so that a solve holds
    ``b``, ``x`` and three vectors of its own whatever the iterations (a new vector per call
    held up to two more at once: 48 B per node, 100 MB at 128³ nodes): the preconditioned
    residual ``z`` is written into ``q``, whose product is spent once ``r`` is updated.
    Written in Python around the numba vector kernels: with a V-cycle per iteration, a few
    tens of iterations, the interpreter's share is negligible. ``overwrite_b``: ``b``
    becomes the residual (changed on return).
    """
    bnorm = np.sqrt(dot(b.reshape(-1), b.reshape(-1)))
    r = b if overwrite_b else b.copy()
    rf, xf = r.reshape(-1), x.reshape(-1)
    if bnorm == 0.0:
        return 0
    q = np.empty_like(b)  # A p, then z = D⁻¹ r in the same vector
    qf = q.reshape(-1)
    precondition(r, q)
    p = q.copy()
    pf = p.reshape(-1)
    rz = dot(rf, qf)
    for it in range(1, maxiter + 1):
        matvec(p, q)
        alpha = rz / dot(pf, qf)
        axpy(alpha, pf, xf)
        axpy(-alpha, qf, rf)
        if np.sqrt(dot(rf, rf)) <= rtol * bnorm:
            return it
        precondition(r, q)
        rz_new = dot(rf, qf)
        beta = rz_new / rz
        p *= beta
        p += q
        rz = rz_new
    return -1


@numba.njit(nogil=True, cache=True)
def dot(a, b):
    s = 0.0
    for k in range(a.size):
        s += a[k] * b[k]
    return s


@numba.njit(nogil=True, cache=True)
def axpy(alpha, a, y):
    """``y += alpha * a`` (flat arrays)."""
    for k in range(a.size):
        y[k] += alpha * a[k]
