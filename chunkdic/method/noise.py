"""How correlated the residual's noise is: the factor that scales every noise estimate.

A fitted unknown absorbs, on average, ``sᵀ C s / sᵀ s`` of the misfit, ``s`` its
sensitivity (``N_a ∂_i f`` over the voxels) and ``C`` the covariance of the residual's
noise. For white noise that is the noise variance ``σ_r²``; the residual of CT scans is
far from white (filtered back-projection, then the low-pass of both scans), and a fitted
unknown absorbs ``κ σ_r²`` with ``κ`` of 10–20 on the CT specimens. Every noise-based
estimate (the automatic regularisation length, the per-node uncertainty) multiplies
``σ_r²`` by ``κ``.

``κ`` is estimated from data the passes already sweep: the correlation along x of the
residual (its variogram, ``b`` passes) and of each sensitivity's gradient factor (``M``
pass), for lags 0 … :data:`chunkdic.kernels.blocks.LAGS` voxels, assuming the correlations are
separable and alike along the three axes:

    κ_i = (1 + 2 Σ_{k≥1} ρ_r(k) ρ_{∂_i f}(k))³,   κ = mean over i.

On the grains CT specimen at ℓ = 12 the misfit a fitted unknown absorbs was measured at 14;
the estimate reads 19 on a 100³ grains pair translated with independent noise in each scan
(ℓ = 12), 28 where the residual also holds the field's own misfit (a wave, a band). The lag
sums take every row, each lag on the same voxels, so that the blocks' cut does not bias them
(:data:`chunkdic.kernels.blocks.LAGS`; docs/engine.md, "Noise correlation").
"""

from __future__ import annotations

import numpy as np

from ..mesh import node_colours
from ..solve.cg import StencilSolver
from ..solve.stencil import stencil_matvec

#: the estimate is kept within these bounds (an anticorrelated residual gives κ < 1)
BOUNDS = (0.25, 1000.0)


def correlation_factor(residual_lags: np.ndarray, sensitivity_lags: np.ndarray, gain: float = 1.0,
                       noise_variance: float | None = None) -> float:
    """``κ`` from the lag sums of the residual (6, L+1) and of the sensitivities (3, L+1).

    The residual's correlation comes from its variogram along x,
    ``ρ(k) = 1 - γ(k) / σ_r²`` with ``γ(k) = ½ mean (r_x - r_{x+k})²``: the difference of
    two voxels of one row cancels whatever is constant along the row (a brightness offset,
    a drift along z), which a covariance would count as correlated noise. ``r = d - α g'``
    (``α = gain - 1``) is formed from :attr:`chunkdic.kernels.blocks.ElementSums.lags`;
    ``noise_variance`` is the brightness-corrected ``σ_r²`` (default: ``r``'s own
    variance). ``sensitivity_lags``: ``Σ ∂_i f ∂_i f'`` per component and lag (``M``
    pass). Returns 1 when there is nothing to estimate from.
    """
    r = np.asarray(residual_lags, dtype=np.float64)
    s = np.asarray(sensitivity_lags, dtype=np.float64)
    if r[1, 0] <= 0 or np.any(r[1] <= 0) or np.any(s[:, 0] <= 0):
        return 1.0
    alpha = float(gain) - 1.0
    # k = 0: mean r²; k >= 1: mean (r_x - r_{x+k})² (ElementSums.lags)
    moments = (r[0] - alpha * r[2] + alpha * alpha * r[3]) / r[1]
    gamma = 0.5 * moments
    gamma[0] = 0.0  # semivariogram
    sill = float(noise_variance) if noise_variance else moments[0] - ((r[4, 0] - alpha * r[5, 0]) / r[1, 0]) ** 2
    if not sill > 0:
        return 1.0
    rho_r = 1.0 - gamma / sill
    rho_s = s / s[:, :1]
    kappa = np.mean((1.0 + 2.0 * np.sum(rho_r[None, 1:] * rho_s[:, 1:], axis=1)) ** 3)
    return float(np.clip(kappa, *BOUNDS))


#: the exact diagonal is computed on a central sub-mesh of at most this many nodes per axis
#: (a dense factorisation of at most 3 · 8³ = 1 536 unknowns: under a second)
PROBE_EDGE = 8
#: nodes over which ``M + λ R`` couples two nodes at most (``M`` 1, both penalties 2: the
#: discrete operator applied twice) ...
OPERATOR_REACH = 2
#: ... so that unit vectors this many nodes apart have columns that do not overlap
PROBE_PERIOD = 2 * OPERATOR_REACH + 1


