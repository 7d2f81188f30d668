"""Regularisation of the C8 field: Tikhonov (H¹) and the equilibrium gap.

With small elements the image term alone leaves the nodal values noisy (C8 nodal values
are de-averaged by the inverse of the mass-like matrix ``M``) and nodes that see little
texture ill-determined. The modified Gauss–Newton step then solves

    (M + λ R) δa = b − λ R a

with a penalty ``aᵀ R a`` that damps the short wavelengths of the field and leaves the
long ones to the images (the usual regularised global DVC: pyxel, UFreckles, Correli):

``tikhonov``
    ``R = Σ_axes D2ᵀ D2 + 2 Σ_planes Dmᵀ Dm``, the squared Frobenius norm of the discrete
    Hessian of each component: second differences along every grid line of nodes plus
    twice the squared mixed differences ``u₀₀ − u₁₀ − u₀₁ + u₁₁`` of every 2×2 square of
    nodes in the three grid planes (a discrete curvature, in voxel units scaled away by the
    normalisation). Its plane-wave symbol is ``(Σ_i s_i)²`` with ``s_i = 2 − 2 cos θ_i``,
    ``|θ|⁴`` to leading order: a wave is damped by its wavelength whatever its direction.
    The second differences alone (``Σ s_i²``, the form until issue 20) damp a wave along a
    grid diagonal 2–3× less than one along an axis, so at the same resolution along the
    axes the field kept 1.2× more noise (measured on the star, docs/engine.md). It reaches
    every node, the ROI's edges and corners included, and costs nothing for rigid and
    linear fields: it penalises the curvature of the field, not its gradient (the H¹
    energy ``∫ |∇u|²`` would pull a homogeneous strain towards zero: on a 5³-node mesh of a
    −2 % compression it measured −1.7 %). A fourth-order low-pass.
``equilibrium-gap``
    ``R = Kᵀ P K + μ_s Σ_faces Lᵀ P_s L + μ_e Σ_edges D2ᵀ D2``: ``K`` the stiffness of a
    homogeneous isotropic elastic solid on the C8 mesh (Poisson ratio ``POISSON``), ``P``
    keeps its rows at interior nodes: the equilibrium gap, zero for any field in
    equilibrium (Tomičević, Hild, Roux 2013). On the ROI faces, where ``K u`` is a traction
    the images cannot constrain, ``L`` is the in-plane (Q4) Laplacian of each face, ``P_s``
    keeps the rows inside the face; on the 12 edges of the box, which the face rows leave
    out, ``D2`` is the second difference along the edge. ``μ_s`` and ``μ_e`` make a plane
    wave cost as much per face node and per edge node as per interior node. Each term sets
    the next lower-dimensional part from its boundary (interior from the faces, faces from
    the edges, edges from the corners), so the null space is 24 fields fixed by the 8
    corners, as many as Tikhonov's; without the edge term it held every field set by its
    edge values (3 (12 (n - 2) + 8) of them), left to the few voxels of the edge nodes, and
    Gauss–Newton on CT scans at ℓ = 6 and 4 moved those nodes by up to 88 voxels and ended
    stalled or diverged (issue 20, docs/engine.md). It couples the components as an
    elastic solid does; a localised band (a local softening) is not in equilibrium for a
    homogeneous material, and the equilibrium gap damps it more than Tikhonov does.

Normalisation (as pyxel does for its weak regularisation): ``λ`` is such that a plane
wave of wavelength ``T`` is penalised ``(ℓ_reg / T)^4`` times its image term
``vᵀ M v``: one length ``ℓ_reg`` (voxels)
sets the weight; features shorter than it are damped, longer ones left to the images.
``λ`` is measured with waves of wavelength ``T_ref = 10 ℓ`` (bounded by the mesh), where
the discrete operators follow the continuous scaling, averaged over the three directions
and polarisations.

Everything is built from the mesh alone (no voxels) and applied matrix-free on the client
by element loops (:func:`apply`), next to the stencil product of ``M`` in the same CG.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np

from ..mesh import LOCAL_NODES, node_colours

KINDS = ("none", "tikhonov", "equilibrium-gap")
#: the kinds of terms of the Tikhonov penalty, in the order of :attr:`Regularizer.freed`'s last axis:
#: second differences along z, y, x, then the mixed differences of the (z, y), (z, x), (y, x) squares
TERM_KINDS = ("zz", "yy", "xx", "zy", "zx", "yx")
#: the robust reweighting frees a term beyond this many robust standard deviations of its kind and
#: component (:func:`robust_freed`; docs/engine.md, "The band and the slip at ℓ = 8")
ROBUST_THRESHOLD = 6.0
#: terms beyond the threshold are freed only as a connected set (same kind and component, 26
#: neighbours) that spans at least this fraction of the mesh's nodes along one axis: a kink is
#: a surface or a line across the field, outliers of the noise (weakly textured nodes) compact
#: clusters (:func:`robust_freed`)
SPANNING_FRACTION = 0.5
#: the robust standard deviation of a normal sample from its median absolute value
MAD_TO_SIGMA = 1.4826
#: an empty ``freed`` for :func:`add_weighted`: no term freed
NO_FREED = np.zeros((0, 0, 0, len(TERM_KINDS)), np.uint8)
#: Poisson ratio of the equilibrium-gap material (the result depends on it only weakly)
POISSON = 0.3
#: order of the low-pass: penalty ∝ (ℓ_reg / T)^ORDER for a plane wave of wavelength T
ORDER = {"tikhonov": 4, "equilibrium-gap": 4}

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
def _apply_vector(Ke, x, y):
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
def _apply_curvature(x, y, w):
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
def _apply_mixed(x, y, w):
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
def _apply_hessian(x, y, w):
    """y += w R x for Tikhonov: the squared Frobenius norm of the discrete Hessian (the mixed
    terms counted twice, as ``∂_i∂_j`` and ``∂_j∂_i``)."""
    _apply_curvature(x, y, w)
    _apply_mixed(x, y, 2.0 * w)


@numba.njit(nogil=True, cache=True)
def _apply_hessian_freed(x, y, w, freed):
    """:func:`_apply_hessian` without the freed terms: bit ``c`` of ``freed[i, j, k, t]`` set
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
def _term_exists(t, i, j, k, nz, ny, nx):
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
def _freed_diagonal(freed, z0, out):
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
                        if not freed[i, j, k, t] & bit or not _term_exists(t, i, j, k, nz, ny, nx):
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
def _face_node(axis, k0, i1, i2):
    """(z, y, x) of node (i1, i2) of the face ``axis = k0`` (in-plane axes in cyclic order)."""
    if axis == 0:
        return k0, i1, i2
    if axis == 1:
        return i2, k0, i1
    return i1, i2, k0


