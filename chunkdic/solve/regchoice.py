"""The automatic regularisation length: Morozov's discrepancy principle on the client.

Once the correlated level has converged without knowing ``ℓ_reg``, :func:`choose_length`
picks the longest candidate length whose linearised data-misfit increase the noise can
explain (docs/engine.md, "Automatic length"). Mesh-sized work only (sub-meshes of at most
:data:`CHOICE_EDGE`³ nodes), no voxels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .regularization import Regularizer, plane_wave_weight
from .stencil import stencil_matvec


#: candidate lengths of the automatic choice, in element sizes (geometric, 1 to 32)
CANDIDATES = tuple(float(2.0 ** (k / 2)) for k in range(0, 11))
#: the automatic choice looks at the central sub-mesh of at most this many nodes per axis
CHOICE_EDGE = 24


@dataclass
class Choice:
    """Outcome of :func:`choose_length`.

    Attributes
    ----------
    length : float
        The chosen ``ℓ_reg``, voxels of the level.
    weight : float
        Its ``λ``.
    lengths, misfit, roughness : ndarray
        The candidates (voxels), the linearised data misfit increase ``Φ(λ) - Φ_0``
        (grey levels²) and ``aᵀ R a`` of each (the L-curve).
    budget : float
        The misfit increase the noise can explain: ``κ σ_r² · 3 N`` (grey levels²).
    l_curve_length : float
        The candidate at the L-curve's corner (largest curvature of ``(log Φ, log Ψ)``),
        for comparison.
    """

    length: float
    weight: float
    lengths: np.ndarray
    misfit: np.ndarray
    roughness: np.ndarray
    budget: float
    l_curve_length: float


def regions(shape, edge: int = None) -> list[tuple[slice, slice, slice]]:
    """Sub-meshes of at most ``edge`` nodes per axis where the automatic choice looks.

    Per axis: the whole axis when it fits; one central box when it is less than 1.5 boxes
    long (two boxes would overlap by more than half and see the same field); otherwise two
    boxes centred on the axis's quarters. Up to 8 boxes, so that a feature anywhere in the
    ROI is seen.
    """
    edge = CHOICE_EDGE if edge is None else edge
    per_axis = []
    for n in shape:
        if n <= edge:
            per_axis.append([slice(0, n)])
            continue
        centres = (n / 2,) if n < 1.5 * edge else (n / 4, 3 * n / 4)
        starts = [max(min(int(round(c - edge / 2)), n - edge), 0) for c in centres]
        per_axis.append([slice(a, a + edge) for a in starts])
    return [(a, b, c) for a in per_axis[0] for b in per_axis[1] for c in per_axis[2]]


def choose_length(kind: str, half: np.ndarray, ell: float, a: np.ndarray, b: np.ndarray,
                  noise_variance: float, solve_with, *, sweep: bool = False) -> Choice:
    """The regularisation length by the discrepancy principle, on the client.

    At a converged field ``a`` with right-hand side ``b``, the data misfit of a field
    ``a + Δ`` is, to second order, ``Φ_0 - 2 bᵀΔ + Δᵀ M Δ`` (modified Gauss–Newton). For each
    candidate length the field minimising that misfit plus ``λ aᵀ R a`` is one solve of
    ``(M + λ R) a' = M a + b``. Noise alone explains a misfit increase of ``κ σ_r²`` per
    unknown (a fitted unknown absorbs that much of the noise, :mod:`chunkdic.engine.noise`): the
    longest length whose increase stays within ``κ σ_r² · 3 N`` is chosen (Morozov's
    discrepancy principle). A smooth field (a translation, a homogeneous strain) then gets
    a long length, a field with short features (a band) a short one. It is evaluated on
    each of :func:`regions` and the shortest length wins (a feature anywhere is kept).

    The misfit grows with ``λ`` (a larger penalty moves the minimiser further from the
    data), so the longest admissible candidate is found by bisection: 3 to 5 solves per
    region instead of 11, and a later region only searches below the best so far. Solves
    at long lengths are the slow ones (block-Jacobi CG needs ~45× more iterations at 32ℓ
    than at ℓ on a 24³ sub-mesh, measured; the multigrid preconditioner that
    :class:`~chunkdic.solve.cg.StencilSolver` switches to there still costs ~5× a
    block-Jacobi iteration), so the search starts in the middle; starting
    CG from the solution of a neighbouring candidate did not save iterations (measured:
    the slow modes are the smooth ones the two solutions differ by).

    Parameters
    ----------
    kind : {"tikhonov", "equilibrium-gap"}
    half : ndarray, shape (nz, ny, nx, 14, 3, 3)
        The half stencil of ``M`` (:mod:`chunkdic.solve.cg`).
    ell : float
        Element size, voxels of the level.
    a, b : ndarray, shape (nz, ny, nx, 3)
        Converged field and its right-hand side.
    noise_variance : float
        What one fitted unknown absorbs from the noise: ``κ σ_r²``, grey levels²
        (:mod:`chunkdic.engine.noise`).
    solve_with : callable
        ``solve_with(half, regularizer, weight, rhs) -> x``: the solver of ``(M + λ R) x = rhs``.
        Every call of one region passes the same ``half`` and ``regularizer`` objects, so
        it may keep a solver per region (the engine does: the coarse ``M`` of the V-cycle
        are built once per region).
    sweep : bool
        Solve every candidate on every region (the whole L-curve, and its corner in
        :attr:`Choice.l_curve_length`) instead of bisecting; for benchmarks.

    Returns
    -------
    Choice
        For the region that decided. Candidates the bisection did not solve have NaN
        misfit and roughness; ``l_curve_length`` is NaN unless ``sweep``.
    """
    lengths = np.array([c * ell for c in CANDIDATES])
    best, best_index = None, len(lengths) - 1
    for sub in regions(half.shape[:3]):
        if best_index == 0 and not sweep:
            break  # the shortest candidate already: no region can choose shorter
        H = np.ascontiguousarray(half[sub])
        reg = Regularizer(kind, H.shape[:3], ell)
        matvec = lambda v, H=H: stencil_matvec(H, v)  # noqa: E731
        a_s, b_s = np.ascontiguousarray(a[sub]), np.ascontiguousarray(b[sub])
        rhs = matvec(a_s) + b_s
        misfit, rough = np.full(len(lengths), np.nan), np.full(len(lengths), np.nan)

        def evaluate(i: int) -> float:
            x = solve_with(H, reg, plane_wave_weight(reg, matvec, lengths[i]), rhs)
            d = x - a_s
            misfit[i] = float(-2.0 * np.sum(b_s * d) + np.sum(d * matvec(d)))
            rough[i] = float(np.sum(x * reg.apply(x)))
            return misfit[i]

        budget = float(noise_variance) * 3 * int(np.prod(H.shape[:3]))
        base = evaluate(0)
        if sweep:
            for i in range(1, len(lengths)):
                evaluate(i)
            ok = np.flatnonzero(misfit - base <= budget)
            pick = int(ok.max())
        else:
            # The first region starts in the middle (the slow long-length solves only when
            # needed); a later one first tries the best so far: one solve when it is no stricter.
            pick = _longest_within(lambda i: evaluate(i) - base <= budget, best_index + 1,
                                   len(lengths) // 2 if best is None else best_index)
        if best is None or pick < best_index:
            corner = float(lengths[_corner(misfit - base, rough)]) if sweep else math.nan
            best, best_index = Choice(float(lengths[pick]), 0.0, lengths, misfit, rough, budget, corner), pick
    full = Regularizer(kind, half.shape[:3], ell)
    best.weight = plane_wave_weight(full, lambda v: stencil_matvec(half, v), best.length)
    return best


def _longest_within(admissible, stop: int, first: int) -> int:
    """Largest ``i < stop`` with ``admissible(i)``, given ``admissible(0)`` and that it is monotone.

    Bisection whose first probe is ``first``.
    """
    lo, hi, probe = 0, stop, first
    while hi - lo > 1:
        if admissible(probe):
            lo = probe
        else:
            hi = probe
        probe = (lo + hi) // 2
    return lo


def _corner(misfit: np.ndarray, rough: np.ndarray) -> int:
    """Index of the largest curvature of the L-curve ``(log misfit, log roughness)``."""
    x = np.log(np.maximum(misfit, max(1e-30 * float(misfit.max()), 1e-300)))  # no log(0)
    y = np.log(np.maximum(rough, 1e-300))
    if len(x) < 3:
        return 0
    dx, dy = np.gradient(x), np.gradient(y)
    ddx, ddy = np.gradient(dx), np.gradient(dy)
    kappa = (dx * ddy - dy * ddx) / np.maximum((dx * dx + dy * dy) ** 1.5, 1e-30)
    return int(np.argmax(kappa[1:-1]) + 1)
