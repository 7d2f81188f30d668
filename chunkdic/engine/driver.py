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
import logging
import shutil
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import dask.config

from .. import config
from ..errors import InputError
from ..io.formats.anyscan import open_any
from ..io.outputs import Outputs
from ..io.ownership import (OutputLock, adopt_scratch, directory_bytes, interrupted_run_of, leave_scratch,
                            make_scratch, reclaim_stale_scratch)
from ..io.scan import open_scan
from ..io.units import lengths_in_voxels
from ..kernels import jit as kernels
from ..results.result import Result
from ..scheduler import check_scheduler, open_runner
from ..solve import cg as solve
from .budget import calibrated, make_plan, memory_target_of
from .checkpoint import (
    Checkpoint,
    completed_already,
    fingerprint,
    identify_input,
    kept_checkpoint_error,
)
from .events import emit
from .haloed import COMPLETE
from .initial import init_identity, open_init
from .level import prune_adopted
from .masks import check_mask_shape, prepare_mask
from .planning import parse_roi, plan_meshes
from .prefilter import face_margin
from .runstate import LevelOutcome, RunState
from .schedule import measure_texture, start_length
from .settings import Settings
from .stored_matrix import StoredMatrix
from .steps import (
    RunContext,
    assemble_result,
    finish_level,
    measure_start_gaps,
    open_level,
    regularization_length,
    release_scan_levels,
    solve_level,
    start_field,
    start_state,
)

__all__ = ["correlate", "Settings"]