@numba.njit(nogil=True, cache=True)
def _apply_faces(Kf, x, y, w):
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
                            z, yy, xx = _face_node(axis, k0, e1 + (b >> 1), e2 + (b & 1))
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
                        z, yy, xx = _face_node(axis, k0, e1 + (a >> 1), e2 + (a & 1))
                        for b in range(4):
                            j1, j2 = e1 + (b >> 1), e2 + (b & 1)
                            for c in range(3):
                                y[z, yy, xx, c] += w * Kf[a, b] * Lx[j1, j2, c]


@numba.njit(nogil=True, cache=True)
def _apply_edges(x, y, w):
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
                    z0, y0, x0 = _face_node(axis, k - 1, s1 * m1, s2 * m2)
                    z1, y1, x1 = _face_node(axis, k, s1 * m1, s2 * m2)
                    z2, y2, x2 = _face_node(axis, k + 1, s1 * m1, s2 * m2)
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
            _apply_hessian(x, y, lam)
        else:
            _apply_hessian_freed(x, y, lam, freed)
        return
    k = np.zeros_like(x)
    _apply_vector(Ke, x, k)
    k[0, :, :, :] = 0.0
    k[-1, :, :, :] = 0.0
    k[:, 0, :, :] = 0.0
    k[:, -1, :, :] = 0.0
    k[:, :, 0, :] = 0.0
    k[:, :, -1, :] = 0.0
    t = np.zeros_like(x)
    _apply_vector(Ke, k, t)
    if surface_weight != 0.0:
        _apply_faces(Kf, x, t, surface_weight)
    if edge_weight != 0.0:
        _apply_edges(x, t, edge_weight)
    for i in range(x.shape[0]):
        for j in range(x.shape[1]):
            for l in range(x.shape[2]):
                for c in range(3):
                    y[i, j, l, c] += lam * t[i, j, l, c]


