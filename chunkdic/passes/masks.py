"""Specimen masks: which elements hold material and take part in the correlation.

A specimen seldom fills its scan (a cylinder in air is the usual case): elements of air
see no texture, their nodes are poorly determined and they would count in the mean strain.
With a mask (a scan of the reference's shape, any format :func:`chunkdic.open_scan`
reads, non-zero = material) an element takes part only when at least
:data:`MIN_MATERIAL` of its volume is material; the other elements are left out of ``M``,
``b`` and the matching gap, nodes with no active element around them are *missing*
(NaN in the result, :data:`chunkdic.results.result.FLAG_MASKED`), and strain means run over the
active elements only.

Out of core: the mask is binarised (0/1, uint8) and its ``2^s`` sum pyramid written chunk
by chunk into the run's scratch directory once (:func:`prepare_mask`); on level ``s`` a
level voxel's sum over ``8^s`` is its material fraction, and each ``M`` task reads its
block's sums to get its elements' fractions (:func:`element_fractions`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.coarsen import pyramid_dtype
from ..io.handles import ArrayRef
from ..io.levels import create_level, mark_complete
from ..io.scan import open_scan
from ..io.scratch_levels import build_level, region_chunks, task_regions
from ..io.store import check_write_alignment, chunk_shape_for, write_region

#: an element takes part when at least this fraction of its voxels is material
MIN_MATERIAL = 0.5


def prepare_mask(src, ref_shape0, levels, scratch: Path, runner) -> dict[int, ArrayRef]:
    """Binarise ``src`` (non-zero = material) and give its sum levels ``levels`` (ArrayRefs).

    Out of core, by tasks on ``runner`` (:mod:`chunkdic.scheduler`) and without a Dask
    graph: the mask's level 0 on disk (stored, or written to scratch from memory by
    :meth:`~chunkdic.io.scan.Scan.refs`) is binarised chunk by chunk (:func:`binarise_task`)
    into ``scratch``/binary.zarr, whose sum levels :mod:`chunkdic.io.scratch_levels` builds
    (uint8 level 0, then the :func:`~chunkdic.io.coarsen.pyramid_dtype` of each level).

    Raises :class:`InputError` if the mask is not 3-D of the reference's level-0 shape.
    """
    import zarr

    mask = open_scan(src)
    check_mask_shape(mask, ref_shape0)
    source = mask.refs([0], scratch / "source", runner=runner)[0]
    Path(scratch).mkdir(parents=True, exist_ok=True)
    group = str(Path(scratch) / "binary.zarr")
    zarr.open_group(store=group, mode="w-", zarr_format=3).update_attributes(
        {"chunkdic": {"kind": "scratch", "scratch": True}})
    chunks = chunk_shape_for(source.shape, None)
    create_level(group, 0, source.shape, "uint8", chunks)
    binary = ArrayRef("zarr", group, "0", source.shape, "uint8")
    regions = task_regions(source.shape, chunks)
    check_write_alignment(region_chunks(regions, source.shape), source.shape, chunks, name=f"{group}/0")
    for _ in runner.map_unordered(binarise_task, [(source, binary, r) for r in regions]):
        pass
    mark_complete(group, 0)
    out = {0: binary}
    for s in range(1, max(int(v) for v in levels) + 1):
        out[s] = build_level(group, s, out[s - 1], 1, [pyramid_dtype(np.uint8, s)], runner)
    return {int(s): out[int(s)] for s in levels}


def binarise_task(src: ArrayRef, out: ArrayRef, region) -> int:
    """Task: ``region`` of ``src`` as 1 where non-zero (material), else 0 (uint8), into ``out``.

    The region covers whole chunks of ``out``. Returns the voxels written.
    """

    data = (src.read(region) != 0).astype(np.uint8)
    write_region(out.path, out.key, region, data)
    return int(data.size)


def check_mask_shape(mask, ref_shape0) -> None:
    """Raise :class:`InputError` unless the mask (a :class:`chunkdic.io.scan.Scan`) has the reference's level-0 shape."""
    shape = tuple(int(n) for n in mask.shape(0))
    if shape != tuple(int(n) for n in ref_shape0):
        raise InputError(f"the mask has shape {shape}, the reference {tuple(ref_shape0)}: they must be equal")


def element_fractions(mask: ArrayRef, level: int, start, shape, ell: int) -> np.ndarray:
    """Material fraction of each element of a block, shape ``(ez, ey, ex)``, float64.

    ``start, shape``: the block's core (voxels of ``level``); ``mask``: the binary mask's
    sum at that level (:func:`prepare_mask`).
    """
    core = mask.read(tuple(slice(a, a + n) for a, n in zip(start, shape))).astype(np.float64)
    e = tuple(n // ell for n in shape)
    per_element = core.reshape(e[0], ell, e[1], ell, e[2], ell).sum(axis=(1, 3, 5))
    return per_element / (ell**3 * 8.0**level)


def active_elements(fractions: np.ndarray) -> np.ndarray:
    """1 for the elements that take part (material fraction at least :data:`MIN_MATERIAL`), else 0 (uint8)."""
    return (fractions >= MIN_MATERIAL).astype(np.uint8)
