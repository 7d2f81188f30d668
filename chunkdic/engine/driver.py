"""The C8-DIC driver: levels coarsest first, rigid step, Gauss–Newton per level, checkpoints.

Paper sections 3–4 (Roux, Hild, Viot, Bernard): the displacement is sought on 8-node
cubic elements; each level of the ``2^s`` sum pyramid is solved by modified Gauss–Newton
(:mod:`chunkdic.engine.gauss_newton`) with ``M`` built once from the reference and ``b``
re-assembled from the corrected deformed image at every iteration (:mod:`chunkdic.engine.level`,
:mod:`chunkdic.engine.tasks`). Out of core: every task reads its own block of ``f`` and the exact
window of ``g`` it needs from the store and returns mesh-sized partials that the client
adds up (shared/DESIGN.md, "Out-of-core shape").
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import shutil
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .. import config
from ..kernels import jit as kernels
from .checkpoint import Checkpoint, fingerprint, identify_input
from ..errors import InputError
from .affine import affine_step
from .gauss_newton import History, State, iterate, rigid_step
from .level import Level, emit
from .initial import init_identity, open_init, start_field
from ..mesh import transfer
from ..io.outputs import Outputs
from ..io.ownership import OutputLock, make_scratch
from .planning import parse_roi, plan_meshes
from .prefilter import face_margin
from .masks import check_mask_shape, prepare_mask
from .noise import nodal_uncertainty
from ..solve.regchoice import choose_length
from ..results.result import FLAG_MASKED, FLAG_NO_DATA, FLAG_WEAK, Result, node_flags
from .rigid import translation_task
from ..scheduler import check_scheduler, open_runner
from .settings import Settings
from ..io.scan import open_scan

__all__ = ["correlate", "Settings"]


def correlate(
    ref,
    deformed,
    settings: Settings | None = None,
    *,
    roi=None,
    scheduler=None,
    output=None,
    overwrite: bool = False,
    progress: Callable[[dict], None] | None = None,
    mask=None,
    init=None,
    **options,
) -> Result:
    """Measure the displacement field between two scans by multiscale C8-DIC.

    Parameters
    ----------
    ref, deformed : str, Path, ndarray, dask array or zarr array/group
        Reference ``f`` and deformed ``g`` scans (see :func:`chunkdic.open_scan`); shapes
        may differ. Convention: ``f(X) = g(X + u(X))``.
    settings : Settings, optional
        Algorithm settings; keyword ``options`` (any :class:`Settings` field, e.g.
        ``element_size=16``, ``level=2``, ``interpolation="linear"``) override its fields
        or, without ``settings``, make a new one (``element_size`` is then required).
    roi : str or sequence, optional
        ``"z0:z1,y0:y1,x0:x1"`` in level-0 voxels; default: the largest centred box of
        whole elements with a small margin. Trimmed to whole elements (reported).
    scheduler : None, "threads", "local[:N]", address or distributed.Client
        Where tasks run (see :func:`chunkdic.scheduler.open_runner`).
    output : path, optional
        Write the result there as a Zarr v3 group; a checkpoint after every iteration
        lets an interrupted run resume (same command, inputs unchanged). One run at a
        time per output (a lock file next to it). An existing output is refused unless
        ``overwrite``, which replaces only a result chunkdic wrote, never an input
        (:mod:`chunkdic.io.outputs`).
    progress : callable, optional
        Called with a dict per event (``stage`` = "rigid", "iteration", "level", ...).
    mask : str, Path, array, optional
        Specimen mask of the reference's shape (any input :func:`chunkdic.open_scan`
        reads; non-zero = material): only elements with enough material take part, nodes
        outside are NaN (:mod:`chunkdic.engine.masks`).
    init : str, Path or Result, optional
        An earlier result to start from instead of the rigid translation (a previous
        step of a loading series, another element size, ROI or level): its field is
        evaluated at this run's nodes on the level the run starts on, which is the
        finest level unless ``coarsest`` is given (:mod:`chunkdic.engine.initial`). Checked
        before any output (a result of the same reference shape); recorded in
        ``info["init"]`` and in the resume fingerprint.

    Returns
    -------
    Result
        ``displacement`` (3, nz, ny, nx) float64 in voxels of ``level`` and the rest
        (see :class:`chunkdic.Result`).

    References
    ----------
    Roux, Hild, Viot, Bernard, sections 3 (C8-DIC, multiscale), 4.2 and 5.1 (gap).

    Examples
    --------
    >>> import numpy as np, chunkdic
    >>> rng = np.random.default_rng(0)
    >>> f = rng.random((40, 40, 40)).astype(np.float32)
    >>> g = np.roll(f, 1, axis=0)  # g(x) = f(x - (1, 0, 0))
    >>> res = chunkdic.correlate(f, g, element_size=16, coarsest=0)
    >>> round(float(res.displacement[0].mean()), 3), res.info["status"]
    (1.0, 'converged')
    """
    settings = settings_from(settings, options)
    f_scan, g_scan = open_scan(ref), open_scan(deformed)
    init_result = None if init is None else open_init(init, f_scan.shape(0))
    # with a start field, no coarse level is needed to find the large displacements (chunkdic.engine.initial)
    coarsest = settings.level if init is not None and settings.coarsest is None else settings.coarsest
    meshes = plan_meshes(f_scan.shape(0), element_size=settings.element_size, roi=roi,
                         level=settings.level, coarsest=coarsest,
                         min_margin=face_margin(settings.smoothing))
    levels = sorted(meshes, reverse=True)
    for s in levels:
        if min(g_scan.shape(s)) < 2:
            raise InputError(f"the deformed scan is too small at level {s} ({g_scan.shape(s)})")
    mask_scan = None if mask is None else open_scan(mask)
    if mask_scan is not None:
        check_mask_shape(mask_scan, f_scan.shape(0))
    plan = entry = None
    if output is not None:  # every output rule (chunkdic.io.outputs), nothing written yet
        plan = Outputs(inputs=(ref, deformed, mask, _init_path(init_result)), overwrite=overwrite)
        entry = plan.add(output, "result", resumable=True)
    identities = {role: identify_input(src, scan) for role, src, scan in
                  (("reference", ref, f_scan), ("deformed", deformed, g_scan))}
    if mask is not None:
        identities["mask"] = identify_input(mask, mask_scan)
    described = {"settings": settings.to_json(), "roi": parse_roi(roi),
                 "inputs": [identities["reference"], identities["deformed"]], "mask": identities.get("mask")}
    init_id = None
    if init_result is not None:  # absent otherwise: fingerprints of runs without init are unchanged
        init_id = described["init"] = init_identity(init_result)
        if init_result.path is None:  # an in-memory result never resumes, as in-memory scans
            init_id["in-memory"] = uuid.uuid4().hex
    run_print = fingerprint(described)
    check_scheduler(scheduler)  # an unreachable or foreign address: refused before anything is written
    scratch = make_scratch()  # also reclaims the scratch of dead runs
    try:
        with contextlib.ExitStack() as stack:
            if output is not None:
                stack.enter_context(OutputLock(output))  # one writer per output
            runner = stack.enter_context(open_runner(scheduler))
            ckpt = resume = None
            if output is not None:
                ckpt, resume = _start_output(plan, entry, run_print, identities)
            try:
                emit(progress, stage="start", scheduler=repr(runner), dashboard=runner.dashboard_link,
                     levels=levels, roi=[[r.start, r.stop] for r in meshes[settings.level].roi],
                     requested_roi=None if roi is None else [list(p) for p in parse_roi(roi)],
                     nodes=list(meshes[settings.level].nodes_shape))
                # inside the runner: with a cluster, missing levels are built by its workers
                f_refs = f_scan.refs(levels, scratch / "ref", runner=runner)
                g_refs = g_scan.refs(levels, scratch / "def", runner=runner)
                mask_refs = None if mask is None else prepare_mask(mask, f_scan.shape(0), levels, scratch / "mask",
                                                                    runner)
                _compile_kernels(runner, progress)
                result = _run(settings, meshes, levels, f_refs, g_refs, runner, progress, scratch, ckpt, resume,
                              mask_refs, init_result)
            except (InputError, OSError) as exc:
                # bad input found by a pass (a constant or non-finite image), or a full or read-only
                # disk before the first checkpoint: nothing to resume, so what this run created goes.
                # A checkpoint this run saved stays for a re-run to resume (marked incomplete), and
                # so does a resumed run's, which was there before.
                fresh = plan is not None and resume is None
                if fresh and (isinstance(exc, InputError) or ckpt is None or not ckpt.saved):
                    plan.rollback()
                raise
            result.info.update(
                voxel_size=f_scan.voxel_size, unit=f_scan.unit, fingerprint=run_print,
                inputs={"reference": _describe(ref), "deformed": _describe(deformed),
                        "mask": None if mask is None else _describe(mask)},
                input_shapes={"reference": list(f_scan.shape(0)), "deformed": list(g_scan.shape(0))},
                init=init_id,
            )
            if init_id is not None:
                result.info["settings"] = dict(result.info["settings"], init=init_id)
            if output is not None:  # replaces the checkpointed group once complete, under the lock
                result.save(output, overwrite=True, inputs=(ref, deformed, mask, _init_path(init_result)))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return result


def _start_output(plan: Outputs, entry, run_print: str, identities: dict):
    """Under the lock: replace an old result (``--overwrite``), then start or resume."""
    if entry.state == "resume":
        return Checkpoint.start(entry.final, run_print, identities=identities)
    plan.__enter__()  # removes the old result that --overwrite replaces (checked: ours, a result)
    if entry.final.exists():  # created meanwhile by another run, which has finished
        raise InputError(f"output {entry.final} appeared while this run was starting: choose another path "
                         "or pass --overwrite")
    return Checkpoint.start(entry.final, run_print, identities=identities)


def settings_from(settings: Settings | None, options: dict) -> Settings:
    """``settings`` (default ``Settings()``) with the keyword ``options`` of a call applied, checked."""
    unknown = set(options) - set(Settings.names())
    if unknown:
        raise TypeError(f"correlate() got unexpected keyword arguments {sorted(unknown)}")
    if settings is None:
        if "element_size" not in options:
            raise TypeError("correlate() needs element_size (or settings=Settings(...))")
        return Settings(**options)
    return dataclasses.replace(settings, **options)


def _init_path(init_result: Result | None):
    """The earlier result's path as an input of the output rules (it may not be the output)."""
    return None if init_result is None else init_result.path