def _interior(x: np.ndarray) -> np.ndarray:
    """Zero the rows of the boundary nodes (the projection ``P``)."""
    out = np.zeros_like(x)
    out[1:-1, 1:-1, 1:-1] = x[1:-1, 1:-1, 1:-1]
    return out


@dataclass
class Regularizer:
    """The operator ``R`` of one mesh (no weight): :meth:`apply` and :meth:`diagonal_blocks`.

    Parameters
    ----------
    kind : {"tikhonov", "equilibrium-gap"}
    nodes_shape : tuple of 3 int
    ell : float
        Element edge, voxels of the level.
    freed : ndarray, shape (nz, ny, nx, 6), uint8, optional
        Tikhonov only: the terms the robust reweighting left out (weight 0; every other
        term keeps weight 1). Bit ``c`` of ``freed[i, j, k, t]`` frees component ``c`` of the
        term of kind ``TERM_KINDS[t]`` anchored at node ``(i, j, k)`` (a second difference at
        its centre node, a mixed one at its square's first corner): 6 B per node
        (:func:`robust_freed`). The normalisation (:func:`plane_wave_weight`), the probed
        diagonal classes of the preconditioners and the V-cycle's coarse operators are
        those of the plain penalty (docs/engine.md).
    """

    kind: str
    nodes_shape: tuple[int, int, int]
    ell: float
    freed: np.ndarray | None = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        if self.kind not in KINDS[1:]:
            raise ValueError(f"unknown regularisation {self.kind!r}")
        self.nodes_shape = tuple(int(n) for n in self.nodes_shape)
        if self.freed is not None:
            if self.kind != "tikhonov":
                raise ValueError("only the Tikhonov penalty is reweighted term by term")
            self.freed = np.ascontiguousarray(self.freed, np.uint8)
            if self.freed.shape != self.nodes_shape + (len(TERM_KINDS),):
                raise ValueError(f"freed terms of shape {self.freed.shape} on a mesh of {self.nodes_shape} nodes")
            if not self.freed.any():
                self.freed = None
        self._Kf = face_laplacian_element()
        self.surface_weight = self.edge_weight = 0.0
        if self.kind == "tikhonov":
            self._Ke = np.zeros((24, 24))
        else:
            self._Ke = elastic_element(self.ell)
            self.surface_weight, self.edge_weight = self._balance_boundary()

    @property
    def order(self) -> int:
        return ORDER[self.kind]

    def numba_args(self) -> tuple:
        """``(code, Ke, Kf, surface weight, edge weight, freed)`` for :func:`add_weighted`."""
        return ((1 if self.kind == "tikhonov" else 2), self._Ke, self._Kf, float(self.surface_weight),
                float(self.edge_weight), NO_FREED if self.freed is None else self.freed)

    def resized(self, nodes_shape) -> "Regularizer":
        """The same plain operator on a mesh of ``nodes_shape`` nodes, with this one's boundary
        weights (for probing its stencil on a small mesh: the weights balanced on the small
        mesh differ) and no freed term."""
        small = Regularizer(self.kind, nodes_shape, self.ell)
        small.surface_weight, small.edge_weight = self.surface_weight, self.edge_weight
        return small

    def plain(self) -> "Regularizer":
        """This operator with every term at weight 1 (itself when none is freed)."""
        return self if self.freed is None else self.with_freed(None)

    def with_freed(self, freed: np.ndarray | None) -> "Regularizer":
        """The same operator with the terms ``freed`` left out (:attr:`freed`), sharing this
        one's probed diagonal classes and V-cycle operators (those of the plain penalty)."""
        out = Regularizer(self.kind, self.nodes_shape, self.ell, freed)
        out.surface_weight, out.edge_weight = self.surface_weight, self.edge_weight
        for cache in ("_diagonal", "_multigrid"):
            if hasattr(self, cache):
                setattr(out, cache, getattr(self, cache))
        return out

    def sub(self, region: tuple[slice, slice, slice]) -> "Regularizer":
        """The operator on the sub-mesh ``region`` of the nodes (its freed terms with it)."""
        shape = tuple(len(range(*r.indices(n))) for r, n in zip(region, self.nodes_shape))
        return Regularizer(self.kind, shape, self.ell, None if self.freed is None else self.freed[region])

    def _K(self, x: np.ndarray) -> np.ndarray:
        y = np.zeros_like(x)
        _apply_vector(self._Ke, x, y)
        return y

    def apply(self, x: np.ndarray) -> np.ndarray:
        """``R x`` for a nodal field ``x`` of shape (nz, ny, nx, 3), float64."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        if self.kind == "tikhonov":
            y = np.zeros_like(x)
            if self.freed is None:
                _apply_hessian(x, y, 1.0)
            else:
                _apply_hessian_freed(x, y, 1.0, self.freed)
            return y
        y = self._K(_interior(self._K(x)))
        if self.surface_weight:
            _apply_faces(self._Kf, x, y, float(self.surface_weight))
        if self.edge_weight:
            _apply_edges(x, y, float(self.edge_weight))
        return y

    def _boundary_terms(self, x: np.ndarray) -> tuple[float, float, float]:
        """The three terms of ``xᵀ R x`` (volume; faces and edges with unit weight)."""
        vol = float(np.sum(_interior(self._K(x)) ** 2))
        y = np.zeros_like(x)
        _apply_faces(self._Kf, x, y, 1.0)
        z = np.zeros_like(x)
        _apply_edges(x, z, 1.0)
        return vol, float(np.sum(x * y)), float(np.sum(x * z))

    def _balance_boundary(self) -> tuple[float, float]:
        """``(μ_s, μ_e)``: plane waves cost the same per face node and per edge node as per interior node."""
        n = [int(k) for k in self.nodes_shape]
        n_int = max(int(np.prod([max(k - 2, 0) for k in n])), 1)
        n_face = max(sum(2 * max(n[(a + 1) % 3] - 2, 0) * max(n[(a + 2) % 3] - 2, 0) for a in range(3)), 1)
        n_edge = max(sum(4 * max(n[a] - 2, 0) for a in range(3)), 1)
        vol = surf = edge = 0.0
        for v in plane_waves(self.nodes_shape, self.ell, reference_wavelength(self.nodes_shape, self.ell)):
            a, b, c = self._boundary_terms(v)
            vol, surf, edge = vol + a, surf + b, edge + c
        if vol <= 0:
            return 0.0, 0.0
        mu_s = (vol / n_int) / (surf / n_face) if surf > 0 else 0.0
        mu_e = (vol / n_int) / (edge / n_edge) if edge > 0 else 0.0
        return mu_s, mu_e

    def diagonal_blocks(self, planes: slice = slice(None)) -> np.ndarray:
        """The 3×3 diagonal blocks of ``R`` on the z planes ``planes`` of the nodes (default:
        all), shape (nz', ny, nx, 3, 3), float64 (for the preconditioner).

        ``R`` is the same at every node farther than its reach (2 nodes for the equilibrium
        gap, 1 for Tikhonov) from the mesh faces: the blocks are probed on a mesh of at
        most ``2 (reach + 1) + 1`` nodes per axis, with unit vectors on a colouring of
        nodes whose supports do not overlap, and mapped back by distance to the faces.
        The probed blocks are kept (a few kB): a slab of planes costs only its own copy,
        so that the client never needs all of them at once (72 B per node). With freed
        terms, their share of the diagonal is taken off (``planes`` a contiguous slice).
        """
        blocks, index = self.diagonal_classes()
        out = blocks[np.ix_(index[0][planes], index[1], index[2])]
        if self.freed is not None:  # Tikhonov's blocks are diagonal: the freed terms' share off
            z = np.arange(self.nodes_shape[0])[planes]
            if z.size:
                less = np.zeros(out.shape[:4])
                _freed_diagonal(self.freed, int(z[0]), less)
                out[..., [0, 1, 2], [0, 1, 2]] += less
        return out

    def diagonal_classes(self) -> tuple[np.ndarray, list]:
        """``(blocks, index)``: the diagonal blocks probed on the small mesh (float64) and, per
        axis, each node's position in it (int64 arrays of the mesh's length): block ``(i, j, k)``
        is ``blocks[index[0][i], index[1][j], index[2][k]]`` (block-Jacobi reads them so,
        :func:`chunkdic.solve.stencil.block_solve`). Those of the plain penalty: with freed
        terms, block-Jacobi preconditions with a diagonal a little too large at their
        nodes, which keeps it symmetric positive definite (docs/engine.md)."""
        cached = getattr(self, "_diagonal", None)
        if cached is not None:
            return cached
        reach = 2
        core = reach + 1
        small_shape = tuple(min(n, 2 * core + 1) for n in self.nodes_shape)
        small = self.plain() if small_shape == self.nodes_shape else self.resized(small_shape)
        period = 2 * reach + 1
        blocks = np.zeros(small_shape + (3, 3))
        for sel in node_colours(small_shape, period):
            for j in range(3):
                e = np.zeros(small_shape + (3,))
                e[sel, j] = 1.0
                blocks[sel, :, j] = small.apply(e)[sel]
        index = [np.where(np.arange(n) < core, np.arange(n),
                          np.where(np.arange(n) >= n - core, m - (n - np.arange(n)), core))
                 for n, m in zip(self.nodes_shape, small_shape)]
        self._diagonal = blocks, index
        return self._diagonal


def reference_wavelength(nodes_shape, ell: float) -> float:
    """Wavelength (voxels) of the normalising plane waves: ``10 ℓ``, at most the mesh's smallest extent."""
    extent = (min(nodes_shape) - 1) * ell
    return float(max(min(10.0 * ell, extent), 4.0 * ell))