log = logging.getLogger(__name__)


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
    roi_unit: str | None = None,
    memory_target=None,
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
        ``element_size`` may be a physical length, ``"80um"``, converted with the reference's
        voxel size and rounded to whole voxels of ``level``, as ``--element-size`` does
        (:func:`chunkdic.io.units.lengths_in_voxels`; the conversion is logged).
    roi : str or sequence, optional
        ``"z0:z1,y0:y1,x0:x1"`` in level-0 voxels, in ``roi_unit``, or with a unit suffix
        (``"0:500,0:500,0:500um"``); default: the largest centred box of whole elements with
        a small margin. Trimmed to whole elements (reported).
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
        An earlier result to start from (a previous step of a loading series, another
        element size, ROI or level), when its gap is lower than no motion's and the rigid
        translation's (docs/engine.md, "The start"): its field is
        evaluated at this run's nodes on the level the run starts on, which is the
        finest level unless ``coarsest`` is given (:mod:`chunkdic.engine.initial`). Checked
        before any output (a result of the same reference shape); recorded in
        ``info["init"]`` and in the resume fingerprint.
    roi_unit : str, optional
        Length unit of a ``roi`` string without suffix (``"um"``), as ``--roi-unit``.
    memory_target : str or int, optional
        Peak resident memory per process to plan for (``"2GiB"`` or bytes; default
        ``chunkdic.memory-target``): blocks and prefilter tasks are sized to fit it
        (:mod:`chunkdic.engine.budget`). A run it cannot hold, or whose scratch or output
        the free disk cannot hold, is refused (:class:`InputError`) before anything is
        written; :func:`chunkdic.plan` shows the plan without running.

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
    options, roi = voxel_lengths(settings, options, roi, roi_unit, ref)
    settings = settings_from(settings, options)
    f_scan, g_scan = open_scan(ref), open_scan(deformed)
    for role, scan in (("reference", f_scan), ("deformed scan", g_scan)):
        if scan.dtype(0) == bool:  # a mask is bool; a scan to correlate must have grey levels
            raise InputError(f"the {role} is a two-level (bool) image: it has no sub-voxel information; correlate "
                             "the grey-level scan it was segmented from")
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
    mask_scan = None if mask is None else open_any(mask)  # also a TIFF or HDF5 mask, read in place
    if mask_scan is not None:
        check_mask_shape(mask_scan, f_scan.shape(0))
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
    plan = entry = None
    if output is not None and not overwrite:
        done = completed_already(output, run_print)  # the same command re-run on its own complete result
        if done is not None:
            emit(progress, stage="complete", path=str(output))
            return done
    budget = make_plan(f_scan, g_scan, meshes, settings, scheduler=scheduler, output=output,
                       target=memory_target_of(memory_target))
    budget.check()  # memory target and free disk: refused before anything is written
    if output is not None:  # every output rule (chunkdic.io.outputs), nothing written yet
        plan = Outputs(inputs=(ref, deformed, mask, _init_path(init_result)), overwrite=overwrite)
        entry = plan.add(output, "result", resumable=True)
    check_scheduler(scheduler)  # an unreachable or foreign address: refused before anything is written
    scratch = None
    with contextlib.ExitStack() as stack:
        if budget.memory_target is not None:  # the block and prefilter task sizes the target chose
            stack.enter_context(dask.config.set({"chunkdic.block-voxels": budget.block_voxels,
                                                 "chunkdic.prepare-voxels": budget.prepare_edge}))
        # the scratch layout the plan chose (compact only when the fast one does not fit)
        stack.enter_context(dask.config.set({"chunkdic.scratch-layout": budget.layout}))
        if output is not None:
            stack.enter_context(OutputLock(output))  # one writer per output
        # the scratch is removed (or left for the resume) once the runner is closed (no task
        # writes into it) and before the lock goes: the next run of the output may adopt it
        kept_for = (str(output), run_print) if _resumable(output, identities, init_id) else None
        stack.callback(lambda: scratch is not None and _close_scratch(scratch, kept_for, progress))
        runner = stack.enter_context(open_runner(scheduler))
        ckpt = resume = None
        if output is not None:
            ckpt, resume = _start_output(plan, entry, run_print, identities)
        try:
            # an interrupted run of this very run (its output was there): its scratch is
            # adopted when that run is over (killed, or ended interrupted), else a new one (also
            # reclaims dead runs' scratch, but not what is kept for other outputs' resumes)
            resuming = output is not None and entry.state == "resume"
            scratch, adopted = _open_scratch(_scratch_identity(run_print, output, runner), resuming,
                                             None if resume is None else int(resume["level"]),
                                             kept_for)
            emit(progress, stage="start", scheduler=repr(runner), dashboard=runner.dashboard_link,
                 levels=levels, roi=[[r.start, r.stop] for r in meshes[settings.level].roi],
                 requested_roi=None if roi is None else [list(p) for p in parse_roi(roi)],
                 nodes=list(meshes[settings.level].nodes_shape))
            # a resumed run needs no level coarser than the one it was solving (done)
            needed = levels if resume is None else [s for s in levels if s <= int(resume["level"])]
            # inside the runner: with a cluster, missing levels are built by its workers
            f_refs = f_scan.refs(needed, scratch / "ref", runner=runner, adopt=adopted)
            g_refs = g_scan.refs(needed, scratch / "def", runner=runner, adopt=adopted)
            mask_refs = None if mask is None else prepare_mask(mask_scan, f_scan.shape(0), needed, scratch / "mask",
                                                                runner)
            _compile_kernels(runner, progress)
            emit(progress, stage="plan", plan=calibrated(budget, g_scan, settings))
            ctx = RunContext(settings, meshes, levels, f_refs, g_refs, runner, scratch, progress, ckpt,
                             mask_refs, init_result, matrix=None if ckpt is None else StoredMatrix(ckpt.path),
                             adopted=adopted)
            result = _run(ctx, None if resume is None else RunState.from_checkpoint(resume))
        except (InputError, OSError) as exc:
            # bad input found by a pass (a constant or non-finite image), or a full or read-only
            # disk before the first checkpoint: nothing to resume, so what this run created goes.
            # A checkpoint this run saved stays for a re-run to resume (marked incomplete), and
            # so does a resumed run's, which was there before.
            fresh = plan is not None and resume is None
            if fresh and (isinstance(exc, InputError) or ckpt is None or not ckpt.saved):
                plan.rollback()
            elif isinstance(exc, OSError) and ckpt is not None:
                raise kept_checkpoint_error(exc, output) from None  # say it is kept, and how to resume
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
            try:
                result.save(output, overwrite=True, inputs=(ref, deformed, mask, _init_path(init_result)))
            except OSError as exc:  # the staged copy is gone, the checkpoint stays
                raise kept_checkpoint_error(exc, output) from None
    return result


