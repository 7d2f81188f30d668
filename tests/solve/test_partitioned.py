"""The partitioned solver (node blocks on disk or on workers) against the in-memory one."""

from __future__ import annotations

import numpy as np
import pytest

from chunkdic.mesh import LOCAL_NODES, STENCIL_OFFSETS
from chunkdic.solve.cg import StencilSolver
from chunkdic.solve.nodeblocks import DiskHolder, WorkerHolder, extended_chunks, fold_faces, from_client, node_chunks
from chunkdic.solve.partitioned import PartitionedSolver
from chunkdic.solve.regularizer import Regularizer

NODES = (24, 24, 24)
#: 2 blocks per axis: 8 partitions
BLOCK = 12


def random_half(nodes=NODES, seed=0) -> np.ndarray:
    """A half stencil summed from random SPD 24×24 element matrices (float32)."""
    rng = np.random.default_rng(seed)
    elements = tuple(n - 1 for n in nodes)
    B = rng.standard_normal(elements + (24, 30))
    K = np.einsum("...ik,...jk->...ij", B, B) / 30
    full = np.zeros(nodes + (27, 3, 3))
    for a, da_ in enumerate(LOCAL_NODES):
        for b, db in enumerate(LOCAL_NODES):
            off = np.array(db) - np.array(da_)
            k = int(np.flatnonzero((STENCIL_OFFSETS == off).all(axis=1))[0])
            region = tuple(slice(d, d + e) for d, e in zip(da_, elements))
            full[region + (k,)] += K[..., 3 * a:3 * a + 3, 3 * b:3 * b + 3]
    return np.ascontiguousarray(full[..., 13:, :, :]).astype(np.float32)


