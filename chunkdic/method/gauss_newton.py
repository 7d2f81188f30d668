"""Modified Gauss–Newton on one level (paper section 3), state in, state out.

``M`` is built once per level from the reference (the :class:`~chunkdic.method.operator.Operator`
of the ``M`` pass); every pass of :func:`iterate` assembles ``b`` and the matching gap of the
current field (:meth:`~chunkdic.method.protocol.Passes.assemble_b`), solves
``(M + λR) δa = b − λ R a`` on the client and updates the field, until the stopping rule of
:mod:`chunkdic.method.stopping` ends the level. :func:`iterate` takes a
:class:`~chunkdic.method.stopping.State` and returns the next one (with the last pass), which
holds everything needed to resume exactly after an interruption. docs/engine.md,
"Iterations and stopping".
"""

from __future__ import annotations

import math
import time

import numpy as np

import copy

from ..solve.cg import rhs_norm
from .crack import solve_coupled
from .events import Iteration, Rigid, emit
from .operator import Operator
from .protocol import Pass, Passes
from .stopping import History, State, decide, noise_step_of, still_to_come


def element_fields(p):
    """The rows of a pass's element fields: per-element gain, offset (at the centre), valid
    voxels, the drift (grey levels per voxel, z, y, x, repeated per element) and the residual
    rows (:func:`~chunkdic.method.brightness.residual_rows`): 8 arrays of shape (ez, ey, ex),
    float64, the pass's own or broadcast (no copy), which
    :meth:`~chunkdic.method.protocol.Passes.park` stacks (8, ez, ey, ex) row by row; or, a pass
    whose fields were parked already (:meth:`~chunkdic.method.brightness.Fit.share`), those."""
    if p.fit.gain is None:
        return p.fit.parked
    shape = p.fit.gain.shape
    residual = [np.broadcast_to(np.nan, shape)] * 2 if p.fit.residual is None else list(p.fit.residual)
    drift = [np.broadcast_to(np.float64(d), shape) for d in p.fit.drift]
    return [p.fit.gain, p.fit.offset, p.fit.valid_per_element, *drift, *residual]


def noise_step(op: Operator, p: Pass, delta: np.ndarray, tolerance: float) -> tuple[float, np.ndarray, float]:
    """The increment ``delta`` (nz, ny, nx, 3) in units of the field's own uncertainty
    (:func:`~chunkdic.method.stopping.noise_step_of`: RMS of ``δa / σ_u`` over the settled
    nodes), the unsettled nodes (bool, shape (nz, ny, nx): beyond ``STEP_CAP`` σ_u and
    ``tolerance``, voxels of the level) and their fraction of the measured nodes.

    ``σ_u² = κ σ_r² [A_ii⁻¹ M_ii A_ii⁻¹]`` from each node's diagonal block (``A = M + λR``;
    the coupling to the neighbours, which :func:`~chunkdic.method.noise.nodal_uncertainty`
    adds, only raises ``σ_u``: this is the stricter measure). Weak nodes are left out.
    """
    solver = op.solver
    var = solver.local_variances()
    var *= float(p.kappa * p.noise_variance)
    ok = None
    if solver.weak_nodes.size or not (var > 0).all():  # the weak and unmeasured nodes left out
        ok = (var > 0).all(axis=-1)
        if solver.weak_nodes.size:
            ok[tuple(solver.weak_nodes.T)] = False
        ok = ok.reshape(-1)
    # flat views and a mask: no mesh-sized copies of the increment and the variances
    q, unsettled = noise_step_of(delta.reshape(-1, 3), var.reshape(-1, 3), tolerance, where=ok)
    measured = unsettled.size if ok is None else int(np.count_nonzero(ok))
    fraction = float(np.count_nonzero(unsettled)) / measured if measured else 0.0
    return q, unsettled.reshape(var.shape[:-1]), fraction


