"""The node blocks' haloed files: summed from voxel-block partials, and their products."""

from __future__ import annotations

import dask.array as da
import numpy as np
import pytest
import zarr

from chunkdic.mesh import LOCAL_NODES, STENCIL_OFFSETS
from chunkdic.solve.haloedfiles import HaloedFiles
from chunkdic.solve.nodeblocks import MAX_TASK_BYTES, TASK_BYTES_PER_NODE, node_block_elements, node_chunks
from chunkdic.solve.stencil import half_matvec, subtract_cells

#: elements per axis (uneven: the last voxel and node blocks are shorter)
ELEMENTS = (23, 17, 12)
#: the passes' voxel blocks
M = 4


def half_of(K: np.ndarray) -> np.ndarray:
    """The half stencil (nodes…, 14, 3, 3) float64 summed from element matrices K (elements…, 24, 24)."""
    elements = K.shape[:3]
    nodes = tuple(e + 1 for e in elements)
    full = np.zeros(nodes + (27, 3, 3))
    for a, da_ in enumerate(LOCAL_NODES):
        for b, db in enumerate(LOCAL_NODES):
            k = int(np.flatnonzero((STENCIL_OFFSETS == np.array(db) - np.array(da_)).all(axis=1))[0])
            region = tuple(slice(d, d + e) for d, e in zip(da_, elements))
            full[region + (k,)] += K[..., 3 * a:3 * a + 3, 3 * b:3 * b + 3]
    return full[..., 13:, :, :]


@pytest.fixture(scope="module")
def elements():
    rng = np.random.default_rng(0)
    B = rng.standard_normal(ELEMENTS + (24, 30))
    return np.einsum("...ik,...jk->...ij", B, B) / 30


def partials_store(K, path) -> zarr.Array:
    """Each voxel block's partial stencil over its extended nodes, written where the ``M`` pass
    writes it (block ``i`` from ``i (M + 1)``), float32."""
    blocks = [-(-e // M) for e in ELEMENTS]
    shape = tuple((b - 1) * (M + 1) + e - (b - 1) * M + 1 for b, e in zip(blocks, ELEMENTS))
    z = zarr.create_array(str(path), shape=shape + (14, 3, 3), chunks=(M + 1,) * 3 + (14, 3, 3), dtype=np.float32,
                          fill_value=0, compressors=None, zarr_format=3)
    for i in range(blocks[0]):
        for j in range(blocks[1]):
            for k in range(blocks[2]):
                e0 = (i * M, j * M, k * M)
                part = half_of(K[tuple(slice(e, e + M) for e in e0)])
                z[tuple(slice(b * (M + 1), b * (M + 1) + n) for b, n in zip((i, j, k), part.shape[:3]))] = part
    return z


def test_files_summed_from_partials_hold_the_whole_mesh_stencil(elements, tmp_path):
    nodes = tuple(e + 1 for e in ELEMENTS)
    want = half_of(elements)
    cell = 2
    n_cells = tuple(-(-e // cell) for e in ELEMENTS)
    cells = (0.05 * np.random.default_rng(1).standard_normal(n_cells + (cell + 1,) * 3 + (3, 4))).astype(np.float32)
    cells_store = zarr.create_array(str(tmp_path / "cells.zarr"), shape=cells.shape, chunks=(2, 2, 2) + cells.shape[3:],
                                    dtype=np.float32, compressors=None, zarr_format=3)
    cells_store[...] = cells
    chunks = node_chunks(nodes, 2 * M)  # node blocks of two voxel blocks a side
    cell_chunks = tuple(tuple(-(-c // cell) for c in axis[:-1]) + (n - sum(-(-c // cell) for c in axis[:-1]),)
                        for axis, n in zip(chunks, n_cells))
    files = HaloedFiles.from_partials(partials_store(elements, tmp_path / "p.zarr"), M, chunks, cells_store,
                                      cell_chunks, cell, tmp_path / "files", threads=2)
    assert len(files.blocks) == 3 * 3 * 2
    got = files.array().compute(scheduler="sync")
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * np.abs(want).max())
    np.testing.assert_array_equal(files.cells_array().compute(scheduler="sync"), cells)
    # the product with the cells' complement, against the whole mesh's kernels
    x = np.random.default_rng(2).standard_normal(nodes + (3,))
    ref = np.zeros(x.shape)
    half_matvec(got, x, ref)
    subtract_cells(cells, cell, x, ref)
    out = files.product(x, np.empty(x.shape))
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    files.close()


@pytest.mark.parametrize("block", [4, 8, 24])
def test_products_do_not_change_with_the_node_blocks(elements, tmp_path, block):
    half = half_of(elements).astype(np.float32)
    x = np.random.default_rng(3).standard_normal(half.shape[:3] + (3,))
    ref = np.zeros(x.shape)
    half_matvec(half, x, ref)
    stencil = da.from_array(half.reshape(half.shape[:3] + (126,)), chunks=node_chunks(half.shape[:3], block) + ((126,),))
    files = HaloedFiles.from_array(stencil, None, 1, tmp_path / "files", threads=2)
    # each node's sum over its stencil in the same order in a haloed block as in the whole mesh
    np.testing.assert_array_equal(files.product(x, np.empty(x.shape)), ref)
    files.close()


@pytest.mark.parametrize("elements_shape, voxel_block, tasks", [((64,) * 3, 16, 2), ((96, 96, 40), 16, 2),
                                                                 ((192,) * 3, 16, 4), ((5,) * 3, 4, 2),
                                                                 ((23, 17, 12), 4, 1)])
def test_node_blocks_are_unions_of_voxel_blocks_within_a_task_memory(elements_shape, voxel_block, tasks):
    m = node_block_elements(elements_shape, voxel_block, tasks)
    assert m % voxel_block == 0
    count = np.prod([-(-e // m) for e in elements_shape])
    assert count >= min(2 * tasks, np.prod([-(-e // voxel_block) for e in elements_shape]))
    if m > voxel_block:
        assert TASK_BYTES_PER_NODE * np.prod([min(m, e) + 3 for e in elements_shape]) <= MAX_TASK_BYTES
