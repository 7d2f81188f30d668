"""The brightness cells' Schur complement (kernels.m.cell_couplings) against the Gauss–Newton
matrix of the variable-projection problem written out voxel by voxel."""

import numpy as np
import pytest

from chunkdic.kernels.blocks import gradient_block
from chunkdic.kernels.m import m_block
from chunkdic.mesh import shape_table
from chunkdic.solve.cg import StencilSolver
from chunkdic.solve.stencil import half_stencil, stencil_matvec


def dense_reduced_hessian(f, ell, elems, k, weight=None):
    """``Jᵀ W J - Jᵀ W B (Bᵀ W B)⁺ Bᵀ W J``: ``J`` the C8 sensitivities ``N_n ∂_i f`` of every
    core voxel, ``B`` an affine function ``1, z, y, x`` per cell of ``k³`` elements (the b pass's
    brightness model), ``W`` the voxel weights; dense, (3 n_nodes)²."""
    grad = gradient_block(f, (1, 1, 1), (1, 1, 1)).astype(np.float64)  # (3, core)
    core = grad.shape[1:]
    nodes = tuple(e + 1 for e in elems)
    n_dof = 3 * int(np.prod(nodes))
    N = shape_table(ell)
    cells = tuple(-(-e // k) for e in elems)
    J = np.zeros(core + (n_dof,))
    B = np.zeros(core + (4 * int(np.prod(cells)),))
    w = np.ones(core) if weight is None else weight
    for z, y, x in np.ndindex(*core):
        e = (z // ell, y // ell, x // ell)
        loc = (z % ell, y % ell, x % ell)
        for a in range(8):
            d = (a >> 2, (a >> 1) & 1, a & 1)
            node = np.ravel_multi_index(tuple(e[i] + d[i] for i in range(3)), nodes)
            J[z, y, x, 3 * node:3 * node + 3] = N[loc + (a,)] * grad[:, z, y, x]
        c = np.ravel_multi_index(tuple(ei // k for ei in e), cells)
        B[z, y, x, 4 * c:4 * c + 4] = (1.0, z / 7.0, y / 7.0, x / 7.0)  # any affine basis: same span
    J = J.reshape(-1, n_dof) * np.sqrt(w.reshape(-1, 1))
    B = B.reshape(-1, B.shape[-1]) * np.sqrt(w.reshape(-1, 1))
    P = B @ np.linalg.pinv(B.T @ B, rcond=1e-12, hermitian=True) @ B.T
    return J.T @ J - J.T @ P @ J


def dense_of(solver, nodes):
    n = 3 * int(np.prod(nodes))
    A = np.zeros((n, n))
    e = np.zeros(tuple(nodes) + (3,))
    for j in range(n):
        e.reshape(-1)[j] = 1.0
        A[:, j] = solver.data_matvec(e).reshape(-1)
        e.reshape(-1)[j] = 0.0
    return A


@pytest.mark.parametrize("elems,k", [((4, 4, 4), 2), ((3, 4, 5), 2), ((4, 3, 3), 3)])
def test_cells_complement_is_the_reduced_gauss_newton_matrix(elems, k):
    # a random texture, cells of k³ elements, partial ones at the far faces included: M minus
    # the stored complement equals the matrix of the field with each cell's affine offset
    # eliminated, written out from the voxels
    ell = 3
    rng = np.random.default_rng(3)
    f = rng.normal(100.0, 20.0, tuple(ell * e + 2 for e in elems)).astype(np.float32)
    S, _, _, cells = m_block(f, (1, 1, 1), (1, 1, 1), ell, grey="drift", cell=k)
    assert cells.shape == tuple(-(-e // k) for e in elems) + (k + 1,) * 3 + (3, 4)
    solver = StencilSolver(np.ascontiguousarray(half_stencil(S)).astype(np.float32), cells=cells, cell=k,
                           weak_threshold=0.0)
    nodes = tuple(e + 1 for e in elems)
    got = dense_of(solver, nodes)
    want = dense_reduced_hessian(f, ell, elems, k)
    scale = np.abs(want).max()
    assert np.abs(got - want).max() < 2e-5 * scale
    # and the complement is no small correction: a Gauss–Newton step with M alone leaves
    # the error component along M⁻¹(M - H)'s top eigenvector shrunk by that eigenvalue only
    M = np.stack([stencil_matvec(solver.matrix, e).reshape(-1)
                  for e in np.eye(got.shape[0]).reshape((-1,) + nodes + (3,))], axis=1)
    slowest = np.linalg.eigvals(np.linalg.solve(M, M - want)).real.max()
    assert slowest > 0.2  # 0.39 on the first case: the ×0.2-0.35 per pass measured at 512³-1024³


@pytest.mark.parametrize("two_lanes", [False, True])
@pytest.mark.parametrize("weight", [0.0, 30.0])
def test_cg_with_cells_solves_the_reduced_system(monkeypatch, two_lanes, weight):
    # CG on M minus the cells' complement (plus a Tikhonov penalty) against numpy's dense
    # solve of the voxel-by-voxel matrix: the serial CG, and the client's two-lane one
    # (solve.lanes: the stencil on one thread, the cells and the penalty on another)
    from chunkdic.solve import lanes
    from chunkdic.solve.regularizer import Regularizer

    monkeypatch.setattr(lanes, "LANES_FROM", 0 if two_lanes else 10**12)
    monkeypatch.setattr(lanes, "second_lane", lambda real=lanes.second_lane: real() if two_lanes else None)
    if two_lanes and lanes.second_lane() is None:
        pytest.skip("one core: no second lane")
    ell, elems, k = 3, (4, 4, 4), 2
    rng = np.random.default_rng(5)
    f = rng.normal(100.0, 20.0, tuple(ell * e + 2 for e in elems)).astype(np.float32)
    S, _, _, cells = m_block(f, (1, 1, 1), (1, 1, 1), ell, grey="drift", cell=k)
    solver = StencilSolver(np.ascontiguousarray(half_stencil(S)).astype(np.float32), cells=cells, cell=k,
                           weak_threshold=0.0)
    nodes = tuple(e + 1 for e in elems)
    want = dense_reduced_hessian(f, ell, elems, k)
    if weight:
        reg = Regularizer("tikhonov", nodes, float(ell))
        solver.regularize(reg, weight)
        want = want + weight * np.stack([reg.apply(e.reshape(nodes + (3,))).ravel()
                                         for e in np.eye(want.shape[0])], axis=1)
    b = rng.standard_normal(nodes + (3,))
    x, iterations = solver.solve(b)
    exact = np.linalg.solve(want, b.ravel())
    assert 0 < iterations < 2000
    assert np.abs(x.ravel() - exact).max() < 1e-4 * np.abs(exact).max()  # 1e-5 measured (rtol, float32 M)


def test_no_couplings_without_cells():
    # one element per cell is the per-element offset, condensed in the stencil itself
    f = np.random.default_rng(0).normal(0, 1, (8, 8, 8)).astype(np.float32)
    out = m_block(f, (1, 1, 1), (1, 1, 1), 3, grey="drift", cell=1)
    assert len(out) == 3