def nodal_uncertainty(solver, noise_variance: float, kappa: float) -> np.ndarray:
    """Standard deviation of each nodal displacement, shape (3, nz, ny, nx), voxels.

    The global-DIC estimate ``Cov(a) = κ σ_r² A⁻¹ M A⁻¹`` (``A = M + λ R``; for ``λ = 0``
    the usual ``σ_r² M⁻¹``, with the noise correlation factor ``κ``): the variance of node
    ``i`` is modelled locally as ``c · [A_ii⁻¹ M_ii A_ii⁻¹]`` (its own 3×3 blocks), and the
    factor ``c`` (how much the coupling to the neighbours adds) is measured once on a
    central sub-mesh of at most :data:`PROBE_EDGE` nodes per axis, where the diagonal of
    ``A⁻¹ M A⁻¹`` is computed exactly (:func:`exact_diagonal`): the median ratio over its
    inner nodes. Mesh-sized work only.

    Exact and dense rather than probed by CG solves on coloured unit vectors: with a long
    regularisation length ``A⁻¹`` reaches across the whole mesh, so the unit vectors of one
    colour contaminate each other's diagonal (measured: ``c`` off by 1.6×), and CG on that
    ill-conditioned ``A`` needs hundreds of iterations per probe (the 384 probe solves took
    5–40 s at 100³, more than the correlation itself).

    Parameters
    ----------
    solver : StencilSolver
        The level's solver (``M`` and its regularisation).
    noise_variance : float
        ``σ_r²``, grey levels².
    kappa : float
        Noise correlation factor (:func:`correlation_factor`).
    """

    H = solver.matrix
    n = H.shape[:3]
    local_diag = solver.local_variances()  # diag(A_ii⁻¹ M_ii A_ii⁻¹), (nz, ny, nx, 3)
    # the factor c on a central sub-mesh
    sub = tuple(slice(max((k - PROBE_EDGE) // 2, 0), max((k - PROBE_EDGE) // 2, 0) + min(k, PROBE_EDGE)) for k in n)
    small = StencilSolver(np.ascontiguousarray(H[sub]).copy(), multigrid=False)  # matvec only
    if solver.regularizer is not None:

        small.regularize(solver.regularizer.sub(sub), solver.weight)
    shape = small.nodes_shape
    inner = tuple(slice(1, -1) if k > 2 else slice(None) for k in shape)
    exact = exact_diagonal(small, inner)
    ratio = exact / np.maximum(local_diag[sub][inner], 1e-300)
    c = float(np.median(ratio)) if ratio.size else 1.0
    local_diag *= float(kappa) * float(noise_variance) * c  # in place: mesh-sized (24 B per node)
    np.sqrt(local_diag, out=local_diag)  # and the root: no second copy
    return np.moveaxis(local_diag, -1, 0)


def exact_diagonal(small, region: tuple[slice, slice, slice] | None = None) -> np.ndarray:
    """The diagonal of ``A⁻¹ M A⁻¹`` of a small :class:`~chunkdic.solve.cg.StencilSolver` over the
    nodes ``region`` (default: all), shape (region's nodes, 3).

    Dense: ``A = M + λ R`` and ``M`` are assembled from their products with unit vectors on a
    colouring of the nodes (:data:`PROBE_PERIOD`; ``M`` without brightness cells, whose
    complement would reach across a cell) and ``A`` is factorised (Cholesky; ``A`` is
    symmetric positive definite). With
    ``z = A⁻¹ e_i`` the entry is ``zᵀ M z``: one triangular solve per wanted unknown and a
    sparse product, not the whole ``A⁻¹ M A⁻¹`` (on 8³ nodes with the inner 6³ wanted:
    about a third of the floating-point work). Meant for a few thousand unknowns at most
    (:data:`PROBE_EDGE`).
    """
    import scipy.linalg as sla
    import scipy.sparse as sp

    if small.cells.shape[0]:
        raise ValueError("exact_diagonal probes M + λR by colours: a solver without brightness cells")
    shape = tuple(small.nodes_shape)
    size = 3 * int(np.prod(shape))
    A = np.zeros((size, size))
    M = np.zeros((size, size))
    # The columns from products with unit vectors on a colouring: nodes PROBE_PERIOD apart
    # on every axis, whose columns (at most OPERATOR_REACH nodes from their own) cannot
    # overlap: 125 × 3 pairs of products on 8³ nodes instead of one pair per unknown (1 536)
    index = np.arange(size).reshape(shape + (3,))
    for colour in node_colours(shape, PROBE_PERIOD):
        nodes = np.argwhere(colour)
        for j in range(3):
            e = np.zeros(shape + (3,))
            e[tuple(nodes.T) + (j,)] = 1.0
            a_e, m_e = small.matvec(e), stencil_matvec(small.matrix, e)
            for node in nodes:
                window = tuple(slice(max(c - OPERATOR_REACH, 0), c + OPERATOR_REACH + 1) for c in node)
                rows, column = index[window].reshape(-1), index[tuple(node) + (j,)]
                A[rows, column] = a_e[window].reshape(-1)
                M[rows, column] = m_e[window].reshape(-1)
    A = 0.5 * (A + A.T)  # symmetric up to round-off
    wanted = np.arange(size).reshape(shape + (3,))
    if region is not None:
        wanted = wanted[region]
    out_shape = wanted.shape
    wanted = wanted.reshape(-1)
    unit = np.zeros((size, wanted.size))
    unit[wanted, np.arange(wanted.size)] = 1.0
    try:
        Z = sla.cho_solve(sla.cho_factor(A), unit)
    except np.linalg.LinAlgError:  # numerically indefinite: a symmetric solve still gives it
        Z = sla.solve(A, unit, assume_a="sym")
    return np.sum(Z * (sp.csr_matrix(M) @ Z), axis=0).reshape(out_shape)
