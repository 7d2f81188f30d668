"""The C8-DIC engine: blocks → tasks → reductions → client solve → iterations → levels.

Paper sections 3–4 (Roux, Hild, Viot, Bernard): the displacement is sought on 8-node
cubic elements; each level of the ``2^s`` sum pyramid is solved by modified
Gauss–Newton with ``M`` built once from the reference and ``b`` re-assembled from the
corrected deformed image at every iteration. Out of core: every task reads its own
block of ``f`` and the exact window of ``g`` it needs from the store and returns
mesh-sized partials that the client adds up (shared/DESIGN.md, "Out-of-core shape").
"""

from __future__ import annotations

import logging
import math
import shutil
import tempfile
import time
import uuid
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from . import config, kernels
from .errors import InputError
from .mesh import Block, Mesh, transfer
from .prefilter import Coefficients, build_coefficients, reachable_box
from .checkpoint import Checkpoint, fingerprint, refuse_existing
from .haloed import HaloedBlocks
from .result import HISTORY_FIELDS, Result
from .rigid import translation_task
from .scheduler import open_runner
from .solve import StencilSolver, PoorTextureWarning
from .volume import ArrayRef, forget_open_arrays, open_scan

log = logging.getLogger(__name__)

Box = tuple[tuple[int, int], tuple[int, int], tuple[int, int]]


@dataclass(frozen=True)
class Settings:
    """Algorithm settings of one correlation (stored with the result).

    Parameters
    ----------
    element_size : int
        Element edge ``ell``, voxels of ``level``.
    level : int
        Pyramid level correlated last (0 = full resolution, 2 = the paper's 4³ compression).
    coarsest : int or None
        Coarsest pyramid level; ``None`` picks the coarsest level at most 3 above
        ``level`` whose ROI is still at least ``MIN_COARSE_EDGE`` voxels on every axis.
    interpolation : {"cubic", "linear"}
        Interpolation of the deformed image (cubic B-spline, or the paper's trilinear).
    tolerance : float
        Convergence when ``max |δa|`` falls below it (voxels of ``level``).
    coarse_tolerance : float
        The same on coarser levels, whose field is only a starting point.
    max_iterations : int
        Iteration cap per level.
    block_elements : int or None
        Elements per block side; ``None`` uses ``chunkdic.block-voxels`` (config).
    """

    element_size: int
    level: int = 0
    coarsest: int | None = None
    interpolation: str = "cubic"
    tolerance: float = 1e-3
    coarse_tolerance: float = 1e-2
    max_iterations: int = 30
    block_elements: int | None = None


MIN_COARSE_EDGE = 24
#: interval of block-count progress events during a long pass over the voxels (seconds)
PROGRESS_SECONDS = 5.0
#: stop as stalled after this many iterations without a lower gap
STALL_PATIENCE = 4
#: a gap this many times the best one so far means divergence
DIVERGENCE_FACTOR = 2.0


# --------------------------------------------------------------------------- ROI / meshes


def parse_roi(roi) -> Box | None:
    """Parse ``"z0:z1,y0:y1,x0:x1"`` (or a sequence of 3 pairs/slices) to a box."""
    if roi is None:
        return None
    if isinstance(roi, str):
        parts = roi.split(",")
        if len(parts) != 3:
            raise InputError(f"ROI {roi!r}: expected z0:z1,y0:y1,x0:x1")
        try:
            pairs = [tuple(int(v) for v in p.split(":")) for p in parts]
        except ValueError:
            raise InputError(f"ROI {roi!r}: bounds must be integers, as in 10:90,10:90,10:90") from None
    else:
        pairs = [(s.start, s.stop) if isinstance(s, slice) else tuple(s) for s in roi]
    if len(pairs) != 3 or any(len(p) != 2 for p in pairs):
        raise InputError(f"ROI {roi!r}: expected three ranges z0:z1,y0:y1,x0:x1")
    if any(a is None or b is None or b <= a for a, b in pairs):
        raise InputError(f"ROI {roi!r}: every range needs start < stop")
    return tuple((int(a), int(b)) for a, b in pairs)


