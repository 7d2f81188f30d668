"""The penalty kernels of the regularizer: element matrices and matrix-free products on the node grid.

What :class:`chunkdic.solve.regularizer.Regularizer` applies, as numba loops over the nodes
(serial, ``nogil``): the Tikhonov penalty's second differences along the grid lines and
mixed differences of the 2×2 squares (:func:`apply_hessian`, with the robust reweighting's
freed terms :func:`apply_hessian_freed`), the equilibrium gap's elastic element
(:func:`elastic_element`, applied by :func:`apply_vector`), its face Laplacians and edge
second differences, and :func:`add_weighted`, the one entry the CG loops of
:mod:`chunkdic.solve.stencil` call for ``y += λ R x``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..mesh import LOCAL_NODES

#: the kinds of terms of the Tikhonov penalty, in the order of :attr:`Regularizer.freed`'s last axis:
#: second differences along z, y, x, then the mixed differences of the (z, y), (z, x), (y, x) squares
TERM_KINDS = ("zz", "yy", "xx", "zy", "zx", "yx")
#: an empty ``freed`` for :func:`add_weighted`: no term freed
NO_FREED = np.zeros((0, 0, 0, len(TERM_KINDS)), np.uint8)
#: Poisson ratio of the equilibrium-gap material (the result depends on it only weakly)
POISSON = 0.3

_GAUSS = (0.5 - 0.5 / math.sqrt(3.0), 0.5 + 0.5 / math.sqrt(3.0))


def _shape_gradients(xi) -> np.ndarray:
    """Gradients (8, 3) of the trilinear shape functions of the unit cube at ``xi`` (z, y, x)."""
    out = np.empty((8, 3))
    for a, d in enumerate(LOCAL_NODES):
        phi = [xi[k] if d[k] else 1.0 - xi[k] for k in range(3)]
        dphi = [1.0 if d[k] else -1.0 for k in range(3)]
        out[a] = (dphi[0] * phi[1] * phi[2], phi[0] * dphi[1] * phi[2], phi[0] * phi[1] * dphi[2])
    return out


def elastic_element(ell: float, poisson: float = POISSON) -> np.ndarray:
    """Isotropic elastic stiffness (E = 1) of a cube of edge ``ell``, (24, 24), dofs ``(a, i)``."""
    lam = poisson / ((1 + poisson) * (1 - 2 * poisson))
    mu = 0.5 / (1 + poisson)
    D = np.zeros((6, 6))
    D[:3, :3] = lam
    D[np.arange(3), np.arange(3)] += 2 * mu
    D[np.arange(3, 6), np.arange(3, 6)] = mu
    K = np.zeros((24, 24))
    for xi in np.array(np.meshgrid(_GAUSS, _GAUSS, _GAUSS, indexing="ij")).reshape(3, -1).T:
        G = _shape_gradients(xi)
        B = np.zeros((6, 24))
        for a in range(8):
            for i in range(3):
                B[i, 3 * a + i] = G[a, i]
            # engineering shears (0,1), (0,2), (1,2)
            B[3, 3 * a + 0], B[3, 3 * a + 1] = G[a, 1], G[a, 0]
            B[4, 3 * a + 0], B[4, 3 * a + 2] = G[a, 2], G[a, 0]
            B[5, 3 * a + 1], B[5, 3 * a + 2] = G[a, 2], G[a, 1]
        K += B.T @ D @ B / 8.0
    return K * ell


def face_laplacian_element() -> np.ndarray:
    """``∫ ∇N_a · ∇N_b`` of a bilinear square (4, 4), local nodes ``2 dy + dx`` (scale-free in 2-D)."""
    K = np.zeros((4, 4))
    for t in np.array(np.meshgrid(_GAUSS, _GAUSS, indexing="ij")).reshape(2, -1).T:
        G = np.array([[(1.0 if dy else -1.0) * (t[1] if dx else 1 - t[1]),
                       (t[0] if dy else 1 - t[0]) * (1.0 if dx else -1.0)]
                      for dy in (0, 1) for dx in (0, 1)])
        K += G @ G.T / 4.0
    return K


@numba.njit(nogil=True, cache=True)
def apply_vector(Ke, x, y):
    """y += Σ_elements Ke (24×24, dofs (a, i)) on the nodal field x (nz, ny, nx, 3)."""
    nz, ny, nx = x.shape[0], x.shape[1], x.shape[2]
    xe = np.empty(24)
    for ez in range(nz - 1):
        for ey in range(ny - 1):
            for ex in range(nx - 1):
                for b in range(8):
                    zb, yb, xb = ez + (b >> 2), ey + ((b >> 1) & 1), ex + (b & 1)
                    for j in range(3):
                        xe[3 * b + j] = x[zb, yb, xb, j]
                for a in range(8):
                    za, ya, xa = ez + (a >> 2), ey + ((a >> 1) & 1), ex + (a & 1)
                    for i in range(3):
                        s = 0.0
                        for q in range(24):
                            s += Ke[3 * a + i, q] * xe[q]
                        y[za, ya, xa, i] += s


@numba.njit(nogil=True, cache=True)
def apply_curvature(x, y, w):
    """y += w Σ_axes D2ᵀ D2 x: squared second differences along every grid line, per component."""
    nz, ny, nx = x.shape[0], x.shape[1], x.shape[2]
    for i in range(nz):
        for j in range(ny):
            for k in range(nx):
                for c in range(3):
                    v = x[i, j, k, c]
                    if 0 < i < nz - 1:
                        t = w * (x[i - 1, j, k, c] - 2.0 * v + x[i + 1, j, k, c])
                        y[i - 1, j, k, c] += t
                        y[i, j, k, c] -= 2.0 * t
                        y[i + 1, j, k, c] += t
                    if 0 < j < ny - 1:
                        t = w * (x[i, j - 1, k, c] - 2.0 * v + x[i, j + 1, k, c])
                        y[i, j - 1, k, c] += t
                        y[i, j, k, c] -= 2.0 * t
                        y[i, j + 1, k, c] += t
                    if 0 < k < nx - 1:
                        t = w * (x[i, j, k - 1, c] - 2.0 * v + x[i, j, k + 1, c])
                        y[i, j, k - 1, c] += t
                        y[i, j, k, c] -= 2.0 * t
                        y[i, j, k + 1, c] += t


@numba.njit(nogil=True, cache=True)
def apply_mixed(x, y, w):
    """y += w Σ_planes Dmᵀ Dm x: the mixed difference of every 2×2 square of nodes, per component."""
    nz, ny, nx = x.shape[0], x.shape[1], x.shape[2]
    for i in range(nz):
        for j in range(ny):
            for k in range(nx):
                for c in range(3):
                    v = x[i, j, k, c]
                    if i < nz - 1 and j < ny - 1:  # the (z, y) square
                        t = w * (v - x[i + 1, j, k, c] - x[i, j + 1, k, c] + x[i + 1, j + 1, k, c])
                        y[i, j, k, c] += t
                        y[i + 1, j, k, c] -= t
                        y[i, j + 1, k, c] -= t
                        y[i + 1, j + 1, k, c] += t
                    if i < nz - 1 and k < nx - 1:  # (z, x)
                        t = w * (v - x[i + 1, j, k, c] - x[i, j, k + 1, c] + x[i + 1, j, k + 1, c])
                        y[i, j, k, c] += t
                        y[i + 1, j, k, c] -= t
                        y[i, j, k + 1, c] -= t
                        y[i + 1, j, k + 1, c] += t
                    if j < ny - 1 and k < nx - 1:  # (y, x)
                        t = w * (v - x[i, j + 1, k, c] - x[i, j, k + 1, c] + x[i, j + 1, k + 1, c])
                        y[i, j, k, c] += t
                        y[i, j + 1, k, c] -= t
                        y[i, j, k + 1, c] -= t
                        y[i, j + 1, k + 1, c] += t


@numba.njit(nogil=True, cache=True)
def apply_hessian(x, y, w):
    """y += w R x for Tikhonov: the squared Frobenius norm of the discrete Hessian (the mixed
    terms counted twice, as ``∂_i∂_j`` and ``∂_j∂_i``)."""
    apply_curvature(x, y, w)
    apply_mixed(x, y, 2.0 * w)


@numba.njit(nogil=True, cache=True)
def apply_hessian_freed(x, y, w, freed):
    """:func:`apply_hessian` without the freed terms: bit ``c`` of ``freed[i, j, k, t]`` set
    leaves out component ``c`` of the term of kind ``t`` (:data:`TERM_KINDS`) anchored at
    node ``(i, j, k)``: a second difference at its centre node, a mixed difference at the
    square's first corner (the lower indices)."""
    nz, ny, nx = x.shape[0], x.shape[1], x.shape[2]
    w2 = 2.0 * w
    for i in range(nz):
        for j in range(ny):
            for k in range(nx):
                for c in range(3):
                    bit = 1 << c
                    v = x[i, j, k, c]
                    if 0 < i < nz - 1 and not freed[i, j, k, 0] & bit:
                        t = w * (x[i - 1, j, k, c] - 2.0 * v + x[i + 1, j, k, c])
                        y[i - 1, j, k, c] += t
                        y[i, j, k, c] -= 2.0 * t
                        y[i + 1, j, k, c] += t
                    if 0 < j < ny - 1 and not freed[i, j, k, 1] & bit:
                        t = w * (x[i, j - 1, k, c] - 2.0 * v + x[i, j + 1, k, c])
                        y[i, j - 1, k, c] += t
                        y[i, j, k, c] -= 2.0 * t
                        y[i, j + 1, k, c] += t
                    if 0 < k < nx - 1 and not freed[i, j, k, 2] & bit:
                        t = w * (x[i, j, k - 1, c] - 2.0 * v + x[i, j, k + 1, c])
                        y[i, j, k - 1, c] += t
                        y[i, j, k, c] -= 2.0 * t
                        y[i, j, k + 1, c] += t
                    if i < nz - 1 and j < ny - 1 and not freed[i, j, k, 3] & bit:  # (z, y)
                        t = w2 * (v - x[i + 1, j, k, c] - x[i, j + 1, k, c] + x[i + 1, j + 1, k, c])
                        y[i, j, k, c] += t
                        y[i + 1, j, k, c] -= t
                        y[i, j + 1, k, c] -= t
                        y[i + 1, j + 1, k, c] += t
                    if i < nz - 1 and k < nx - 1 and not freed[i, j, k, 4] & bit:  # (z, x)
                        t = w2 * (v - x[i + 1, j, k, c] - x[i, j, k + 1, c] + x[i + 1, j, k + 1, c])
                        y[i, j, k, c] += t
                        y[i + 1, j, k, c] -= t
                        y[i, j, k + 1, c] -= t
                        y[i + 1, j, k + 1, c] += t
                    if j < ny - 1 and k < nx - 1 and not freed[i, j, k, 5] & bit:  # (y, x)
                        t = w2 * (v - x[i, j + 1, k, c] - x[i, j, k + 1, c] + x[i, j + 1, k + 1, c])
                        y[i, j, k, c] += t
                        y[i, j + 1, k, c] -= t
                        y[i, j, k + 1, c] -= t
                        y[i, j + 1, k + 1, c] += t