def plane_waves(nodes_shape, ell: float, wavelength: float):
    """The 9 plane waves (3 directions × 3 polarisations) of ``wavelength`` (voxels) on the nodes.

    Each is ``sin(2π x_d / T + 1)`` in one component, over node positions ``k ell``.
    """
    axes = [np.arange(n) * ell for n in nodes_shape]
    for d in range(3):
        shape = [1, 1, 1]
        shape[d] = -1
        s = np.sin(2 * np.pi * axes[d] / wavelength + 1.0).reshape(shape)
        for c in range(3):
            v = np.zeros(tuple(nodes_shape) + (3,))
            v[..., c] = np.broadcast_to(s, nodes_shape)
            yield v


def plane_wave_weight(reg: Regularizer, matvec, length: float) -> float:
    """``λ`` such that a plane wave of wavelength ``T`` costs ``(length / T)^p`` of its image term.

    ``matvec(x)`` applies ``M``; measured at :func:`reference_wavelength` over the 9 waves:
    ``λ = (length / T)^p · Σ vᵀ M v / Σ vᵀ R v``, i.e. :func:`plane_wave_unit` ``· length^p``.
    """
    return plane_wave_unit(reg, matvec) * float(length) ** reg.order


def plane_wave_unit(reg: Regularizer, matvec) -> float:
    """The ``λ`` of :func:`plane_wave_weight` for a length of one voxel: ``Σ vᵀ M v / Σ vᵀ R v / T^p``.

    Nine products of ``M`` and of ``R`` over the whole mesh (0.6 s at 65³ nodes, 1024³ at
    ℓ = 16): a caller that weighs several lengths against the same ``M`` keeps it
    (:meth:`chunkdic.engine.level.Level.regularize`).
    """
    T = reference_wavelength(reg.nodes_shape, reg.ell)
    reg = reg.plain()  # one length means one weight, whatever the robust reweighting freed
    m = r = 0.0
    for v in plane_waves(reg.nodes_shape, reg.ell, T):
        m += float(np.sum(v * matvec(v)))
        r += float(np.sum(v * reg.apply(v)))
    if r <= 0:
        return 0.0
    return m / r / T ** reg.order