def random_cells(nodes, k, seed=1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    cells = tuple(-(-(n - 1) // k) for n in nodes)
    return (0.05 * rng.standard_normal(cells + (k + 1,) * 3 + (3, 4))).astype(np.float32)


def partitioned(half, holder, cells=None, cell=1, block=BLOCK) -> PartitionedSolver:
    chunks = node_chunks(half.shape[:3], block)
    S = from_client(half, chunks, holder, "stencil")
    W = None
    if cells is not None:
        per = block // cell
        wchunks = tuple(tuple(min(per, n - i) for i in range(0, n, per)) for n in cells.shape[:3])
        W = from_client(cells, wchunks, holder, "cells")
    return PartitionedSolver(S, holder, cells=W, cell=cell)


@pytest.fixture
def disk(tmp_path):
    holder = DiskHolder(tmp_path / "mesh", threads=2)
    yield holder
    holder.close()


def test_node_chunks_follow_the_voxel_blocks_and_fold_adds_shared_faces(disk):
    assert node_chunks((24, 24, 24), 12) == ((12, 12),) * 3
    assert node_chunks((25, 8, 2), 12) == ((12, 13), (8,), (2,))
    # per-block sums over each block's elements (extended nodes) of ones: a node's count is the
    # number of blocks whose elements touch it (1 inside, 2 on a face, 4 on an edge, 8 at a corner)
    chunks = node_chunks((9, 9, 9), 4)
    ext = extended_chunks(chunks)
    import dask.array as da

    ones = da.ones(tuple(sum(c) for c in ext) + (1,), chunks=ext + ((1,),))
    folded = disk.values(fold_faces(ones))[0][..., 0]
    count = np.ones(9)
    count[4] = 2  # node 4 is shared by blocks 0 and 1 (its elements 0-3 and 4-7)
    np.testing.assert_array_equal(folded, count[:, None, None] * count[None, :, None] * count[None, None, :])


@pytest.mark.parametrize("kind", ["tikhonov", "equilibrium-gap", "freed"])
def test_block_products_equal_the_whole_mesh_products(disk, kind):
    half = random_half()
    cells = random_cells(NODES, 4)
    ref = StencilSolver(half.copy(), cells=cells, cell=4)
    part = partitioned(half, disk, cells, 4)
    freed = None
    if kind == "freed":
        freed = np.random.default_rng(5).integers(0, 8, NODES + (6,)).astype(np.uint8)
    reg = Regularizer("tikhonov" if kind == "freed" else kind, NODES, 8.0, freed)
    ref.regularize(reg, 0.7)
    part.regularize(reg, 0.7)
    x = np.random.default_rng(2).standard_normal(NODES + (3,))
    want = ref.matvec(x)
    np.testing.assert_allclose(part.matvec(x), want, rtol=0, atol=1e-12 * np.abs(want).max())
    want = ref.data_matvec(x)
    np.testing.assert_allclose(part.data_matvec(x), want, rtol=0, atol=1e-12 * np.abs(want).max())
    np.testing.assert_allclose(part.rigid_matrix, ref.rigid_matrix, rtol=1e-9)
    np.testing.assert_allclose(part.local_variances(), ref.local_variances(), rtol=1e-12)


def test_weak_nodes_are_found_and_held_as_in_memory(disk):
    half = random_half(seed=3)
    half[3:5, 7:9, 10:12, 0] *= 1e-6  # a few poorly textured nodes
    ref = StencilSolver(half.copy())
    part = partitioned(half, disk)
    assert len(ref.weak_nodes) > 0
    np.testing.assert_array_equal(part.weak_nodes, ref.weak_nodes)
    np.testing.assert_array_equal(part.matrix[...], ref.matrix)
    np.testing.assert_array_equal(part.diagonal_blocks(slice(2, 6)), ref.diagonal_blocks(slice(2, 6)))
    # the products with the weak nodes held (on disk: the files keep M's own blocks, the
    # product adds the held ones' difference)
    x = np.random.default_rng(6).standard_normal(NODES + (3,))
    want = ref.matvec(x)
    np.testing.assert_allclose(part.matvec(x), want, rtol=0, atol=1e-12 * np.abs(want).max())


def _solves_agree(holder):
    half = random_half(seed=3)
    half[..., 0, [0, 1, 2], [0, 1, 2]] += 10.0  # well conditioned: about ten iterations
    b = np.random.default_rng(4).standard_normal(NODES + (3,))
    ref = StencilSolver(half.copy(), multigrid=False)
    part = partitioned(half, holder)
    reg = Regularizer("tikhonov", NODES, 8.0)
    for weight in (0.0, 0.05):
        ref.regularize(reg, weight)
        part.regularize(reg, weight)
        want, it_ref = ref.solve(b.copy())
        got, it = part.solve(b.copy())
        assert it == it_ref and it > 3
        assert np.linalg.norm(got - want) <= 1e-10 * np.linalg.norm(want)


def test_partitioned_solve_equals_in_memory_solve_on_disk(disk):
    _solves_agree(disk)


def test_the_solution_does_not_change_with_the_node_blocks(tmp_path):
    """1, 8 and 27 node blocks (cells and a penalty): the same iterations and solution."""
    half = random_half(seed=3)
    half[..., 0, [0, 1, 2], [0, 1, 2]] += 10.0
    cells = random_cells(NODES, 4)
    b = np.random.default_rng(4).standard_normal(NODES + (3,))
    reg = Regularizer("tikhonov", NODES, 8.0)
    solutions = []
    for block in (24, 12, 8):
        holder = DiskHolder(tmp_path / f"mesh{block}", threads=2)
        part = partitioned(half, holder, cells, 4, block=block)
        part.regularize(reg, 0.05)
        solutions.append(part.solve(b.copy()))
        holder.close()
    (x1, it1), *others = solutions
    for x, it in others:
        assert it == it1
        assert np.linalg.norm(x - x1) <= 1e-13 * np.linalg.norm(x1)


def test_partitioned_solve_equals_in_memory_solve_on_a_local_cluster():
    from distributed import Client, LocalCluster

    # in-process workers (their own event loop and memory accounting; no ports opened)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        _solves_agree(WorkerHolder(client))
