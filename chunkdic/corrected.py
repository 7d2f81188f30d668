"""The corrected deformed image and the residual of a result, written as Zarr volumes.

One idea: :func:`write_corrected` writes the deformed scan corrected by the measured field,
``g(X + u(X))``, and the residual ``r = f(X) - g(X + u(X))`` over the ROI as two Zarr v3
arrays, chunk by chunk: one task per block of whole elements, each block exactly one
chunk of the outputs (the task owns it), arrays created first, marked complete last
(shared/DESIGN.md, "Out-of-core shape"; paper section 5.3, Figs. 6-8);
:func:`open_corrected` reads such a group back.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from . import config
from .errors import InputError
from .outputs import Outputs
from .correction import Correction, correct_block, element_slice
from .result import Result
from .resultscans import as_result, input_paths, input_scans, interpolation_of, level_refs

log = logging.getLogger(__name__)

__all__ = ["write_corrected", "open_corrected", "corrected_task"]


def corrected_task(c: Correction, block, u_block: np.ndarray, brightness, local, out_path: str):
    """Task: the corrected image and the residual over one block, written to its own chunk.

    Returns ``(Σ r², n_valid, n_excluded, min f̃, max f̃)`` over the block (float64 sums;
    ``f̃`` the reference as the engine saw it).
    """
    import zarr

    f, corrected, valid = correct_block(c, block, u_block, brightness)
    residual = (f - corrected).astype(np.float32)
    region = tuple(slice(a, a + n) for a, n in zip(local, f.shape))
    for name, data in (("corrected", corrected), ("residual", residual)):
        arr = zarr.open_array(store=out_path, path=name, mode="r+")
        arr[region] = data
    r = residual[valid].astype(np.float64)
    return float(r @ r), int(valid.sum()), int(valid.size - valid.sum()), float(f.min()), float(f.max())


def write_corrected(result, out, *, ref=None, deformed=None, interpolation: str | None = None,
                    scheduler=None, overwrite: bool = False,
                    progress: Callable[[float], None] | None = None) -> dict:
    """Write the corrected deformed image and the residual over the ROI as Zarr volumes.

    Parameters
    ----------
    result : Result or path
        A correlation result.
    out : path
        Zarr v3 group to create, holding arrays ``corrected`` and ``residual``, shape = ROI
        shape ``(Lz, Ly, Lx)`` in voxels of the result's level, float32 grey levels of that
        level, NaN where ``X + u(X)`` leaves the deformed scan. Voxel ``(i, j, k)`` of them
        is voxel ``roi_start + (i, j, k)`` of the reference level.
    ref, deformed : path or array, optional
        The scans (default: the paths recorded in the result).
    interpolation : {"cubic", "linear"}, optional
        Interpolation of ``g`` (default: the result's).
    scheduler
        As in :func:`chunkdic.correlate`.
    overwrite : bool
        Replace an existing ``out``.
    progress : callable(float), optional
        Fraction of blocks done.

    Returns
    -------
    dict
        ``path``, ``gap`` (matching gap of paper section 5.1 over the valid voxels, which
        equals the result's ``final_gap`` up to float round-off), ``valid`` and ``excluded``
        voxel counts.

    References
    ----------
    Paper sections 3 ("corrected deformed image") and 5.3 (mid-plane cuts, Figs. 6-8).
    """
    result = as_result(result)
    interpolation = interpolation or interpolation_of(result)
    if interpolation not in ("cubic", "linear"):
        raise InputError(f"interpolation must be cubic or linear, got {interpolation!r}")
    out = Path(out)
    plan = Outputs(inputs=input_paths(result, ref, deformed), overwrite=overwrite)
    entry = plan.add(out, "corrected")
    input_scans(result, ref, deformed)  # every input checked before anything is written
    with plan:
        return _write_corrected(result, entry.work, out, ref, deformed, interpolation, scheduler, progress)


def _write_corrected(result: Result, work: Path, out: Path, ref, deformed, interpolation: str, scheduler,
                     progress) -> dict:
    """:func:`write_corrected` into ``work`` (renamed to ``out`` by the caller)."""
    import zarr

    from .scheduler import open_runner

    mesh = result.mesh
    ell = mesh.element_size
    m = max(1, int(config.get("chunk-size")) // ell)
    chunk = tuple(min(m, n) * ell for n in mesh.shape)  # a block of m^3 elements = one chunk
    roi_shape = tuple(n * ell for n in mesh.shape)
    u = result.displacement
    # the runner first: with a cluster, missing levels are then written to scratch by its
    # workers, not by the client (as crosscheck and the engine do)
    with open_runner(scheduler) as runner, level_refs(result, ref, deformed) as (f_ref, g_ref):
        corr = Correction.of_result(result, f_ref, g_ref, interpolation)
        root = zarr.open_group(str(work), mode="w", zarr_format=3)
        meta = {
            "kind": "corrected", "complete": False, "result": result.path, "level": result.info.get("level", 0),
            "roi": [[r.start, r.stop] for r in mesh.roi], "element_size": ell, "interpolation": interpolation,
            "voxel_size": result.info.get("voxel_size"), "unit": result.info.get("unit"),
            "smoothing": corr.inputs.sigma, "grey_level": corr.inputs.grey,
            "description": "corrected = gain * g~(X + u(X)) + offset(X), residual = f~(X) - corrected over the "
                           "ROI, with f~, g~ the scans low-passed as the engine did and the brightness it found "
                           "(chunkdic.correction); voxel (i, j, k) is ROI start + (i, j, k) of the reference level",
        }
        root.attrs["chunkdic"] = meta
        for name in ("corrected", "residual"):
            root.create_array(name, shape=roi_shape, chunks=chunk, dtype="float32", fill_value=float("nan"),
                              dimension_names=("z", "y", "x"))
        blocks = mesh.blocks(m)
        args = []
        for blk in blocks:
            local = tuple(e0 * ell for e0, _ in blk.elements)
            assert all(a % c == 0 for a, c in zip(local, chunk))  # each task owns one whole chunk
            args.append((corr, blk, np.ascontiguousarray(u[(slice(None), *blk.node_slices)]),
                         element_slice(result.brightness, blk), local, str(work)))
        ssr, n_valid, n_bad, fmin, fmax = 0.0, 0, 0, math.inf, -math.inf
        for done, (r2, nv, nb, lo, hi) in enumerate(runner.map_unordered(corrected_task, args), 1):
            ssr, n_valid, n_bad = ssr + r2, n_valid + nv, n_bad + nb
            fmin, fmax = min(fmin, lo), max(fmax, hi)
            if progress is not None:
                progress(done / len(args))
    gap = math.sqrt(ssr / n_valid) / (fmax - fmin) if n_valid and fmax > fmin else math.nan
    meta.update(complete=True, gap=gap, valid_voxels=n_valid, excluded_voxels=n_bad)
    zarr.open_group(str(work), mode="r+").attrs["chunkdic"] = meta
    log.info("corrected image and residual written to %s (gap %.4g)", out, gap)
    return {"path": str(out), "gap": gap, "valid": n_valid, "excluded": n_bad}


def open_corrected(path):
    """Open a group written by :func:`write_corrected`: ``(corrected, residual, attrs)`` as
    lazily read Zarr arrays (refuses an incomplete one)."""
    import zarr

    try:
        g = zarr.open_group(str(path), mode="r")
        meta = dict(g.attrs["chunkdic"])
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"{path} is not a corrected-image group ({exc.__class__.__name__})") from None
    if not meta.get("complete"):
        raise InputError(f"{path} is incomplete (the run that wrote it was interrupted)")
    return g["corrected"], g["residual"], meta
