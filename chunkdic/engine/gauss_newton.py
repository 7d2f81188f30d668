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
from dataclasses import dataclass

import numpy as np

from .level import Level, emit
from ..results.result import HISTORY_FIELDS

#: stalled: this many passes with neither a lower gap nor a smaller increment
STALL_PATIENCE = 4
#: an increment counts as smaller when below this fraction of the smallest one so far
SHRINK = 0.9
#: a gap this many times the best one so far means divergence...
DIVERGENCE_FACTOR = 2.0
#: ...when it also exceeds the best by this much (a gap at round-off level, 1e-5 of the
#: range on exactly matching images, may double without meaning anything)
DIVERGENCE_FLOOR = 1e-4


def json_float(v):
    """A float for JSON: ``inf``/``nan`` as strings (JSON has no such numbers)."""
    if isinstance(v, float) and not math.isfinite(v):
        return repr(v)
    return v


def from_json_float(v) -> float:
    return float(v) if v is not None else math.nan


class History:
    """Per pass: level, iteration, gap, max |δa| of the update that followed, excluded voxels."""

    def __init__(self, rows: dict | None = None):
        self.rows = {name: [] for name in HISTORY_FIELDS}
        if rows is not None:
            self.rows = {k: [from_json_float(v) if k in ("gap", "max_delta") else v for v in vals]
                         for k, vals in rows.items()}

    def add(self, level, iteration, gap, max_delta, excluded) -> None:
        for name, value in zip(HISTORY_FIELDS, (level, iteration, gap, max_delta, excluded)):
            self.rows[name].append(value)

    def to_json(self) -> dict:
        return {k: [json_float(v) for v in vals] for k, vals in self.rows.items()}

    def arrays(self) -> dict[str, np.ndarray]:
        return {
            "level": np.asarray(self.rows["level"], dtype=np.int32),
            "iteration": np.asarray(self.rows["iteration"], dtype=np.int32),
            "gap": np.asarray(self.rows["gap"], dtype=np.float64),
            "max_delta": np.asarray(self.rows["max_delta"], dtype=np.float64),
            "excluded": np.asarray(self.rows["excluded"], dtype=np.int64),
        }


@dataclass
class State:
    """Modified Gauss–Newton state on one level: everything needed to resume exactly.

    ``elements`` holds the per-element brightness gain, offset and valid voxel count of
    the pass that measured ``u`` (shape (3, ez, ey, ex)); ``best_*`` the same for the
    field of lowest gap.
    """

    u: np.ndarray
    iteration: int = 0
    best_gap: float = math.inf
    best_u: np.ndarray | None = None
    best_excluded: int = 0
    best_valid: int = 0
    since_best: int = 0
    last_delta: float = math.inf
    best_delta: float = math.inf
    since_smaller: int = 0
    status: str | None = None  # set once the level is finished
    gap: float = math.nan
    excluded: int = 0
    n_valid: int = 0
    elements: np.ndarray | None = None
    best_elements: np.ndarray | None = None
    reg_length: float = math.nan  # automatic regularisation length once chosen (voxels of the level)
    largest_rhs: float = 0.0  # the level solver's CG reference (StencilSolver.largest_rhs)
    # the latest pass's noise (σ_r², κ): the nodal uncertainty of a level resumed after its end
    noise_variance: float = math.nan
    kappa: float = math.nan
    m_start: np.ndarray | None = None  # the field the level's M was built at (a resumed level rebuilds the same M)

    SCALARS = ("iteration", "best_gap", "best_excluded", "best_valid", "since_best", "last_delta",
               "best_delta", "since_smaller", "status", "gap", "excluded", "n_valid", "reg_length",
               "largest_rhs", "noise_variance", "kappa")
    _FLOATS = ("best_gap", "last_delta", "best_delta", "gap", "reg_length", "largest_rhs", "noise_variance",
               "kappa")
    _ARRAYS = ("u", "best_u", "elements", "best_elements", "m_start")

    def scalars(self) -> dict:
        return {k: json_float(getattr(self, k)) for k in self.SCALARS}

    def arrays(self) -> dict:
        out = {"u": self.u, "best_u": self.u if self.best_u is None else self.best_u}
        for k in ("elements", "best_elements", "m_start"):
            if getattr(self, k) is not None:
                out[k] = getattr(self, k)
        return out

    @classmethod
    def restore(cls, scalars: dict, arrays: dict) -> "State":
        state = cls(**{k: arrays.get(k) for k in cls._ARRAYS})
        for k in cls.SCALARS:
            value = scalars.get(k, getattr(state, k))
            setattr(state, k, from_json_float(value) if k in cls._FLOATS else value)
        return state

    def record(self, p, elements: np.ndarray) -> None:
        """Keep the pass ``p`` that measured the current field; it becomes the best if its gap is lowest."""
        self.gap, self.excluded, self.n_valid, self.elements = p.gap, p.n_excluded, p.n_valid, elements
        if p.gap < self.best_gap * (1 - 1e-9):
            self.best_gap, self.best_u, self.best_excluded, self.best_valid = p.gap, self.u, p.n_excluded, p.n_valid
            self.best_elements = elements
            self.since_best = 0
        else:
            self.since_best += 1

    def restart(self) -> None:
        """Iterate again from the current field with a changed objective (a new regularisation)."""
        self.status = None
        self.best_gap, self.best_u, self.since_best = math.inf, None, 0
        self.last_delta, self.best_delta, self.since_smaller = math.inf, math.inf, 0

    def finish(self, status: str, *, keep_current: bool) -> None:
        self.status = status
        if not keep_current and self.best_u is not None:  # diverged / stalled: the best field met
            self.u, self.gap, self.excluded, self.n_valid = self.best_u, self.best_gap, self.best_excluded, self.best_valid
            self.elements = self.best_elements

    def step(self, delta: np.ndarray) -> None:
        """Apply the increment ``delta`` (nz, ny, nx, 3) and track how increments shrink."""
        self.last_delta = float(np.abs(delta).max())
        if self.last_delta < SHRINK * self.best_delta:
            self.best_delta, self.since_smaller = self.last_delta, 0
        else:
            self.since_smaller += 1
        self.u = self.u + np.moveaxis(delta, -1, 0)
        self.iteration += 1


