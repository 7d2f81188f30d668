"""Modified Gauss–Newton on one level (paper section 3): state, stopping rule, history.

``M`` is built once per level from the reference; every pass assembles ``b`` and the
matching gap of the current field, solves ``M δa = b`` on the client and updates the
field. The state (:class:`State`) holds everything needed to resume exactly after an
interruption, and has a JSON form for the checkpoint. docs/engine.md, "Iterations and
stopping".
"""

from __future__ import annotations

import math
import time

import numpy as np

from .events import emit
from .level import Level
from .stopping import History, State, decide, noise_step_of, still_to_come


def element_fields(p) -> np.ndarray:
    """Per-element gain, offset (at the centre), valid voxels of a pass, the drift (grey
    levels per voxel, z, y, x, repeated per element) and the residual rows
    (:func:`~chunkdic.engine.greylevel.residual_rows`): shape (8, ez, ey, ex)."""
    out = np.empty((8,) + p.fit.gain.shape)  # filled row by row: no stacked temporary
    out[0], out[1], out[2] = p.fit.gain, p.fit.offset, p.fit.valid_per_element
    out[3:6] = p.fit.drift[:, None, None, None]
    out[6:] = np.nan if p.fit.residual is None else p.fit.residual
    return out


def noise_step(lvl: Level, p, delta: np.ndarray, tolerance: float) -> tuple[float, np.ndarray, float]:
    """The increment ``delta`` (nz, ny, nx, 3) in units of the field's own uncertainty
    (:func:`~chunkdic.engine.stopping.noise_step_of`: RMS of ``δa / σ_u`` over the settled
    nodes), the unsettled nodes (bool, shape (nz, ny, nx): beyond ``STEP_CAP`` σ_u and
    ``tolerance``, voxels of the level) and their fraction of the measured nodes.

    ``σ_u² = κ σ_r² [A_ii⁻¹ M_ii A_ii⁻¹]`` from each node's diagonal block (``A = M + λR``;
    the coupling to the neighbours, which :func:`~chunkdic.engine.noise.nodal_uncertainty`
    adds, only raises ``σ_u``: this is the stricter measure). Weak nodes are left out.
    """
    solver = lvl.solver
    var = solver.local_variances()
    var *= float(p.kappa * p.noise_variance)
    ok = (var > 0).all(axis=-1)
    if solver.weak_nodes.size:
        ok[tuple(solver.weak_nodes.T)] = False
    if ok.all():  # every node: no mesh-sized copies of the increment and the variances
        q, moving = noise_step_of(delta.reshape(-1, 3), var.reshape(-1, 3), tolerance)
        return q, moving.reshape(ok.shape), float(moving.mean()) if moving.size else 0.0
    q, moving = noise_step_of(delta[ok], var[ok], tolerance)
    unsettled = np.zeros(ok.shape, bool)
    unsettled[ok] = moving
    return q, unsettled, float(moving.mean()) if moving.size else 0.0


