"""The steps of a correlation on one level, each a function of the run's context and state.

:func:`chunkdic.engine.driver.correlate` strings them together, coarsest level first
(paper section 3): the start field (:func:`start_field`), the level with its ``M``
(:func:`open_level`), its start state with the rigid step on the coarsest level (:func:`start_state`), the
Gauss–Newton solve with the choice of the regularisation length (:func:`solve_level`),
and the result (:func:`assemble_result`). docs/engine.md describes each choice.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .. import config
from ..io.handles import forget_open_arrays
from ..mesh import Mesh, transfer
from ..results.result import FLAG_MASKED, FLAG_NO_DATA, FLAG_WEAK, Result, node_flags
from ..solve.cg import StencilSolver
from ..solve.regchoice import choose_length
from ..solve.regularization import TERM_KINDS, robust_freed
from ..solve.transfer import nominal_l10
from .affine import affine_step
from .checkpoint import Checkpoint, resumed_pass
from .events import emit
from .gauss_newton import iterate, rigid_step
from .initial import start_field as init_start_field
from .level import Level
from .noise import nodal_uncertainty
from .rigid import translation_task
from .runstate import LevelOutcome, RunState
from .settings import Settings
from .stopping import State
from .stored_matrix import StoredMatrix

#: Gauss-Newton passes of the rigid step (a uniform translation: three unknowns)
RIGID_ITERATIONS = 10
#: a chosen start farther than this (voxels of the level) from the field M was built at rebuilds M
MOVED_START = 0.5


@dataclasses.dataclass(frozen=True)
class RunContext:
    """What does not change during a run: settings, meshes, scans, where tasks run.

    ``levels`` are coarsest first; ``f_refs``, ``g_refs``, ``mask_refs`` map a level to the
    :class:`~chunkdic.io.handles.ArrayRef` tasks read (a resumed run: the levels still to
    solve); ``init`` an earlier result to start from (:mod:`chunkdic.engine.initial`);
    ``matrix`` where each level's ``M`` is kept for a resumed run (the output,
    :mod:`chunkdic.engine.stored_matrix`); ``adopted``: the scratch is an interrupted run's,
    whose complete level stores are reused.
    """

    settings: Settings
    meshes: dict[int, Mesh]
    levels: list[int]
    f_refs: dict
    g_refs: dict
    runner: object
    scratch: Path
    progress: Callable[[dict], None] | None = None
    checkpoint: Checkpoint | None = None
    mask_refs: dict | None = None
    init: Result | None = None
    matrix: StoredMatrix | None = None
    adopted: bool = False

    @property
    def finest(self) -> int:
        return self.levels[-1]

    @property
    def coarsest(self) -> int:
        return self.levels[0]

    def tolerance(self, s: int) -> float:
        """The level's tolerance: coarser levels only give the next one its start."""
        return self.settings.tolerance if s == self.finest else self.settings.coarse_tolerance

    def save(self, run: RunState, s: int) -> None:
        """Checkpoint ``run`` while level ``s`` is solved (nothing without an output)."""
        if self.checkpoint is not None:
            self.checkpoint.save(run.to_json(s), run.arrays())


def start_field(ctx: RunContext, run: RunState, s: int, coarser_u: np.ndarray | None):
    """The field level ``s`` starts from, shape (3, nz, ny, nx), voxels of the level, and
    the integer translation the rigid step refines (coarsest level only, else ``None``).

    Resumed: the saved field. Coarsest level: an ``init`` result evaluated at the nodes,
    or the phase-correlation translation (:mod:`chunkdic.engine.rigid`). Finer levels: the
    coarser level's field carried to the finer nodes (DESIGN.md, half-voxel offset, × 2).
    """
    mesh = ctx.meshes[s]
    if run.gn is not None:
        return run.gn.u, None
    if s == ctx.coarsest and ctx.init is not None:
        start = init_start_field(ctx.init, mesh, s)
        emit(ctx.progress, stage="init", level=s, path=ctx.init.path,
             mean=[float(v) for v in start.mean(axis=(1, 2, 3))])
        return start, None
    if s == ctx.coarsest:
        t_int = run_one(ctx.runner, translation_task, (ctx.f_refs[s], ctx.g_refs[s], mesh.roi))
        return uniform(t_int, mesh), t_int
    return transfer(coarser_u, ctx.meshes[s + 1], s + 1, mesh, s), None


