"""Stencil matrix-vector product and block-Jacobi CG against a dense assembly."""

from __future__ import annotations

import numpy as np
import pytest

from chunkdic.errors import InputError
from chunkdic.mesh import LOCAL_NODES, STENCIL_OFFSETS
from chunkdic.solve.cg import StencilSolver
from chunkdic.solve.regularizer import Regularizer
from chunkdic.solve.stencil import half_stencil, rigid_restriction, stencil_matvec


def _random_system(elements=(2, 3, 2), seed=0, weak_element=None):
    """Dense M from random SPD 24x24 element matrices, and the same M as a stencil."""
    rng = np.random.default_rng(seed)
    nodes = tuple(e + 1 for e in elements)
    n = 3 * int(np.prod(nodes))
    dense = np.zeros((n, n))
    S = np.zeros(nodes + (27, 3, 3))
    for ez, ey, ex in np.ndindex(*elements):
        B = rng.standard_normal((24, 30))
        K = B @ B.T / 30
        if (ez, ey, ex) == weak_element:
            K[:] = 0.0  # an element with no texture at all
        idx = [np.ravel_multi_index((ez + dz, ey + dy, ex + dx), nodes) for dz, dy, dx in LOCAL_NODES]
        for a in range(8):
            for b in range(8):
                blk = K[3 * a : 3 * a + 3, 3 * b : 3 * b + 3]
                dense[3 * idx[a] : 3 * idx[a] + 3, 3 * idx[b] : 3 * idx[b] + 3] += blk
                na = np.array(np.unravel_index(idx[a], nodes))
                off = np.array(np.unravel_index(idx[b], nodes)) - na
                k = int(np.flatnonzero((STENCIL_OFFSETS == off).all(axis=1))[0])
                S[tuple(na) + (k,)] += blk
    return dense, S


def _half(S):
    return np.ascontiguousarray(half_stencil(S)).astype(np.float32)