def iterate(lvl: Level, state: State, tolerance: float, max_iterations: int, history: History, progress,
            on_iteration=None, first_pass=None, resolve: bool = False) -> State:
    """Modified Gauss–Newton on one level (paper section 3), from ``state``.

    Each pass evaluates ``b`` and the gap of the current field and solves for an increment;
    an increment below ``tolerance``, or one after which the increments still to come add
    up to less than it (:func:`~chunkdic.engine.stopping.still_to_come`: shrinking by ×0.25
    or faster, a geometric series), is applied and ends the level as converged, without a
    pass to confirm it: the reported gap is that of the last pass, whose field differs from
    the returned one by about ``tolerance`` (the gap by the square of that, relative).
    A run whose gap and increments both
    stop improving is *stalled*; one whose gap grows past ``DIVERGENCE_FACTOR`` × the best
    (plus ``DIVERGENCE_FLOOR``) is *diverged*; both return the best field met, never
    flagged as converged.
    ``on_iteration(state)`` is called after every pass (checkpoints). ``first_pass``: the
    pass already evaluated at ``state.u`` (``b`` and the gap depend on the images and the
    field only, not on the regularisation), used instead of evaluating it again.
    ``resolve``: the caller solves again from the last pass with another operator (the
    regularisation about to be chosen), so the increment that ends the level is left
    *unapplied*: the field stays the one that pass measured, which the next solve starts from.
    """
    while state.status is None:
        it = state.iteration
        t0, c0 = time.perf_counter(), time.process_time()
        ahead = first_pass is not None and not first_pass.reported  # summed ahead (steps.measure_start_gaps)
        p, first_pass = (lvl.assemble_b(state.u) if first_pass is None else first_pass), None
        if ahead:  # its time is this iteration's
            t0 -= p.seconds
        p.reported = True
        state.noise_variance, state.kappa = float(p.noise_variance), float(p.kappa)
        cpu = time.process_time() - c0  # this process only: the tasks too with the thread pool
        event = dict(stage="iteration", level=lvl.s, iteration=it, gap=p.gap, max_delta=None,
                     excluded=p.n_excluded, gain=float(np.median(p.fit.gain)))
        if math.isfinite(p.gap):
            fields = element_fields(p)
            state.record(p, fields)
            p.fit.share(fields)
            del fields
        decide(state, p.gap, tolerance, max_iterations)
        if state.status is not None:
            history.add(lvl.s, it, p.gap, math.nan, p.n_excluded)
            emit(progress, **event, status=state.status, seconds=time.perf_counter() - t0)
        else:
            t1 = time.perf_counter()
            # (M + λR) δa = b − λ R a: the penalty acts on the whole field, not the increment
            rhs = lvl.solver.penalty_gradient(np.moveaxis(state.u, 0, -1))
            np.subtract(p.b, rhs, out=rhs)  # in place: one mesh-sized vector fewer
            delta, cg_iterations = lvl.solver.solve(rhs, overwrite_b=True)
            del rhs
            state.largest_rhs = lvl.solver.largest_rhs  # recorded for the checkpoint; the solver owns it
            t2 = time.perf_counter()
            q, unsettled, fraction = noise_step(lvl, p, delta, tolerance)
            state.note_noise_step(q, unsettled, fraction)
            d = float(np.abs(delta).max())
            # converged: the increment, or once the increments shrink fast, all those still to
            # come (a geometric series from the last two) below the tolerance; no pass
            # confirms it (the gap differs from this pass's to second order in the increment)
            if d >= tolerance and still_to_come(state.last_delta, d) >= tolerance:
                state.step(delta)
            else:
                # no node moves by the tolerance any more (nor, predicted, in the passes to
                # come): none is unsettled, whatever its step measured in its own noise
                state.unsettled = None
                if resolve:
                    state.last_delta = d
                else:
                    state.step(delta)
                state.finish("converged", keep_current=True)
                event.update(status=state.status)
            history.add(lvl.s, it, p.gap, state.last_delta, p.n_excluded)
            event.update(max_delta=state.last_delta, noise_step=state.last_noise_step,
                         unsettled=0 if state.unsettled is None else int(unsettled.sum()), seconds=t2 - t0,
                         assemble_seconds=t1 - t0, solve_seconds=t2 - t1, cg_iterations=cg_iterations,
                         voxels=lvl.mesh.n_voxels, assemble_cpu_seconds=cpu)
            emit(progress, **event)
        if on_iteration is not None:
            on_iteration(state)
        p = None  # the pass is not held while the next one is summed (the level keeps it)
    return state


def rigid_step(lvl: Level, t0: np.ndarray, tolerance: float, max_iterations: int, history: History,
               progress) -> np.ndarray:
    """Sub-voxel refinement of a uniform translation with the rigid restriction of ``M``.

    Since ``Σ_a N_a = 1``, the rigid 3×3 system is the sum of all stencil entries of ``M``
    and of all nodal ``b``: no extra pass over the voxels (paper section 5.1).
    """
    t = np.array(t0, dtype=np.float64)
    ones = np.ones((3,) + lvl.mesh.nodes_shape)
    for it in range(max_iterations):
        p = lvl.assemble_b(t[:, None, None, None] * ones)
        delta = np.linalg.solve(lvl.rigid_matrix, p.b.sum(axis=(0, 1, 2)))
        history.add(lvl.s, -1 - it, p.gap, float(np.abs(delta).max()), p.n_excluded)
        emit(progress, stage="rigid", level=lvl.s, iteration=it, gap=p.gap,
             max_delta=float(np.abs(delta).max()), translation=t.tolist())
        t += delta
        if np.abs(delta).max() < tolerance:
            break
    return t