def open_level(ctx: RunContext, run: RunState, s: int, start: np.ndarray) -> Level:
    """Level ``s`` with its ``M`` assembled around ``start`` (one pass over the voxels); a
    resumed level around the field its ``M`` was first built at (``gn.m_start``, in the
    checkpoint), so that it rebuilds the very same ``M`` and the resumed run equals the
    uninterrupted one to round-off."""
    t0, c0 = time.perf_counter(), time.process_time()
    mesh = ctx.meshes[s]
    if run.gn is not None and run.gn.m_start is not None:
        start = run.gn.m_start
    lvl = Level(s, mesh, ctx.f_refs[s], ctx.g_refs[s], ctx.runner, ctx.settings, ctx.scratch, ctx.progress,
                None if ctx.mask_refs is None else ctx.mask_refs[s], start=start,
                start_to_choose=run.gn is None and s == ctx.coarsest, matrix=ctx.matrix, adopt=ctx.adopted)
    if run.gn is not None:  # resumed: the solver's CG reference as before the interruption
        lvl.solver.largest_rhs = run.gn.largest_rhs
    emit(ctx.progress, stage="matrix", level=s, nodes=list(mesh.nodes_shape), blocks=len(lvl.jobs),
         voxels=mesh.n_voxels, seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0,
         reused=lvl.m_reused, f_adopted=lvl.f_copy_ready)
    return lvl


def start_state(ctx: RunContext, run: RunState, lvl: Level, start: np.ndarray, t_int) -> None:
    """The Gauss–Newton state a level starts with: on the coarsest level of a new run the
    best of the candidate starts (:func:`best_start`), on finer levels the carried field."""
    if lvl.s == ctx.coarsest:
        start = best_start(ctx, run, lvl, start, t_int)
    run.gn = State(start)
    run.gn.m_start = lvl.m_start  # in the checkpoint: a resumed level rebuilds the very same M


def best_start(ctx: RunContext, run: RunState, lvl: Level, start: np.ndarray, t_int) -> np.ndarray:
    """The start of lowest gap on the coarsest level, shape (3, nz, ny, nx), voxels of the level.

    Candidates: no motion (the zero field), the rigid translation refined by Gauss–Newton
    then an affine field (paper section 5.1), and with ``init`` the earlier result's field
    (``start``; ``t_int`` is then ``None`` and the phase-correlation translation is found
    here). Without ``init``, no motion is a candidate only when the part of ``g`` prepared
    for the rigid field covers it (a motion within about an element): a larger translation
    found by phase correlation is trusted as before, without a second prefilter of ``g``
    for a field that cannot win. Each is measured by :meth:`Level.gap` and the lowest wins:
    an earlier result is a good start only when the motion goes on as before, and between
    two identical scans of a loading series the previous increment started the iterations
    at 13 % instead of 0.001 % and stalled them (docs/engine.md, "The start"). With ``init`` the rigid and
    affine passes run only when the translation alone already beats the other candidates,
    so a good earlier field costs three gap passes and one small task, not ten passes.
    ``run.rigid_t`` becomes the chosen start's translation (refined, or its mean).
    """
    mesh = lvl.mesh
    zero = np.zeros((3,) + mesh.nodes_shape)
    gaps, fields = {}, {}

    def measure(name: str, u: np.ndarray) -> None:
        lvl.prepare_interpolation(u)
        gaps[name], fields[name] = lvl.gap(u), u

    if t_int is not None:  # a new run: the rigid step as before, then compared with no motion
        fields["rigid"] = rigid_and_affine(ctx, run, lvl, t_int)
        measure("rigid", fields["rigid"])
        if lvl.prepared_for(zero):  # a motion within the prepared window's margin (≥ 8 voxels)
            measure("zero", zero)
    else:  # from an earlier result: that field, no motion, the translation alone
        measure("init", start)
        measure("zero", zero)
        t_int = run_one(ctx.runner, translation_task, (ctx.f_refs[lvl.s], ctx.g_refs[lvl.s], mesh.roi))
        measure("translation", uniform(t_int, mesh))
        if min(gaps, key=gaps.get) == "translation":
            measure("rigid", rigid_and_affine(ctx, run, lvl, t_int))
    chosen = min(gaps, key=gaps.get)  # ties: the first measured (the rigid step, or the earlier field)
    emit(ctx.progress, stage="start-choice", level=lvl.s, chosen=chosen, gaps=dict(gaps))
    if chosen != "rigid":
        run.rigid_t = fields[chosen].mean(axis=(1, 2, 3))
    # M was built around the earlier field (init) or the translation: again around another
    # start that moves some node by more than MOVED_START voxels (voxels mapped out of g differ)
    built_at = "init" if "init" in gaps else "rigid"
    moved = chosen != built_at and float(np.abs(fields[chosen] - lvl.m_start).max()) > MOVED_START
    t0, c0 = time.perf_counter(), time.process_time()
    lvl.settle_start(fields[chosen], rebuild=moved)
    if moved:
        emit(ctx.progress, stage="matrix", level=lvl.s, nodes=list(mesh.nodes_shape), blocks=len(lvl.jobs),
             voxels=mesh.n_voxels, seconds=time.perf_counter() - t0,
             cpu_seconds=time.process_time() - c0)
    return fields[chosen]