@numba.njit(nogil=True, cache=True)
def term_exists(t, i, j, k, nz, ny, nx):
    """Whether the mesh has a term of kind ``t`` anchored at node ``(i, j, k)`` (the bits of
    :attr:`Regularizer.freed` elsewhere mean nothing)."""
    if t == 0:
        return 0 < i < nz - 1
    if t == 1:
        return 0 < j < ny - 1
    if t == 2:
        return 0 < k < nx - 1
    if t == 3:
        return i < nz - 1 and j < ny - 1
    if t == 4:
        return i < nz - 1 and k < nx - 1
    return j < ny - 1 and k < nx - 1


@numba.njit(nogil=True, cache=True)
def freed_diagonal(freed, z0, out):
    """``out -= `` the diagonal of ``R`` that the freed terms of ``freed`` take away, on the z
    planes ``z0 … z0 + len(out) - 1`` of the mesh (``out`` (nz', ny, nx, 3)): a second
    difference adds 1, 4, 1 to its three nodes, a mixed one 2 (its weight) to each corner."""
    nz, ny, nx = freed.shape[0], freed.shape[1], freed.shape[2]
    lo, hi = z0, z0 + out.shape[0]
    for i in range(max(lo - 1, 0), min(hi + 1, nz)):
        for j in range(ny):
            for k in range(nx):
                for c in range(3):
                    bit = 1 << c
                    for t in range(6):
                        if not freed[i, j, k, t] & bit or not term_exists(t, i, j, k, nz, ny, nx):
                            continue
                        if t < 3:  # second difference along axis t, centred at (i, j, k)
                            for d in (-1, 0, 1):
                                z, yy, xx = i, j, k
                                if t == 0:
                                    z += d
                                elif t == 1:
                                    yy += d
                                else:
                                    xx += d
                                if lo <= z < hi:
                                    out[z - lo, yy, xx, c] -= 4.0 if d == 0 else 1.0
                        else:  # mixed difference of the square at (i, j, k)
                            p = 0 if t < 5 else 1
                            q = 1 if t == 3 else 2
                            for a in range(2):
                                for b in range(2):
                                    z, yy, xx = i, j, k
                                    if p == 0:
                                        z += a
                                    else:
                                        yy += a
                                    if q == 1:
                                        yy += b
                                    else:
                                        xx += b
                                    if lo <= z < hi:
                                        out[z - lo, yy, xx, c] -= 2.0