def _run(settings: Settings, meshes, levels, f_refs, g_refs, runner, progress, scratch: Path,
         checkpoint=None, resume: dict | None = None, mask_refs: dict | None = None,
         init: Result | None = None) -> Result:
    """All levels, coarsest first; resumes from ``resume`` (a checkpoint state) if given.

    ``init``: an earlier result whose field is the start on the coarsest level, instead of
    the rigid translation (:mod:`chunkdic.engine.initial`)."""
    finest, coarsest = levels[-1], levels[0]
    statuses: dict[int, str] = {}
    rigid_t = initial_gap = rigid_gap = None
    state = None
    weak = []  # poorly textured nodes of the finest level
    masked, active = None, None  # nodes outside the mask, active elements (finest level)
    sigma_u, noise = None, {}  # per-node uncertainty and the noise it comes from (finest level)
    reg_length = math.nan  # regularisation length of the finest level, level-0 voxels
    history = History()
    if resume is not None:
        history = History(resume["history"])
        statuses = {int(k): v for k, v in resume["statuses"].items()}
        rigid_t = np.array(resume["rigid_t"])
        initial_gap, rigid_gap = resume.get("initial_gap"), resume.get("rigid_gap")
        state = State.restore(resume["gn"], resume["arrays"])
        emit(progress, stage="resume", level=resume["level"], iteration=state.iteration)
    u = None

    def save_checkpoint(st: State, s: int) -> None:
        if checkpoint is None:
            return
        checkpoint.save(
            {"level": s, "gn": st.scalars(), "statuses": {str(k): v for k, v in statuses.items()},
             "history": history.to_json(), "rigid_t": rigid_t.tolist(),
             "initial_gap": initial_gap, "rigid_gap": rigid_gap},
            st.arrays(),
        )

    for s in levels:
        if resume is not None and s > resume["level"]:
            continue  # finished before the interruption
        mesh = meshes[s]
        tol = settings.tolerance if s == finest else settings.coarse_tolerance
        if state is None or state.status is None:
            t0, c0 = time.perf_counter(), time.process_time()
            if state is not None:
                start = state.u  # resumed
            elif s == coarsest and init is not None:
                start = start_field(init, mesh, s)
                emit(progress, stage="init", level=s, path=init.path,
                     mean=[float(v) for v in start.mean(axis=(1, 2, 3))])
            elif s == coarsest:
                t_int = run_one(runner, translation_task, (f_refs[s], g_refs[s], mesh.roi))
                start = _uniform(t_int, mesh)
            else:
                start = transfer(u, meshes[s + 1], s + 1, mesh, s)
            lvl = Level(s, mesh, f_refs[s], g_refs[s], runner, settings, scratch, progress,
                        None if mask_refs is None else mask_refs[s])
            lvl.assemble_m(start)
            emit(progress, stage="matrix", level=s, nodes=list(mesh.nodes_shape), blocks=len(lvl.jobs),
                 voxels=mesh.n_voxels, seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0)
            if state is None:
                if s == coarsest and init is not None:
                    rigid_t = start.mean(axis=(1, 2, 3))  # reported as the run's mean start translation
                elif s == coarsest:
                    lvl.prepare_interpolation(start)
                    rigid_t = rigid_step(lvl, t_int, tol, 10, history, progress)
                    start = affine_step(lvl, rigid_t, tol, history, progress)
                state = State(start)
            lvl.regularize(_regularization_length(settings, state, s, mesh))
            lvl.prepare_interpolation(state.u)
            if s == finest and initial_gap is None:
                rigid_fine = rigid_t * 2.0 ** (coarsest - finest)
                initial_gap = lvl.gap(np.zeros((3,) + mesh.nodes_shape))
                rigid_gap = lvl.gap(_uniform(rigid_fine, mesh))
                emit(progress, stage="gaps", level=s, initial_gap=initial_gap, rigid_gap=rigid_gap,
                     translation=rigid_fine.tolist())
            # With the length still to choose, iterate only to the coarse levels' tolerance
            # first, and stop at the pass whose increment is below it without applying it:
            # the choice linearises around that pass's field and `b` anyway, and the
            # regularised iterations that follow converge it to `tol` (each a b pass fewer)
            choosing = s == finest and _length_to_choose(settings, state)
            state = iterate(lvl, state, max(tol, settings.coarse_tolerance) if choosing else tol,
                            settings.max_iterations, history, progress,
                            on_iteration=lambda st, s=s: save_checkpoint(st, s), resolve=choosing)
            if s == finest and _choose_automatically(settings, state):
                state = _with_chosen_regularization(lvl, state, progress)
                state = iterate(lvl, state, tol, settings.max_iterations, history, progress,
                                on_iteration=lambda st, s=s: save_checkpoint(st, s), first_pass=lvl.last_pass)
            reg_length = lvl.regularization_length * 2**s
            lvl.release()
            statuses[s] = state.status
            save_checkpoint(state, s)
            emit(progress, stage="level", level=s, status=state.status, gap=state.gap,
                 seconds=time.perf_counter() - t0)
            weak, masked, active = lvl.weak_nodes(), lvl.masked_nodes(), lvl.active
            if s == finest:
                p = lvl.last_pass
                sigma_u = nodal_uncertainty(lvl.solver, p.noise_variance, p.kappa)
                noise = {"sigma_r": float(np.sqrt(p.noise_variance)), "kappa": float(p.kappa)}
        final, u, state = state, state.u, None
    mesh = meshes[finest]
    flags = node_flags(mesh, final.elements, weak, masked)
    missing = (flags & (FLAG_NO_DATA | FLAG_MASKED))[None] > 0
    u = np.where(missing, np.nan, u)
    if sigma_u is not None:
        sigma_u = np.where(missing, np.nan, sigma_u)
    status = statuses[finest]
    excluded_fraction = final.excluded / max(final.excluded + final.n_valid, 1)
    if status == "converged" and excluded_fraction > config.get("max-excluded-fraction"):
        status = statuses[finest] = "excluded"
    info = {
        "element_size": settings.element_size,
        "roi": [[r.start, r.stop] for r in mesh.roi],
        "roi_level0": [[r.start * 2**finest, r.stop * 2**finest] for r in mesh.roi],
        "level": finest,
        "scale": 2**finest,
        "levels": levels,
        "level_status": {str(k): v for k, v in statuses.items()},
        "status": status,
        "converged": status == "converged",
        "initial_gap": initial_gap,
        "rigid_gap": rigid_gap,
        "final_gap": final.gap,
        "rigid_translation": (rigid_t * 2.0 ** (coarsest - finest)).tolist(),
        "excluded_voxels": int(final.excluded),
        "used_voxels": int(final.n_valid),
        "excluded_fraction": float(excluded_fraction),
        "nodes_without_data": int(np.count_nonzero(flags & FLAG_NO_DATA)),
        "masked_nodes": int(np.count_nonzero(flags & FLAG_MASKED)),
        "weak_nodes": int(np.count_nonzero(flags & FLAG_WEAK)),
        "grey_level": _brightness_summary(settings.grey, final.elements),
        "noise": noise,
        "regularization": {"kind": settings.regularization,
                           "length": None if not np.isfinite(reg_length) else float(reg_length),
                           "automatic": settings.regularization_length is None},
        "settings": settings.to_json(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "chunkdic_version": _version(),
    }
    brightness = None if final.elements is None else final.elements[:2]
    return Result(u, mesh.node_coords(), history.arrays(), info, flags=flags, brightness=brightness,
                  active=active, uncertainty=sigma_u)


def _brightness_summary(model: str, elements: np.ndarray | None) -> dict:
    out = {"model": model}
    if elements is not None:
        used = elements[2] > 0
        gain, offset = elements[0][used], elements[1][used]
        if gain.size:
            out.update(gain=float(np.median(gain)), offset=float(np.median(offset)),
                       offset_range=[float(offset.min()), float(offset.max())],
                       drift=[float(v) for v in elements[3:, 0, 0, 0]])
    return out


#: the regularisation length before (coarse levels: instead of) the automatic choice, in element sizes
START_LENGTH = 2.0


def _regularization_length(settings: Settings, state: State, s: int, mesh) -> float:
    """``ℓ_reg`` for level ``s``, voxels of the level: given, chosen (resumed), or the starting one."""
    if settings.regularization_length is not None:
        return settings.regularization_length / 2.0**s
    if math.isfinite(state.reg_length):
        return state.reg_length
    return START_LENGTH * mesh.element_size


def _compile_kernels(runner, progress) -> None:
    """Compile (or load from numba's cache) the workers' block kernels and the client's solver.

    The first run on a machine compiles for ~20 s before the first iteration: say so first,
    and report the time (the stage timings would otherwise hide it).
    """
    from ..solve import cg as solve

    cold = not kernels.compiled_on_disk()
    if cold:
        emit(progress, stage="compile", done=False)
    t0 = time.perf_counter()
    runner.run_everywhere(kernels.warmup)
    solve.warmup()
    if cold:
        emit(progress, stage="compile", done=True, seconds=time.perf_counter() - t0)


def _length_to_choose(settings: Settings, state: State) -> bool:
    return (settings.regularization != "none" and settings.regularization_length is None
            and not math.isfinite(state.reg_length))


def _choose_automatically(settings: Settings, state: State) -> bool:
    return _length_to_choose(settings, state) and state.status == "converged"


def _with_chosen_regularization(lvl: Level, state: State, progress) -> State:
    """Choose ``ℓ_reg`` at the converged field (:func:`chunkdic.solve.regchoice.choose_length`), restart."""
    p = lvl.last_pass
    u = np.moveaxis(state.u, 0, -1)

    last = {"half": None, "solver": None}

    def solve_with(half, reg, weight, rhs):
        from ..solve.cg import StencilSolver

        # one solver per sub-mesh (its coarse M, block inverse and weak nodes reused by every
        # candidate); rtol 1e-5, not the iterations' 1e-7: 30 % fewer CG iterations, and the
        # same length chosen on every case measured (docs/engine.md, "Automatic length")
        if last["half"] is not half:
            last["half"], last["solver"] = half, StencilSolver(half.copy(), rtol=1e-5)
        last["solver"].regularize(reg, weight)
        return last["solver"].solve(rhs)[0]

    choice = choose_length(lvl.settings.regularization, lvl.solver.matrix, lvl.mesh.element_size, u, p.b,
                           p.kappa * p.noise_variance, solve_with)
    scale = 2.0**lvl.s
    corner = choice.l_curve_length * scale if math.isfinite(choice.l_curve_length) else None  # sweep only
    emit(progress, stage="regularization", level=lvl.s, length=choice.length * scale, l_curve_length=corner,
         kind=lvl.settings.regularization, kappa=p.kappa)
    lvl.regularize(choice.length)
    state.reg_length = choice.length
    state.restart()
    return state


def _uniform(t, mesh) -> np.ndarray:
    """A uniform nodal field ``t`` (3,) over ``mesh``: shape (3, nz, ny, nx)."""
    return np.asarray(t, dtype=np.float64)[:, None, None, None] * np.ones((3,) + mesh.nodes_shape)


def run_one(runner, fn, args):
    """Run one task on the runner and return its result."""
    return next(iter(runner.map_unordered(fn, [args])))


def _describe(src) -> str:
    if isinstance(src, (str, Path)):
        return str(Path(src).resolve())
    return f"<in-memory {type(src).__name__}>"


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("chunkdic")
    except PackageNotFoundError:
        return "unknown"

