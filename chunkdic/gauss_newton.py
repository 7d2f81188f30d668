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
from .result import HISTORY_FIELDS

#: stop as stalled after this many iterations without a lower gap
STALL_PATIENCE = 4
#: a gap this many times the best one so far means divergence
DIVERGENCE_FACTOR = 2.0


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
    """Modified Gauss–Newton state on one level: everything needed to resume exactly."""

    u: np.ndarray
    iteration: int = 0
    best_gap: float = math.inf
    best_u: np.ndarray | None = None
    best_excluded: int = 0
    best_valid: int = 0
    since_best: int = 0
    last_delta: float = math.inf
    status: str | None = None  # set once the level is finished
    gap: float = math.nan
    excluded: int = 0
    n_valid: int = 0

    SCALARS = ("iteration", "best_gap", "best_excluded", "best_valid", "since_best", "last_delta",
               "status", "gap", "excluded", "n_valid")
    _FLOATS = ("best_gap", "last_delta", "gap")

    def scalars(self) -> dict:
        return {k: json_float(getattr(self, k)) for k in self.SCALARS}

    def arrays(self) -> dict:
        return {"u": self.u, "best_u": self.u if self.best_u is None else self.best_u}

    @classmethod
    def restore(cls, scalars: dict, arrays: dict) -> "State":
        state = cls(u=arrays["u"], best_u=arrays["best_u"])
        for k in cls.SCALARS:
            value = scalars[k]
            setattr(state, k, from_json_float(value) if k in cls._FLOATS else value)
        return state

    def finish(self, status: str, gap: float, excluded: int, n_valid: int, *, keep_current: bool) -> None:
        self.status = status
        if keep_current:
            self.gap, self.excluded, self.n_valid = gap, excluded, n_valid
        else:  # diverged / stalled / out of iterations: the best field met, never "converged"
            self.u, self.gap, self.excluded, self.n_valid = self.best_u, self.best_gap, self.best_excluded, self.best_valid


def iterate(lvl: Level, state: State, tolerance: float, max_iterations: int, history: History, progress,
            on_iteration=None) -> State:
    """Modified Gauss–Newton on one level (paper section 3), from ``state``.

    Each pass evaluates ``b`` and the gap of the current field; the increment of the
    previous pass being below ``tolerance`` means the current field is converged, so the
    reported gap is always that of the returned field. A gap that stops decreasing is
    *stalled*; one that grows past ``DIVERGENCE_FACTOR`` × the best is *diverged*; both
    return the best field met, never flagged as converged. ``on_iteration(state)`` is
    called after every pass (checkpoints).
    """
    while state.status is None:
        it = state.iteration
        t0, c0 = time.perf_counter(), time.process_time()
        b, gap, n_valid, excluded = lvl.assemble_b(state.u)
        cpu = time.process_time() - c0  # this process only: the tasks too with the thread pool
        event = dict(stage="iteration", level=lvl.s, iteration=it, gap=gap, max_delta=None, excluded=excluded)
        if not math.isfinite(gap) or gap > DIVERGENCE_FACTOR * state.best_gap:
            state.finish("diverged", gap, excluded, n_valid, keep_current=False)
        else:
            if gap < state.best_gap * (1 - 1e-9):
                state.best_gap, state.best_u, state.best_excluded, state.best_valid = gap, state.u, excluded, n_valid
                state.since_best = 0
            else:
                state.since_best += 1
            if state.last_delta < tolerance:
                # the converged field is returned even if round-off left its gap a hair above the best
                state.finish("converged", gap, excluded, n_valid, keep_current=True)
            elif state.since_best >= STALL_PATIENCE:
                state.finish("stalled", gap, excluded, n_valid, keep_current=False)
            elif it == max_iterations:
                state.finish("max-iterations", gap, excluded, n_valid, keep_current=False)
        if state.status is not None:
            history.add(lvl.s, it, gap, math.nan, excluded)
            emit(progress, **event, status=state.status, seconds=time.perf_counter() - t0)
        else:
            t1 = time.perf_counter()
            delta, cg_iterations = lvl.solver.solve(b)
            t2 = time.perf_counter()
            state.last_delta = float(np.abs(delta).max())
            history.add(lvl.s, it, gap, state.last_delta, excluded)
            event.update(max_delta=state.last_delta, seconds=t2 - t0, assemble_seconds=t1 - t0,
                         solve_seconds=t2 - t1, cg_iterations=cg_iterations, voxels=lvl.mesh.n_voxels,
                         assemble_cpu_seconds=cpu)
            emit(progress, **event)
            state.u = state.u + np.moveaxis(delta, -1, 0)
            state.iteration += 1
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
        b, gap, _, excluded = lvl.assemble_b(t[:, None, None, None] * ones)
        delta = np.linalg.solve(lvl.rigid_matrix, b.sum(axis=(0, 1, 2)))
        history.add(lvl.s, -1 - it, gap, float(np.abs(delta).max()), excluded)
        emit(progress, stage="rigid", level=lvl.s, iteration=it, gap=gap,
             max_delta=float(np.abs(delta).max()), translation=t.tolist())
        t += delta
        if np.abs(delta).max() < tolerance:
            break
    return t
