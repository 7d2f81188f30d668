"""Stencil matrix-vector product and block-Jacobi CG against a dense assembly."""

from __future__ import annotations

import numpy as np
from chunkdic.mesh import LOCAL_NODES, STENCIL_OFFSETS
from chunkdic.solve import StencilSolver, stencil_matvec


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


def test_stencil_matvec_equals_dense_product():
    dense, S = _random_system()
    x = np.random.default_rng(1).standard_normal(S.shape[:3] + (3,))
    np.testing.assert_allclose(stencil_matvec(S, x).ravel(), dense @ x.ravel(), rtol=1e-12, atol=1e-12)


def test_cg_solves_the_system():
    dense, S = _random_system(seed=2)
    b = np.random.default_rng(3).standard_normal(S.shape[:3] + (3,))
    x, iters = StencilSolver(S.copy()).solve(b)
    # the matrix-vector product uses M rounded to float32 (solve.py): agreement to ~1e-5
    exact = np.linalg.solve(dense, b.ravel())
    assert np.abs(x.ravel() - exact).max() < 1e-4 * np.abs(exact).max()
    assert 0 < iters < 200


def test_untextured_nodes_are_regularised_not_nan():
    # the corner node belongs to the untextured corner element only
    _, S = _random_system(elements=(3, 3, 3), seed=4, weak_element=(0, 0, 0))
    solver = StencilSolver(S)
    assert [tuple(n) for n in solver.weak_nodes] == [(0, 0, 0)]
    x, _ = solver.solve(np.ones(S.shape[:3] + (3,)))
    assert np.isfinite(x).all()