def rigid_and_affine(ctx: RunContext, run: RunState, lvl: Level, t_int) -> np.ndarray:
    """The rigid translation from ``t_int`` refined by Gauss–Newton (``run.rigid_t``), then
    the affine field from it: a uniform translation cannot start 10-20 % strain or a 10°
    rotation (12 unknowns, ``M`` restricted to affine fields: no extra voxel pass; docs/engine.md)."""
    lvl.prepare_interpolation(uniform(t_int, lvl.mesh))
    run.rigid_t = rigid_step(lvl, t_int, ctx.tolerance(lvl.s), RIGID_ITERATIONS, run.history, ctx.progress)
    return affine_step(lvl, run.rigid_t, ctx.tolerance(lvl.s), run.history, ctx.progress)


def measure_start_gaps(ctx: RunContext, run: RunState, lvl: Level) -> None:
    """The finest level's gaps of the zero and of the rigid field (reported, never iterated on),
    measured inside the level's first Gauss–Newton pass (:meth:`Level.assemble_b`'s ``probes``:
    the same element sample and brightness fit as :meth:`Level.gap`, from that pass's reads of
    ``f`` and ``g``), which :func:`solve_level` then iterates from instead of summing it again.
    Two voxel passes of their own before: ~10 s of a 254 s 1024³ run (docs/engine.md, "The start")."""
    t0, c0 = time.perf_counter(), time.process_time()
    rigid_fine = run.rigid_t * 2.0 ** (ctx.coarsest - ctx.finest)
    p = lvl.assemble_b(run.gn.u, probes={"initial": np.zeros((3,) + lvl.mesh.nodes_shape),
                                         "rigid": uniform(rigid_fine, lvl.mesh)})
    run.initial_gap, run.rigid_gap = p.probe_gaps["initial"], p.probe_gaps["rigid"]
    lvl.keep_first_pass(run.gn.u, p)
    emit(ctx.progress, stage="gaps", level=lvl.s, initial_gap=run.initial_gap, rigid_gap=run.rigid_gap,
         translation=rigid_fine.tolist(), seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0)


def solve_level(ctx: RunContext, run: RunState, lvl: Level) -> None:
    """Modified Gauss–Newton on the level from ``run.gn``, choosing the regularisation length
    on the finest level when the settings leave it automatic; checkpoints every pass.

    With the length still to choose, the level first iterates to the coarse levels'
    tolerance only and stops at the pass whose increment (or, shrinking fast, the increments
    still to come: :func:`~chunkdic.engine.stopping.still_to_come`) is below it without applying it:
    the choice linearises around that pass's field and ``b`` anyway, and the regularised
    iterations that follow converge it to the tolerance (each a ``b`` pass fewer).
    """
    s, settings = lvl.s, ctx.settings
    tol = ctx.tolerance(s)

    def save(gn: State) -> None:
        ctx.save(run, s)

    choosing = s == ctx.finest and length_to_choose(settings, run.gn)
    run.gn = iterate(lvl, run.gn, max(tol, settings.coarse_tolerance) if choosing else tol,
                     settings.max_iterations, run.history, ctx.progress, on_iteration=save, resolve=choosing,
                     first_pass=lvl.take_first_pass(run.gn.u))
    if choosing and run.gn.status == "converged":
        choose_regularization(lvl, run.gn, ctx.progress)
        run.gn = iterate(lvl, run.gn, tol, settings.max_iterations, run.history, ctx.progress,
                         on_iteration=save, first_pass=lvl.last_pass)