def _centred_mesh(box: Box, ell: int) -> Mesh | None:
    """Largest centred mesh of whole ``ell`` elements inside ``box`` (None if none fits)."""
    n = tuple((b - a) // ell for a, b in box)
    if min(n) < 1:
        return None
    origin = tuple(a + ((b - a) - k * ell) // 2 for (a, b), k in zip(box, n))
    return Mesh(origin, ell, n)


def _box_at_level(box: Box, factor: int) -> Box:
    """Voxels of a level ``factor`` times coarser that lie wholly inside ``box``."""
    return tuple((-(-a // factor), b // factor) for a, b in box)


def plan_meshes(ref_shape0, *, element_size: int, roi=None, level: int = 0, coarsest=None) -> dict[int, Mesh]:
    """Meshes per pyramid level, finest (``level``) first.

    The ROI is given in level-0 voxels (the scan a user looks at). On ``level`` it is
    reduced to the voxels of that level inside it and trimmed, centred, to a whole number
    of elements (paper section 4.1 adjusts the ROI the same way). Coarser levels use the
    same element edge (the basis coarsens with the image, paper section 3) over the
    level's share of that ROI, smaller elements only when the ROI is smaller than one.
    """
    ell = int(element_size)
    shape0 = tuple(int(n) for n in ref_shape0)
    box0 = parse_roi(roi)
    if box0 is None:
        factor = 2**level
        shape = tuple(n // factor for n in shape0)
        margin = max(2, ell // 4)
        inner = tuple((margin, n - margin) for n in shape)
        mesh = _centred_mesh(inner, ell)
        if mesh is None:
            raise InputError(
                f"element size {ell} does not fit in the reference at level {level} "
                f"(shape {shape}, margin {margin}): choose a smaller element size or level"
            )
    else:
        for axis, ((a, b), n) in enumerate(zip(box0, shape0)):
            if a < 0 or b > n:
                raise InputError(
                    f"ROI {a}:{b} on axis {'zyx'[axis]} lies outside the reference (0:{n}, level-0 voxels)"
                )
        box = _box_at_level(box0, 2**level)
        mesh = _centred_mesh(box, ell)
        if mesh is None:
            raise InputError(
                f"element size {ell} is larger than the ROI at level {level} "
                f"({' x '.join(str(b - a) for a, b in box)} voxels)"
            )
    meshes = {level: mesh}
    top = level + 3 if coarsest is None else int(coarsest)
    if top < level:
        raise InputError(f"coarsest level {top} is finer than the correlated level {level}")
    box_fine = tuple((r.start, r.stop) for r in mesh.roi)
    for s in range(level + 1, top + 1):
        box = _box_at_level(box_fine, 2 ** (s - level))
        edge = min(b - a for a, b in box)
        if coarsest is None and edge < MIN_COARSE_EDGE:
            break
        ell_s = min(ell, edge)
        if ell_s < 2:
            raise InputError(f"coarsest level {top} is too coarse for this ROI (edge {edge} voxels at level {s})")
        meshes[s] = _centred_mesh(box, ell_s)
    return meshes


# --------------------------------------------------------------------------- tasks


def _halo_region(start, shape, full_shape, halo: int = 1):
    """Core box grown by ``halo`` voxels, clipped to the volume; and the halos obtained."""
    region, lo, hi = [], [], []
    for a, n, N in zip(start, shape, full_shape):
        r0, r1 = max(a - halo, 0), min(a + n + halo, N)
        region.append(slice(r0, r1))
        lo.append(a - r0)
        hi.append(r1 - (a + n))
    return tuple(region), tuple(lo), tuple(hi)


def m_task(f_ref: ArrayRef, ell: int, block: Block, start, shape, copy: HaloedBlocks, index):
    """Task: this block's share of ``M`` (a nodal stencil) and the min/max of ``f``.

    Also keeps the block's haloed ``f`` as chunk ``index`` of ``copy`` for the ``b`` passes.
    """
    region, lo, hi = _halo_region(start, shape, f_ref.shape)
    raw = f_ref.read(region)
    copy.write(index, raw)
    stencil, fmin, fmax = kernels.m_block(raw.astype(np.float32, copy=False), lo, hi, ell)
    return block, stencil, fmin, fmax


def b_task(f_ref: ArrayRef, g_ref: ArrayRef, ell: int, block: Block, start, shape,
           u_block: np.ndarray, interpolation: str, halo: int, coefficients: Coefficients | None,
           copy: HaloedBlocks, index):
    """Task: this block's share of ``b``, ``Σ r²`` and the valid/excluded voxel counts.

    ``f`` (with its halo) comes from the level's haloed copy written by the ``M`` pass.
    With cubic interpolation the window of ``g`` comes from the level's prefiltered
    ``coefficients`` when they cover it, else it is read raw with a halo and prefiltered
    here (same result to float32 precision, see :mod:`chunkdic.prefilter`).
    """
    region, lo, hi = _halo_region(start, shape, f_ref.shape)
    f = copy.read(index, tuple(r.stop - r.start for r in region)).astype(np.float32, copy=False)
    window = kernels.g_window(start, shape, u_block, g_ref.shape, interpolation=interpolation)
    if any(s.stop <= s.start for s in window):
        b = np.zeros(u_block.shape[1:] + (3,))
        return block, b, 0.0, 0, int(np.prod(shape))
    prefiltered = coefficients is not None and coefficients.covers(window)
    if prefiltered:
        g = coefficients.read(window)
    else:
        if interpolation == "cubic":
            window = kernels.g_window(start, shape, u_block, g_ref.shape, interpolation=interpolation, halo=halo)
        g = g_ref.read(window)
    g_origin = tuple(s.start for s in window)
    b, ssr, n_valid, n_excluded = kernels.b_block(
        f, lo, hi, ell, u_block, start, g, g_origin, g_ref.shape, interpolation=interpolation,
        prefiltered=prefiltered,
    )
    return block, b, ssr, n_valid, n_excluded


# --------------------------------------------------------------------------- one level


class _Level:
    """State of one pyramid level: its mesh, data, assembled ``M`` and solver."""

    def __init__(self, s: int, mesh: Mesh, f_ref: ArrayRef, g_ref: ArrayRef, runner, settings: Settings,
                 scratch: Path, progress=None):
        self.s, self.mesh, self.f_ref, self.g_ref, self.runner = s, mesh, f_ref, g_ref, runner
        self.settings = settings
        self.scratch = scratch
        self.progress = progress
        self.coefficients = None
        self._builds = 0
        ell = mesh.element_size
        m = settings.block_elements or max(1, config.get("block-voxels") // ell)
        self.blocks = mesh.blocks(m)
        self.block_index = {blk: tuple(e0 // m for e0, _ in blk.elements) for blk in self.blocks}
        self.halo = int(config.get("bspline-halo"))
        self.f_copy = None

    def _map(self, fn, args, label: str, voxels: int | None = None):
        """Run one task per block, yield results as they come, report long passes.

        A pass that lasts more than ``PROGRESS_SECONDS`` emits ``stage="blocks"`` events
        (done/total, voxel rate, ETA) at that interval, for a person at a terminal.
        ``voxels``: what the tasks cover together (default: the mesh's ROI).
        """
        total = len(args)
        voxels_per_block = (self.mesh.n_voxels if voxels is None else voxels) / max(total, 1)
        t0 = last = time.perf_counter()
        for done, result in enumerate(self.runner.map_unordered(fn, args), start=1):
            yield result
            now = time.perf_counter()
            if now - last >= PROGRESS_SECONDS and done < total:
                last = now
                rate = done * voxels_per_block / (now - t0)
                _emit(self.progress, stage="blocks", level=self.s, label=label, done=done, total=total,
                      rate=rate, eta=(total - done) * voxels_per_block / rate)

    def assemble_m(self) -> None:
        mesh = self.mesh
        # float32: M only steers the modified Gauss-Newton steps (the converged field solves
        # b = 0 whatever M), and at 128³ nodes a float64 stencil alone would be 4 GB.
        # Each block's partial is summed in float64 by its task.
        S = np.zeros(mesh.nodes_shape + (27, 3, 3), dtype=np.float32)
        fmin, fmax = np.inf, -np.inf
        self.f_copy = self._create_f_copy()
        args = [(self.f_ref, mesh.element_size, blk, *mesh.block_core(blk), self.f_copy, self.block_index[blk])
                for blk in self.blocks]
        for blk, part, lo, hi in self._map(m_task, args, "M pass"):
            S[blk.node_slices] += part
            fmin, fmax = min(fmin, lo), max(fmax, hi)
        self.dynamic_range = float(fmax - fmin)
        if self.dynamic_range <= 0:
            raise InputError(f"the reference is constant over the ROI at level {self.s}: nothing to correlate")
        # Rigid-body restriction of M: since Σ_a N_a = 1, Σ_voxels ∇f ∇fᵀ = Σ_ij M_ij.
        self.rigid_matrix = S.sum(axis=(0, 1, 2, 3), dtype=np.float64)
        self.solver = StencilSolver(S)
        self._warn_weak_nodes()

    def _create_f_copy(self) -> HaloedBlocks:
        """Empty store for the blocks' haloed ``f`` (see :mod:`chunkdic.haloed`)."""
        grid = tuple(max(i[a] for i in self.block_index.values()) + 1 for a in range(3))
        regions = [_halo_region(*self.mesh.block_core(blk), self.f_ref.shape)[0] for blk in self.blocks]
        chunk = tuple(max(r[a].stop - r[a].start for r in regions) for a in range(3))
        return HaloedBlocks.create(self.scratch / f"f-level{self.s}.zarr", grid, chunk, self.f_ref.dtype)

    def _warn_weak_nodes(self) -> None:
        weak = self.solver.weak_nodes
        if len(weak) == 0:
            return
        coords = self.mesh.node_coords()
        where = ", ".join(
            "node (%d, %d, %d) at voxel (%.1f, %.1f, %.1f)" % (*n, *coords[(slice(None), *n)]) for n in weak[:5]
        )
        more = f" and {len(weak) - 5} more" if len(weak) > 5 else ""
        warnings.warn(
            f"level {self.s}: {len(weak)} of {np.prod(self.mesh.nodes_shape)} nodes see too little texture "
            f"to be measured ({where}{more}); they are regularised and their values are unreliable",
            PoorTextureWarning,
            stacklevel=3,
        )

    def prepare_interpolation(self, u: np.ndarray) -> None:
        """Cubic: prefilter once the part of ``g`` that ``u`` (± a margin) can reach."""
        if self.settings.interpolation != "cubic":
            return
        needed = reachable_box(self.mesh, u, self.g_ref.shape, margin=0)
        if needed is None or (self.coefficients is not None and self.coefficients.covers(
                tuple(slice(a, b) for a, b in needed))):
            return
        box = reachable_box(self.mesh, u, self.g_ref.shape, margin=max(8, self.mesh.element_size))
        self.release()
        self._builds += 1
        path = self.scratch / f"bspline-level{self.s}-{self._builds}.zarr"
        t0 = time.perf_counter()
        voxels = int(np.prod([b - a for a, b in box]))
        self.coefficients = build_coefficients(
            self.g_ref, box, path, lambda fn, args: self._map(fn, args, "prefilter of g", voxels),
            halo=self.halo, local=self.runner.local,
        )
        log.info("level %d: g prefiltered over %s in %.1f s", self.s, box, time.perf_counter() - t0)

    def release(self, *, f_copy: bool = False) -> None:
        """Delete this level's scratch coefficients and, with ``f_copy``, the haloed copy of
        ``f`` (and forget open handles on them)."""
        paths = []
        if self.coefficients is not None:
            paths.append(Path(self.coefficients.ref.path))
            self.coefficients = None
        if f_copy and self.f_copy is not None:
            paths.append(Path(self.f_copy.path))
            self.f_copy = None
        if paths:
            self.runner.run_everywhere(forget_open_arrays)
        for path in paths:
            shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)

    def assemble_b(self, u: np.ndarray):
        """``b``, matching gap, valid and excluded voxel counts for the nodal field ``u``."""
        mesh = self.mesh
        b = np.zeros(mesh.nodes_shape + (3,))
        ssr, n_valid, n_excluded = 0.0, 0, 0
        args = [
            (self.f_ref, self.g_ref, mesh.element_size, blk, *mesh.block_core(blk),
             np.ascontiguousarray(u[(slice(None), *blk.node_slices)]), self.settings.interpolation, self.halo,
             self.coefficients, self.f_copy, self.block_index[blk])
            for blk in self.blocks
        ]
        for blk, part, r2, nv, ne in self._map(b_task, args, "b pass"):
            b[blk.node_slices] += part
            ssr += r2
            n_valid += nv
            n_excluded += ne
        gap = math.sqrt(ssr / n_valid) / self.dynamic_range if n_valid else math.inf
        return b, gap, n_valid, n_excluded


# --------------------------------------------------------------------------- driver


class _History:
    def __init__(self):
        self.rows = {name: [] for name in HISTORY_FIELDS}

    def add(self, level, iteration, gap, max_delta, excluded):
        for name, value in zip(HISTORY_FIELDS, (level, iteration, gap, max_delta, excluded)):
            self.rows[name].append(value)

    def arrays(self):
        return {
            "level": np.asarray(self.rows["level"], dtype=np.int32),
            "iteration": np.asarray(self.rows["iteration"], dtype=np.int32),
            "gap": np.asarray(self.rows["gap"], dtype=np.float64),
            "max_delta": np.asarray(self.rows["max_delta"], dtype=np.float64),
            "excluded": np.asarray(self.rows["excluded"], dtype=np.int64),
        }


def _emit(progress, **event):
    log.info("%s", event)
    if progress is not None:
        progress(event)


def _rigid_step(lvl: _Level, t0: np.ndarray, tolerance: float, max_iterations: int, history, progress):
    """Sub-voxel refinement of a uniform translation with the rigid restriction of M."""
    t = np.array(t0, dtype=np.float64)
    ones = np.ones((3,) + lvl.mesh.nodes_shape)
    for it in range(max_iterations):
        b, gap, _, excluded = lvl.assemble_b(t[:, None, None, None] * ones)
        delta = np.linalg.solve(lvl.rigid_matrix, b.sum(axis=(0, 1, 2)))
        history.add(lvl.s, -1 - it, gap, float(np.abs(delta).max()), excluded)
        _emit(progress, stage="rigid", level=lvl.s, iteration=it, gap=gap,
              max_delta=float(np.abs(delta).max()), translation=t.tolist())
        t += delta
        if np.abs(delta).max() < tolerance:
            break
    return t


@dataclass
class _GaussNewton:
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

    def scalars(self) -> dict:
        return {k: _json_float(getattr(self, k)) for k in self.SCALARS}

    def arrays(self) -> dict:
        return {"u": self.u, "best_u": self.u if self.best_u is None else self.best_u}

    @classmethod
    def restore(cls, scalars: dict, arrays: dict) -> "_GaussNewton":
        gn = cls(u=arrays["u"], best_u=arrays["best_u"])
        for k in cls.SCALARS:
            value = scalars[k]
            setattr(gn, k, _from_json_float(value) if k in ("best_gap", "last_delta", "gap") else value)
        return gn

    def finish(self, status: str, gap: float, excluded: int, n_valid: int, *, keep_current: bool) -> None:
        self.status = status
        if keep_current:
            self.gap, self.excluded, self.n_valid = gap, excluded, n_valid
        else:  # diverged / stalled / out of iterations: the best field met, never "converged"
            self.u, self.gap, self.excluded, self.n_valid = self.best_u, self.best_gap, self.best_excluded, self.best_valid


def _json_float(v):
    if isinstance(v, float) and not math.isfinite(v):
        return repr(v)  # "inf" / "nan": JSON has no such numbers
    return v


def _from_json_float(v):
    return float(v) if v is not None else math.nan


def _gauss_newton(lvl: _Level, gn: _GaussNewton, tolerance: float, settings: Settings, history, progress,
                  on_iteration=None) -> _GaussNewton:
    """Modified Gauss–Newton on one level (paper section 3), from state ``gn``.

    Each pass evaluates ``b`` and the gap of the current field; the increment of the
    previous pass being below ``tolerance`` means the current field is converged, so the
    reported gap is always that of the returned field. A gap that stops decreasing is
    *stalled*; one that grows past ``DIVERGENCE_FACTOR`` × the best is *diverged*; both
    return the best field met, never flagged as converged. ``on_iteration(gn)`` is
    called after every pass (checkpoints).
    """
    while gn.status is None:
        it = gn.iteration
        t0, c0 = time.perf_counter(), time.process_time()
        b, gap, n_valid, excluded = lvl.assemble_b(gn.u)
        cpu = time.process_time() - c0  # this process only: the tasks too with the thread pool
        event = dict(stage="iteration", level=lvl.s, iteration=it, gap=gap, max_delta=None, excluded=excluded)
        if not math.isfinite(gap) or gap > DIVERGENCE_FACTOR * gn.best_gap:
            gn.finish("diverged", gap, excluded, n_valid, keep_current=False)
        else:
            if gap < gn.best_gap * (1 - 1e-9):
                gn.best_gap, gn.best_u, gn.best_excluded, gn.best_valid = gap, gn.u, excluded, n_valid
                gn.since_best = 0
            else:
                gn.since_best += 1
            if gn.last_delta < tolerance:
                # the converged field is returned even if round-off left its gap a hair above the best
                gn.finish("converged", gap, excluded, n_valid, keep_current=True)
            elif gn.since_best >= STALL_PATIENCE:
                gn.finish("stalled", gap, excluded, n_valid, keep_current=False)
            elif it == settings.max_iterations:
                gn.finish("max-iterations", gap, excluded, n_valid, keep_current=False)
        if gn.status is not None:
            history.add(lvl.s, it, gap, math.nan, excluded)
            _emit(progress, **event, status=gn.status, seconds=time.perf_counter() - t0)
        else:
            t1 = time.perf_counter()
            delta, cg_iterations = lvl.solver.solve(b)
            t2 = time.perf_counter()
            gn.last_delta = float(np.abs(delta).max())
            history.add(lvl.s, it, gap, gn.last_delta, excluded)
            event.update(max_delta=gn.last_delta, seconds=t2 - t0, assemble_seconds=t1 - t0,
                         solve_seconds=t2 - t1, cg_iterations=cg_iterations, voxels=lvl.mesh.n_voxels,
                         assemble_cpu_seconds=cpu)
            _emit(progress, **event)
            gn.u = gn.u + np.moveaxis(delta, -1, 0)
            gn.iteration += 1
        if on_iteration is not None:
            on_iteration(gn)
    return gn


def correlate(
    ref,
    deformed,
    *,
    element_size: int,
    roi=None,
    level: int = 0,
    coarsest: int | None = None,
    interpolation: str = "cubic",
    tolerance: float = 1e-3,
    max_iterations: int = 30,
    block_elements: int | None = None,
    scheduler=None,
    output=None,
    overwrite: bool = False,
    progress: Callable[[dict], None] | None = None,
) -> Result:
    """Measure the displacement field between two scans by multiscale C8-DIC.

    Parameters
    ----------
    ref, deformed : str, Path, ndarray, dask array or zarr array/group
        Reference ``f`` and deformed ``g`` scans (see :func:`chunkdic.open_scan`); shapes
        may differ. Convention: ``f(X) = g(X + u(X))``.
    element_size : int
        Element edge ``ell`` in voxels of ``level`` (the paper's ZOI size).
    roi : str or sequence, optional
        ``"z0:z1,y0:y1,x0:x1"`` in level-0 voxels; default: the largest centred box of
        whole elements with a small margin. Trimmed to whole elements (reported).
    level : int
        Pyramid level correlated last (2 = the paper's 4³ super-voxels).
    coarsest : int, optional
        First (coarsest) level of the multiscale scheme; see :class:`Settings`.
    interpolation : {"cubic", "linear"}
        Interpolation of ``g``: cubic B-spline (default, more accurate) or trilinear.
    tolerance : float
        Convergence on ``max |δa|`` (voxels of ``level``).
    max_iterations : int
        Iteration cap per level.
    block_elements : int, optional
        Elements per block side (work unit); default from ``chunkdic.block-voxels``.
    scheduler : None, "threads", "local[:N]", address or distributed.Client
        Where tasks run (see :func:`chunkdic.scheduler.open_runner`).
    output : path, optional
        Write the result there as a Zarr v3 group (refused if it exists, unless
        ``overwrite``).
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
    """
    settings = Settings(
        element_size=_positive_int(element_size, "element size", minimum=2),
        level=_positive_int(level, "level", minimum=0),
        coarsest=None if coarsest is None else _positive_int(coarsest, "coarsest level", minimum=0),
        interpolation=_choice(interpolation, ("cubic", "linear"), "interpolation"),
        tolerance=float(tolerance),
        max_iterations=_positive_int(max_iterations, "max iterations", minimum=1),
        block_elements=None if block_elements is None else _positive_int(block_elements, "block elements", minimum=1),
    )
    if output is not None and not overwrite:
        refuse_existing(output)  # early: before any input is opened
    f_scan, g_scan = open_scan(ref), open_scan(deformed)
    meshes = plan_meshes(f_scan.shape(0), element_size=settings.element_size, roi=roi,
                         level=settings.level, coarsest=settings.coarsest)
    levels = sorted(meshes, reverse=True)
    for s in levels:
        if min(g_scan.shape(s)) < 2:
            raise InputError(f"the deformed scan is too small at level {s} ({g_scan.shape(s)})")
    ckpt = resume = None
    run_print = fingerprint({
        "settings": asdict(settings), "roi": parse_roi(roi),
        "inputs": [_identify(src, scan) for src, scan in ((ref, f_scan), (deformed, g_scan))],
    })
    if output is not None:
        # all input checks passed: only now is anything written
        ckpt, resume = Checkpoint.start(output, run_print, overwrite=overwrite, inputs=(ref, deformed))
    scratch_root = config.get("scratch-directory")
    scratch = Path(tempfile.mkdtemp(prefix="chunkdic-", dir=scratch_root))
    try:
        with open_runner(scheduler) as runner:
            _emit(progress, stage="start", scheduler=repr(runner), dashboard=runner.dashboard_link,
                  levels=levels, roi=[[r.start, r.stop] for r in meshes[settings.level].roi],
                  requested_roi=None if roi is None else [list(p) for p in parse_roi(roi)],
                  nodes=list(meshes[settings.level].nodes_shape))
            # inside the runner: with a cluster, missing levels are built by its workers
            f_refs = f_scan.refs(levels, scratch / "ref")
            g_refs = g_scan.refs(levels, scratch / "def")
            runner.run_everywhere(kernels.warmup)
            result = _run(settings, meshes, levels, f_refs, g_refs, runner, progress, scratch, ckpt, resume)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    result.info.update(
        voxel_size=f_scan.voxel_size, unit=f_scan.unit, fingerprint=run_print,
        inputs={"reference": _describe(ref), "deformed": _describe(deformed)},
    )
    if output is not None:
        result.save(output, overwrite=True)  # replaces the checkpointed group, marked complete last
    return result


def _run(settings: Settings, meshes, levels, f_refs, g_refs, runner, progress, scratch: Path,
         checkpoint=None, resume: dict | None = None) -> Result:
    """All levels, coarsest first; resumes from ``resume`` (a checkpoint state) if given."""
    history = _History()
    finest, coarsest = levels[-1], levels[0]
    statuses: dict[int, str] = {}
    rigid_t = initial_gap = rigid_gap = None
    gn = None
    if resume is not None:
        history.rows = {k: [_from_json_float(v) if k in ("gap", "max_delta") else v for v in vals]
                        for k, vals in resume["history"].items()}
        statuses = {int(k): v for k, v in resume["statuses"].items()}
        rigid_t = np.array(resume["rigid_t"])
        initial_gap, rigid_gap = resume.get("initial_gap"), resume.get("rigid_gap")
        gn = _GaussNewton.restore(resume["gn"], resume["arrays"])
        _emit(progress, stage="resume", level=resume["level"], iteration=gn.iteration)
    u = None

    def save_checkpoint(state: _GaussNewton, s: int) -> None:
        if checkpoint is None:
            return
        checkpoint.save(
            {"level": s, "gn": state.scalars(), "statuses": {str(k): v for k, v in statuses.items()},
             "history": {k: [_json_float(v) for v in vals] for k, vals in history.rows.items()},
             "rigid_t": rigid_t.tolist(), "initial_gap": initial_gap, "rigid_gap": rigid_gap},
            state.arrays(),
        )

    for s in levels:
        if resume is not None and s > resume["level"]:
            continue  # finished before the interruption
        mesh = meshes[s]
        tol = settings.tolerance if s == finest else settings.coarse_tolerance
        if gn is None or gn.status is None:
            t0, c0 = time.perf_counter(), time.process_time()
            lvl = _Level(s, mesh, f_refs[s], g_refs[s], runner, settings, scratch, progress)
            lvl.assemble_m()
            _emit(progress, stage="matrix", level=s, nodes=list(mesh.nodes_shape), blocks=len(lvl.blocks),
                  voxels=mesh.n_voxels, seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0)
            if gn is None:
                if s == coarsest:
                    t_int = runner_single(runner, translation_task, (f_refs[s], g_refs[s], mesh.roi))
                    lvl.prepare_interpolation(t_int[:, None, None, None] * np.ones((3,) + mesh.nodes_shape))
                    rigid_t = _rigid_step(lvl, t_int, tol, 10, history, progress)
                    u = rigid_t[:, None, None, None] * np.ones((3,) + mesh.nodes_shape)
                else:
                    u = transfer(u, meshes[s + 1], s + 1, mesh, s)
                gn = _GaussNewton(u)
            lvl.prepare_interpolation(gn.u)
            if s == finest and initial_gap is None:
                rigid_fine = rigid_t * 2.0 ** (coarsest - finest)
                _, initial_gap, _, _ = lvl.assemble_b(np.zeros((3,) + mesh.nodes_shape))
                _, rigid_gap, _, _ = lvl.assemble_b(rigid_fine[:, None, None, None] * np.ones((3,) + mesh.nodes_shape))
                _emit(progress, stage="gaps", level=s, initial_gap=initial_gap, rigid_gap=rigid_gap,
                      translation=rigid_fine.tolist())
            gn = _gauss_newton(lvl, gn, tol, settings, history, progress,
                               on_iteration=lambda state, s=s: save_checkpoint(state, s))
            lvl.release(f_copy=True)
            statuses[s] = gn.status
            save_checkpoint(gn, s)
            _emit(progress, stage="level", level=s, status=gn.status, gap=gn.gap, seconds=time.perf_counter() - t0)
        final, u, gn = gn, gn.u, None
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
        "settings": asdict(settings),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "chunkdic_version": _version(),
    }
    return Result(u, mesh.node_coords(), history.arrays(), info)


def runner_single(runner, fn, args):
    """Run one task on the runner and return its result."""
    return next(iter(runner.map_unordered(fn, [args])))


def _positive_int(value, name: str, *, minimum: int) -> int:
    try:
        out = int(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be an integer, got {value!r}") from None
    if out != value or out < minimum:
        raise InputError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return out


def _choice(value, choices, name):
    if value not in choices:
        raise InputError(f"{name} must be one of {', '.join(choices)}; got {value!r}")
    return value


def _identify(src, scan) -> dict:
    """What identifies an input for resuming: its path, shape and dtype (in-memory: never)."""
    if isinstance(src, (str, Path)):
        return {"path": str(Path(src).resolve()), "shape": scan.shape(0), "dtype": str(scan.dtype(0))}
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
