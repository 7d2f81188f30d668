"""The stopping rule of a Gauss–Newton level and what a level remembers: state and history.

Kept apart from :mod:`chunkdic.method.gauss_newton` (which drives the 3-D block engine) so
that the 2-D check of :mod:`chunkdic.analysis.q4` shares the very same rule without loading
the block kernels or the solvers. The state (:class:`State`) holds everything needed to
resume exactly after an interruption and has a JSON form for the checkpoint.
docs/engine.md, "Iterations and stopping".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..results.layout import HISTORY_FIELDS

#: stalled: this many passes with neither a lower gap nor a smaller increment
STALL_PATIENCE = 4
#: an increment counts as smaller when below this fraction of the smallest one so far
SHRINK = 0.9
#: an increment below this fraction of the field's own uncertainty (RMS of δa / σ_u) moves
#: the field within its noise: STALL_PATIENCE such passes and a level that would stop
#: stalled or out of iterations has converged at the noise level (docs/engine.md)
NOISE_STEP = 0.5
#: ...and this many passes with such increments, no longer shrinking, and a gap that fell
#: by less than GAP_GAIN (relative) below its best: converged at the noise level at once
NOISE_PATIENCE = 2
GAP_GAIN = 1e-4
#: a node whose increment exceeds this many σ_u along some axis is not settled: it is left
#: out of that measure, which says how much the rest of the field still moves...
STEP_CAP = 3.0
#: ...and the field counts as moving within its noise only while at most this fraction of
#: its measured nodes is unsettled (the ℓ = 6 waves at 100³: 0.5-5 % of the nodes, at
#: the specimen's edge, ran away by 1-2.5 voxels while the median node moved by 0.01 σ_u);
#: a converged level flags those nodes as unreliable (``FLAG_WEAK``)
UNSETTLED_FRACTION = 0.1
#: an increment at most this fraction of the one before it (max |δa|) shrinks fast enough for
#: the passes still to come to be predicted (a geometric series, :func:`still_to_come`): a
#: level converges when they would add up to less than its tolerance (docs/engine.md)
CONTRACTION = 0.25
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


#: nodes per slab of :func:`noise_step_of`: its temporaries (the squared ratios, the
#: magnitudes, the masks) are a slab's, not the mesh's (~70 B per node at 2048³, ℓ = 8)
NOISE_SLAB = 1 << 16


def noise_step_of(delta: np.ndarray, variance: np.ndarray, tolerance: float = 0.0,
                  where: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """The increment in units of the field's own uncertainty, and the nodes it leaves unsettled.

    Parameters
    ----------
    delta, variance : ndarray, shape (n, k), float
        The increment of ``n`` nodes (``k`` components, voxels) and their variance ``σ_u²``
        (voxels², positive where measured).
    tolerance : float, voxels
        A component moving by less than this never makes its node unsettled (an exact
        pair's ``σ_u`` is far below any tolerance).
    where : ndarray, shape (n,), bool, optional
        The measured nodes (default: all); the others are neither settled nor unsettled.

    Returns
    -------
    q : float
        RMS of ``δa / σ_u`` over the unknowns of the settled nodes (``inf`` if none).
    unsettled : ndarray, shape (n,), bool
        Measured nodes with a component beyond :data:`STEP_CAP` ``σ_u`` (and ``tolerance``).

    A plain RMS over every node let 3-4 running-away nodes at the specimen's edge hold
    half of it (the ℓ = 6 waves: 0.4-1.1, above :data:`NOISE_STEP`, with the median node at
    0.003 σ_u and the gap within 2 %): the rule then said "stalled" of a field that had
    stopped improving (docs/engine.md, "Iterations and stopping"). Summed over slabs of
    :data:`NOISE_SLAB` nodes: no mesh-sized temporary.
    """
    n = len(delta)
    unsettled = np.zeros(n, bool)
    total, count = 0.0, 0
    for s in range(0, n, NOISE_SLAB):
        part = slice(s, s + NOISE_SLAB)
        d, var = np.asarray(delta[part], np.float64), np.asarray(variance[part], np.float64)
        if where is not None:
            d, var = d[where[part]], var[where[part]]
        ratio2 = d**2
        ratio2 /= var  # in place: the same quotients, one array fewer
        moving = ((ratio2 > STEP_CAP**2) & (np.abs(d) >= tolerance)).any(axis=-1)
        if where is None:
            unsettled[part] = moving
        else:
            unsettled[np.flatnonzero(where[part]) + s] = moving
        settled = ratio2[~moving]
        total += float(settled.sum())
        count += settled.size
    return (math.sqrt(total / count) if count else math.inf), unsettled


def still_to_come(previous: float, current: float) -> float:
    """What the increments after ``current`` add up to (max |δa|, voxels) if they keep
    shrinking by the ratio ``r = current / previous`` of the last two: ``current r / (1 - r)``;
    ``inf`` unless ``r ≤ CONTRACTION`` (no ratio yet, or too slow a contraction to trust).

    Modified Gauss–Newton contracts geometrically once near the solution (``M`` fixed): the
    1024³ band pair's level-0 increments fell by ×0.075, ×0.05, then after the
    regularisation choice ×0.034 and ×0.053 per pass.

    >>> round(still_to_come(0.0353, 0.00174), 6)  # the 1024³ run's level 0, iterations 1-2
    9e-05
    >>> still_to_come(float("inf"), 0.001), still_to_come(0.002, 0.001)
    (inf, inf)
    """
    if not (math.isfinite(previous) and previous > 0):
        return math.inf
    r = current / previous
    return current * r / (1.0 - r) if r <= CONTRACTION else math.inf


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

    ``elements`` holds the element fields of the pass that measured ``u``
    (:func:`chunkdic.method.gauss_newton.element_fields`, shape (8, ez, ey, ex): brightness
    gain, offset, valid voxel count, drift, the residual rows :mod:`chunkdic.method.mismatch`
    judges); ``best_*`` the same for the field of lowest gap.
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
    largest_rhs: float = 0.0  # a record of the level solver's CG reference (StencilSolver.largest_rhs owns it)
    # the latest pass's noise (σ_r², κ): the nodal uncertainty of a level resumed after its end
    noise_variance: float = math.nan
    kappa: float = math.nan
    m_start: np.ndarray | None = None  # the field the level's M was built at (a resumed level rebuilds the same M)
    last_noise_step: float = math.inf  # the latest increment in units of the field's uncertainty
    # what the increments still to come add up to, in the same units, if they keep shrinking
    # as the last two did (a geometric series; inf while they do not shrink)
    noise_remaining: float = math.inf
    noise_quiet: int = 0  # consecutive increments within NOISE_STEP of the uncertainty
    gain_gap: float = math.inf  # the last gap that fell by more than GAP_GAIN below the one before
    since_gain: int = 0
    # nodes (bool, nodes shape) the latest increment left unsettled (beyond STEP_CAP × σ_u and
    # the tolerance): a level converged at the noise level flags them as unreliable
    unsettled: np.ndarray | None = None
    # the Tikhonov terms the robust reweighting freed (uint8, nodes shape + (6,), bits per
    # component; Regularizer.freed) once chosen with the length: a resumed level solves the same problem
    freed: np.ndarray | None = None
    # with a known crack, the second copies (K, 3) of the split nodes (chunkdic.method.crack),
    # and those of the best field
    u_other: np.ndarray | None = None
    best_u_other: np.ndarray | None = None

    SCALARS = ("iteration", "best_gap", "best_excluded", "best_valid", "since_best", "last_delta",
               "best_delta", "since_smaller", "status", "gap", "excluded", "n_valid", "reg_length",
               "largest_rhs", "noise_variance", "kappa", "last_noise_step", "noise_quiet", "gain_gap", "since_gain",
               "noise_remaining")
    _FLOATS = ("best_gap", "last_delta", "best_delta", "gap", "reg_length", "largest_rhs", "noise_variance",
               "kappa", "last_noise_step", "gain_gap", "noise_remaining")
    _ARRAYS = ("u", "best_u", "elements", "best_elements", "m_start", "unsettled", "freed", "u_other", "best_u_other")

    def scalars(self) -> dict:
        return {k: json_float(getattr(self, k)) for k in self.SCALARS}

    def arrays(self) -> dict:
        out = {"u": self.u, "best_u": self.u if self.best_u is None else self.best_u}
        for k in ("elements", "best_elements", "m_start", "unsettled", "freed", "u_other", "best_u_other"):
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

    def record(self, p, elements: np.ndarray, park=None) -> None:
        """Keep the pass ``p`` that measured the current field; it becomes the best if its gap is lowest.

        ``park``: :meth:`~chunkdic.method.protocol.Passes.park`, through which the best field is
        kept (the iterations read it only when they return it); the element fields are kept as
        given. ``best_u`` and the element fields may therefore be parked array-likes, which
        ``np.asarray`` reads (:meth:`arrays` leaves that to the checkpoint's writer)."""
        self.gap, self.excluded, self.n_valid, self.elements = p.gap, p.n_excluded, p.n_valid, elements
        if p.gap < self.best_gap * (1 - 1e-9):
            best_u = self.u if park is None else park(self.u)
            self.best_gap, self.best_u, self.best_excluded, self.best_valid = p.gap, best_u, p.n_excluded, p.n_valid
            self.best_u_other = self.u_other
            self.best_elements = elements
            self.since_best = 0
        else:
            self.since_best += 1
        if p.gap < self.gain_gap * (1 - GAP_GAIN):
            self.gain_gap, self.since_gain = p.gap, 0
        else:
            self.since_gain += 1

    def restart(self) -> None:
        """Iterate again from the current field with a changed objective (a new regularisation)."""
        self.status = None
        self.best_gap, self.best_u, self.since_best = math.inf, None, 0
        self.last_delta, self.best_delta, self.since_smaller = math.inf, math.inf, 0
        self.last_noise_step, self.noise_quiet, self.unsettled = math.inf, 0, None
        self.noise_remaining = math.inf
        self.gain_gap, self.since_gain = math.inf, 0

    def note_noise_step(self, q: float, unsettled: np.ndarray | None = None, fraction: float = 0.0) -> None:
        """Record the increment ``q`` measured in units of the field's uncertainty over the
        settled nodes (:func:`noise_step_of`), the unsettled nodes (bool, nodes shape) and
        their ``fraction`` of the measured nodes."""
        last = self.last_noise_step  # inf before the first increment (or after a restart): no ratio yet
        ratio = float(q) / last if math.isfinite(last) and last > 0 else math.inf
        self.noise_remaining = float(q) * ratio / (1.0 - ratio) if ratio < 1.0 else math.inf
        self.last_noise_step = float(q)
        quiet = q < NOISE_STEP and fraction <= UNSETTLED_FRACTION
        self.noise_quiet = self.noise_quiet + 1 if quiet else 0
        self.unsettled = unsettled

    def finish(self, status: str, *, keep_current: bool) -> None:
        self.status = status
        if not keep_current and self.best_u is not None:  # diverged / stalled: the best field met
            self.u = np.asarray(self.best_u)  # an array, also where it was parked
            self.gap, self.excluded, self.n_valid = self.best_gap, self.best_excluded, self.best_valid
            self.u_other = self.best_u_other
            self.elements = self.best_elements

    def step(self, delta: np.ndarray, delta_other: np.ndarray | None = None) -> None:
        """Apply the increment ``delta`` (nz, ny, nx, 3) (and ``delta_other`` (K, 3) to the
        second copies of a crack's split nodes) and track how increments shrink."""
        self.last_delta = float(np.abs(delta).max())
        if delta_other is not None and delta_other.size:
            self.last_delta = max(self.last_delta, float(np.abs(delta_other).max()))
            self.u_other = self.u_other + delta_other
        if self.last_delta < SHRINK * self.best_delta:
            self.best_delta, self.since_smaller = self.last_delta, 0
        else:
            self.since_smaller += 1
        self.u = self.u + np.moveaxis(delta, -1, 0)
        self.iteration += 1


def decide(state: State, gap: float, tolerance: float, max_iterations: int) -> None:
    """The stopping rule (docs/engine.md, "Iterations and stopping"), applied after a pass."""
    if not math.isfinite(gap) or gap > DIVERGENCE_FACTOR * state.best_gap + DIVERGENCE_FLOOR:
        state.finish("diverged", keep_current=False)
    elif state.last_delta < tolerance:
        # the converged field is returned even if round-off left its gap a hair above the best
        state.finish("converged", keep_current=True)
    elif (state.noise_quiet >= NOISE_PATIENCE and state.since_gain >= NOISE_PATIENCE
          and (state.since_smaller >= 1 or state.noise_remaining < NOISE_STEP)):
        # the field moves within its own uncertainty, the gap no longer falls and the
        # increments no longer shrink, or shrink so that all the passes still to come would
        # move it by less than half its uncertainty (a slow geometric convergence: 72³ ℓ = 6
        # spent 29 passes at 0.1-0.01 σ_u per pass): it has stopped improving at the noise
        # level (the current field, within half its uncertainty of the last ones and measured
        # by this pass, which the regularisation choice linearises around)
        state.finish("converged", keep_current=True)
    elif state.since_best >= STALL_PATIENCE and state.since_smaller >= STALL_PATIENCE:
        # neither the gap nor the increments improve any more: a still-improving field
        # (increments shrinking while the gap sits at the noise floor) is never "stalled";
        # one whose last increments all stayed within its own uncertainty has stopped
        # improving at the noise level: converged (the best field), not stalled
        state.finish("converged" if state.noise_quiet >= STALL_PATIENCE else "stalled", keep_current=False)
    elif state.iteration == max_iterations and state.noise_quiet >= STALL_PATIENCE:
        state.finish("converged", keep_current=gap <= state.best_gap * (1 + 1e-6))
    elif state.iteration == max_iterations:
        # out of iterations: the latest field if it is as good as the best (the increments
        # were still shrinking), else the best
        state.finish("max-iterations", keep_current=gap <= state.best_gap * (1 + 1e-6))