def robust_freed(x: np.ndarray, threshold: float = ROBUST_THRESHOLD) -> np.ndarray:
    """The Tikhonov terms of the field ``x`` to free: one robust reweighting (IRLS with a
    hard threshold) of the Hessian penalty.

    Each term (a second difference along a grid line, a mixed difference of a 2×2 square,
    per component) whose value exceeds ``threshold`` robust standard deviations of its kind
    and component (:data:`MAD_TO_SIGMA` × the median of their absolute values over the
    mesh), in a connected set of such terms (same kind and component) spanning at least
    :data:`SPANNING_FRACTION` of the mesh along one axis, gets weight 0: the kinks of a band
    or a slip, where the field truly bends along a surface, while the noise and smooth fields
    (a wave's differences are the wave itself, their robust σ its amplitude) keep every
    term. Without the span, weakly textured nodes (elements small against the texture's
    features), whose noise is heavy-tailed and correlated over a few nodes, freed clusters of
    up to ~13 terms (extent ≤ 5 nodes of 25) on waves, and the length chosen for the freed
    penalty went long (docs/engine.md, "The regularisation length"). docs/engine.md, "The
    band and the slip at ℓ = 8".

    Parameters
    ----------
    x : ndarray, shape (nz, ny, nx, 3), float
        The nodal field (voxels of the level), e.g. the regularised solution at the chosen length.
    threshold : float
        In robust standard deviations.

    Returns
    -------
    freed : ndarray, shape (nz, ny, nx, 6), uint8
        :attr:`Regularizer.freed`. Built one kind and component at a time: the client holds
        one float64 difference array of the mesh's size at once (8 B per node).
    """
    x = np.asarray(x)
    shape = x.shape[:3]
    freed = np.zeros(shape + (len(TERM_KINDS),), np.uint8)
    for c in range(3):
        u = x[..., c]
        for t in range(len(TERM_KINDS)):
            d, anchor = _term_values(u, t)
            if d.size == 0:
                continue
            a = np.abs(d)
            sigma = MAD_TO_SIGMA * float(np.median(a))
            if not sigma > 0:
                continue
            beyond = a > threshold * sigma
            del a, d
            freed[anchor + (t,)] |= (_spanning(beyond, shape).astype(np.uint8) << c)
    return freed