def finish_level(ctx: RunContext, run: RunState, lvl: Level, t0: float) -> LevelOutcome:
    """Record the level's status, checkpoint, free its scratch; what it leaves for the result."""
    s = lvl.s
    outcome = LevelOutcome(weak=unreliable_nodes(lvl, run.gn), masked=lvl.masked_nodes(), active=lvl.active,
                           reg_length=lvl.regularization_length * 2**s)
    lvl.release()
    run.statuses[s] = run.gn.status
    ctx.save(run, s)
    if ctx.matrix is not None and s != ctx.finest:  # no resumed run reads it now (the finest's goes with the checkpoint)
        ctx.matrix.drop()
    emit(ctx.progress, stage="level", level=s, status=run.gn.status, gap=run.gn.gap,
         seconds=time.perf_counter() - t0)
    if s == ctx.finest:  # the latest pass's noise (kept in the state: a level resumed after its end)
        p = run.gn if math.isfinite(run.gn.noise_variance) else resumed_pass(lvl, run.gn)
        outcome.sigma_u = nodal_uncertainty(lvl.solver, p.noise_variance, p.kappa)
        outcome.noise = {"sigma_r": float(np.sqrt(p.noise_variance)), "kappa": float(p.kappa)}
    return outcome


def unreliable_nodes(lvl: Level, state: State) -> np.ndarray:
    """The level's weak nodes (index triples, shape (n, 3)) and, when it converged at the
    noise level, the nodes its latest increment still moved by more than ``STEP_CAP`` σ_u:
    a few poorly seen nodes at the specimen's edge can run away while the rest of the field
    has stopped (docs/engine.md, "Iterations and stopping"); their values are not measured
    and are flagged ``FLAG_WEAK`` with the poorly textured ones."""
    weak = lvl.weak_nodes()
    if state.status != "converged" or state.unsettled is None or not state.unsettled.any():
        return weak
    moving = state.unsettled & ~lvl.masked_nodes()
    emit(lvl.progress, stage="unsettled", level=lvl.s, nodes=int(moving.sum()))
    return np.unique(np.concatenate([weak.reshape(-1, 3), np.argwhere(moving)]), axis=0)


def release_scan_levels(ctx: RunContext, s: int) -> None:
    """Delete the pyramid level ``s`` of both scans (and the mask) that the run wrote into scratch,
    once level ``s`` is done and a finer one follows.

    Every missing level is built at the start (each from the finest on disk below it), and
    nothing reads level ``s`` after its own Gauss–Newton iterations: at 2048³ the levels
    1–3 of a pair hold up to 9.8 GB that the level-0 run no longer needs
    (docs/engine.md, "Scratch disk"). Stored levels (the user's) are never touched.
    """
    if s == ctx.finest:
        return
    doomed = []
    for refs in (ctx.f_refs, ctx.g_refs, ctx.mask_refs or {}):
        ref = refs.get(s)
        if ref is None or ref.kind != "zarr" or not ref.key:
            continue
        path = Path(ref.path) / ref.key
        if Path(ctx.scratch).resolve() in path.resolve().parents:
            doomed.append(path)
    if doomed:
        ctx.runner.run_everywhere(forget_open_arrays)
        for path in doomed:
            shutil.rmtree(path, ignore_errors=True)


def regularization_length(settings: Settings, state: State, s: int, start: float) -> float:
    """``ℓ_reg`` for level ``s``, voxels of the level: given, chosen (resumed), or ``start``, the
    length the level starts with (:func:`chunkdic.engine.schedule.start_length`)."""
    if settings.regularization_length is not None:
        return settings.regularization_length / 2.0**s
    if math.isfinite(state.reg_length):
        return state.reg_length
    return start


def length_to_choose(settings: Settings, state: State) -> bool:
    """The finest level's regularisation length is automatic and not chosen yet."""
    return (settings.regularization != "none" and settings.regularization_length is None
            and not math.isfinite(state.reg_length))


