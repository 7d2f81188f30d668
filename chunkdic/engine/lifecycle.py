"""The life of a run around its levels: lock, scratch, runner, checkpoint, and what stays when it fails.

:func:`chunkdic.correlate` checks everything first (:func:`chunkdic.engine.front.prepare_run`,
the plan, the outputs), then runs its levels inside :func:`holding`: the configuration the
plan chose, the one-writer lock of the output, the runner, the checkpoint started or
resumed, and the scratch directory, removed once the runner is closed (no task writes into
it) and before the lock goes, or left for the resume of an interrupted run. Inside,
:func:`failing` decides what a failure leaves (docs/safety.md): what a fresh run created
goes, a checkpoint this run saved stays; :func:`open_levels` prepares the scans' levels and
the :class:`~chunkdic.engine.coarse_to_fine.RunContext`; :func:`finish` describes the result
and saves it under the lock.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from pathlib import Path

import dask.config

from .. import config
from ..errors import InputError
from ..io.outputs import Outputs
from ..io.locks import OutputLock
from ..io.owntree import remove
from ..io.scratch import (adopt_scratch, directory_bytes, interrupted_run_of, leave_scratch, make_scratch,
                          reclaim_stale_scratch)
from ..kernels import jit as kernels
from ..method.events import Compile, PlanMade, ScratchKept, Start, emit
from ..method.runstate import RunState
from ..passes.masks import prepare_mask
from ..passes.scratchstore import prune_adopted
from ..passes.stored_matrix import StoredMatrix
from ..results.result import Result
from ..scheduler import open_runner
from ..solve import cg as solve
from .checkpoint import Checkpoint, RunIdentity, fingerprint, kept_checkpoint_error
from .coarse_to_fine import RunContext
from .front import RunSpec
from .meshes import parse_roi
from .runplan import Plan, calibrated
from .texture_check import check_texture

#: the settings of ``chunkdic.`` (dask config) that a scratch directory's stores depend on
SCRATCH_CONFIG = ("block-voxels", "scratch-precision", "scratch-layout", "bspline-halo", "chunk-size", "compressor")


@dataclasses.dataclass
class Holding:
    """What a run holds while its levels are solved (:func:`holding`).

    ``checkpoint`` and ``resume`` (the interrupted run's saved state) with an output;
    ``scratch`` once :func:`open_levels` made or adopted it (``adopted``).
    """

    spec: RunSpec
    identity: RunIdentity
    runner: object
    output: object = None
    outputs: Outputs | None = None
    entry: object = None
    checkpoint: Checkpoint | None = None
    resume: dict | None = None
    scratch: Path | None = None
    adopted: bool = False

    @property
    def kept_for(self) -> tuple[str, str] | None:
        """``(output, fingerprint)`` when the same command can resume this run (an output, every input on disk)."""
        if self.output is None or not self.identity.resumable:
            return None
        return str(self.output), self.identity.fingerprint


@contextlib.contextmanager
def holding(spec: RunSpec, identity: RunIdentity, budget: Plan, output, outputs: Outputs | None, entry, scheduler,
            progress=None):
    """The run's configuration, the lock of its ``output`` (as the user gave it; its
    :class:`~chunkdic.io.outputs.Outputs` entry ``entry``), runner and checkpoint, and the
    removal of its scratch on the way out (module docstring): yields a :class:`Holding`."""
    with contextlib.ExitStack() as stack:
        if budget.memory_target is not None:  # the block and prefilter task sizes the target chose
            stack.enter_context(dask.config.set({"chunkdic.block-voxels": budget.block_voxels,
                                                 "chunkdic.prepare-voxels": budget.prepare_edge}))
        # the scratch layout the plan chose (compact only when the fast one does not fit), and
        # the levels whose mesh data go to node blocks
        stack.enter_context(dask.config.set({"chunkdic.scratch-layout": budget.layout,
                                             "chunkdic.mesh-blocks-from": budget.mesh_blocks_from,
                                             "chunkdic.mesh-blocks-on": budget.mesh_data}))
        if output is not None:
            stack.enter_context(OutputLock(output))  # one writer per output
        held = None
        # the scratch is removed (or left for the resume) once the runner is closed (no task
        # writes into it) and before the lock goes: the next run of the output may adopt it
        stack.callback(lambda: held is not None and held.scratch is not None
                       and _close_scratch(held.scratch, held.kept_for, progress))
        runner = stack.enter_context(open_runner(scheduler))
        held = Holding(spec, identity, runner, output, outputs, entry)
        if output is not None:
            held.checkpoint, held.resume = _start_output(outputs, entry, identity)
        yield held


@contextlib.contextmanager
def failing(held: Holding):
    """What a failure of the run leaves: bad input found by a pass (a constant or non-finite
    image), or a full or read-only disk before the first checkpoint, leave nothing to resume,
    so what this run created goes. A checkpoint this run saved stays for a re-run to resume
    (marked incomplete), and so does a resumed run's, which was there before."""
    try:
        yield
    except (InputError, OSError) as exc:
        ckpt = held.checkpoint
        fresh = held.outputs is not None and held.resume is None
        if fresh and (isinstance(exc, InputError) or ckpt is None or not ckpt.saved):
            held.outputs.rollback()
        elif isinstance(exc, OSError) and ckpt is not None:
            raise kept_checkpoint_error(exc, held.output) from None  # say it is kept, and how to resume
        raise


