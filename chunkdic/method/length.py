"""The regularisation of a level: its penalty and the choice of its length.

Every level solves ``(M + λR) δa = b − λ R a`` with the penalty ``R`` of
:mod:`chunkdic.solve.regularizer` weighted so that a plane wave of wavelength ``T`` costs
``(ℓ_reg / T)^4`` of its image term (:func:`regularize`). Coarse levels and the correlated
level until its length is chosen start with :func:`start_length`: :data:`START_LENGTH`
elements on a texture the elements resolve, longer on a coarse one; with the length left
automatic, the correlated level chooses it at its converged field
(:func:`choose_regularization`: :func:`chunkdic.solve.regchoice.choose_length`, then the
robust reweighting's rounds, :mod:`chunkdic.solve.reweighting`). docs/engine.md,
"Automatic length" and "Robust reweighting".
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import numpy as np

from ..mesh import Mesh
from ..solve.cg import StencilSolver
from ..solve.penalty import TERM_KINDS
from ..solve.regchoice import CANDIDATES, choose_length, feature_regions, regions_cover
from ..solve.regularizer import Regularizer
from ..solve.reweighting import SPANNING_FRACTION, robust_freed
from .events import Regularization, Reweighting, emit
from .operator import Operator
from .protocol import Pass
from .settings import Settings
from .stopping import State

log = logging.getLogger(__name__)

#: the regularisation length before (coarse levels: instead of) the automatic choice on a texture
#: the elements resolve, in element sizes (:func:`start_length`)
START_LENGTH = 2.0
#: an autocorrelation length (voxels of the level) up to which a texture counts as fine at any
#: element size (:func:`start_length`): the CT specimens' 5.5–6.4 voxels at ℓ = 4 keep their
#: band's error only with a 2ℓ start
FINE_TEXTURE = 8.0
#: a field whose mean displacement gradient reaches this is a large deformation
#: (:func:`start_length`, :func:`choose_regularization`): 10 % compression is 0.03–0.10, a 10°
#: rotation 0.17, the heterogeneous cases (a −8 % band 6 voxels wide, waves and slips of 0.5
#: voxel) below 0.01
LARGE_GRADIENT = 0.02
#: CG's tolerance of the whole-mesh solve that places the length choice's boxes
#: (:func:`misfit_map`): it ranks places, and 1e-3 puts them where the iterations' 1e-5 does
#: (the 300³ slip at ℓ = 6: 10 CG iterations instead of 23, 1.8 s instead of 3.3)
PROBE_RTOL = 1e-3


@dataclasses.dataclass(frozen=True)
class Penalty:
    """The regularisation a level's solver holds: ``kind``, ``length`` (``ℓ_reg``, voxels of
    the level; NaN: none) and ``weight`` (``λ``)."""

    kind: str = "none"
    length: float = math.nan
    weight: float = 0.0


def regularize(op: Operator, settings: Settings, level: int, element_size: float, length: float,
               freed: np.ndarray | None = None) -> Penalty:
    """Solve with ``λ R`` from now on; ``length``: ``ℓ_reg``, voxels of the level; ``freed``:
    the Tikhonov terms the robust reweighting left out (:attr:`Regularizer.freed`, the
    correlated level only; the weight is the plain penalty's for ``length``).

    Coarser levels only give the finest one its starting field, and their low-passed
    sums may leave elements with too little texture: they are always regularised
    (Tikhonov when the run asks for none). Unregularised, a 128³ foam correlated at
    ℓ = 6 moved by 33-82 voxels on level 1 and ended stalled at σ 0.098 voxel; with the
    coarse levels regularised it converged at σ 0.0048.
    """
    kind = settings.regularization
    if kind == "none":
        if level == settings.level:
            return Penalty()
        kind = "tikhonov"
    weight = hold_penalty(op, kind, element_size, length, freed)
    log.info("level %d: %s regularisation over %.1f voxels (weight %.3g)", level, kind, length, weight)
    return Penalty(kind, float(length), weight)


def hold_penalty(op: Operator, kind: str, element_size: float, length: float, freed: np.ndarray | None = None) -> float:
    """Make the operator's solver hold the penalty ``kind`` of ``length`` (voxels of the level)
    with the terms ``freed`` and those across a known crack left out; returns its weight ``λ``."""
    reg = Regularizer(kind, op.nodes_shape, element_size)
    weight = op.unit_weight(kind, element_size) * float(length) ** reg.order
    freed = released(op, freed)
    if freed is not None:
        reg = reg.with_freed(freed)
    op.solver.regularize(reg, weight)
    return weight


def released(op: Operator, freed: np.ndarray | None) -> np.ndarray | None:
    """``freed`` with the terms across a known crack freed too (:meth:`chunkdic.method.crack.CrackCoupling.release`)."""
    return freed if op.crack is None else op.crack.release(freed, op.nodes_shape)


def start_length(element_size: float, texture_length: float, gradient: float = math.inf) -> float:
    """The regularisation length a level starts with, voxels of the level.

    On a texture the elements resolve (an autocorrelation length at most about ℓ: the
    granular and cementitious CT specimens, 6 voxels), or under a small deformation, it is
    :data:`START_LENGTH` elements. Under a large one (a displacement gradient of
    :data:`LARGE_GRADIENT` or more) on a coarse texture (autocorrelation length of 12–24
    voxels at ℓ = 8 or 6) many elements hold no edge: under a 2ℓ penalty the field fits what
    the imaging does not carry with the material (the partial volume and the blur of the
    edges, which do not deform with it) and settles 0.05–0.1 voxel off, where the choice,
    linearised around that field, keeps a short length. So the start grows with the square
    of the texture's scale in elements, ``START_LENGTH ℓ (A / max(ℓ, FINE_TEXTURE))²``, on
    the grid of the choice's candidates (:data:`~chunkdic.solve.regchoice.CANDIDATES`), at
    most its longest. Under a small deformation a long start does the opposite harm: the
    noise correlation measured around its smooth field is 2–3× larger, and the choice keeps
    a long length for a band or a wave (docs/engine.md, "The regularisation length on a
    coarse texture").

    Parameters
    ----------
    element_size : float
        ``ℓ``, voxels of the level.
    texture_length : float
        The reference's autocorrelation length ``A`` on that level (the median over the axes,
        :func:`chunkdic.kernels.autocorrelation.autocorrelation_length`), voxels; NaN: unknown.
    gradient : float
        The largest component of the start field's mean displacement gradient
        (:func:`mean_gradient`); default: large.

    Returns
    -------
    float
        Voxels of the level.

    Examples
    --------
    >>> start_length(8, 6.0), start_length(4, 6.0), start_length(8, 11.5), start_length(8, 20.0)
    (16.0, 8.0, 32.0, 90.50966799187809)
    >>> start_length(8, 20.0, gradient=0.005)
    16.0
    """
    ell = float(element_size)
    coarse = math.isfinite(texture_length) and gradient >= LARGE_GRADIENT
    ratio = texture_length / max(ell, FINE_TEXTURE) if coarse else 1.0
    wanted = START_LENGTH * max(1.0, ratio) ** 2
    grid = np.array([START_LENGTH * c for c in CANDIDATES if START_LENGTH * c <= CANDIDATES[-1]])
    return float(grid[np.argmin(np.abs(np.log(grid / wanted)))] * ell)


def mean_gradient(u: np.ndarray, element_size: float) -> float:
    """The largest component of a nodal field's mean displacement gradient (dimensionless):
    per component and axis, the difference between the last and the first node plane's means
    over their distance.

    Parameters
    ----------
    u : ndarray, shape (3, nz, ny, nx), float64, voxels of the level
    element_size : float
        Voxels of the level.
    """
    u = np.asarray(u, dtype=np.float64)
    out = 0.0
    for axis in range(3):
        n = u.shape[axis + 1]
        if n > 1:
            last = np.take(u, n - 1, axis=axis + 1).reshape(3, -1).mean(axis=1)
            first = np.take(u, 0, axis=axis + 1).reshape(3, -1).mean(axis=1)
            out = max(out, float(np.abs(last - first).max()) / ((n - 1) * float(element_size)))
    return out


def regularization_length(settings: Settings, state: State, level: int, mesh: Mesh,
                          texture_length: float = math.nan) -> float:
    """``ℓ_reg`` for ``level``, voxels of the level: given, chosen (resumed), or the starting one
    (:func:`start_length` for the reference's autocorrelation length ``texture_length`` on the
    level, voxels, NaN: unknown, and the gradient of the level's field ``state.u``)."""
    if settings.regularization_length is not None:
        return settings.regularization_length / 2.0**level
    if math.isfinite(state.reg_length):
        return state.reg_length
    return start_length(mesh.element_size, texture_length, mean_gradient(state.u, mesh.element_size))


def length_to_choose(settings: Settings, state: State) -> bool:
    """The finest level's regularisation length is automatic and not chosen yet."""
    return (settings.regularization != "none" and settings.regularization_length is None
            and not math.isfinite(state.reg_length))


def choose_regularization(op: Operator, state: State, p: Pass, penalty: Penalty, settings: Settings, level: int,
                          mesh: Mesh, progress=None, texture_length: float = math.nan) -> tuple[State, Penalty]:
    """``ℓ_reg`` chosen at the converged field ``state.u`` and its pass ``p``
    (:func:`chunkdic.solve.regchoice.choose_length`; under a large deformation, a mean
    gradient of :data:`LARGE_GRADIENT` or more, a candidate over budget bounds the length only
    where :func:`~chunkdic.solve.regchoice.no_feature` does not hold), then
    ``settings.reweights`` times: the
    curvature terms of the field this length gives (:func:`linearised_field`) beyond
    :data:`~chunkdic.solve.reweighting.ROBUST_THRESHOLD` robust σ freed
    (:func:`~chunkdic.solve.reweighting.robust_freed`) and the length chosen again for the
    reweighted penalty (docs/engine.md, "Robust reweighting"). Where the texture's features
    outgrow the elements (``texture_length``, the reference's autocorrelation length on the
    level, above :data:`FINE_TEXTURE` or above ``ℓ``) only terms in sheets spanning the mesh
    are freed (:data:`~chunkdic.solve.reweighting.SPANNING_FRACTION`): there the weakly
    textured nodes' heavy-tailed noise frees clusters and streaks (waves at ℓ = 4 on a
    6-voxel texture: 0.031–0.073 voxel with them, 0.018–0.055 without); where every element
    holds texture the small sets go with the kinks' (a slip at ℓ = 8: 0.0555 voxel with
    them, 0.0586 without).

    Returns the state restarted under the outcome (``reg_length``, ``freed``, which the
    checkpoint keeps) and the penalty the operator's solver now holds.
    """
    t0 = time.perf_counter()
    u = np.moveaxis(state.u, 0, -1)
    last = {"half": None, "solver": None}

    def solve_with(half, reg, weight, rhs):
        # one solver per sub-mesh (its coarse M, block inverse and weak nodes reused by every
        # candidate); rtol 1e-5, as the iterations' (1e-7: 30 % more CG iterations for the
        # same length on every case measured, docs/engine.md, "Automatic length")
        if last["half"] is not half:
            last["half"], last["solver"] = half, StencilSolver(half.copy(), rtol=1e-5)
        last["solver"].regularize(reg, weight)
        return last["solver"].solve(rhs)[0]

    large = mean_gradient(state.u, mesh.element_size) >= LARGE_GRADIENT
    boxes = choice_boxes(op, settings.regularization, mesh.element_size, penalty.length, u, p.b, state.largest_rhs)

    def choose(freed, guess=None):
        return choose_length(settings.regularization, op.solver.matrix, mesh.element_size, u, p.b,
                             p.kappa * p.noise_variance, solve_with, kappa=p.kappa,
                             rule=settings.regularization_rule, freed=released(op, freed), guess=guess,
                             large_deformation=large, boxes=boxes)

    # probed first: the length the level has iterated with so far (2ℓ; on heterogeneous fields
    # the choice is 1-3 candidates from it), not the middle candidate, whose long-length solve
    # was the slowest of the plain choice (docs/engine.md, "Robust reweighting", Cost); the
    # same choice
    choice = choose(None, guess=penalty.length)
    scale = 2.0**level
    corner = choice.l_curve_length * scale if math.isfinite(choice.l_curve_length) else None  # sweep only
    emit(progress, Regularization(level=level, length=choice.length * scale, l_curve_length=corner, kind=settings.regularization, kappa=p.kappa, rule=choice.rule, seconds=time.perf_counter() - t0))
    penalty = regularize(op, settings, level, mesh.element_size, choice.length)
    length, freed = choice.length, None
    for k in range(settings.reweights):
        outgrown = texture_length > min(mesh.element_size, FINE_TEXTURE)  # weakly textured elements
        freed = robust_freed(linearised_field(op, u, p.b, state.largest_rhs),
                             spanning=SPANNING_FRACTION if outgrown else 0.0)
        terms = freed_terms(freed)
        if terms == 0:  # nothing beyond the threshold: the plain penalty, as chosen
            freed = None
            emit(progress, Reweighting(level=level, round=k + 1, freed=0, length=length * scale, seconds=time.perf_counter() - t0))
            break
        length = choose(freed, guess=length).length  # the plain choice probed first
        penalty = regularize(op, settings, level, mesh.element_size, length, freed)
        emit(progress, Reweighting(level=level, round=k + 1, freed=terms, fraction=terms / (3 * len(TERM_KINDS) * int(np.prod(mesh.nodes_shape))), length=length * scale, seconds=time.perf_counter() - t0))
    state = dataclasses.replace(state, reg_length=length, freed=freed)
    state.restart()
    return state, penalty


def misfit_map(op: Operator, kind: str, element_size: float, length: float, u: np.ndarray, b: np.ndarray,
               reference: float) -> np.ndarray:
    """Each node's share of the linearised misfit increase over the data fit at ``u`` (nz, ny,
    nx, 3) with right-hand side ``b`` that the penalty ``kind`` of ``length`` (voxels of the
    level) gives on the whole mesh: ``Δ_i·(MΔ)_i − 2 b_i·Δ_i`` with ``Δ`` the step to its field
    (:func:`linearised_field`); shape (nz, ny, nx), grey levels². Its sum is the misfit increase
    :func:`~chunkdic.solve.regchoice.choose_length` weighs. Leaves the solver holding that
    penalty: the caller sets the one it wants next."""
    hold_penalty(op, kind, element_size, length)
    step = linearised_field(op, u, b, reference, rtol=PROBE_RTOL)
    step -= u
    out = np.einsum("...c,...c->...", step, op.solver.stencil_product(step))
    out -= 2.0 * np.einsum("...c,...c->...", b, step)
    return out


def choice_boxes(op: Operator, kind: str, element_size: float, guess: float, u: np.ndarray, b: np.ndarray,
                 reference: float) -> list | None:
    """The sub-meshes the length choice looks at: None (the fixed
    :func:`~chunkdic.solve.regchoice.regions`) where they leave no element out between them
    (:func:`~chunkdic.solve.regchoice.regions_cover`), otherwise
    boxes centred on the misfit a length twice ``guess`` gives (:func:`misfit_map`,
    :func:`~chunkdic.solve.regchoice.feature_regions`; docs/engine.md, "Where the choice looks")."""
    if regions_cover(op.nodes_shape):
        return None
    guess = guess if math.isfinite(guess) else START_LENGTH * element_size
    probe = min(2.0 * guess, CANDIDATES[-1] * element_size)
    return feature_regions(misfit_map(op, kind, element_size, probe, u, b, reference))


def linearised_field(op: Operator, u: np.ndarray, b: np.ndarray, reference: float,
                     rtol: float | None = None) -> np.ndarray:
    """The field the operator's current regularisation gives in one modified Gauss–Newton
    step from ``u`` (nz, ny, nx, 3) with right-hand side ``b``: ``(M + λR) x = M u + b``, shape
    (nz, ny, nx, 3), voxels of the level; within 1 % of the converged field on the
    heterogeneous cases (docs/engine.md), and no pass over the voxels. ``reference``: the
    iterations' CG reference (:meth:`~chunkdic.solve.cg.StencilSolver.solve`), which this
    solve leaves as it was, so that the iterations that follow stop CG where they would
    have without it; ``rtol``: CG's tolerance (default the solver's)."""
    rhs = op.solver.data_matvec(u)
    rhs += b
    x, _ = op.solver.solve(rhs, overwrite_b=True, reference=reference, rtol=rtol)
    return x


def freed_terms(freed: np.ndarray | None) -> int:
    """How many Tikhonov terms (per component) the robust reweighting left out."""
    if freed is None:
        return 0
    return int(sum(np.count_nonzero(freed & (1 << c)) for c in range(3)))


__all__ = ["START_LENGTH", "FINE_TEXTURE", "LARGE_GRADIENT", "Penalty", "regularize", "start_length", "mean_gradient",
           "regularization_length", "length_to_choose", "choose_regularization", "hold_penalty", "misfit_map",
           "choice_boxes", "linearised_field", "freed_terms"]
