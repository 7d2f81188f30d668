"""The C8-DIC driver: levels coarsest first, rigid step, Gauss–Newton per level, checkpoints.

Paper sections 3–4 (Roux, Hild, Viot, Bernard): the displacement is sought on 8-node
cubic elements; each level of the ``2^s`` sum pyramid is solved by modified Gauss–Newton
(:mod:`chunkdic.gauss_newton`) with ``M`` built once from the reference and ``b``
re-assembled from the corrected deformed image at every iteration (:mod:`chunkdic.level`,
:mod:`chunkdic.tasks`). Out of core: every task reads its own block of ``f`` and the exact
window of ``g`` it needs from the store and returns mesh-sized partials that the client
adds up (shared/DESIGN.md, "Out-of-core shape").
"""

from __future__ import annotations

import contextlib
import dataclasses
import shutil
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np

from . import kernels
from .checkpoint import Checkpoint, fingerprint
from .errors import InputError
from .gauss_newton import History, State, iterate, rigid_step
from .level import Level, emit
from .integrity import content_identity
from .mesh import transfer
from .outputs import Outputs
from .ownership import OutputLock, make_scratch
from .planning import parse_roi, plan_meshes
from .result import Result
from .rigid import translation_task
from .scheduler import check_scheduler, open_runner
from .settings import Settings
from .volume import open_scan

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
        (:mod:`chunkdic.outputs`).
    progress : callable, optional
        Called with a dict per event (``stage`` = "rigid", "iteration", "level", ...).

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
    >>> np.round(res.displacement[0].mean(), 3), res.info["status"]
    (1.0, 'converged')
    """
    settings = _settings(settings, options)
    f_scan, g_scan = open_scan(ref), open_scan(deformed)
    meshes = plan_meshes(f_scan.shape(0), element_size=settings.element_size, roi=roi,
                         level=settings.level, coarsest=settings.coarsest)
    levels = sorted(meshes, reverse=True)
    for s in levels:
        if min(g_scan.shape(s)) < 2:
            raise InputError(f"the deformed scan is too small at level {s} ({g_scan.shape(s)})")
    plan = entry = None
    if output is not None:  # every output rule (chunkdic.outputs), nothing written yet
        plan = Outputs(inputs=(ref, deformed), overwrite=overwrite)
        entry = plan.add(output, "result", resumable=True)
    identities = {role: _identify(src, scan) for role, src, scan in
                  (("reference", ref, f_scan), ("deformed", deformed, g_scan))}
    run_print = fingerprint({"settings": settings.to_json(), "roi": parse_roi(roi),
                             "inputs": [identities["reference"], identities["deformed"]]})
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
                f_refs = f_scan.refs(levels, scratch / "ref")
                g_refs = g_scan.refs(levels, scratch / "def")
                runner.run_everywhere(kernels.warmup)
                result = _run(settings, meshes, levels, f_refs, g_refs, runner, progress, scratch, ckpt, resume)
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
                inputs={"reference": _describe(ref), "deformed": _describe(deformed)},
                input_shapes={"reference": list(f_scan.shape(0)), "deformed": list(g_scan.shape(0))},
            )
            if output is not None:  # replaces the checkpointed group once complete, under the lock
                result.save(output, overwrite=True, inputs=(ref, deformed))
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


def _settings(settings: Settings | None, options: dict) -> Settings:
    unknown = set(options) - set(Settings.names())
    if unknown:
        raise TypeError(f"correlate() got unexpected keyword arguments {sorted(unknown)}")
    if settings is None:
        if "element_size" not in options:
            raise TypeError("correlate() needs element_size (or settings=Settings(...))")
        return Settings(**options)
    return dataclasses.replace(settings, **options)


def _run(settings: Settings, meshes, levels, f_refs, g_refs, runner, progress, scratch: Path,
         checkpoint=None, resume: dict | None = None) -> Result:
    """All levels, coarsest first; resumes from ``resume`` (a checkpoint state) if given."""
    finest, coarsest = levels[-1], levels[0]
    statuses: dict[int, str] = {}
    rigid_t = initial_gap = rigid_gap = None
    state = None
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
            lvl = Level(s, mesh, f_refs[s], g_refs[s], runner, settings, scratch, progress)
            lvl.assemble_m()
            emit(progress, stage="matrix", level=s, nodes=list(mesh.nodes_shape), blocks=len(lvl.jobs),
                 voxels=mesh.n_voxels, seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0)
            if state is None:
                if s == coarsest:
                    t_int = run_one(runner, translation_task, (f_refs[s], g_refs[s], mesh.roi))
                    lvl.prepare_interpolation(_uniform(t_int, mesh))
                    rigid_t = rigid_step(lvl, t_int, tol, 10, history, progress)
                    u = _uniform(rigid_t, mesh)
                else:
                    u = transfer(u, meshes[s + 1], s + 1, mesh, s)
                state = State(u)
            lvl.prepare_interpolation(state.u)
            if s == finest and initial_gap is None:
                rigid_fine = rigid_t * 2.0 ** (coarsest - finest)
                _, initial_gap, _, _ = lvl.assemble_b(np.zeros((3,) + mesh.nodes_shape))
                _, rigid_gap, _, _ = lvl.assemble_b(_uniform(rigid_fine, mesh))
                emit(progress, stage="gaps", level=s, initial_gap=initial_gap, rigid_gap=rigid_gap,
                     translation=rigid_fine.tolist())
            state = iterate(lvl, state, tol, settings.max_iterations, history, progress,
                            on_iteration=lambda st, s=s: save_checkpoint(st, s))
            lvl.release()
            statuses[s] = state.status
            save_checkpoint(state, s)
            emit(progress, stage="level", level=s, status=state.status, gap=state.gap,
                 seconds=time.perf_counter() - t0)
        final, u, state = state, state.u, None
    mesh = meshes[finest]
    info = {
        "element_size": settings.element_size,
        "roi": [[r.start, r.stop] for r in mesh.roi],
        "roi_level0": [[r.start * 2**finest, r.stop * 2**finest] for r in mesh.roi],
        "level": finest,
        "scale": 2**finest,
        "levels": levels,
        "level_status": {str(k): v for k, v in statuses.items()},
        "status": statuses[finest],
        "converged": statuses[finest] == "converged",
        "initial_gap": initial_gap,
        "rigid_gap": rigid_gap,
        "final_gap": final.gap,
        "rigid_translation": (rigid_t * 2.0 ** (coarsest - finest)).tolist(),
        "excluded_voxels": int(final.excluded),
        "used_voxels": int(final.n_valid),
        "settings": settings.to_json(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "chunkdic_version": _version(),
    }
    return Result(u, mesh.node_coords(), history.arrays(), info)


def _uniform(t, mesh) -> np.ndarray:
    """A uniform nodal field ``t`` (3,) over ``mesh``: shape (3, nz, ny, nx)."""
    return np.asarray(t, dtype=np.float64)[:, None, None, None] * np.ones((3,) + mesh.nodes_shape)


def run_one(runner, fn, args):
    """Run one task on the runner and return its result."""
    return next(iter(runner.map_unordered(fn, [args])))


def _identify(src, scan) -> dict:
    """What identifies an input for resuming: path, shape, dtype and a cheap content
    identity of every stored level (:func:`chunkdic.integrity.content_identity`: chunk
    list, sizes, times and a fixed sample of chunk bytes, never the scan). In-memory
    inputs never match (no resume)."""
    if isinstance(src, (str, Path)):
        content = {str(s): content_identity(r.kind, r.path, r.key) for s, r in sorted(scan.stored_refs().items())}
        return {"path": str(Path(src).resolve()), "shape": scan.shape(0), "dtype": str(scan.dtype(0)),
                "content": content}
    return {"in-memory": uuid.uuid4().hex}


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