def open_levels(held: Holding, budget: Plan, progress=None) -> tuple[RunContext, RunState | None]:
    """The run's scratch (an interrupted run's adopted), the scans' levels it solves (missing
    pyramid levels built by the runner's tasks), the mask's, the kernels compiled, the
    reference's texture read (:func:`~chunkdic.engine.texture_check.check_texture`): the
    :class:`RunContext` of its levels and the state it resumes from (None: a new run)."""
    spec, runner, resume = held.spec, held.runner, held.resume
    # an interrupted run of this very run (its output was there): its scratch is adopted when
    # that run is over (killed, or ended interrupted), else a new one (also reclaims dead runs'
    # scratch, but not what is kept for other outputs' resumes)
    resuming = held.entry is not None and held.entry.state == "resume"
    held.scratch, held.adopted = _open_scratch(_scratch_identity(held, runner), resuming,
                                               None if resume is None else int(resume["level"]), held.kept_for)
    finest = spec.meshes[spec.settings.level]
    emit(progress, Start(scheduler=repr(runner), dashboard=runner.dashboard_link, levels=spec.levels, roi=[[r.start, r.stop] for r in finest.roi], requested_roi=None if spec.roi is None else [list(p) for p in parse_roi(spec.roi)], nodes=list(finest.nodes_shape)))
    # a resumed run needs no level coarser than the one it was solving (done)
    needed = spec.levels if resume is None else [s for s in spec.levels if s <= int(resume["level"])]
    # inside the runner: with a cluster, missing levels are built by its workers
    scratch, adopted = held.scratch, held.adopted
    f_refs = spec.f_scan.refs(needed, scratch / "ref", runner=runner, adopt=adopted)
    g_refs = spec.g_scan.refs(needed, scratch / "def", runner=runner, adopt=adopted)
    mask_refs = None if spec.mask_scan is None else prepare_mask(spec.mask_scan, spec.f_scan.shape(0), needed,
                                                                 scratch / "mask", runner)
    # the crack surface on the correlated level only: coarser levels give it a continuous start
    crack_ref = None if spec.crack_scan is None else prepare_mask(spec.crack_scan, spec.f_scan.shape(0), [spec.finest],
                                                                  scratch / "crack", runner)[spec.finest]
    _compile_kernels(runner, progress)
    level = spec.settings.level
    texture = check_texture(f_refs[level], spec.meshes[level], spec.settings, runner, progress)
    emit(progress, PlanMade(plan=calibrated(budget, spec.g_scan, spec.settings)))
    ckpt = held.checkpoint
    ctx = RunContext(spec.settings, spec.meshes, spec.levels, f_refs, g_refs, runner, scratch, progress, ckpt,
                     mask_refs, spec.init, matrix=None if ckpt is None else StoredMatrix(ckpt.path), adopted=adopted,
                     crack_ref=crack_ref, texture_length=texture)
    return ctx, None if resume is None else RunState.from_checkpoint(resume)


def finish(result: Result, held: Holding, ref, deformed, mask=None) -> Result:
    """The run's facts in ``result.info`` (voxel size, inputs, fingerprint, start field), and
    the result saved into the output (replacing the checkpointed group once complete, under the lock)."""
    spec, identity = held.spec, held.identity
    result.info.update(
        voxel_size=spec.f_scan.voxel_size, unit=spec.f_scan.unit, fingerprint=identity.fingerprint,
        inputs={"reference": _describe(ref), "deformed": _describe(deformed),
                "mask": None if mask is None else _describe(mask),
                **({} if spec.crack is None else {"crack": _describe(spec.crack)})},
        input_shapes={"reference": list(spec.f_scan.shape(0)), "deformed": list(spec.g_scan.shape(0))},
        init=identity.init,
    )
    if identity.init is not None:
        result.info["settings"] = dict(result.info["settings"], init=identity.init)
    if held.output is not None:
        try:
            result.save(held.output, overwrite=True, inputs=run_inputs(spec, ref, deformed, mask))
        except OSError as exc:  # the staged copy is gone, the checkpoint stays
            raise kept_checkpoint_error(exc, held.output) from None
    return result