def test_half_stencil_matvec_equals_dense_product():
    dense, S = _random_system()
    x = np.random.default_rng(1).standard_normal(S.shape[:3] + (3,))
    H = np.ascontiguousarray(half_stencil(S))  # float64: the product itself is exact
    np.testing.assert_allclose(stencil_matvec(H, x).ravel(), dense @ x.ravel(), rtol=1e-12, atol=1e-12)
    # the rigid restriction is the sum of every entry of M (uniform translations)
    ones = np.zeros((dense.shape[0] // 3, 3, 3))
    ones[:, np.arange(3), np.arange(3)] = 1.0
    T = ones.reshape(-1, 3)
    np.testing.assert_allclose(rigid_restriction(H), T.T @ dense @ T, rtol=1e-12)


def test_cg_solves_the_system():
    dense, S = _random_system(seed=2)
    b = np.random.default_rng(3).standard_normal(S.shape[:3] + (3,))
    x, iters = StencilSolver(_half(S)).solve(b)
    # the matrix-vector product uses M rounded to float32 (solve.py): agreement to ~1e-5
    exact = np.linalg.solve(dense, b.ravel())
    assert np.abs(x.ravel() - exact).max() < 1e-4 * np.abs(exact).max()
    assert 0 < iters < 200


def test_untextured_nodes_are_regularised_not_nan():
    # the corner node belongs to the untextured corner element only
    _, S = _random_system(elements=(3, 3, 3), seed=4, weak_element=(0, 0, 0))
    solver = StencilSolver(_half(S))
    assert [tuple(n) for n in solver.weak_nodes] == [(0, 0, 0)]
    b = np.ones(S.shape[:3] + (3,))
    x, _ = solver.solve(b)
    # the truth: the dense system with the documented Tikhonov term on the weak node's
    # block only, weak_threshold (1e-3) times the median mean eigenvalue of the blocks
    dense, _ = _random_system(elements=(3, 3, 3), seed=4, weak_element=(0, 0, 0))
    dense[:3, :3] += 1e-3 * solver.scale * np.eye(3)
    exact = np.linalg.solve(dense, b.ravel())
    assert np.abs(x.ravel() - exact).max() < 1e-4 * np.abs(exact).max()


def test_regularised_cg_equals_a_dense_solve():
    """(M + λR) x = b by CG against numpy's dense solve of the same assembled matrices."""
    dense, S = _random_system(elements=(3, 4, 3), seed=5)
    b = np.random.default_rng(6).standard_normal(S.shape[:3] + (3,))
    for kind, weight in (("tikhonov", 0.7), ("equilibrium-gap", 0.05)):
        reg = Regularizer(kind, S.shape[:3], 4.0)
        n = dense.shape[0]
        R = np.stack([reg.apply(e.reshape(S.shape[:3] + (3,))).ravel() for e in np.eye(n)], axis=1)
        np.testing.assert_allclose(R, R.T, atol=1e-9 * np.abs(R).max())  # symmetric
        solver = StencilSolver(_half(S))
        solver.regularize(reg, weight)
        x, _ = solver.solve(b)
        exact = np.linalg.solve(dense + weight * R, b.ravel())
        assert np.abs(x.ravel() - exact).max() < 1e-4 * np.abs(exact).max(), kind
        a = np.random.default_rng(7).standard_normal(b.shape)
        np.testing.assert_allclose(solver.penalty_gradient(a).ravel(), weight * R @ a.ravel(), rtol=1e-10,
                                   atol=1e-12)


def test_no_gradient_at_all_is_a_one_line_input_error():
    with pytest.raises(InputError, match="no gradient"):
        StencilSolver(np.zeros((3, 3, 3, 14, 3, 3), np.float32))


def _dense_regularizer(reg, nodes):
    n = 3 * int(np.prod(nodes))
    return np.stack([reg.apply(e.reshape(tuple(nodes) + (3,))).ravel() for e in np.eye(n)], axis=1)


@pytest.mark.parametrize("slab_nodes", [5, 10**6])  # slabs of one plane, and the whole mesh at once
def test_block_jacobi_solves_each_diagonal_block_of_m_plus_lambda_r(monkeypatch, slab_nodes):
    """Block-Jacobi forms each node's block of ``M + λ R`` as it goes (no stored inverse):
    applied to unit vectors, times the blocks assembled densely (``M`` as the solver stores
    it, float32; ``R`` from its matrix-vector product), it gives the identity to float64
    precision, and is symmetric; the inverses of the nodal variances too, whatever the slabs."""
    import chunkdic.solve.cg as cg
    from chunkdic.solve.stencil import block_solve

    monkeypatch.setattr(cg, "SLAB_NODES", slab_nodes)
    dense, S = _random_system(elements=(3, 4, 2), seed=8)
    nodes = S.shape[:3]
    H = _half(S)
    reg = Regularizer("tikhonov", nodes, 4.0)
    R = _dense_regularizer(reg, nodes)
    solver = StencilSolver(H.copy())
    solver.regularize(reg, 0.3)
    assert not hasattr(solver, "block_inverse")  # nothing mesh-sized held for it
    # the truth: M's blocks as the solver stores them (float32) plus λ R's, from the dense R
    blocks = H[..., 0, :, :].astype(np.float64).reshape(-1, 3, 3)
    blocks += 0.3 * np.stack([R[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(len(blocks))])
    columns = []
    for j in range(3):
        e = np.zeros(nodes + (3,))
        e[..., j] = 1.0
        z = np.empty_like(e)
        block_solve(solver.matrix, *solver._diag_args, solver.weight, e, z)
        columns.append(z.reshape(-1, 3))
    binv = np.stack(columns, axis=-1)  # (nodes, 3, 3): column j is D⁻¹ e_j
    cond = np.linalg.cond(blocks)
    assert np.abs(binv @ blocks - np.eye(3)).max() < 1e-13 * cond.max()
    np.testing.assert_allclose(binv, np.swapaxes(binv, 1, 2), rtol=0, atol=1e-14 * np.abs(binv).max())
    exact = solver.diagonal_inverse().reshape(-1, 3, 3)
    assert np.abs(exact @ blocks - np.eye(3)).max() < 1e-12 * cond.max()
    # the nodal variances diag(A_ii⁻¹ M_ii A_ii⁻¹) from the same dense blocks
    Mii = H[..., 0, :, :].astype(np.float64).reshape(-1, 3, 3)
    inv = np.linalg.inv(blocks)
    want = np.diagonal(inv @ Mii @ inv, axis1=1, axis2=2)
    np.testing.assert_allclose(solver.local_variances().reshape(-1, 3), want, rtol=1e-10)


def test_block_jacobi_cg_solves_a_hand_built_spd_system():
    """A 3-node system written by hand (couplings along x, the same SPD diagonal block at
    every node): block-Jacobi CG converges to numpy's direct solve of the assembled
    matrix, within the 9 iterations exact arithmetic needs."""
    nodes = (1, 1, 3)
    H = np.zeros(nodes + (14, 3, 3), np.float32)
    D = np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 0.5], [0.0, 0.5, 2.0]])
    C = -0.5 * np.eye(3)  # coupling to the +x neighbour (offset index 1 of the half stencil)
    H[0, 0, :, 0] = D
    H[0, 0, :2, 1] = C
    A = np.kron(np.eye(3), D) + np.kron(np.eye(3, k=1), C) + np.kron(np.eye(3, k=-1), C.T)
    b = np.arange(1.0, 10.0).reshape(nodes + (3,))
    solver = StencilSolver(H.copy(), rtol=1e-12)
    x, iterations = solver.solve(b)
    np.testing.assert_allclose(x.ravel(), np.linalg.solve(A, b.ravel()), rtol=1e-10)
    assert iterations <= 9  # CG in exact arithmetic: at most the 9 unknowns