@numba.njit(nogil=True, cache=True)
def face_node(axis, k0, i1, i2):
    """(z, y, x) of node (i1, i2) of the face ``axis = k0`` (in-plane axes in cyclic order)."""
    if axis == 0:
        return k0, i1, i2
    if axis == 1:
        return i2, k0, i1
    return i1, i2, k0


@numba.njit(nogil=True, cache=True)
def apply_faces(Kf, x, y, w):
    """y += w Σ over the 6 faces of Lᵀ P_s L x, L the face Q4 Laplacian per component."""
    dims = (x.shape[0], x.shape[1], x.shape[2])
    for axis in range(3):
        n1 = dims[(axis + 1) % 3]
        n2 = dims[(axis + 2) % 3]
        if n1 < 3 or n2 < 3:
            continue
        for side in range(2):
            k0 = 0 if side == 0 else dims[axis] - 1
            Lx = np.zeros((n1, n2, 3))
            for e1 in range(n1 - 1):
                for e2 in range(n2 - 1):
                    for a in range(4):
                        i1, i2 = e1 + (a >> 1), e2 + (a & 1)
                        for b in range(4):
                            z, yy, xx = face_node(axis, k0, e1 + (b >> 1), e2 + (b & 1))
                            for c in range(3):
                                Lx[i1, i2, c] += Kf[a, b] * x[z, yy, xx, c]
            # P_s: keep the rows inside the face (its own boundary carries edge terms)
            Lx[0, :, :] = 0.0
            Lx[n1 - 1, :, :] = 0.0
            Lx[:, 0, :] = 0.0
            Lx[:, n2 - 1, :] = 0.0
            for e1 in range(n1 - 1):
                for e2 in range(n2 - 1):
                    for a in range(4):
                        z, yy, xx = face_node(axis, k0, e1 + (a >> 1), e2 + (a & 1))
                        for b in range(4):
                            j1, j2 = e1 + (b >> 1), e2 + (b & 1)
                            for c in range(3):
                                y[z, yy, xx, c] += w * Kf[a, b] * Lx[j1, j2, c]