def element_fields(p) -> np.ndarray:
    """Per-element gain, offset (at the centre), valid voxels of a pass, and the drift
    (grey levels per voxel, z, y, x, repeated per element): shape (6, ez, ey, ex)."""
    drift = np.broadcast_to(p.fit.drift[:, None, None, None], (3,) + p.fit.gain.shape)
    return np.concatenate([np.stack([p.fit.gain, p.fit.offset, p.fit.valid_per_element]), drift])


def decide(state: State, gap: float, tolerance: float, max_iterations: int) -> None:
    """The stopping rule (docs/engine.md, "Iterations and stopping"), applied after a pass."""
    if not math.isfinite(gap) or gap > DIVERGENCE_FACTOR * state.best_gap + DIVERGENCE_FLOOR:
        state.finish("diverged", keep_current=False)
    elif state.last_delta < tolerance:
        # the converged field is returned even if round-off left its gap a hair above the best
        state.finish("converged", keep_current=True)
    elif state.since_best >= STALL_PATIENCE and state.since_smaller >= STALL_PATIENCE:
        # neither the gap nor the increments improve any more: a still-improving field
        # (increments shrinking while the gap sits at the noise floor) is never "stalled"
        state.finish("stalled", keep_current=False)
    elif state.iteration == max_iterations:
        # out of iterations: the latest field if it is as good as the best (the increments
        # were still shrinking), else the best
        state.finish("max-iterations", keep_current=gap <= state.best_gap * (1 + 1e-6))


def iterate(lvl: Level, state: State, tolerance: float, max_iterations: int, history: History, progress,
            on_iteration=None, first_pass=None, resolve: bool = False) -> State:
    """Modified Gauss–Newton on one level (paper section 3), from ``state``.

    Each pass evaluates ``b`` and the gap of the current field and solves for an increment;
    an increment below ``tolerance`` is applied and ends the level as converged, without a
    pass to confirm it: the reported gap is that of the last pass, whose field differs from
    the returned one by less than ``tolerance`` (the gap by the square of that, relative).
    A run whose gap and increments both
    stop improving is *stalled*; one whose gap grows past ``DIVERGENCE_FACTOR`` × the best
    (plus ``DIVERGENCE_FLOOR``) is *diverged*; both return the best field met, never
    flagged as converged.
    ``on_iteration(state)`` is called after every pass (checkpoints). ``first_pass``: the
    pass already evaluated at ``state.u`` (``b`` and the gap depend on the images and the
    field only, not on the regularisation), used instead of evaluating it again.
    ``resolve``: the caller solves again from the last pass with another operator (the
    regularisation about to be chosen), so an increment below ``tolerance`` ends the level
    *unapplied*: the field stays the one that pass measured, which the next solve starts from.
    """
    while state.status is None:
        it = state.iteration
        t0, c0 = time.perf_counter(), time.process_time()
        p, first_pass = (lvl.assemble_b(state.u) if first_pass is None else first_pass), None
        state.noise_variance, state.kappa = float(p.noise_variance), float(p.kappa)
        cpu = time.process_time() - c0  # this process only: the tasks too with the thread pool
        event = dict(stage="iteration", level=lvl.s, iteration=it, gap=p.gap, max_delta=None,
                     excluded=p.n_excluded, gain=float(np.median(p.fit.gain)))
        if math.isfinite(p.gap):
            state.record(p, element_fields(p))
        decide(state, p.gap, tolerance, max_iterations)
        if state.status is not None:
            history.add(lvl.s, it, p.gap, math.nan, p.n_excluded)
            emit(progress, **event, status=state.status, seconds=time.perf_counter() - t0)
        else:
            t1 = time.perf_counter()
            # (M + λR) δa = b − λ R a: the penalty acts on the whole field, not the increment
            rhs = p.b - lvl.solver.penalty_gradient(np.moveaxis(state.u, 0, -1))
            lvl.solver.largest_rhs = max(lvl.solver.largest_rhs, state.largest_rhs)  # as before a resume
            delta, cg_iterations = lvl.solver.solve(rhs)
            state.largest_rhs = lvl.solver.largest_rhs
            t2 = time.perf_counter()
            if float(np.abs(delta).max()) >= tolerance:
                state.step(delta)
            else:
                # converged: no pass confirms a field that moved by less than the tolerance
                # (its gap differs from this pass's to second order in the increment)
                if resolve:
                    state.last_delta = float(np.abs(delta).max())
                else:
                    state.step(delta)
                state.finish("converged", keep_current=True)
                event.update(status=state.status)
            history.add(lvl.s, it, p.gap, state.last_delta, p.n_excluded)
            event.update(max_delta=state.last_delta, seconds=t2 - t0, assemble_seconds=t1 - t0,
                         solve_seconds=t2 - t1, cg_iterations=cg_iterations, voxels=lvl.mesh.n_voxels,
                         assemble_cpu_seconds=cpu)
            emit(progress, **event)
        if on_iteration is not None:
            on_iteration(state)
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
