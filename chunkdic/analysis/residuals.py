"""The residual of a result per element: the RMS of ``f − corrected g`` over each element's voxels.

A displacement jump inside an element cannot be followed by the trilinear C8 field: the
correlation spreads it over the element and leaves a misfit on both sides of the jump, so the
element's residual stands out from its neighbours' (the paper's section 5.3 reads the
residual map the same way). :func:`element_residuals` computes it out of core: one task per
block of whole elements corrects the deformed scan by the result with the engine's own warp
(:func:`chunkdic.export.correction.correct_block`) and returns the per-element sums of ``r²``
and the voxel counts (mesh-sized); the client never reads a voxel.
"""

from __future__ import annotations

import contextlib

import numpy as np

from ..mesh import Block
from ..results.scans import input_scans, interpolation_of, level_refs
from ..scheduler import open_runner
from ..export.correction import Correction, brightness_fields, correct_block, element_slice

__all__ = ["element_residuals", "BLOCK_ELEMENTS"]

#: elements per block side of a residual task (8³ elements of 16³ voxels: 16 M voxels)
BLOCK_ELEMENTS = 8


def _residual_task(corr: Correction, block: Block, u_block, brightness, active) -> tuple:
    """Task: ``(block, Σ r², count)`` per element of one block."""
    f, corrected, valid = correct_block(corr, block, u_block, brightness, active)
    ell = corr.mesh.element_size
    n = block.n_elements
    r2 = np.where(valid, (np.asarray(f, np.float64) - corrected) ** 2, 0.0)
    shape = (n[0], ell, n[1], ell, n[2], ell)
    return block, r2.reshape(shape).sum(axis=(1, 3, 5)), valid.reshape(shape).sum(axis=(1, 3, 5))


def element_residuals(result, *, ref=None, deformed=None, scheduler=None) -> np.ndarray:
    """RMS residual of each element, shape (ez, ey, ex), float64, grey levels of the result's level.

    Parameters
    ----------
    result : Result
    ref, deformed : path, optional
        The scans (default: the paths recorded in the result).
    scheduler
        Where the tasks run (:func:`chunkdic.scheduler.open_runner`).

    Returns
    -------
    ndarray
        NaN for an element with no valid voxel (outside a mask, nodes not measured, ``X + u``
        outside the deformed scan).
    """
    scans = input_scans(result, ref, deformed)
    mesh = result.mesh
    total = np.zeros(mesh.shape)
    count = np.zeros(mesh.shape)
    bright = brightness_fields(result)
    with contextlib.ExitStack() as stack:
        f_ref, g_ref = stack.enter_context(level_refs(result, scans=scans))
        corr = Correction.of_result(result, f_ref, g_ref, interpolation_of(result))
        runner = stack.enter_context(open_runner(scheduler))
        tasks = []
        for b in mesh.blocks(BLOCK_ELEMENTS):
            active = None if result.active is None else np.ascontiguousarray(
                result.active[tuple(slice(e0, e1) for e0, e1 in b.elements)])
            tasks.append((corr, b, np.ascontiguousarray(result.displacement[(slice(None),) + b.node_slices]),
                          element_slice(bright, b), active))
        for block, r2, n in runner.map_unordered(_residual_task, tasks):
            at = tuple(slice(e0, e1) for e0, e1 in block.elements)
            total[at] += r2
            count[at] += n
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, np.sqrt(total / np.maximum(count, 1)), np.nan)
