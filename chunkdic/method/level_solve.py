"""The method on one pyramid level, from its start to what it leaves for the next one.

:func:`run_level` is the level on one screen, each step a function of the level's state
that returns the next one (paper sections 3–5):

1. the start (:mod:`chunkdic.method.start`): the coarser level's field, or on the coarsest
   level the best of no motion, the rigid translation with an affine field, an earlier result;
2. ``M`` summed once, around the start (:meth:`~chunkdic.method.protocol.Passes.assemble_m`);
3. the penalty of the level's regularisation length (:func:`chunkdic.method.length.regularize`);
4. on the correlated level, the reported gaps of no motion and of the rigid translation
   (:func:`measure_start_gaps`, inside the first pass);
5. modified Gauss–Newton (:func:`solve_level`: :func:`chunkdic.method.gauss_newton.iterate`
   and, with the length left automatic, its choice at the converged field followed by the
   regularised iterations, :func:`chunkdic.method.length.choose_regularization`);
6. what the level leaves (:func:`level_outcome`): weak, unsettled and masked nodes and, on
   the correlated level, the nodal uncertainty.

The voxels are reached only through the level's passes (:class:`~chunkdic.method.protocol.Passes`).
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from .events import Gaps, Unsettled, emit
from .gauss_newton import iterate
from .length import Penalty, choose_regularization, length_to_choose, regularization_length, regularize
from .noise import nodal_uncertainty
from .operator import Operator, warn_weak_nodes
from .protocol import Pass, Passes
from .runstate import RunState
from .settings import Settings
from .start import best_start, fresh_state, level_start, uniform
from .stopping import History, State


@dataclasses.dataclass
class LevelOutcome:
    """What a solved level leaves for the result (used for the finest level).

    Attributes
    ----------
    weak : ndarray, shape (n, 3), int
        Poorly textured nodes (index triples), and those a level converged at the noise level
        still moved beyond their uncertainty (:func:`unreliable_nodes`).
    masked : ndarray, shape (nz, ny, nx), bool
        Nodes outside the specimen mask.
    active : ndarray, shape (ez, ey, ex), bool, optional
        Elements with enough material (``None`` without a mask).
    reg_length : float
        The regularisation length used, level-0 voxels (NaN: none).
    sigma_u : ndarray, shape (3, nz, ny, nx), optional
        Per-node uncertainty, voxels of the level.
    noise : dict
        ``sigma_r`` and ``kappa`` the uncertainty comes from.
    split : ndarray, shape (K, 3), int, optional
        With a known crack, the nodes it splits (the state's ``u_other`` holds their second copies).
    crack_edges : int
        The mesh edges the crack meets (0: none, or no crack).
    """

    weak: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3), int))
    masked: np.ndarray | None = None
    active: np.ndarray | None = None
    reg_length: float = math.nan
    sigma_u: np.ndarray | None = None
    noise: dict = dataclasses.field(default_factory=dict)
    split: np.ndarray | None = None
    crack_edges: int = 0


def run_level(passes: Passes, run: RunState, coarser_u: np.ndarray | None, *, meshes: dict, levels: list,
              settings: Settings, earlier=None, progress=None, on_iteration=None,
              texture_length: float = math.nan) -> tuple[RunState, LevelOutcome]:
    """Solve the level of ``passes`` from the run's state (module docstring).

    Parameters
    ----------
    passes : Passes
        The level's passes over the voxels.
    run : RunState
        The run so far: ``run.gn`` is the level's state when it is resumed, else None.
    coarser_u : ndarray, shape (3, nz', ny', nx'), optional
        The coarser level's field (finer levels), voxels of that level.
    meshes : dict of int to Mesh
        Every level's mesh.
    levels : list of int
        The run's levels, coarsest first (the last one is correlated).
    settings : Settings
    earlier : Result, optional
        An earlier result to start from (``correlate(init=…)``; the coarsest level only).
    progress : callable, optional
        Receives the method's events.
    on_iteration : callable, optional
        ``on_iteration(run)`` after every Gauss–Newton pass, with the run's state then
        (checkpoints).
    texture_length : float
        The reference's autocorrelation length on this level, voxels of it (NaN: unknown): it
        sets the regularisation length the level starts with
        (:func:`chunkdic.method.length.start_length`).

    Returns
    -------
    run : RunState
        The run with the level ended: its state in ``gn``, its status recorded.
    outcome : LevelOutcome
        What the level leaves for the result.
    """
    s, mesh = passes.level, passes.mesh
    coarsest, correlated = levels[0], s == levels[-1]
    tolerance = settings.tolerance if correlated else settings.coarse_tolerance
    state = run.gn
    if state is None:  # a new level
        start, t_int = level_start(passes, meshes, coarsest, coarser_u, earlier=earlier if s == coarsest else None,
                                   progress=progress)
        op = passes.assemble_m(start)
        if s == coarsest:  # the start of lowest gap, M built again around it if it moved
            chosen = best_start(passes, op, start, t_int, tolerance, run.history, progress)
            start, op, run = chosen.u, chosen.op, dataclasses.replace(run, rigid_t=chosen.rigid_t)
        state = fresh_state(start, op)
    else:  # resumed: the very same M, around the field it was first built at (the checkpoint's)
        op = passes.assemble_m(state.u if state.m_start is None else state.m_start)
    warn_weak_nodes(op, mesh, s, settings.level)
    penalty = regularize(op, settings, s, mesh.element_size,
                         regularization_length(settings, state, s, mesh, texture_length), state.freed)
    ahead = None
    if correlated and run.initial_gap is None:
        first, initial, rigid = measure_start_gaps(passes, op, state, run.rigid_t * 2.0 ** (coarsest - s), progress)
        run = dataclasses.replace(run, initial_gap=initial, rigid_gap=rigid)
        ahead = [first]
        del first

    def saved(current: State) -> None:
        if on_iteration is not None:
            on_iteration(dataclasses.replace(run, gn=current))

    state, penalty, last = solve_level(passes, op, state, penalty, settings, tolerance=tolerance, choose=correlated,
                                       history=run.history, progress=progress, on_iteration=saved, ahead=ahead,
                                       texture_length=texture_length)
    outcome = level_outcome(passes, op, state, last, penalty, correlated=correlated, progress=progress)
    return dataclasses.replace(run, gn=state, statuses={**run.statuses, s: state.status}), outcome


def measure_start_gaps(passes: Passes, op: Operator, state: State, rigid_t: np.ndarray,
                       progress=None) -> tuple[Pass, float, float]:
    """The correlated level's gaps of the zero and of the rigid field ``rigid_t`` (3,), voxels
    of the level (reported, never iterated on), measured inside the level's first Gauss–Newton
    pass (:meth:`~chunkdic.method.protocol.Passes.assemble_b`'s ``probes``: the same element
    sample and brightness fit as :meth:`~chunkdic.method.protocol.Passes.gap`, from that
    pass's reads of ``f`` and ``g``), which :func:`solve_level` then iterates from instead of
    summing it again. Two voxel passes of their own before: ~10 s of a 254 s 1024³ run
    (docs/engine.md, "The start"). Returns ``(pass at state.u, initial gap, rigid gap)``."""
    t0, c0 = time.perf_counter(), time.process_time()
    passes.prepare(state.u)
    p = passes.assemble_b(state.u, op, other=state.u_other, probes={"initial": np.zeros((3,) + passes.mesh.nodes_shape),
                                               "rigid": uniform(rigid_t, passes.mesh)})
    initial, rigid = p.probe_gaps["initial"], p.probe_gaps["rigid"]
    emit(progress, Gaps(level=passes.level, initial_gap=initial, rigid_gap=rigid, translation=np.asarray(rigid_t).tolist(), seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0))
    return p, initial, rigid


def solve_level(passes: Passes, op: Operator, state: State, penalty: Penalty, settings: Settings, *,
                tolerance: float, choose: bool, history: History, progress=None, on_iteration=None,
                ahead: list[Pass] | None = None, texture_length: float = math.nan
                ) -> tuple[State, Penalty, Pass | None]:
    """Modified Gauss–Newton on the level from ``state`` with the penalty ``op``'s solver
    holds, choosing the regularisation length when ``choose`` (the correlated level) and the
    settings leave it automatic.

    With the length still to choose, the level first iterates to the coarse levels'
    tolerance only and stops at the pass whose increment (or, shrinking fast, the increments
    still to come: :func:`~chunkdic.method.stopping.still_to_come`) is below it without applying it:
    the choice linearises around that pass's field and ``b`` anyway, and the regularised
    iterations that follow converge it to the tolerance (each a ``b`` pass fewer).

    ``ahead``: the pass already summed at ``state.u`` (:func:`measure_start_gaps`), handed
    over in a list that the iterations empty; ``texture_length``: the reference's
    autocorrelation length on the level (voxels), which the robust reweighting reads
    (:func:`~chunkdic.method.length.choose_regularization`). Returns the state, the penalty
    the solver holds, and the last pass (None: none ran).
    """
    choosing = choose and length_to_choose(settings, state)
    if state.status is None:
        passes.prepare(state.u)
    state, last = iterate(passes, op, state, max(tolerance, settings.coarse_tolerance) if choosing else tolerance,
                          settings.max_iterations, history, progress, on_iteration=on_iteration, ahead=ahead,
                          resolve=choosing)
    if choosing and state.status == "converged":
        summed_now = last is None
        if summed_now:  # a level resumed after its iterations ended: the pass at its field again
            passes.prepare(state.u)
            last = passes.assemble_b(state.u, op, other=state.u_other)
        state, penalty = choose_regularization(op, state, last, penalty, settings, passes.level, passes.mesh,
                                               progress, texture_length=texture_length)
        ahead = [last]
        del last
        state, last = iterate(passes, op, state, tolerance, settings.max_iterations, history, progress,
                              on_iteration=on_iteration, ahead=ahead, ahead_new=summed_now)
    return state, penalty, last


def level_outcome(passes: Passes, op: Operator, state: State, last: Pass | None, penalty: Penalty, *,
                  correlated: bool, progress=None) -> LevelOutcome:
    """What the solved level leaves for the result: its weak, masked and active nodes, the
    length used and, on the ``correlated`` level, the nodal uncertainty from the latest
    pass's noise (kept in the state: a level resumed after its end ran no pass)."""
    s = passes.level
    outcome = LevelOutcome(weak=unreliable_nodes(op, state, s, progress), masked=op.masked_nodes(),
                           active=op.active, reg_length=penalty.length * 2**s,
                           split=None if op.crack is None else op.crack.nodes,
                           crack_edges=0 if op.crack is None else len(op.crack.edges))
    if correlated:
        noise = state
        if not math.isfinite(state.noise_variance):
            if last is None:
                passes.prepare(state.u)
                last = passes.assemble_b(state.u, op, other=state.u_other)
            noise = last
        outcome.sigma_u = nodal_uncertainty(op.solver, noise.noise_variance, noise.kappa)
        outcome.noise = {"sigma_r": float(np.sqrt(noise.noise_variance)), "kappa": float(noise.kappa)}
    return outcome


def unreliable_nodes(op: Operator, state: State, level: int, progress=None) -> np.ndarray:
    """The level's weak nodes (index triples, shape (n, 3)) and, when it converged at the
    noise level, the nodes its latest increment still moved by more than ``STEP_CAP`` σ_u:
    a few poorly seen nodes at the specimen's edge can run away while the rest of the field
    has stopped (docs/engine.md, "Iterations and stopping"); their values are not measured
    and are flagged ``FLAG_WEAK`` with the poorly textured ones."""
    weak = op.weak_nodes()
    if state.status != "converged" or state.unsettled is None or not state.unsettled.any():
        return weak
    moving = state.unsettled & ~op.masked_nodes()
    emit(progress, Unsettled(level=level, nodes=int(moving.sum())))
    return np.unique(np.concatenate([weak.reshape(-1, 3), np.argwhere(moving)]), axis=0)