@pytest.mark.parametrize("multigrid", [False, True])
def test_solve_overwriting_its_right_hand_side_gives_the_same_field(multigrid, monkeypatch):
    from chunkdic.solve import galerkin

    monkeypatch.setattr(galerkin, "COARSEST", 8)
    _, S = _random_system(elements=(3, 4, 3), seed=9)
    solver = StencilSolver(_half(S), multigrid=multigrid)
    solver.regularize(Regularizer("tikhonov", S.shape[:3], 4.0), 5.0)
    assert (solver._vcycle is not None) == multigrid
    b = np.random.default_rng(10).standard_normal(S.shape[:3] + (3,))
    x, it = solver.solve(b)
    b2 = b.copy()
    x2, it2 = solver.solve(b2, overwrite_b=True)
    np.testing.assert_array_equal(x2, x)
    assert it2 == it
    assert not np.array_equal(b2, b)  # it was the residual


def test_weak_nodes_keep_their_float64_blocks(monkeypatch):
    """The held block of a weak node is ``M_ii`` plus the documented Tikhonov term in
    float64 (the stencil keeps it rounded to float32), whichever slab reads it."""
    import chunkdic.solve.cg as cg

    monkeypatch.setattr(cg, "SLAB_NODES", 16)
    _, S = _random_system(elements=(3, 3, 3), seed=4, weak_element=(0, 0, 0))
    H = _half(S)
    solver = StencilSolver(H.copy())
    want = H[0, 0, 0, 0].astype(np.float64) + 1e-3 * solver.scale * np.eye(3)
    np.testing.assert_array_equal(solver.diagonal_blocks()[0, 0, 0], want)
    np.testing.assert_array_equal(solver.diagonal_blocks(slice(0, 1))[0, 0, 0], want)
    np.testing.assert_array_equal(solver.diagonal_blocks(slice(1, 4)), H[1:, :, :, 0].astype(np.float64))
