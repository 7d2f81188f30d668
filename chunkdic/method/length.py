"""The regularisation of a level: its penalty and the choice of its length.

Every level solves ``(M + λR) δa = b − λ R a`` with the penalty ``R`` of
:mod:`chunkdic.solve.regularizer` weighted so that a plane wave of wavelength ``T`` costs
``(ℓ_reg / T)^4`` of its image term (:func:`regularize`). Coarse levels and the correlated
level until its length is chosen use :data:`START_LENGTH` elements; with the length left
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
from ..solve.regchoice import choose_length
from ..solve.regularizer import Regularizer
from ..solve.reweighting import robust_freed
from .events import Regularization, Reweighting, emit
from .operator import Operator
from .protocol import Pass
from .settings import Settings
from .stopping import State

log = logging.getLogger(__name__)

#: the regularisation length before (coarse levels: instead of) the automatic choice, in element sizes
START_LENGTH = 2.0


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
    reg = Regularizer(kind, op.nodes_shape, element_size)
    weight = op.unit_weight(kind, element_size) * float(length) ** reg.order
    freed = released(op, freed)
    if freed is not None:
        reg = reg.with_freed(freed)
    op.solver.regularize(reg, weight)
    log.info("level %d: %s regularisation over %.1f voxels (weight %.3g)", level, kind, length, weight)
    return Penalty(kind, float(length), weight)


def released(op: Operator, freed: np.ndarray | None) -> np.ndarray | None:
    """``freed`` with the terms across a known crack freed too (:meth:`chunkdic.method.crack.CrackCoupling.release`)."""
    return freed if op.crack is None else op.crack.release(freed, op.nodes_shape)


def regularization_length(settings: Settings, state: State, level: int, mesh: Mesh) -> float:
    """``ℓ_reg`` for ``level``, voxels of the level: given, chosen (resumed), or the starting one."""
    if settings.regularization_length is not None:
        return settings.regularization_length / 2.0**level
    if math.isfinite(state.reg_length):
        return state.reg_length
    return START_LENGTH * mesh.element_size


def length_to_choose(settings: Settings, state: State) -> bool:
    """The finest level's regularisation length is automatic and not chosen yet."""
    return (settings.regularization != "none" and settings.regularization_length is None
            and not math.isfinite(state.reg_length))


def choose_regularization(op: Operator, state: State, p: Pass, penalty: Penalty, settings: Settings, level: int,
                          mesh: Mesh, progress=None) -> tuple[State, Penalty]:
    """``ℓ_reg`` chosen at the converged field ``state.u`` and its pass ``p``
    (:func:`chunkdic.solve.regchoice.choose_length`), then ``settings.reweights`` times: the
    curvature terms of the field this length gives (:func:`linearised_field`) beyond
    :data:`~chunkdic.solve.reweighting.ROBUST_THRESHOLD` robust σ freed
    (:func:`~chunkdic.solve.reweighting.robust_freed`) and the length chosen again for the
    reweighted penalty (docs/engine.md, "Robust reweighting").

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

    def choose(freed, guess=None):
        return choose_length(settings.regularization, op.solver.matrix, mesh.element_size, u, p.b,
                             p.kappa * p.noise_variance, solve_with, kappa=p.kappa,
                             rule=settings.regularization_rule, freed=released(op, freed), guess=guess)

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
        freed = robust_freed(linearised_field(op, u, p.b, state.largest_rhs))
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


def linearised_field(op: Operator, u: np.ndarray, b: np.ndarray, reference: float) -> np.ndarray:
    """The field the operator's current regularisation gives in one modified Gauss–Newton
    step from ``u`` (nz, ny, nx, 3) with right-hand side ``b``: ``(M + λR) x = M u + b``, shape
    (nz, ny, nx, 3), voxels of the level; within 1 % of the converged field on the
    heterogeneous cases (docs/engine.md), and no pass over the voxels. ``reference``: the
    iterations' CG reference (:meth:`~chunkdic.solve.cg.StencilSolver.solve`), which this
    solve leaves as it was, so that the iterations that follow stop CG where they would
    have without it."""
    rhs = op.solver.data_matvec(u)
    rhs += b
    x, _ = op.solver.solve(rhs, overwrite_b=True, reference=reference)
    return x


def freed_terms(freed: np.ndarray | None) -> int:
    """How many Tikhonov terms (per component) the robust reweighting left out."""
    if freed is None:
        return 0
    return int(sum(np.count_nonzero(freed & (1 << c)) for c in range(3)))


__all__ = ["START_LENGTH", "Penalty", "regularize", "regularization_length", "length_to_choose",
           "choose_regularization", "linearised_field", "freed_terms"]
