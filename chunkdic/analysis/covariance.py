"""The solve's covariance of a result's nodal field, for the uncertainty of anything linear in it.

A global-DIC field's noise covariance is ``C = κ σ_r² A⁻¹ M A⁻¹`` (``A = M + λ R``; the
per-node uncertainty of :func:`chunkdic.method.noise.nodal_uncertainty` is its diagonal). The
uncertainty of a region mean, a rigid motion, a gauge or a strain is ``wᵀ C w`` for the
weights ``w`` that make the quantity from the nodes: its off-diagonal terms decide it.
Neighbouring C8 nodes are anticorrelated by ``M`` (the inverse of a mass matrix alternates
in sign) and positively correlated over the regularisation length by ``λ R``, so neither
the per-node σ nor ``std/√N`` gives it.

A result keeps ``σ_r``, ``κ``, the regularisation (kind, length) and the per-node σ, not
``M`` (504 bytes per node, five times the rest of a result). The covariance used here is
the solve's, *homogenised*: ``M`` is replaced by the voxel-sum mass matrix of the C8 shape
functions over the elements that were measured (a uniform texture), ``A`` by that ``M``
plus the result's regularisation weighted as the engine weighs it
(:func:`chunkdic.solve.regularizer.plane_wave_weight`), and the result is scaled node by
node to the stored σ::

    C ≈ S Ĉ S,   Ĉ = Â⁻¹ M̂ Â⁻¹,   S = diag(σ_i / σ̂_i)

with ``σ̂`` the diagonal of ``Ĉ`` computed by the engine's own :func:`nodal_uncertainty`, so
that ``C_ii = σ_i²`` holds for every node. The correlation structure comes from the mesh and
the regularisation; the variance of each node (texture, noise, κ) from the solve.
``wᵀ C w`` is one conjugate-gradient solve, ``z = Â⁻¹ S w``, then ``zᵀ M̂ z``: mesh-sized work.
Measured against 20 independent noise draws (docs/statistics.md): region means within
0.89–1.33× of the observed spread, with and without regularisation.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from ..method.noise import nodal_uncertainty
from ..errors import InputError
from ..mesh import LOCAL_NODES, STENCIL_OFFSETS
from ..results.result import FLAG_MASKED, FLAG_NO_DATA
from ..solve.cg import PoorTextureWarning, StencilSolver
from ..solve.regularizer import Regularizer, plane_wave_weight
from ..solve.reweighting import robust_freed
from ..solve.stencil import stencil_matvec

__all__ = ["NodalCovariance", "mass_stencil", "measured_elements", "gradient_adjoint", "element_gradient_weights",
           "point_stencil", "point_weights"]

#: relative residual of the CG solves (the variances need a few digits)
RTOL = 1e-8


def measured_elements(result) -> np.ndarray:
    """Elements whose 8 nodes were measured (finite) and that took part (a mask's active ones),
    shape (ez, ey, ex), bool."""
    finite = np.isfinite(result.displacement).all(axis=0)
    used = np.ones(tuple(n - 1 for n in finite.shape), bool)
    for dz, dy, dx in LOCAL_NODES:
        used &= finite[dz:dz + used.shape[0], dy:dy + used.shape[1], dx:dx + used.shape[2]]
    if result.active is not None:
        used &= result.active > 0
    return used


def mass_stencil(nodes_shape, ell: int, elements: np.ndarray | None = None) -> np.ndarray:
    """Half stencil of the C8 voxel-sum mass matrix ``Σ_voxels N_a N_b`` (times I₃), over ``elements``.

    Parameters
    ----------
    nodes_shape : tuple of 3 int
    ell : int
        Element edge, voxels.
    elements : ndarray of bool, shape (ez, ey, ex), optional
        The elements that count (default: all).

    Returns
    -------
    ndarray, shape (nz, ny, nx, 14, 3, 3), float32
        :data:`chunkdic.solve.stencil.HALF_OFFSETS` layout, per voxel (divided by ``ell³``).
    """
    xi = (np.arange(int(ell)) + 0.5) / int(ell)
    hat = np.stack([1.0 - xi, xi])
    m1 = hat @ hat.T / int(ell)  # the 1-D voxel sums of N_a N_b, per voxel
    shape = tuple(int(n) for n in nodes_shape)
    n_el = tuple(n - 1 for n in shape)
    weight = np.ones(n_el) if elements is None else np.asarray(elements, np.float64)
    H = np.zeros(shape + (14, 3, 3))
    for da in LOCAL_NODES:
        for db in LOCAL_NODES:
            k = int(np.flatnonzero((STENCIL_OFFSETS == db - da).all(axis=1))[0])
            if k < 13:
                continue  # its transpose, held by the other node
            mab = m1[da[0], db[0]] * m1[da[1], db[1]] * m1[da[2], db[2]]
            at = tuple(slice(int(d), int(d) + e) for d, e in zip(da, n_el))
            H[at + (k - 13,)] += (mab * weight)[..., None, None] * np.eye(3)
    return H.astype(np.float32)


def gradient_adjoint(G: np.ndarray, ell: float) -> np.ndarray:
    """Nodal weights of ``Σ_e G[:, :, e] : H_e``, ``H`` the C8 gradient at the element centres.

    The transpose of :func:`chunkdic.results.strain.displacement_gradient`: ``H[i, j]`` of an
    element is the mean of its four edge differences of ``U_i`` along ``j`` over ``ell``, so
    each of its 8 nodes weighs ``±1/(4 ell)``.

    Parameters
    ----------
    G : ndarray, shape (3, 3, ez, ey, ex), float64
        Coefficient of each ``H[i, j]`` of each element.
    ell : float
        Element edge, voxels.

    Returns
    -------
    ndarray, shape (3, ez+1, ey+1, ex+1), float64
        ``w`` with ``Σ_e G_e : H_e = Σ_nodes w · u``.
    """
    G = np.nan_to_num(np.asarray(G, np.float64))
    n_el = G.shape[2:]
    w = np.zeros((3,) + tuple(n + 1 for n in n_el))
    for d in LOCAL_NODES:
        sign = np.where(d == 1, 1.0, -1.0) / (4.0 * float(ell))  # along j = z, y, x
        at = (slice(None),) + tuple(slice(int(a), int(a) + n) for a, n in zip(d, n_el))
        w[at] += np.einsum("j,ij...->i...", sign, G)
    return w


def point_stencil(mesh, point) -> tuple[np.ndarray, np.ndarray]:
    """The 8 nodes of the C8 field at one point and their trilinear weights.

    ``point``: position ``(z, y, x)`` in voxels of the mesh's level (outside the mesh: the
    linear extension of the nearest element, as :meth:`chunkdic.mesh.Mesh.evaluate`).

    Returns
    -------
    nodes : ndarray, shape (8, 3), int64
        Node indices.
    weights : ndarray, shape (8,), float64
        Summing to 1.
    """
    idx, frac = zip(*(mesh.element_index(a, np.asarray(float(point[a]))) for a in range(3)))
    first = np.array([int(i) for i in idx])
    f = np.array([float(v) for v in frac])
    weights = np.prod(np.where(LOCAL_NODES == 1, f, 1.0 - f), axis=1)
    return first + LOCAL_NODES, weights


def point_weights(mesh, point) -> np.ndarray:
    """Nodal weights of the C8 field at one point (:func:`point_stencil`) on the whole mesh,
    shape (nz, ny, nx), float64."""
    w = np.zeros(mesh.nodes_shape)
    nodes, weights = point_stencil(mesh, point)
    np.add.at(w, tuple(nodes.T), weights)
    return w


def element_gradient_weights(G: np.ndarray, ell: float) -> np.ndarray:
    """Weights (8, 3) on one element's nodes (``LOCAL_NODES`` order) of ``G : H`` of that element.

    The one-element case of :func:`gradient_adjoint`: node ``d`` weighs
    ``Σ_j G[i, j] (±1)_j / (4 ell)`` on component ``i``, ``+`` where ``d_j = 1``.
    """
    sign = np.where(LOCAL_NODES == 1, 1.0, -1.0) / (4.0 * float(ell))  # (8, j)
    return sign @ np.asarray(G, np.float64).T


@dataclass
class NodalCovariance:
    """The homogenised solve covariance of one result's nodal field (module docstring).

    Build it with :meth:`of_result`. :meth:`covariance` gives ``W C Wᵀ`` for a few weight
    fields (one CG solve each); :meth:`local_variance` the variance of a functional that
    involves nodes at most one apart (a point value, an element strain) from the correlations
    of the mesh's central node, without a solve.

    Attributes
    ----------
    solver : StencilSolver
        ``Â = M̂ + λ R`` and ``M̂`` (its matrix).
    sigma : ndarray, shape (3, nz, ny, nx), float64
        The result's per-node σ, voxels of its level (0 where not measured).
    model : ndarray, shape (3, nz, ny, nx), float64
        ``σ̂``, the per-node σ of ``Ĉ`` (:func:`chunkdic.method.noise.nodal_uncertainty` of ``Â``).
    """

    solver: StencilSolver
    sigma: np.ndarray
    model: np.ndarray
    _local: tuple | None = None

    @property
    def scale(self) -> np.ndarray:
        """``S = σ_i / σ̂_i`` per node and component (0 where a node was not measured)."""
        return self.sigma / np.maximum(self.model, 1e-300)

    @classmethod
    def of_result(cls, result) -> "NodalCovariance":
        """The covariance of ``result`` (needs its per-node uncertainty).

        Raises
        ------
        InputError
            The result holds no per-node uncertainty (a composed series field, a result
            of another tool): no interval can be given.
        """
        sigma = result.uncertainty
        if sigma is None or not np.isfinite(sigma).any():
            raise InputError(f"result {result.path}: it holds no per-node uncertainty (a composed field, or "
                             "written without one), so no confidence interval can be given")
        used = measured_elements(result)
        if not used.any():
            raise InputError(f"result {result.path}: no element has all its nodes measured")
        ell = int(result.info["element_size"])
        H = mass_stencil(result.displacement.shape[1:], ell, used)
        with warnings.catch_warnings():  # the unmeasured nodes are held: expected, not news
            warnings.simplefilter("ignore", PoorTextureWarning)
            solver = StencilSolver(H, rtol=RTOL)
            reg = _regularizer(result)
            if reg is not None:
                length = float(result.info["regularization"]["length"]) / result.scale
                solver.regularize(reg, plane_wave_weight(reg, lambda v: stencil_matvec(solver.matrix, v), length))
            model = nodal_uncertainty(solver, 1.0, 1.0)
        measured = np.isfinite(sigma) & np.isfinite(result.displacement)
        if result.flags is not None:
            measured &= ((result.flags & (FLAG_NO_DATA | FLAG_MASKED)) == 0)[None]
        return cls(solver, np.where(measured, sigma, 0.0), model)

    def _apply(self, w: np.ndarray) -> np.ndarray:
        """``z = Â⁻¹ S w``, shape (nz, ny, nx, 3)."""
        v = np.ascontiguousarray(np.moveaxis(np.nan_to_num(self.scale * w), 0, -1))
        z, _ = self.solver.solve(v)
        return z

    def covariance(self, weights) -> np.ndarray:
        """``W C Wᵀ`` for weight fields ``W[k]`` of shape (3, nz, ny, nx): shape (k, k), voxels²."""
        zs = [self._apply(np.asarray(w, np.float64)) for w in weights]
        mz = [stencil_matvec(self.solver.matrix, z) for z in zs]
        return np.array([[float(np.sum(a * b)) for b in mz] for a in zs])

    def variance(self, w: np.ndarray) -> float:
        """``wᵀ C w`` of one weight field (3, nz, ny, nx), voxels²."""
        return float(self.covariance([w])[0, 0])

    def local_correlation(self, radius: int = 1) -> np.ndarray:
        """Correlation of the node nearest the mesh's centre with the nodes around it.

        Parameters
        ----------
        radius : int
            Node offsets ``-radius … radius`` per axis.

        Returns
        -------
        ndarray, shape (2r+1, 2r+1, 2r+1, 3, 3), float64
            ``ρ[oz+r, oy+r, ox+r, i, j]`` between component ``i`` of node ``c + o`` and
            component ``j`` of node ``c`` (six CG solves, once: a column of ``Ĉ`` per component).
        """
        if self._local is None:
            shape = self.solver.nodes_shape
            c = tuple(n // 2 for n in shape)
            columns = []
            for j in range(3):
                e = np.zeros(tuple(shape) + (3,))
                e[c + (j,)] = 1.0
                y, _ = self.solver.solve(e)
                col, _ = self.solver.solve(np.ascontiguousarray(stencil_matvec(self.solver.matrix, y)))
                columns.append(col)
            self._local = (c, np.stack(columns, axis=-1), {})  # (nz, ny, nx, 3 i, 3 j), tables by radius
        c, column = self._local[:2]
        r = int(radius)
        cached = self._local[2].get(r)
        if cached is not None:
            return cached
        rho = np.zeros((2 * r + 1,) * 3 + (3, 3))
        for o in np.ndindex(*(2 * r + 1,) * 3):
            node = tuple(ci + oi - r for ci, oi in zip(c, o))
            if not all(0 <= a < n for a, n in zip(node, column.shape[:3])):
                continue
            denom = self.model[(slice(None),) + node][:, None] * self.model[(slice(None),) + c][None, :]
            rho[o] = np.where(denom > 0, column[node] / np.maximum(denom, 1e-300), 0.0)
        self._local[2][r] = rho
        return rho

    def local_variance(self, w: np.ndarray, radius: int = 1) -> float:
        """``wᵀ C w`` for weights ``w`` (3, nz, ny, nx) whose nodes lie at most ``radius`` nodes
        apart per axis (:meth:`local_variance_at` of its non-zero nodes)."""
        at = np.argwhere(np.any(w != 0, axis=0))
        return self.local_variance_at(at, w[(slice(None),) + tuple(at.T)].T, radius)

    def local_variance_at(self, nodes: np.ndarray, w: np.ndarray, radius: int = 1) -> float:
        """``wᵀ C w`` of weights ``w`` (k, 3) on the nodes ``nodes`` (k, 3; repeats add up) lying
        at most ``radius`` nodes apart per axis, with the central node's correlations
        (:meth:`local_correlation`) and the per-node σ; farther pairs are left out. No work of
        the mesh's size: what a profile point, an element strain or a crack's jump needs."""
        rho = self.local_correlation(radius)
        nodes = np.asarray(nodes, np.int64).reshape(-1, 3)
        v = np.asarray(w, np.float64).reshape(-1, 3) * self.sigma[(slice(None),) + tuple(nodes.T)].T
        offset = nodes[None, :, :] - nodes[:, None, :]  # b - a, (k, k, 3)
        near = np.all(np.abs(offset) <= radius, axis=-1)
        ia, ib = np.nonzero(near)
        table = rho[tuple((offset[ia, ib] + radius).T)]  # (pairs, 3 i, 3 j)
        return float(np.einsum("pi,pij,pj->", v[ib], table, v[ia]))


def _regularizer(result) -> Regularizer | None:
    """The result's penalty (kind, reweighting) on its mesh, or None."""
    reg = result.info.get("regularization") or {}
    kind, length = reg.get("kind", "none"), reg.get("length")
    if kind in (None, "none") or not length:
        return None
    shape = tuple(result.displacement.shape[1:])
    freed = None
    if reg.get("freed_terms"):  # the robust reweighting's freed terms, from the final field
        freed = robust_freed(np.ascontiguousarray(np.moveaxis(np.nan_to_num(result.displacement), 0, -1)))
        freed = freed if freed.any() else None
    return Regularizer(kind, shape, float(result.info["element_size"]), freed)
