"""The pyramid of a run, coarsest level first: each level's passes, then the method on them.

Paper section 3: the displacement is sought on the coarsest level of the ``2^s`` sum
pyramid first, and each level's field starts the next finer one. :func:`run_levels` is that
loop; :func:`solve_one_level` opens a level's out-of-core passes
(:class:`chunkdic.passes.level.LevelPasses`), finds its start
(:mod:`chunkdic.method.start`), its ``M`` and penalty, solves it
(:mod:`chunkdic.method.level_solve`) and records its end in the run's state, which a
checkpoint saves after every pass (:mod:`chunkdic.engine.checkpoint`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..io.handles import forget_open_arrays
from ..io.owntree import remove
from ..mesh import Mesh
from ..method.events import LevelDone, Resume, emit
from ..method.level_solve import LevelOutcome, run_level
from ..method.runstate import RunState
from ..method.settings import Settings
from ..passes.haloed import COMPLETE
from ..passes.level import LevelPasses
from ..passes.scratchstore import f_store
from ..passes.stored_matrix import StoredMatrix
from ..results.result import Result
from .assemble import assemble_result
from .checkpoint import Checkpoint


@dataclasses.dataclass(frozen=True)
class RunContext:
    """What does not change during a run: settings, meshes, scans, where tasks run.

    ``levels`` are coarsest first; ``f_refs``, ``g_refs``, ``mask_refs`` map a level to the
    :class:`~chunkdic.io.handles.ArrayRef` tasks read (a resumed run: the levels still to
    solve); ``init`` an earlier result to start from (:mod:`chunkdic.engine.initial`);
    ``matrix`` where each level's ``M`` is kept for a resumed run (the output,
    :mod:`chunkdic.passes.stored_matrix`); ``adopted``: the scratch is an interrupted run's,
    whose complete level stores are reused; ``texture_length``: the reference's autocorrelation
    length on the correlated level, voxels of it (NaN: unknown;
    :func:`chunkdic.engine.texture_check.check_texture`), which sets each level's start length.
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
    crack_ref: object = None
    texture_length: float = math.nan

    @property
    def finest(self) -> int:
        return self.levels[-1]

    @property
    def coarsest(self) -> int:
        return self.levels[0]

    def save(self, run: RunState, s: int) -> None:
        """Checkpoint ``run`` while level ``s`` is solved (nothing without an output)."""
        if self.checkpoint is not None:
            self.checkpoint.save(run.to_json(s), run.arrays())


def run_levels(ctx: RunContext, run: RunState | None = None) -> Result:
    """All levels, coarsest first (paper section 3), from a fresh or a resumed ``run``."""
    if run is None:
        run = RunState()
    else:
        emit(ctx.progress, Resume(level=run.resumed_level, iteration=run.gn.iteration, reused=reused_stores(ctx, run)))
    u, outcome = None, LevelOutcome()
    for s in ctx.levels:
        if run.done_before_resume(s):
            release_scan_levels(ctx, s)
            continue
        if run.level_to_solve(s, ctx.finest):
            run, outcome = solve_one_level(ctx, run, s, u)
        release_scan_levels(ctx, s)
        final, u, run = run.gn, run.gn.u, dataclasses.replace(run, gn=None)
    return assemble_result(ctx, run, final, outcome)


def solve_one_level(ctx: RunContext, run: RunState, s: int, coarser_u: np.ndarray | None
                    ) -> tuple[RunState, LevelOutcome]:
    """Level ``s`` from ``run`` (its state on the level when resumed, else the coarser
    level's field ``coarser_u``) on its out-of-core passes: the run's state with the level
    ended (checkpointed), and what it leaves."""
    t0 = time.perf_counter()
    passes = LevelPasses(s, ctx.meshes[s], ctx.f_refs[s], ctx.g_refs[s], ctx.runner, ctx.settings, ctx.scratch,
                         ctx.progress, None if ctx.mask_refs is None else ctx.mask_refs[s], matrix=ctx.matrix,
                         adopt=ctx.adopted, crack=ctx.crack_ref if s == ctx.finest else None)
    run, outcome = run_level(passes, run, coarser_u, meshes=ctx.meshes, levels=ctx.levels, settings=ctx.settings,
                             earlier=ctx.init, progress=ctx.progress, on_iteration=lambda r: ctx.save(r, s),
                             texture_length=ctx.texture_length / 2.0 ** (s - ctx.finest))
    # the level's M, solver and last pass are gone with run_level's frame: not held through the
    # next level's M pass (an eighth of its own) or the result's assembly (docs/distributed.md)
    passes.release()
    ctx.save(run, s)
    if ctx.matrix is not None and s != ctx.finest:  # no resumed run reads it now (the finest's goes with the checkpoint)
        ctx.matrix.drop()
    emit(ctx.progress, LevelDone(level=s, status=run.gn.status, gap=run.gn.gap, seconds=time.perf_counter() - t0))
    return run, outcome


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
            remove(path)


def reused_stores(ctx: RunContext, run: RunState) -> list[str]:
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
    if ctx.adopted and (f_store(ctx.scratch, level) / COMPLETE).is_file():
        reused.append("scans")
    return reused