def run_inputs(spec: RunSpec, ref, deformed, mask=None) -> tuple:
    """The run's inputs as the output rules take them (:class:`chunkdic.io.outputs.Outputs`):
    the scans, the mask and the earlier result it starts from (none may be the output)."""
    return ref, deformed, mask, None if spec.init is None else spec.init.path, spec.crack


def _scratch_identity(held: Holding, runner) -> str | None:
    """What a scratch directory's stores depend on beyond the run's fingerprint: the output
    (one run per output), the configuration of :data:`SCRATCH_CONFIG` (blocks, the scratch
    layout the plan chose and its precision, chunks and codecs of the pyramid levels, the
    B-spline halo) and whether every task is local (the prepared ``g`` is then a
    memory-mapped file). None without an output: such a run never resumes."""
    if held.output is None:
        return None
    return fingerprint({"run": held.identity.fingerprint, "output": str(Path(held.output).resolve()),
                        "config": {key: config.get(key) for key in SCRATCH_CONFIG}, "local": bool(runner.local)})


def _open_scratch(identity: str | None, resuming: bool, level: int | None,
                  resume: tuple[str, str] | None = None) -> tuple[Path, bool]:
    """The run's scratch directory and whether it is adopted from the interrupted run.

    Resuming (the output held this run's checkpoint), the scratch directory the interrupted
    run of the same ``identity`` left (its process dead, or it ended interrupted) is adopted
    (:func:`chunkdic.io.scratch.adopt_scratch`) and pruned to the stores of the ``level``
    it was solving (:func:`chunkdic.passes.scratchstore.prune_adopted`); each store is reused only
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


def _close_scratch(scratch: Path, kept_for: tuple[str, str] | None, progress) -> None:
    """Remove the run's scratch directory, unless the run was interrupted with its checkpoint
    kept (Ctrl-C, a lost cluster, a full disk after a checkpoint: the output of ``kept_for =
    (output, fingerprint)`` holds this run's checkpoint, marked incomplete): then it is left
    for the resume, which adopts it instead of preparing the scans again, and no other run
    reclaims it while the output stays so (:func:`chunkdic.io.scratch.leave_scratch`).
    ``kept_for`` None: a run that cannot resume. The runner is closed by now: no task of
    this run writes into it any more."""
    if kept_for is not None and interrupted_run_of(*kept_for):
        output = kept_for[0]
        try:
            leave_scratch(scratch)
            emit(progress, ScratchKept(path=str(scratch), bytes=directory_bytes(scratch), output=str(output)))
            return
        except OSError:  # its owner record cannot be rewritten (a full disk): it goes
            pass
    remove(scratch)


def _start_output(outputs: Outputs, entry, identity: RunIdentity):
    """Under the lock: replace an old result (``--overwrite``), then start or resume."""
    if entry.state == "resume":
        return Checkpoint.start(entry.final, identity.fingerprint, identities=identity.inputs)
    outputs.__enter__()  # removes the old result that --overwrite replaces (checked: ours, a result)
    if entry.final.exists():  # created meanwhile by another run, which has finished
        raise InputError(f"output {entry.final} appeared while this run was starting: choose another path "
                         "or pass --overwrite")
    return Checkpoint.start(entry.final, identity.fingerprint, identities=identity.inputs)


def _compile_kernels(runner, progress) -> None:
    """Compile (or load from numba's cache) the workers' block kernels and the client's solver.

    The first run on a machine compiles for ~20 s before the first iteration: say so first,
    and report the time (the stage timings would otherwise hide it).
    """
    cold = not kernels.compiled_on_disk()
    if cold:
        emit(progress, Compile(done=False))
    t0 = time.perf_counter()
    runner.run_everywhere(kernels.warmup)
    solve.warmup()
    if cold:
        emit(progress, Compile(done=True, seconds=time.perf_counter() - t0))


def _describe(src) -> str:
    if isinstance(src, (str, Path)):
        return str(Path(src).resolve())
    return f"<in-memory {type(src).__name__}>"