def choose_regularization(lvl: Level, state: State, progress) -> None:
    """Choose ``ℓ_reg`` at the converged field (:func:`chunkdic.solve.regchoice.choose_length`),
    then ``settings.reweights`` times: free the curvature terms of the field this length
    gives (:func:`linearised_field`) beyond :data:`~chunkdic.solve.regularization.ROBUST_THRESHOLD`
    robust σ (:func:`~chunkdic.solve.regularization.robust_freed`) and choose the length again
    for the reweighted penalty (docs/engine.md, "Robust reweighting"); restart ``state``
    under the outcome, which the checkpoint keeps (``state.reg_length``, ``state.freed``)."""
    t0 = time.perf_counter()
    p = resumed_pass(lvl, state)
    u = np.moveaxis(state.u, 0, -1)
    last = {"half": None, "solver": None}

    def solve_with(half, reg, weight, rhs):
        # one solver per sub-mesh (its coarse M, block inverse and weak nodes reused by every
        # candidate); rtol 1e-5, as the iterations' since session 30 (1e-7 before: 30 % more
        # CG iterations for the same length on every case measured, docs/engine.md, "Automatic length")
        if last["half"] is not half:
            last["half"], last["solver"] = half, StencilSolver(half.copy(), rtol=1e-5)
        last["solver"].regularize(reg, weight)
        return last["solver"].solve(rhs)[0]

    def choose(freed, guess=None):
        return choose_length(lvl.settings.regularization, lvl.solver.matrix, lvl.mesh.element_size, u, p.b,
                             p.kappa * p.noise_variance, solve_with, kappa=p.kappa,
                             rule=lvl.settings.regularization_rule, freed=freed, guess=guess)

    # probed first: the length the level has iterated with so far (2ℓ; on heterogeneous fields
    # the choice is 1-3 candidates from it), not the middle candidate, whose long-length solve
    # was the slowest of the plain choice (docs/engine.md, "Robust reweighting", Cost); the
    # same choice
    choice = choose(None, guess=lvl.regularization_length)
    scale = 2.0**lvl.s
    corner = choice.l_curve_length * scale if math.isfinite(choice.l_curve_length) else None  # sweep only
    emit(progress, stage="regularization", level=lvl.s, length=choice.length * scale, l_curve_length=corner,
         kind=lvl.settings.regularization, kappa=p.kappa, rule=choice.rule, seconds=time.perf_counter() - t0)
    lvl.regularize(choice.length)
    length, freed = choice.length, None
    for k in range(lvl.settings.reweights):
        freed = robust_freed(linearised_field(lvl, u, p.b))
        terms = freed_terms(freed)
        if terms == 0:  # nothing beyond the threshold: the plain penalty, as chosen
            freed = None
            emit(progress, stage="reweighting", level=lvl.s, round=k + 1, freed=0, length=length * scale,
                 seconds=time.perf_counter() - t0)
            break
        length = choose(freed, guess=length).length  # the plain choice probed first
        lvl.regularize(length, freed)
        emit(progress, stage="reweighting", level=lvl.s, round=k + 1, freed=terms,
             fraction=terms / (3 * len(TERM_KINDS) * int(np.prod(lvl.mesh.nodes_shape))), length=length * scale,
             seconds=time.perf_counter() - t0)
    state.reg_length, state.freed = length, freed
    state.restart()