def iterate(passes: Passes, op: Operator, state: State, tolerance: float, max_iterations: int, history: History,
            progress=None, *, on_iteration=None, ahead: list[Pass] | None = None, ahead_new: bool = True,
            resolve: bool = False) -> tuple[State, Pass | None]:
    """Modified Gauss–Newton on one level (paper section 3), from ``state``.

    Each pass evaluates ``b`` and the gap of the current field and solves for an increment;
    an increment below ``tolerance``, or one after which the increments still to come add
    up to less than it (:func:`~chunkdic.method.stopping.still_to_come`: shrinking by ×0.25
    or faster, a geometric series), is applied and ends the level as converged, without a
    pass to confirm it: the reported gap is that of the last pass, whose field differs from
    the returned one by about ``tolerance`` (the gap by the square of that, relative).
    A run whose gap and increments both
    stop improving is *stalled*; one whose gap grows past ``DIVERGENCE_FACTOR`` × the best
    (plus ``DIVERGENCE_FLOOR``) is *diverged*; both return the best field met, never
    flagged as converged.

    Parameters
    ----------
    passes : Passes
        The level's passes over the voxels.
    op : Operator
        ``M`` and its solver (the penalty it holds is the objective's).
    state : State
        Where the iterations start; not changed (the returned state is a new one).
    tolerance : float
        Voxels of the level.
    max_iterations : int
    history : History
        Every pass is appended to it.
    progress : callable, optional
        Receives the iterations' events.
    on_iteration : callable, optional
        ``on_iteration(state)`` after every pass (checkpoints).
    ahead : list of Pass, optional
        The pass already evaluated at ``state.u`` (``b`` and the gap depend on the images
        and the field only, not on the regularisation), taken out of the list and used
        instead of evaluating it again: the caller keeps no reference to it, so that it is
        not held while the next pass is summed. ``ahead_new``: it was summed for these
        iterations (its time is the first iteration's), not by earlier ones.
    resolve : bool
        The caller solves again from the last pass with another operator (the
        regularisation about to be chosen), so the increment that ends the level is left
        *unapplied*: the field stays the one that pass measured, which the next solve starts from.

    Returns
    -------
    state : State
        The state the iterations ended with (``status`` set).
    last : Pass or None
        The pass that measured the returned field's neighbourhood: the last one evaluated
        (None when the level had ended already and no pass ran).
    """
    state = copy.copy(state)
    first = ahead.pop() if ahead else None
    p = None
    while state.status is None:
        it = state.iteration
        t0, c0 = time.perf_counter(), time.process_time()
        summed_ahead = first is not None and ahead_new
        p, first = (passes.assemble_b(state.u, op, other=state.u_other) if first is None else first), None
        if summed_ahead:  # its time is this iteration's
            t0 -= p.seconds
        state.noise_variance, state.kappa = float(p.noise_variance), float(p.kappa)
        cpu = time.process_time() - c0  # this process only: the tasks too with the thread pool
        event = dict(level=passes.level, iteration=it, gap=p.gap, excluded=p.n_excluded,
                     gain=p.fit.median_gain())
        if math.isfinite(p.gap):
            # stacked (8, ez, ey, ex), or parked: read by the level's end and the checkpoints alone
            fields = passes.park(element_fields(p))
            state.record(p, fields, park=passes.park)
            p.fit.share(fields)
            del fields
        decide(state, p.gap, tolerance, max_iterations)
        if state.status is not None:
            history.add(passes.level, it, p.gap, math.nan, p.n_excluded)
            emit(progress, Iteration(**event, status=state.status, seconds=time.perf_counter() - t0))
        else:
            t1 = time.perf_counter()
            # (M + λR) δa = b − λ R a: the penalty acts on the whole field, not the increment
            rhs = op.solver.penalty_gradient(np.moveaxis(state.u, 0, -1))
            np.subtract(p.b, rhs, out=rhs)  # in place: one mesh-sized vector fewer
            p.fit.b = passes.park(p.fit.b)  # read again only by the caller of the last pass
            norm = rhs_norm(rhs)
            delta_other = None
            if op.crack is None or not op.crack.count:
                delta, cg_iterations = op.solver.solve(rhs, overwrite_b=True, reference=state.largest_rhs)
            else:
                delta, delta_other, cg_iterations = solve_coupled(op.solver, op.crack, rhs, p.b_other)
            del rhs
            state.largest_rhs = max(state.largest_rhs, norm)  # the CG reference (kept by the checkpoint)
            t2 = time.perf_counter()
            q, unsettled, fraction = noise_step(op, p, delta, tolerance)
            state.note_noise_step(q, unsettled, fraction)
            d = float(np.abs(delta).max())
            if delta_other is not None and delta_other.size:
                d = max(d, float(np.abs(delta_other).max()))
            # converged: the increment, or once the increments shrink fast, all those still to
            # come (a geometric series from the last two) below the tolerance; no pass
            # confirms it (the gap differs from this pass's to second order in the increment)
            if d >= tolerance and still_to_come(state.last_delta, d) >= tolerance:
                state.step(delta, delta_other)
            else:
                # no node moves by the tolerance any more (nor, predicted, in the passes to
                # come): none is unsettled, whatever its step measured in its own noise
                state.unsettled = None
                if resolve:
                    state.last_delta = d
                else:
                    state.step(delta, delta_other)
                state.finish("converged", keep_current=True)
                event.update(status=state.status)
            history.add(passes.level, it, p.gap, state.last_delta, p.n_excluded)
            event.update(max_delta=state.last_delta, noise_step=state.last_noise_step,
                         unsettled=0 if state.unsettled is None else int(unsettled.sum()), seconds=t2 - t0,
                         assemble_seconds=t1 - t0, solve_seconds=t2 - t1, cg_iterations=cg_iterations,
                         voxels=passes.mesh.n_voxels, assemble_cpu_seconds=cpu)
            emit(progress, Iteration(**event))
        if on_iteration is not None:
            on_iteration(state)
        if state.status is None:
            p = None  # the pass is not held while the next one is summed
    if p is not None:
        p.fit.b = np.asarray(p.fit.b)  # parked while it was solved for
    return state, (p if p is not None else first)


def rigid_step(passes: Passes, op: Operator, t0: np.ndarray, tolerance: float, max_iterations: int,
               history: History, progress=None) -> np.ndarray:
    """Sub-voxel refinement of a uniform translation with the rigid restriction of ``M``.

    Since ``Σ_a N_a = 1``, the rigid 3×3 system is the sum of all stencil entries of ``M``
    and of all nodal ``b``: no extra pass over the voxels (paper section 5.1).
    """
    t = np.array(t0, dtype=np.float64)
    ones = np.ones((3,) + passes.mesh.nodes_shape)
    for it in range(max_iterations):
        p = passes.assemble_b(t[:, None, None, None] * ones, op)
        delta = np.linalg.solve(op.rigid_matrix, p.b.sum(axis=(0, 1, 2)))
        history.add(passes.level, -1 - it, p.gap, float(np.abs(delta).max()), p.n_excluded)
        emit(progress, Rigid(level=passes.level, iteration=it, gap=p.gap, max_delta=float(np.abs(delta).max()), translation=t.tolist()))
        t += delta
        if np.abs(delta).max() < tolerance:
            break
    return t