#: the settings of ``chunkdic.`` (dask config) that a scratch directory's stores depend on
SCRATCH_CONFIG = ("block-voxels", "scratch-precision", "scratch-layout", "bspline-halo", "chunk-size", "compressor")


def _scratch_identity(run_print: str, output, runner) -> str | None:
    """What a scratch directory's stores depend on beyond the run's fingerprint: the output
    (one run per output), the configuration of :data:`SCRATCH_CONFIG` (blocks, the scratch
    layout the plan chose and its precision, chunks and codecs of the pyramid levels, the
    B-spline halo) and whether every task is local (the prepared ``g`` is then a
    memory-mapped file). None without an output: such a run never resumes."""
    if output is None:
        return None
    return fingerprint({"run": run_print, "output": str(Path(output).resolve()),
                        "config": {key: config.get(key) for key in SCRATCH_CONFIG}, "local": bool(runner.local)})


def _open_scratch(identity: str | None, resuming: bool, level: int | None,
                  resume: tuple[str, str] | None = None) -> tuple[Path, bool]:
    """The run's scratch directory and whether it is adopted from the interrupted run.

    Resuming (the output held this run's checkpoint), the scratch directory the interrupted
    run of the same ``identity`` left (its process dead, or it ended interrupted) is adopted
    (:func:`chunkdic.io.ownership.adopt_scratch`) and pruned to the stores of the ``level``
    it was solving (:func:`chunkdic.engine.level.prune_adopted`); each store is reused only
    when complete (checked where it is opened). Otherwise a new one. ``resume``: ``(output,
    fingerprint)``, recorded so that the directory is kept for the resume of that output
    should this run be interrupted; other dead runs' scratch, and any other kept for this
    output (this run holds its lock: it resumes or starts that run over), is reclaimed.
    """
    if resuming and identity is not None:
        adopted = adopt_scratch(identity, resume=resume)
        if adopted is not None:
            reclaim_stale_scratch(release=None if resume is None else resume[0])  # make_scratch does it otherwise
            prune_adopted(adopted, level)
            return adopted, True
    return make_scratch(run=identity, resume=resume), False


def _resumable(output, identities: dict, init_id: dict | None) -> bool:
    """Whether the same command can resume this run: it has an output and every input is on
    disk (an in-memory input's identity is random: such a run never resumes)."""
    ids = [*(i for i in identities.values() if i is not None), init_id or {}]
    return output is not None and not any("in-memory" in i for i in ids)


def _close_scratch(scratch: Path, kept_for: tuple[str, str] | None, progress) -> None:
    """Remove the run's scratch directory, unless the run was interrupted with its checkpoint
    kept (Ctrl-C, a lost cluster, a full disk after a checkpoint: the output of ``kept_for =
    (output, fingerprint)`` holds this run's checkpoint, marked incomplete): then it is left
    for the resume, which adopts it instead of preparing the scans again, and no other run
    reclaims it while the output stays so (:func:`chunkdic.io.ownership.leave_scratch`).
    ``kept_for`` None: a run that cannot resume. The runner is closed by now: no task of
    this run writes into it any more."""
    if kept_for is not None and interrupted_run_of(*kept_for):
        output = kept_for[0]
        try:
            leave_scratch(scratch)
            emit(progress, stage="scratch-kept", path=str(scratch), bytes=directory_bytes(scratch),
                 output=str(output))
            return
        except OSError:  # its owner record cannot be rewritten (a full disk): it goes, as before
            pass
    shutil.rmtree(scratch, ignore_errors=True)


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