def linearised_field(lvl: Level, u: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The field the level's current regularisation gives in one modified Gauss–Newton step
    from ``u`` (nz, ny, nx, 3) with right-hand side ``b``: ``(M + λR) x = M u + b``, shape
    (nz, ny, nx, 3), voxels of the level; within 1 % of the converged field on the issue-20
    cases (docs/engine.md), and no pass over the voxels. The solver's CG reference
    (``largest_rhs``) is left as it was, so that the iterations that follow stop CG where
    they would have without this solve."""
    solver = lvl.solver
    rhs = solver.data_matvec(u)
    rhs += b
    kept = solver.largest_rhs
    x, _ = solver.solve(rhs, overwrite_b=True)
    solver.largest_rhs = kept
    return x


def assemble_result(ctx: RunContext, run: RunState, final: State, outcome: LevelOutcome) -> Result:
    """The finest level's field, flags, uncertainty and the run's facts as a :class:`Result`."""
    settings, finest, coarsest = ctx.settings, ctx.finest, ctx.coarsest
    mesh = ctx.meshes[finest]
    flags = node_flags(mesh, final.elements, outcome.weak, outcome.masked)
    missing = (flags & (FLAG_NO_DATA | FLAG_MASKED))[None] > 0
    u = np.where(missing, np.nan, final.u)
    sigma_u = None if outcome.sigma_u is None else np.where(missing, np.nan, outcome.sigma_u)
    status = run.statuses[finest]
    excluded_fraction = final.excluded / max(final.excluded + final.n_valid, 1)
    if status == "converged" and excluded_fraction > config.get("max-excluded-fraction"):
        status = run.statuses[finest] = "excluded"
    measured = int(np.count_nonzero((flags & (FLAG_NO_DATA | FLAG_MASKED)) == 0))
    weak_fraction = int(np.count_nonzero(flags & FLAG_WEAK)) / max(measured, 1)
    if status == "converged" and weak_fraction > config.get("max-weak-fraction"):
        # a half-untextured scan "converged" with 2-3.5 voxel errors on its flat half: the
        # iterations converged, but so many nodes are the regularisation's guesses
        status = run.statuses[finest] = "weak-texture"
    reg_length = outcome.reg_length
    info = {
        "element_size": settings.element_size,
        "roi": [[r.start, r.stop] for r in mesh.roi],
        "roi_level0": [[r.start * 2**finest, r.stop * 2**finest] for r in mesh.roi],
        "level": finest,
        "scale": 2**finest,
        "levels": ctx.levels,
        "level_status": {str(k): v for k, v in run.statuses.items()},
        "status": status,
        "converged": status == "converged",
        "initial_gap": run.initial_gap,
        "rigid_gap": run.rigid_gap,
        "final_gap": final.gap,
        "rigid_translation": (run.rigid_t * 2.0 ** (coarsest - finest)).tolist(),
        "excluded_voxels": int(final.excluded),
        "used_voxels": int(final.n_valid),
        "excluded_fraction": float(excluded_fraction),
        "nodes_without_data": int(np.count_nonzero(flags & FLAG_NO_DATA)),
        "masked_nodes": int(np.count_nonzero(flags & FLAG_MASKED)),
        "weak_nodes": int(np.count_nonzero(flags & FLAG_WEAK)),
        "grey_level": brightness_summary(settings.grey, final.elements),
        "noise": outcome.noise,
        "regularization": {"kind": settings.regularization,
                           "length": None if not np.isfinite(reg_length) else float(reg_length),
                           "automatic": settings.regularization_length is None,
                           # the robust reweighting: rounds asked, Tikhonov terms left out
                           "reweights": settings.reweights,
                           "freed_terms": freed_terms(final.freed),
                           # what l and the length let through of a sine, level-0 voxels (a lower
                           # bound of the spatial resolution; `chunkdic resolution` measures it)
                           "nominal_l10": nominal_l10(settings.element_size * 2**finest,
                                                      reg_length if np.isfinite(reg_length) else None)},
        "settings": settings.to_json(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "chunkdic_version": _version(),
    }
    brightness = None if final.elements is None else final.elements[:2]
    return Result(u, mesh.node_coords(), run.history.arrays(), info, flags=flags, brightness=brightness,
                  active=outcome.active, uncertainty=sigma_u)


def freed_terms(freed: np.ndarray | None) -> int:
    """How many Tikhonov terms (per component) the robust reweighting left out."""
    if freed is None:
        return 0
    return int(sum(np.count_nonzero(freed & (1 << c)) for c in range(3)))


def brightness_summary(model: str, elements: np.ndarray | None) -> dict:
    """Median gain and offset, offset range and drift of the last pass (``info["grey_level"]``)."""
    out = {"model": model}
    if elements is not None:
        used = elements[2] > 0
        gain, offset = elements[0][used], elements[1][used]
        if gain.size:
            out.update(gain=float(np.median(gain)), offset=float(np.median(offset)),
                       offset_range=[float(offset.min()), float(offset.max())],
                       drift=[float(v) for v in elements[3:, 0, 0, 0]])
    return out


def uniform(t, mesh: Mesh) -> np.ndarray:
    """A uniform nodal field ``t`` (3,) over ``mesh``: shape (3, nz, ny, nx)."""
    return np.asarray(t, dtype=np.float64)[:, None, None, None] * np.ones((3,) + mesh.nodes_shape)


def run_one(runner, fn, args):
    """Run one task on the runner and return its result."""
    return next(iter(runner.map_unordered(fn, [args])))


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("chunkdic")
    except PackageNotFoundError:
        return "unknown"
