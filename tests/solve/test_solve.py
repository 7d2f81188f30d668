"""Stencil matrix-vector product and block-Jacobi CG against a dense assembly."""

from __future__ import annotations

import numpy as np
import pytest

from chunkdic.errors import InputError
from chunkdic.mesh import LOCAL_NODES, STENCIL_OFFSETS
from chunkdic.solve.cg import StencilSolver
from chunkdic.solve.regularization import Regularizer
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