def voxel_lengths(settings: Settings | None, options: dict, roi, roi_unit, ref) -> tuple[dict, object]:
    """``element_size`` and ``roi`` in voxels (physical lengths converted with the reference's
    voxel size, as the CLI converts them; each conversion logged)."""
    level = options.get("level", settings.level if settings is not None else 0)
    ell, roi, notes = lengths_in_voxels(options.get("element_size"), roi, roi_unit=roi_unit, reference=ref,
                                        level=level)
    for note in notes:
        log.info("%s", note)
    return ({**options, "element_size": ell} if "element_size" in options else options), roi


def _init_path(init_result: Result | None):
    """The earlier result's path as an input of the output rules (it may not be the output)."""
    return None if init_result is None else init_result.path


def _run(ctx: RunContext, run: RunState | None = None) -> Result:
    """All levels, coarsest first (paper section 3), from a fresh or a resumed ``run``."""
    if run is None:
        run = RunState()
    else:
        emit(ctx.progress, stage="resume", level=run.resumed_level, iteration=run.gn.iteration,
             reused=_reused(ctx, run))
    u, outcome = None, LevelOutcome()
    texture = measure_texture(ctx.runner, ctx.f_refs[ctx.finest], ctx.meshes[ctx.finest], ctx.finest, ctx.progress)
    for s in ctx.levels:
        if run.done_before_resume(s):
            release_scan_levels(ctx, s)
            continue
        if run.level_to_solve(s, ctx.finest):
            t0 = time.perf_counter()
            start, t_int = start_field(ctx, run, s, u)
            lvl = open_level(ctx, run, s, start)
            if run.gn is None:
                start_state(ctx, run, lvl, start, t_int)
            start = start_length(lvl.mesh.element_size, texture / 2.0 ** (s - ctx.finest))
            lvl.regularize(regularization_length(ctx.settings, run.gn, s, start), run.gn.freed)
            # a level resumed after its iterations ended (killed at "converged") may run no pass
            lvl.prepare_interpolation(run.gn.u, when_needed=run.gn.status is not None)
            if s == ctx.finest and run.initial_gap is None:
                measure_start_gaps(ctx, run, lvl)
            solve_level(ctx, run, lvl)
            outcome = finish_level(ctx, run, lvl, t0)
            # the level's M, solver and last pass go now: not held through the next level's
            # M pass (an eighth of its own) or the result's assembly (docs/distributed.md)
            lvl = None
        release_scan_levels(ctx, s)
        final, u, run.gn = run.gn, run.gn.u, None
    return assemble_result(ctx, run, final, outcome)


def _reused(ctx: RunContext, run: RunState) -> list[str]:
    """What a resumed run finds of the interrupted one for the first level it solves (the
    checkpoint's, or the next finer one when that level was done): ``"M"`` (kept in the
    output) and ``"scans"`` (its prepared scans: the haloed ``f`` of the level marked
    complete in the adopted scratch). Each is checked again, chunk by chunk, when used."""
    level = run.resumed_level
    if not run.level_to_solve(level, ctx.finest):
        level -= 1
    reused = []
    if ctx.matrix is not None and ctx.matrix.level() == level:
        reused.append("M")
    if ctx.adopted and (Path(ctx.scratch) / f"f-level{level}.zarr" / COMPLETE).is_file():
        reused.append("scans")
    return reused


def _compile_kernels(runner, progress) -> None:
    """Compile (or load from numba's cache) the workers' block kernels and the client's solver.

    The first run on a machine compiles for ~20 s before the first iteration: say so first,
    and report the time (the stage timings would otherwise hide it).
    """
    cold = not kernels.compiled_on_disk()
    if cold:
        emit(progress, stage="compile", done=False)
    t0 = time.perf_counter()
    runner.run_everywhere(kernels.warmup)
    solve.warmup()
    if cold:
        emit(progress, stage="compile", done=True, seconds=time.perf_counter() - t0)


def _describe(src) -> str:
    if isinstance(src, (str, Path)):
        return str(Path(src).resolve())
    return f"<in-memory {type(src).__name__}>"
