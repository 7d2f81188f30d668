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
pass), for lags 0 … :data:`chunkdic.blocks.LAGS` voxels, assuming the correlations are
separable and alike along the three axes:

    κ_i = (1 + 2 Σ_{k≥1} ρ_r(k) ρ_{∂_i f}(k))³,   κ = mean over i.

On the grains CT specimen (ℓ = 12) the estimate is 17 where the misfit a fitted unknown
absorbs was measured at 14 (docs/engine.md, "Noise correlation").
"""

from __future__ import annotations

import numpy as np

#: the estimate is kept within these bounds (an anticorrelated residual gives κ < 1)
BOUNDS = (0.25, 1000.0)


def correlation_factor(residual_lags: np.ndarray, sensitivity_lags: np.ndarray, gain: float = 1.0,
                       noise_variance: float | None = None) -> float:
    """``κ`` from the lag sums of the residual (6, L+1) and of the sensitivities (3, L+1).

    The residual's correlation comes from its variogram along x,
    ``ρ(k) = 1 - γ(k) / σ_r²`` with ``γ(k) = ½ mean (r_x - r_{x+k})²``: the difference of
    two voxels of one row cancels whatever is constant along the row (a brightness offset,
    a drift along z), which a covariance would count as correlated noise. ``r = d - α g'``
    (``α = gain - 1``) is formed from :attr:`chunkdic.blocks.ElementSums.lags`;
    ``noise_variance`` is the brightness-corrected ``σ_r²`` (default: ``r``'s own
    variance). ``sensitivity_lags``: ``Σ ∂_i f ∂_i f'`` per component and lag (``M``
    pass). Returns 1 when there is nothing to estimate from.
    """
    r = np.asarray(residual_lags, dtype=np.float64)
    s = np.asarray(sensitivity_lags, dtype=np.float64)
    if r[1, 0] <= 0 or np.any(r[1] <= 0) or np.any(s[:, 0] <= 0):
        return 1.0
    alpha = float(gain) - 1.0
    second = (r[0] - alpha * r[2] + alpha * alpha * r[3]) / r[1]  # mean r_x r_{x+k}
    gamma = second[0] - second  # semivariogram (stationary: E r_x² the same for every x)
    sill = float(noise_variance) if noise_variance else second[0] - ((r[4, 0] - alpha * r[5, 0]) / r[1, 0]) ** 2
    if not sill > 0:
        return 1.0
    rho_r = 1.0 - gamma / sill
    rho_s = s / s[:, :1]
    kappa = np.mean((1.0 + 2.0 * np.sum(rho_r[None, 1:] * rho_s[:, 1:], axis=1)) ** 3)
    return float(np.clip(kappa, *BOUNDS))


#: the exact diagonal is probed on a central sub-mesh of at most this many nodes per axis
PROBE_EDGE = 10
#: nodes of one colour of the probing are this many nodes apart on every axis
PROBE_PERIOD = 4


def nodal_uncertainty(solver, noise_variance: float, kappa: float) -> np.ndarray:
    """Standard deviation of each nodal displacement, shape (3, nz, ny, nx), voxels.

    The global-DIC estimate ``Cov(a) = κ σ_r² A⁻¹ M A⁻¹`` (``A = M + λ R``; for ``λ = 0``
    the usual ``σ_r² M⁻¹``, with the noise correlation factor ``κ``): the variance of node
    ``i`` is modelled locally as ``c · [A_ii⁻¹ M_ii A_ii⁻¹]`` (its own 3×3 blocks), and the
    factor ``c`` (how much the coupling to the neighbours adds) is measured once on a
    central sub-mesh, where the exact diagonal is probed with solves of ``A`` on coloured
    unit vectors. Mesh-sized work only.

    Parameters
    ----------
    solver : StencilSolver
        The level's solver (``M`` and its regularisation).
    noise_variance : float
        ``σ_r²``, grey levels².
    kappa : float
        Noise correlation factor (:func:`correlation_factor`).
    """
    from .solve import StencilSolver

    H = solver.matrix
    n = H.shape[:3]
    Mii = H[..., 0, :, :].astype(np.float64)
    Ainv = solver.block_inverse
    local = np.einsum("...ij,...jk,...kl->...il", Ainv, Mii, Ainv)
    local_diag = np.diagonal(local, axis1=-2, axis2=-1)  # (nz, ny, nx, 3)
    # the factor c on a central sub-mesh
    sub = tuple(slice(max((k - PROBE_EDGE) // 2, 0), max((k - PROBE_EDGE) // 2, 0) + min(k, PROBE_EDGE)) for k in n)
    small = StencilSolver(np.ascontiguousarray(H[sub]).copy())
    if solver.regularizer is not None:
        from .regularization import Regularizer

        reg = Regularizer(solver.regularizer.kind, small.nodes_shape, solver.regularizer.ell)
        small.regularize(reg, solver.weight)
    from .solve import stencil_matvec

    shape = small.nodes_shape
    exact = np.zeros(shape + (3,))
    grid = np.indices(shape)
    p = PROBE_PERIOD
    for cz in range(p):
        for cy in range(p):
            for cx in range(p):
                sel = (grid[0] % p == cz) & (grid[1] % p == cy) & (grid[2] % p == cx)
                if not sel.any():
                    continue
                for j in range(3):
                    e = np.zeros(shape + (3,))
                    e[sel, j] = 1.0
                    x = small.solve(e)[0]
                    y = small.solve(stencil_matvec(small.matrix, x))[0]
                    exact[sel, j] = y[sel, j]
    ratio = exact / np.maximum(local_diag[sub], 1e-300)
    inner = tuple(slice(1, -1) if k > 2 else slice(None) for k in shape)
    c = float(np.median(ratio[inner])) if ratio[inner].size else 1.0
    var = float(kappa) * float(noise_variance) * c * local_diag
    return np.sqrt(np.moveaxis(var, -1, 0))
