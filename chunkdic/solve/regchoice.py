"""The automatic regularisation length, chosen on the client.

Once the correlated level has converged without knowing ``ℓ_reg``, :func:`choose_length`
picks one of :data:`CANDIDATES` by one of :data:`RULES` (docs/engine.md, "Automatic
length"): by default Morozov's discrepancy principle (``"discrepancy"``), or the length
of least *predicted* total error (``"upre"``: the linearised misfit plus twice the noise
that the field's remaining degrees of freedom absorb, Mallows' C_L / the unbiased
predictive risk), among others compared in docs/engine.md. Mesh-sized work only
(sub-meshes of at most :data:`CHOICE_EDGE`³ nodes), no voxels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..mesh import STENCIL_OFFSETS
from .regularizer import Regularizer, plane_wave_weight
from .cg import z_slabs
from .stencil import stencil_matvec

#: candidate lengths of the automatic choice, in element sizes (geometric, 1 to 32)
CANDIDATES = tuple(float(2.0 ** (k / 2)) for k in range(0, 11))
#: the criteria :func:`choose_length` knows (docs/engine.md, the comparison); :data:`DEFAULT_RULE` is the default
RULES = ("discrepancy-texture", "upre", "discrepancy", "discrepancy-half", "discrepancy-kinks", "gcv", "l-curve")
#: the engine's default (:class:`chunkdic.method.settings.Settings` ``regularization_rule``):
#: the predicted risk measured better on translations at ℓ = 8 (2×) and level on
#: heterogeneous fields, but chose too short at ℓ = 4 on pure noise (docs/engine.md)
DEFAULT_RULE = "discrepancy-texture"
#: ``"discrepancy-texture"``: the share of the noise budget a feature's smoothing may take is
#: the texture's evenness (:func:`texture_evenness`) to this power, and at least
#: :data:`EVENNESS_FLOOR` (docs/engine.md, "The regularisation length on a coarse texture")
EVENNESS_EXPONENT = 0.5
EVENNESS_FLOOR = 0.2
#: ``"discrepancy-texture"``: below this share (most elements small against the texture's
#: features: 0.32–0.35 at ℓ = 4 on textures of 9 and 23 voxels, 0.405 and up elsewhere) the noise's
#: own misfit increase outgrows the share at 2ℓ already, and a longer length is admitted too
#: when the noise explains its misfit increase (:func:`noise_misfit`; docs/engine.md, "The
#: regularisation length on a coarse texture")
NOISE_EXPLAINED_SHARE = 0.4
#: ``"discrepancy-texture"`` under a large deformation: the misfit increase, in noise budgets,
#: that the longest candidate may give up at ℓ = 8 with no feature bounding the length; at
#: other element sizes this times ``(ℓ / 8)²`` (:func:`large_deformation_tolerance`). There the
#: imaging's mismatch (the partial volume and blur of the few edges of a coarse texture, which
#: do not deform with the material) is fitted by short lengths as a feature would be: 10 % and
#: 20 % compression on textures of 12–24 voxels give up at most 1.2 budgets at ℓ = 8, 2.4 at
#: 12 and 4.2 at 16, the best fixed length being the longest. The least a feature gives up
#: (waves, bands, slips, cracks) is 4.25 at ℓ = 8, 8.9 at 12 and 14 at 16 (7–8 for a 24-voxel
#: wave at 16, which no length resolves), 2.4 at 6 and 1.1 at 4: both grow about as ℓ^1.8,
#: the mismatch being a misfit per voxel and the budget one per degree of freedom. A −20 %
#: band 48 voxels wide, itself a large deformation, gives up 7–116 but on the coarsest grains
#: (1.2 at ℓ = 8: :data:`ACCELERATION` tells it) (docs/engine.md, "The regularisation length
#: on a coarse texture")
LARGE_DEFORMATION_TOLERANCE = 2.5
#: ``"discrepancy-texture"``: how many times its misfit increase over the mean texture's
#: weight a feature's smoothing costs in voxels² (:func:`least_voxel_error`); the smoothing
#: sits where the texture is weak, and the misfit shows it there weakly. Measured on the first
#: choices of 130 cases (waves of period 24–64, a band, a slip, a crack; grains and concrete at
#: texture scales 2 and 4; ℓ = 4–16): 5.5–6.5 leave at most 5 cases above 1.15 of the best
#: fixed length's error (at most 1.25), 4 or 8 leave 8–9 (up to 1.45), the share alone 11 (up
#: to 1.96) (docs/engine.md, "The least error in voxels")
BIAS_WEIGHT = 6.0
#: ... unless the misfit accelerates: a √2 step of the length costs at least this many times the
#: step before it (of at least :data:`ACCELERATION_FLOOR` budgets). Smoothing a feature costs a
#: misfit that grows as a power of the length (the penalty weighs ``(ℓ_reg / T)⁴``) until it is
#: gone: 2.7–5.3 on the −20 % band 48 voxels wide, also where its whole misfit stays within 1.3
#: budgets (grains at texture scale 4.5, ℓ = 8); what the degrees of freedom absorb, noise and
#: the imaging's mismatch, grows by at most 1.73 per step on 10–20 % compression at ℓ = 8–16
ACCELERATION = 2.0
ACCELERATION_FLOOR = 0.05
#: ``"discrepancy-kinks"``: in the choice after a robust reweighting, an unknown within one
#: node of a freed term counts this many times in the noise budget (docs/engine.md, "The
#: slip: a budget for the kinks' model error")
KINK_WEIGHT = 2.0
#: frequencies per axis of the Fourier estimate of the degrees of freedom (:func:`dof_fraction`)
DOF_FREQUENCIES = 12
#: the automatic choice looks at sub-meshes of at most this many nodes per axis ...
CHOICE_EDGE = 24
#: ... and at most this many of them (:func:`regions`, :func:`feature_regions`)
MAX_REGIONS = 8


@dataclass
class Choice:
    """Outcome of :func:`choose_length`.

    Attributes
    ----------
    length : float
        The chosen ``ℓ_reg``, voxels of the level (its ``λ`` on the whole mesh:
        :func:`~chunkdic.solve.regularizer.plane_wave_weight`).
    lengths, misfit, roughness : ndarray
        The candidates (voxels), the linearised data misfit increase ``Φ(λ) - Φ_0``
        (grey levels²) and ``aᵀ R a`` of each (the L-curve).
    budget : float
        The misfit increase the noise can explain: ``κ σ_r² · 3 N`` (grey levels²;
        ``"discrepancy-kinks"`` after a reweighting: ``N`` counts the nodes near a freed
        term :data:`KINK_WEIGHT` times).
    l_curve_length : float
        The candidate at the L-curve's corner (largest curvature of ``(log Φ, log Ψ)``),
        for comparison.
    rule : str
        The rule that chose (:data:`RULES`).
    curves : list of dict
        With ``sweep``: per region, ``misfit`` (increase over the shortest candidate),
        ``roughness``, ``penalty`` (the risk's trace term ``2 s² tr(A⁻¹M)``, ``s² = κ σ_r²``
        (``σ_r²`` for ``"gcv"``), whatever the rule), ``budget``.
    """

    length: float
    lengths: np.ndarray
    misfit: np.ndarray
    roughness: np.ndarray
    budget: float
    l_curve_length: float
    rule: str = DEFAULT_RULE
    curves: list = field(default_factory=list)


def regions(shape, edge: int = None) -> list[tuple[slice, slice, slice]]:
    """Sub-meshes of at most ``edge`` nodes per axis where the automatic choice looks.

    Per axis: the whole axis when it fits; one central box when it is less than 1.5 boxes
    long (two boxes would overlap by more than half and see the same field); otherwise two
    boxes centred on the axis's quarters. Up to 8 boxes; from 48 nodes on an axis they leave
    its middle out (:func:`regions_cover`), and the engine places its boxes on the misfit
    instead (:func:`feature_regions`).
    """
    edge = CHOICE_EDGE if edge is None else edge
    per_axis = [_axis_boxes(n, edge) for n in shape]
    return [(a, b, c) for a in per_axis[0] for b in per_axis[1] for c in per_axis[2]]


def _axis_boxes(n: int, edge: int) -> list[slice]:
    """:func:`regions`' boxes along one axis of ``n`` nodes, in increasing order."""
    if n <= edge:
        return [slice(0, n)]
    centres = (n / 2,) if n < 1.5 * edge else (n / 4, 3 * n / 4)
    starts = [max(min(int(round(c - edge / 2)), n - edge), 0) for c in centres]
    return [slice(a, a + edge) for a in starts]