def _spanning(beyond: np.ndarray, shape) -> np.ndarray:
    """The terms of ``beyond`` (bool, one kind and component) in connected sets (26 neighbours)
    whose extent along some axis reaches :data:`SPANNING_FRACTION` of the mesh's ``shape`` (nodes)."""
    from scipy.ndimage import find_objects, label

    if not beyond.any():
        return beyond
    labels, _ = label(beyond, np.ones((3, 3, 3), bool))
    keep = np.zeros(int(labels.max()) + 1, bool)
    for k, box in enumerate(find_objects(labels), start=1):
        keep[k] = any(b.stop - b.start >= SPANNING_FRACTION * n for b, n in zip(box, shape))
    return keep[labels]


def _term_values(u: np.ndarray, t: int) -> tuple[np.ndarray, tuple]:
    """The terms of kind ``TERM_KINDS[t]`` of a scalar nodal field ``u`` (nz, ny, nx) and where
    they are anchored (a tuple of slices into the nodes): the unweighted difference."""
    if t < 3:
        n = u.shape[t]
        lo, mid, hi = ([slice(None)] * 3 for _ in range(3))
        lo[t], mid[t], hi[t] = slice(0, n - 2), slice(1, n - 1), slice(2, n)
        return u[tuple(lo)] - 2.0 * u[tuple(mid)] + u[tuple(hi)], tuple(mid)
    p, q = {3: (0, 1), 4: (0, 2), 5: (1, 2)}[t]

    def corner(dp, dq):
        s = [slice(None)] * 3
        s[p] = slice(dp, u.shape[p] - 1 + dp)
        s[q] = slice(dq, u.shape[q] - 1 + dq)
        return tuple(s)

    return u[corner(0, 0)] - u[corner(1, 0)] - u[corner(0, 1)] + u[corner(1, 1)], corner(0, 0)
