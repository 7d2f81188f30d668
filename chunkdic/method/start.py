"""Affine step on the coarsest level: 12 parameters after the rigid translation.

A rigid translation cannot start a C8 mesh on a large homogeneous strain or rotation: at
10–20 % compression or 10° of rotation the far elements are several voxels (beyond the
texture's capture range) from where a translation puts them, and their Gauss–Newton steps
go astray (issue 20). Gauss–Newton restricted to affine fields ``u(X) = t + A (X - c)``
uses every voxel of the level for 12 unknowns, linearised where the field is right (near
``c``) and pulled outwards pass by pass; the C8 iterations then start within a fraction
of a voxel of any field that is affine to first order.

The C8 basis holds affine fields exactly (trilinear shape functions reproduce linear
functions), so the affine field is a nodal field ``a = P p`` with ``P`` the ``(3N, 12)``
table of node coordinates, and the restricted system is ``Pᵀ M P δp = Pᵀ b``: the nodal
``b`` of an ordinary pass summed with weights, and ``M`` applied to the 12 columns of
``P`` on the client (mesh-sized work, no extra pass over the voxels; paper section 5.1 does
the same for the rigid translation). A regularisation term would vanish on affine fields
(curvature Tikhonov) or nearly (equilibrium gap), so the step leaves it out.

docs/engine.md, "ROI and meshes" (the coarse-to-fine schedule and what it measured).
"""

from __future__ import annotations

import numpy as np

from ..solve.stencil import stencil_matvec
from ..passes.level import Level, emit

#: passes of the affine step at most
MAX_PASSES = 20


def affine_table(mesh) -> tuple[np.ndarray, np.ndarray]:
    """The nodal fields of the 12 affine parameters over ``mesh``.

    Returns
    -------
    P : ndarray, shape (12, nz, ny, nx, 3), float64
        Column ``k`` is the nodal field of parameter ``k``: ``k < 3`` the translation along
        component ``k``; ``k = 3 + 3 i + j`` the gradient ``dU_i/dX_j`` times the ROI's half
        extent along ``j`` (so that all columns move the nodes by O(1) voxel, which keeps
        ``Pᵀ M P`` well conditioned).
    centre : ndarray, shape (3,), float64
        ``c``, the ROI's centre, voxels of the level.
    """
    axes = mesh.node_axes()
    centre = np.array([(a[0] + a[-1]) / 2 for a in axes])
    half = np.array([max((a[-1] - a[0]) / 2, 1.0) for a in axes])
    grid = np.meshgrid(*[(a - c) / h for a, c, h in zip(axes, centre, half)], indexing="ij")
    P = np.zeros((12,) + mesh.nodes_shape + (3,))
    for i in range(3):
        P[i, ..., i] = 1.0
        for j in range(3):
            P[3 + 3 * i + j, ..., i] = grid[j]
    return P, centre


def affine_field(P: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The nodal field ``P p``, shape (3, nz, ny, nx) (the engine's layout)."""
    return np.moveaxis(np.tensordot(p, P, axes=1), -1, 0)


def gradient(p: np.ndarray, mesh) -> np.ndarray:
    """``dU_i/dX_j`` (3, 3) of the affine parameters ``p`` (:func:`affine_table`)."""
    half = np.array([max((a[-1] - a[0]) / 2, 1.0) for a in mesh.node_axes()])
    return p[3:].reshape(3, 3) / half[None, :]


def affine_step(lvl: Level, t: np.ndarray, tolerance: float, history, progress, *,
                max_passes: int = MAX_PASSES) -> np.ndarray:
    """Gauss–Newton restricted to affine fields from the translation ``t``.

    Parameters
    ----------
    lvl : Level
        The coarsest level, its ``M`` assembled.
    t : ndarray, shape (3,), float64, voxels of the level
        The rigid translation (:func:`chunkdic.method.gauss_newton.rigid_step`).
    tolerance : float
        Stop when the step moves no node by more than this (voxels of the level).
    history : History
        Passes are recorded with negative iteration numbers after the rigid step's.
    progress : callable, optional

    Returns
    -------
    ndarray, shape (3, nz, ny, nx), float64, voxels of the level
        The affine field of lowest gap met (the translation's if no affine field was better).
    """
    P, _ = affine_table(lvl.mesh)
    flat = P.reshape(12, -1)
    K = np.stack([stencil_matvec(lvl.solver.matrix, P[k]).reshape(-1) for k in range(12)]) @ flat.T
    K = 0.5 * (K + K.T)
    p = np.zeros(12)
    p[:3] = t
    first = -1 - int(np.count_nonzero(np.asarray(history.rows["iteration"]) < 0) if history.rows["iteration"] else 0)
    best_gap, best_p = np.inf, p.copy()
    for it in range(max_passes):
        u = affine_field(P, p)
        ps = lvl.assemble_b(u)
        if not np.isfinite(ps.gap):
            break
        if ps.gap < best_gap:
            best_gap, best_p = ps.gap, p.copy()
        elif ps.gap > 2.0 * best_gap:  # going astray: keep the best
            history.add(lvl.s, first - it, ps.gap, np.nan, ps.n_excluded)
            break
        rhs = flat @ ps.b.reshape(-1)
        try:
            dp = np.linalg.solve(K, rhs)
        except np.linalg.LinAlgError:
            break
        move = float(np.abs(affine_field(P, dp)).max())
        history.add(lvl.s, first - it, ps.gap, move, ps.n_excluded)
        emit(progress, stage="affine", level=lvl.s, iteration=it, gap=ps.gap, max_delta=move,
             gradient=gradient(p, lvl.mesh).tolist())
        p = p + dp
        if move < tolerance:
            best_p = p  # converged: the last step is below the tolerance
            break
    return affine_field(P, best_p)