def regions_cover(shape, edge: int = None) -> bool:
    """Whether :func:`regions` leave no element out between two of their boxes along any axis
    (the axis's ends may lie outside, as where one central box is used: the field is scored
    away from the faces). Up to 47 nodes per axis they do; from 48 on (a 400³ ROI at ℓ = 8, a
    2048³ scan at any supported size) the quarters' boxes leave the middle out, and a feature
    there is not seen: with a slip across the middle of a 300³ grains pair as the field's only
    feature (ℓ = 6) the choice takes the longest length, 192 voxels, and the run diverges."""
    edge = CHOICE_EDGE if edge is None else edge
    # element k joins nodes k and k + 1: a box's last element is stop - 2, so the next box
    # must start at stop - 1 at the latest
    return all(b.start <= a.stop - 1 for boxes in (_axis_boxes(n, edge) for n in shape)
               for a, b in zip(boxes, boxes[1:]))


def feature_regions(score: np.ndarray, edge: int = None, count: int = MAX_REGIONS) -> list[tuple[slice, slice, slice]]:
    """Up to ``count`` sub-meshes of at most ``edge`` nodes per axis, centred where a per-node
    ``score`` (nz, ny, nx) is highest: the box whose sum of the score, weighted by a half sine
    along each axis (1 in the middle, 0 at the faces), is largest, then the largest among
    those that overlap no box taken by more than half its extent along every axis.

    The engine's score is each node's share of the misfit increase that a longer length than
    the level's gives on the whole mesh (:func:`chunkdic.method.length.misfit_map`): a
    feature's smoothing concentrates there, the noise's spreads evenly, so the first box holds
    the feature that bounds the length wherever it lies, away from the box's faces (where the
    sub-mesh's free boundary would fit it). Box corners are searched on a grid of a quarter
    of ``edge`` (and the last corner of each axis), one axis at a time: no array larger than
    the score is made.
    """
    edge = CHOICE_EDGE if edge is None else edge
    size = tuple(min(n, edge) for n in score.shape)
    corners = [np.unique(np.r_[np.arange(0, n - e, max(e // 4, 1)), n - e]) for n, e in zip(score.shape, size)]
    sums = np.asarray(score, dtype=np.float64)
    for axis, (starts, e) in enumerate(zip(corners, size)):
        taper = np.sin(np.pi * (np.arange(e) + 0.5) / e)
        sums = np.stack([np.tensordot(taper, np.take(sums, np.arange(c, c + e), axis=axis), axes=(0, axis))
                         for c in starts], axis=axis)
    free = np.ones(sums.shape, bool)
    boxes = []
    while len(boxes) < count and free.any():
        k = np.unravel_index(np.argmax(np.where(free, sums, -np.inf)), sums.shape)
        corner = [int(c[i]) for c, i in zip(corners, k)]
        boxes.append(tuple(slice(c, c + e) for c, e in zip(corner, size)))
        near = [np.abs(c - start) * 2 < e for c, start, e in zip(corners, corner, size)]
        free &= ~(near[0][:, None, None] & near[1][None, :, None] & near[2][None, None, :])
    return boxes


def choose_length(kind: str, half: np.ndarray, ell: float, a: np.ndarray, b: np.ndarray,
                  noise_variance: float, solve_with, *, rule: str = DEFAULT_RULE, kappa: float = 1.0,
                  sweep: bool = False, freed: np.ndarray | None = None, guess: float | None = None,
                  large_deformation: bool = False, boxes: list | None = None) -> Choice:
    """The regularisation length by ``rule``, on the client.

    At a converged field ``a`` with right-hand side ``b``, the data misfit of a field
    ``a + Δ`` is, to second order, ``Φ_0 - 2 bᵀΔ + Δᵀ M Δ`` (modified Gauss–Newton). For each
    candidate length the field minimising that misfit plus ``λ aᵀ R a`` is one solve of
    ``(M + λ R) a' = M a + b``; its misfit increase ``D(λ)`` over the data fit is what the
    rules weigh. A fitted unknown absorbs ``s² = κ σ_r²`` of the misfit from the noise
    (:mod:`chunkdic.method.noise`), ``N`` unknowns in all:

    ``"upre"``
        The least predicted mean-square error of the field in the data norm:
        ``E‖x_λ - u‖²_M = D(λ) + 2 s² tr(A⁻¹M) + const`` (``A = M + λR``; Mallows' C_L, the
        unbiased predictive risk), the trace estimated from the sub-mesh's mean stencils
        (:func:`dof_fraction`). Noise alone: the risk falls with the length (longest
        candidate); a field with short features: the misfit rises and the minimum is short.
    ``"gcv"``
        The same with white noise (``s² = σ_r²``, i.e. ``κ = 1``): what generalised
        cross-validation reduces to when the voxels far outnumber the unknowns.
    ``"discrepancy-texture"`` (default)
        Morozov's principle as ``"discrepancy"`` below, but where a feature bounds the length
        (a longer candidate exceeds the budget), the longest length whose misfit increase
        stays within :func:`feature_share` of the budget: on an uneven texture the misfit
        sees a small part of the error a long length makes where the texture is weak; on the
        most uneven, also within what the noise explains (:func:`feature_allowance`); then,
        up to the discrepancy's length, the least predicted error in voxels
        (:func:`least_voxel_error`), where the weakly textured nodes' noise outweighs. Where
        no candidate exceeds the budget (noise only, a uniform or linear field), the longest;
        for a reweighted penalty (``freed``), the discrepancy, but below
        :data:`NOISE_EXPLAINED_SHARE` the same allowance. Under a ``large_deformation``, with
        or without ``freed``, a candidate over budget bounds the length only where the misfit
        says a feature (:func:`no_feature`); otherwise the longest.
    ``"discrepancy"``, ``"discrepancy-half"``
        Morozov's principle: the longest length with ``D(λ) - D(ℓ) <= τ s² N``, ``τ`` = 1
        or 1/2 (a safety factor).
    ``"discrepancy-kinks"``
        The discrepancy, except that in the choice for a reweighted penalty (``freed``) the
        unknowns of the nodes within one node of a freed term (:func:`near_freed`) count
        :data:`KINK_WEIGHT` times in ``N``: there the misfit a longer length gives up is
        mostly the C8 basis's error on the kink (a slip or a band's edge inside an
        element, fitted where the texture is strong), which the plain rule counts as signal.
        Without freed terms, the discrepancy.
    ``"l-curve"``
        The corner of ``(log D, log aᵀRa)`` over all candidates (implies ``sweep``).

    Each rule is applied on each sub-mesh, :func:`regions` or ``boxes``, and the shortest
    length wins (a feature anywhere is kept). Monotone (discrepancy) or unimodal (risk) in the length,
    so the engine searches: bisection, or a ternary search, a later region only below
    the best so far. Solves at long lengths are the slow ones (block-Jacobi CG needs ~45×
    more iterations at 32ℓ than at ℓ on a 24³ sub-mesh; the multigrid preconditioner that
    :class:`~chunkdic.solve.cg.StencilSolver` switches to there still costs ~5× a
    block-Jacobi iteration).

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
        (:mod:`chunkdic.method.noise`).
    solve_with : callable
        ``solve_with(half, regularizer, weight, rhs) -> x``: the solver of ``(M + λ R) x = rhs``.
        Every call of one region passes the same ``half`` and ``regularizer`` objects, so
        it may keep a solver per region (the engine does: the coarse ``M`` of the V-cycle
        are built once per region).
    rule : str
        One of :data:`RULES`.
    kappa : float
        The noise correlation factor ``κ`` (``"gcv"`` only: ``σ_r² = noise_variance / κ``).
    sweep : bool
        Solve every candidate on every region (the whole L-curve, and its corner in
        :attr:`Choice.l_curve_length`, and each region's curves in :attr:`Choice.curves`)
        instead of searching; for benchmarks. Same choice.
    freed : ndarray, shape (nz, ny, nx, 6), uint8, optional
        Tikhonov terms left out by the robust reweighting
        (:attr:`~chunkdic.solve.regularizer.Regularizer.freed`): the length is chosen for
        the reweighted penalty, ``λ`` normalised on the plain one as always.
    guess : float, optional
        A length (voxels of the level) the choice is expected near: the length the level
        iterated with before the choice, or the plain penalty's choice before a reweighting.
        The discrepancy's search probes it first, then walks up from it in growing steps, or
        bisects below it when it fails (fewer slow long-length solves; the same choice, the
        misfit being monotone in the length).
    large_deformation : bool
        The field is a large deformation (:data:`chunkdic.method.length.LARGE_GRADIENT`):
        ``"discrepancy-texture"`` then takes a curve over budget for a feature only where
        :func:`no_feature` does not hold (every candidate solved, only then).
    boxes : list of tuple of 3 slice, optional
        The sub-meshes to look at (default :func:`regions`; the engine's, where those leave
        elements out: :func:`feature_regions`).

    Returns
    -------
    Choice
        For the region that decided. Candidates not solved have NaN misfit and roughness;
        ``l_curve_length`` is NaN unless ``sweep``.
    """
    if rule not in RULES:
        raise ValueError(f"unknown regularisation length rule {rule!r} (known: {', '.join(RULES)})")
    sweep = sweep or rule == "l-curve"
    lengths = np.array([c * ell for c in CANDIDATES])
    near = near_freed(freed) if rule == "discrepancy-kinks" and freed is not None else None
    large_deformation = large_deformation and rule == "discrepancy-texture"
    best, best_index, curves = None, len(lengths) - 1, []
    for sub in regions(half.shape[:3]) if boxes is None else boxes:
        if best_index == 0 and not sweep:
            break  # the shortest candidate already: no region can choose shorter
        H = np.ascontiguousarray(half[sub])
        reg = Regularizer(kind, H.shape[:3], ell, None if freed is None else freed[sub])
        matvec = lambda v, H=H: stencil_matvec(H, v)  # noqa: E731
        a_s, b_s = np.ascontiguousarray(a[sub]), np.ascontiguousarray(b[sub])
        rhs = matvec(a_s) + b_s
        misfit, rough = np.full(len(lengths), np.nan), np.full(len(lengths), np.nan)
        unit = plane_wave_weight(reg, matvec, 1.0)  # λ ∝ length^order
        weights = unit * lengths ** reg.order

        def evaluate(i: int) -> float:
            if np.isnan(misfit[i]):
                x = solve_with(H, reg, weights[i], rhs)
                d = x - a_s
                misfit[i] = float(-2.0 * np.sum(b_s * d) + np.sum(d * matvec(d)))
                rough[i] = float(np.sum(x * reg.apply(x)))
            return misfit[i]

        n_unknowns = 3 * int(np.prod(H.shape[:3]))
        counted = n_unknowns if near is None else n_unknowns + 3 * (KINK_WEIGHT - 1.0) * int(near[sub].sum())
        budget = float(noise_variance) * counted
        tau = 0.5 if rule == "discrepancy-half" else 1.0
        # the choice for a reweighted penalty keeps the whole budget: the features its freed
        # terms leave (a slip's or a band's flanks) are the smooth fields a long length suits;
        # not on the most uneven textures, where the whole budget has no bound below the longest
        share = feature_share(H) if rule == "discrepancy-texture" else 1.0
        if freed is not None and share >= NOISE_EXPLAINED_SHARE:
            share = 1.0
        if rule in ("upre", "gcv") or sweep:
            # A sweep keeps the risk's trace term whatever the rule, so that a benchmark can
            # apply every rule to its curves (with the penalty left at zero, "upre" applied
            # to a discrepancy sweep's curves picked the shortest candidate on every case).
            s2 = float(noise_variance) / (float(kappa) if rule == "gcv" else 1.0)
            penalty = 2.0 * s2 * n_unknowns * dof_fraction(H, reg, weights)
            risk = lambda i: evaluate(i) + penalty[i]  # noqa: E731
        else:
            penalty = np.zeros(len(lengths))
        base = evaluate(0)

        def over_budget(pick: int, increase) -> int:
            # a longer candidate than ``pick`` was solved and went over budget: under a large
            # deformation the longest unless the misfit says a feature (no_feature); a feature
            # bounds the length, and its smoothing may take only the texture's share of the
            # budget (feature_share), or on the most uneven textures what the noise alone explains
            if large_deformation and no_feature(increase, best_index, budget, ell):
                return best_index
            if share < 1.0:
                allowed = feature_allowance(share, budget, H, reg, weights, noise_variance, n_unknowns)
                short = _longest_within(lambda i: increase(i) <= allowed[i], pick + 1, pick)
                if short == pick:
                    return pick  # nothing between the two lengths to weigh
                return least_voxel_error(short, pick, increase, budget, *noise_in_voxels(H, reg, weights))
            return pick
        if sweep:
            for i in range(1, len(lengths)):
                evaluate(i)
            if rule in ("upre", "gcv"):
                pick = int(np.argmin((misfit + penalty)[:best_index + 1]))
            elif rule == "l-curve":
                pick = min(_corner(misfit - base, rough), best_index)
            else:
                pick = int(np.flatnonzero(misfit[:best_index + 1] - base <= tau * budget).max())
                if pick + 1 < len(lengths) and misfit[pick + 1] - base > tau * budget:
                    pick = over_budget(pick, lambda i: misfit[i] - base)
            curves.append({"misfit": misfit - base, "roughness": rough, "penalty": penalty, "budget": budget,
                           "share": share})
        elif rule in ("upre", "gcv"):
            pick = _least(risk, best_index + 1)
        else:
            # The first region starts at the guess, or in the middle without one; a later one
            # first tries the best so far: one solve when it is no stricter. From a guess (the
            # level's length so far, or the plain penalty's choice before a reweighting, which
            # frees terms and so only lengthens the choice) the search walks up in growing steps
            # and bisects below a failed probe: the far probe of a bisection is the slowest solve
            # of all (on the 300³ band, ℓ = 12: 0.85 of the reweighting's 1.5 s, a V-cycle at
            # 32ℓ, for a choice two candidates up; 0.16 of the plain choice's 0.31 s at 4√2 ℓ).
            first = len(lengths) // 2 if guess is None else int(np.argmin(np.abs(np.log(lengths / guess))))
            pick = _longest_within(lambda i: evaluate(i) - base <= tau * budget, best_index + 1,
                                   first if best is None else best_index, walk=guess is not None)
            if pick + 1 <= best_index and evaluate(pick + 1) - base > tau * budget:
                pick = over_budget(pick, lambda i: evaluate(i) - base)
        if best is None or pick < best_index:
            corner = float(lengths[_corner(misfit - base, rough)]) if sweep else math.nan
            best, best_index = Choice(float(lengths[pick]), lengths, misfit, rough, budget, corner), pick
    best.rule, best.curves = rule, curves
    return best


def large_deformation_tolerance(ell: float) -> float:
    """The misfit increase, in noise budgets, the longest candidate may give up under a large
    deformation with no feature bounding the length, at element size ``ell`` (voxels):
    :data:`LARGE_DEFORMATION_TOLERANCE` at ℓ = 8, growing as ℓ²."""
    return LARGE_DEFORMATION_TOLERANCE * (ell / 8.0) ** 2


def no_feature(increase, last: int, budget: float, ell: float) -> bool:
    """Under a large deformation, whether the misfit increase over the shortest candidate,
    ``increase(i)`` for candidates ``i <= last`` (grey levels²), is what the fitted degrees of
    freedom absorb and give back rather than a feature's: at most
    :func:`large_deformation_tolerance` budgets at ``last``, and no step of the length costing
    :data:`ACCELERATION` times the one before it (steps of at least :data:`ACCELERATION_FLOOR`
    budgets). Solves every candidate up to ``last`` when the first test passes."""
    if increase(last) > large_deformation_tolerance(ell) * budget:
        return False
    steps = np.diff([increase(i) for i in range(last + 1)])
    return not any(b >= ACCELERATION * a for a, b in zip(steps[:-1], steps[1:]) if a >= ACCELERATION_FLOOR * budget)


def texture_evenness(half: np.ndarray) -> float:
    """How evenly the texture covers the nodes: the geometric over the arithmetic mean of the
    nodes' texture (the trace of their diagonal block of ``M``) over the inner nodes, in (0, 1].

    Near 1 where every element holds texture (a fine texture at a large ``ℓ``: 0.94–0.97 on
    the CT-like specimens at ℓ = 12–16); small where many nodes see little of it and a few
    see much (elements small against the texture's features: 0.45–0.47 at ℓ = 4 on the same
    specimens; docs/engine.md, "The regularisation length on a coarse texture"). Traces below 1e-3 of the mean
    (air, a pore) count as 1e-3 of it.

    Parameters
    ----------
    half : ndarray, shape (nz, ny, nx, 14, 3, 3)
        The half stencil of ``M``.
    """
    trace = np.trace(half[..., 0, :, :], axis1=-2, axis2=-1).astype(np.float64)
    inner = tuple(slice(1, n - 1) if n > 2 else slice(None) for n in trace.shape)
    t = trace[inner].ravel()
    mean = float(t.mean())
    if not mean > 0:
        return 1.0
    return float(np.exp(np.mean(np.log(np.maximum(t, 1e-3 * mean)))) / mean)


def feature_share(half: np.ndarray) -> float:
    """The share of the noise budget that smoothing a feature may take in the
    ``"discrepancy-texture"`` rule: :func:`texture_evenness` to :data:`EVENNESS_EXPONENT`,
    at least :data:`EVENNESS_FLOOR`, at most 1.

    Why: the misfit of a smoothed feature is its error weighted by the texture, and a length
    smooths most where the texture is weakest (there the penalty outweighs the data). Where
    the texture is uneven the misfit sees a small part of the error the field makes, so
    Morozov's budget, right on an even texture, lets the length grow too long (measured:
    docs/engine.md, "The regularisation length on a coarse texture").
    """
    return float(min(1.0, max(EVENNESS_FLOOR, texture_evenness(half) ** EVENNESS_EXPONENT)))


def least_voxel_error(short: int, pick: int, increase, budget: float, noise: np.ndarray, m0: float) -> int:
    """Between the share's choice ``short`` and the discrepancy's ``pick`` (candidate indices),
    the candidate of least predicted error in voxels, as the field is scored: the smoothing's
    error, :data:`BIAS_WEIGHT` times what its misfit increase ``increase(i)`` (grey levels²)
    shows through the mean texture ``m0``, plus the noise the field keeps
    (:func:`noise_in_voxels`, ``noise`` per unknown and per ``s²``), both in units of
    ``budget / m0``.

    Why: the share stops where the misfit sees little of a feature's smoothing, but the noise
    the field keeps in voxels is dominated by the weakly textured nodes and falls about 2.5×
    per √2 step of the length there: where those nodes are many (elements small against a
    coarse texture) a longer length buys more in noise than it costs in bias (docs/engine.md,
    "The least error in voxels").
    """
    risk = [BIAS_WEIGHT * increase(i) / budget + m0 * noise[i] for i in range(short, pick + 1)]
    return short + int(np.argmin(risk))


def near_freed(freed: np.ndarray) -> np.ndarray:
    """The nodes within one node, along every axis, of a freed term's anchor.

    Parameters
    ----------
    freed : ndarray, shape (nz, ny, nx, 6), uint8
        :attr:`~chunkdic.solve.regularizer.Regularizer.freed`.

    Returns
    -------
    ndarray, shape (nz, ny, nx), bool
        Mesh-sized (1 B per node).
    """
    from scipy.ndimage import binary_dilation

    return binary_dilation(freed.any(axis=-1), structure=np.ones((3, 3, 3), bool))


def feature_allowance(share: float, budget: float, half: np.ndarray, reg: Regularizer, weights,
                      noise_variance: float, n_unknowns: int) -> np.ndarray:
    """The misfit increase (grey levels²) the ``"discrepancy-texture"`` rule admits for each
    candidate once a feature bounds the length: the texture's ``share`` of the ``budget``, and
    below :data:`NOISE_EXPLAINED_SHARE` at least the noise's own increase
    (:func:`noise_misfit`).

    Why: where the elements are small against the texture's features (ℓ = 4 on textures of
    9 and 23 voxels, ``share`` 0.32–0.35) the noise alone raises the misfit past the share at
    2ℓ, and the share alone stops at 2ℓ on every field of a 23-voxel texture, where the best
    fixed length is 3–6ℓ and its error 1.5–2.3× lower on the band, slip, crack and longer
    waves (docs/engine.md, "The regularisation length on a coarse texture").
    """
    allowed = np.full(len(weights), share * budget)
    if share < NOISE_EXPLAINED_SHARE:
        allowed = np.maximum(allowed, noise_misfit(half, reg, weights, noise_variance, n_unknowns))
    return allowed


def noise_misfit(half: np.ndarray, reg: Regularizer, weights, noise_variance: float, n_unknowns: int) -> np.ndarray:
    """The misfit increase the noise explains at each weight of ``weights`` over the first,
    grey levels², by the discrepancy budget's own accounting (a fitted unknown absorbs ``s²``,
    one the penalty takes over gives it back): ``s² · 3N · (f(λ_0) − f(λ))`` with ``f`` the
    fraction of degrees of freedom the data still set (:func:`dof_fraction`), half the drop of
    the ``"upre"`` risk's trace term. Where ``λ_0`` leaves the data nearly every degree of
    freedom it is at least pure noise's expected increase, ``s² Σ (1 − h)²`` over the
    eigenvalues ``h`` of ``(M + λR)⁻¹ M``."""
    dof = dof_fraction(half, reg, weights)
    return float(noise_variance) * n_unknowns * (dof[0] - dof)


def dof_fraction(half: np.ndarray, reg: Regularizer, weights) -> np.ndarray:
    """``tr((M + λR)⁻¹ M) / 3N`` for each ``λ`` of ``weights``: the fraction of the field's
    degrees of freedom the data still set (1 unregularised, → 0 for a long length).

    Estimated in Fourier space from the mean interior stencils of ``M`` (``half``) and of
    ``R`` (probed on a 9³ mesh), both treated as translation invariant: the mean over
    frequencies ``θ = π k / n`` (at most :data:`DOF_FREQUENCIES` per axis) of
    ``tr((M̂ + μR̂)⁻¹ M̂) / 3``, then averaged over the nodes with ``μ = λ m̄ / m_i``
    (``m_i`` the trace of node ``i``'s diagonal block, ``m̄`` its interior mean): the
    texture varies, and where it is weak the penalty weighs more. Measured against a
    Hutchinson estimate (6 probes, 24³ nodes, grains at ℓ = 8): within 10–20 % of the
    trace, closer than the plain mean stencil (15–40 %). Mesh-sized, no solve.
    """
    Mh, Rh, ratio, _ = _mean_symbols(half, reg)
    ratio = ratio.ravel()
    return _node_mean(lambda w: np.real(np.trace(np.linalg.solve(Mh + w * Rh, Mh), axis1=1, axis2=2)).mean() / 3.0,
                      weights, ratio)


def noise_in_voxels(half: np.ndarray, reg: Regularizer, weights) -> tuple[np.ndarray, float]:
    """The noise the field keeps at each weight of ``weights``, in voxels², per unknown and per
    ``s²`` (:func:`choose_length`'s ``noise_variance``): the mean over the nodes of the diagonal
    of ``(M + λR)⁻¹ M (M + λR)⁻¹`` (the right-hand side's noise having covariance ``s² M``, the
    budget's model). Unlike the misfit, which weighs a node's error by its texture, it counts
    every node alike, as the field's error is scored: the weakly textured nodes, whose noise is
    ``1 / m_i`` times larger, dominate it.

    Estimated as :func:`dof_fraction` is, in Fourier space from the mean interior stencils,
    a node of texture ratio ``r_i = m_i / m̄`` seeing ``r_i (M̂ + μ_i R̂)`` with
    ``μ_i = λ / r_i``: ``tr((M̂ + μR̂)⁻¹ M̂ (M̂ + μR̂)⁻¹) / (3 r_i)``.

    Returns
    -------
    noise : ndarray, shape (len(weights),)
        Voxels² per unknown and per grey level² of ``s²``.
    m0 : float
        The mean stencil's weight of a uniform displacement, ``tr M̂(0) / 3`` (grey levels² per
        voxel²): a smooth error ``d`` of the field costs about ``m0 |d|²`` of misfit.
    """
    Mh, Rh, ratio, inner = _mean_symbols(half, reg)
    ratio = ratio[inner].ravel()  # a face node's texture is a half element's

    def variance(w):
        inv = np.linalg.inv(Mh + w * Rh)
        return np.real(np.trace(inv @ Mh @ inv, axis1=1, axis2=2)).mean() / 3.0

    m0 = float(np.real(np.trace(Mh[0])) / 3.0)  # θ = 0
    return _node_mean(variance, weights, ratio, per_node=1.0 / ratio, log=True), m0


def _mean_symbols(half: np.ndarray, reg: Regularizer):
    """Fourier symbols of the mean interior stencil of ``M`` and of ``R`` (probed on a 9³ mesh)
    at up to :data:`DOF_FREQUENCIES` frequencies per axis, shapes (K, 3, 3), the frequency 0
    first; each node's texture ratio ``m_i / m̄`` (at least 1e-3; ``m̄`` over the inner
    nodes), shape (nz, ny, nx); and the slices of the inner nodes."""
    shape = half.shape[:3]
    inner = tuple(slice(1, n - 1) if n > 2 else slice(None) for n in shape)
    # the stencil read a slab of z planes at a time: no whole-mesh copy (504 B per node), and
    # a stencil in node blocks (solve.partitioned.BlockStencil) is read slab by slab too
    S = np.zeros((14, 3, 3))
    diag = np.empty(shape, np.float32)
    for planes in z_slabs(shape):
        slab = half[planes]
        diag[planes] = np.trace(slab[..., 0, :, :], axis1=-2, axis2=-1)
        z = np.arange(shape[0])[planes]
        keep = (z >= inner[0].indices(shape[0])[0]) & (z < inner[0].indices(shape[0])[1])
        S += slab[keep][:, inner[1], inner[2]].sum(axis=(0, 1, 2), dtype=np.float64)
    S /= max(int(np.prod([len(range(*r.indices(n))) for r, n in zip(inner, shape)])), 1)
    theta = np.meshgrid(*[np.pi * np.arange(k) / k for k in (min(n, DOF_FREQUENCIES) for n in shape)],
                        indexing="ij")
    fshape = theta[0].shape
    offsets = STENCIL_OFFSETS[13:]
    Mh = np.broadcast_to(S[0], fshape + (3, 3)).astype(np.complex128)
    for h in range(1, 14):
        phase = np.exp(1j * sum(offsets[h][d] * theta[d] for d in range(3)))[..., None, None]
        Mh = Mh + S[h] * phase + S[h].T * np.conj(phase)
    probe = reg.resized((9, 9, 9))
    Rh = np.zeros(fshape + (3, 3), np.complex128)
    for j in range(3):
        e = np.zeros((9, 9, 9, 3))
        e[4, 4, 4, j] = 1.0
        col = probe.apply(e)
        for dz, dy, dx in np.ndindex(5, 5, 5):
            block = col[2 + dz, 2 + dy, 2 + dx]  # R[(c + off, :), (c, j)]
            if np.any(block):
                off = (dz - 2, dy - 2, dx - 2)
                Rh[..., j, :] += block[None, None, None, :] * np.exp(
                    1j * sum(off[d] * theta[d] for d in range(3)))[..., None]
    Mh = Mh.reshape(-1, 3, 3)
    Rh = Rh.reshape(-1, 3, 3)
    Rh = 0.5 * (Rh + np.conj(np.swapaxes(Rh, 1, 2)))
    ratio = np.maximum(diag / max(float(diag[inner].mean()), 1e-300), 1e-3)
    return Mh, Rh, ratio, inner


def _node_mean(symbol_mean, weights, ratio: np.ndarray, per_node: np.ndarray | float = 1.0,
               log: bool = False) -> np.ndarray:
    """``mean_i per_node_i · f(λ / r_i)`` for each ``λ`` of ``weights``, ``f = symbol_mean``
    tabulated on a log grid spanning every ``λ / r_i`` and interpolated (in ``log f`` with
    ``log``: a variance falls as ``λ⁻²``, over decades)."""
    weights = np.atleast_1d(np.asarray(weights, np.float64))
    grid = np.geomspace(weights.min() / ratio.max() / 2, weights.max() / ratio.min() * 2, 48)
    g = np.array([float(symbol_mean(w)) for w in grid])
    if log:
        g = np.log(np.maximum(g, 1e-300))
    at = lambda w: np.interp(np.log(w / ratio), np.log(grid), g)  # noqa: E731
    return np.array([float((per_node * (np.exp(at(w)) if log else at(w))).mean()) for w in weights])


def _least(risk, stop: int) -> int:
    """Index of the least ``risk(i)`` for ``i < stop``, ``risk`` unimodal: a ternary search
    (the values are cached by the caller), the short candidates first."""
    lo, hi = 0, stop - 1
    while hi - lo > 2:
        m1, m2 = lo + (hi - lo) // 3, hi - (hi - lo) // 3
        if risk(m1) <= risk(m2):
            hi = m2
        else:
            lo = m1
    return min(range(lo, hi + 1), key=risk)


def _longest_within(admissible, stop: int, first: int, walk: bool = False) -> int:
    """Largest ``i < stop`` with ``admissible(i)``, given ``admissible(0)`` and that it is monotone.

    Bisection whose first probe is ``first``; with ``walk``, while no probe has failed, the
    next one is 1, 2, 4, … candidates above the last admissible one instead of half way to
    ``stop`` (an exponential search: the answer expected just above ``first``).
    """
    lo, hi, probe, step = 0, stop, first, 1
    while hi - lo > 1:
        if admissible(probe):
            lo = probe
        else:
            hi = probe
        if walk and hi == stop:
            probe, step = min(lo + step, stop - 1), 2 * step
        else:
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