@numba.njit(nogil=True, cache=True)
def apply_edges(x, y, w):
    """y += w Σ over the 12 edges of the box of D2ᵀ D2 x, D2 the second difference along the edge, per component."""
    dims = (x.shape[0], x.shape[1], x.shape[2])
    for axis in range(3):
        n = dims[axis]
        if n < 3:
            continue
        m1 = dims[(axis + 1) % 3] - 1
        m2 = dims[(axis + 2) % 3] - 1
        for s1 in range(2):
            for s2 in range(2):
                for k in range(1, n - 1):
                    z0, y0, x0 = face_node(axis, k - 1, s1 * m1, s2 * m2)
                    z1, y1, x1 = face_node(axis, k, s1 * m1, s2 * m2)
                    z2, y2, x2 = face_node(axis, k + 1, s1 * m1, s2 * m2)
                    for c in range(3):
                        t = w * (x[z0, y0, x0, c] - 2.0 * x[z1, y1, x1, c] + x[z2, y2, x2, c])
                        y[z0, y0, x0, c] += t
                        y[z1, y1, x1, c] -= 2.0 * t
                        y[z2, y2, x2, c] += t


@numba.njit(nogil=True, cache=True)
def add_weighted(code, Ke, Kf, surface_weight, edge_weight, freed, lam, x, y):
    """``y += λ R x`` (numba, for the CG of :mod:`chunkdic.solve.cg`); ``code`` 1 Tikhonov, 2 equilibrium gap;
    ``freed`` the Tikhonov terms left out (:attr:`Regularizer.freed`; an empty array: none)."""
    if code == 1:
        if freed.shape[0] == 0:
            apply_hessian(x, y, lam)
        else:
            apply_hessian_freed(x, y, lam, freed)
        return
    k = np.zeros_like(x)
    apply_vector(Ke, x, k)
    k[0, :, :, :] = 0.0
    k[-1, :, :, :] = 0.0
    k[:, 0, :, :] = 0.0
    k[:, -1, :, :] = 0.0
    k[:, :, 0, :] = 0.0
    k[:, :, -1, :] = 0.0
    t = np.zeros_like(x)
    apply_vector(Ke, k, t)
    if surface_weight != 0.0:
        apply_faces(Kf, x, t, surface_weight)
    if edge_weight != 0.0:
        apply_edges(x, t, edge_weight)
    for i in range(x.shape[0]):
        for j in range(x.shape[1]):
            for l in range(x.shape[2]):
                for c in range(3):
                    y[i, j, l, c] += lam * t[i, j, l, c]
