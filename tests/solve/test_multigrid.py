"""The multigrid V-cycle preconditioner against independent truths (analytic interpolation, dense algebra)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator

from chunkdic.mesh import LOCAL_NODES, STENCIL_OFFSETS
from chunkdic.solve import galerkin
from chunkdic.solve.cg import StencilSolver
from chunkdic.solve.regularizer import Regularizer, plane_wave_weight
from chunkdic.solve.stencil import stencil_matvec


def _mass_stencil(nodes, seed=0):
    """Half stencil (float32) of ``Σ_e m ⊗ T_e``: the C8 mass matrix ``m`` times a random SPD 3×3 per element."""
    rng = np.random.default_rng(seed)
    elements = tuple(n - 1 for n in nodes)
    G = rng.standard_normal(elements + (3, 3))
    T = G @ np.swapaxes(G, -1, -2) + 0.1 * np.eye(3)
    m1 = np.array([[2.0, 1.0], [1.0, 2.0]]) / 6.0  # ∫ N_a N_b of a 1-D hat pair
    H = np.zeros(tuple(nodes) + (14, 3, 3))
    for a, da in enumerate(LOCAL_NODES):
        for b, db in enumerate(LOCAL_NODES):
            k = int(np.flatnonzero((STENCIL_OFFSETS == np.subtract(db, da)).all(axis=1))[0])
            if k < 13:
                continue  # the transposed pair (b, a) fills the stored half
            mab = m1[da[0], db[0]] * m1[da[1], db[1]] * m1[da[2], db[2]]
            sl = tuple(slice(d, d + e) for d, e in zip(da, elements))
            H[sl + (k - 13,)] += mab * T
    return H.astype(np.float32)


def _coarse_positions(n):
    """Fine positions of the coarse nodes: every other node and the last one (multigrid's convention)."""
    return np.unique(np.append(np.arange(0, n, 2), n - 1)) if n >= 3 else np.arange(n)


def _dense_prolongation(shape):
    """P (3 N_fine, 3 N_coarse) by scipy's trilinear interpolation of each coarse unit field."""
    pos = [_coarse_positions(n) for n in shape]
    coarse = tuple(len(p) for p in pos)
    fine_points = np.indices(shape).reshape(3, -1).T
    P = np.zeros((3 * fine_points.shape[0], 3 * int(np.prod(coarse))))
    for j in range(int(np.prod(coarse))):
        e = np.zeros(coarse)
        e[np.unravel_index(j, coarse)] = 1.0
        col = RegularGridInterpolator(pos, e, method="linear")(fine_points)
        for c in range(3):
            P[c::3, 3 * j + c] = col
    return P, coarse


def _transfers(shape):
    return tuple(galerkin.axis_transfer(n) if galerkin.coarse_size(n) < n else None for n in shape)


def _dense(apply, shape):
    n = 3 * int(np.prod(shape))
    cols = []
    for j in range(n):
        e = np.zeros(n)
        e[j] = 1.0
        cols.append(apply(e.reshape(tuple(shape) + (3,))).ravel())
    return np.array(cols).T


def test_prolongation_is_trilinear_interpolation_and_restriction_its_transpose():
    shape = (5, 6, 2)  # odd, even (last interval one fine step), and an axis too short to coarsen
    pos = [_coarse_positions(n) for n in shape]
    coarse = tuple(len(p) for p in pos)
    rng = np.random.default_rng(0)
    xc = rng.standard_normal(coarse + (3,))
    tables = [t[:2] if t is not None else galerkin.identity_transfer(n)[:2]
              for t, n in zip(_transfers(shape), shape)]
    x = np.zeros(shape + (3,))
    galerkin.transfer(x, *tables[0], *tables[1], *tables[2], xc, False)
    points = np.indices(shape).reshape(3, -1).T
    for c in range(3):  # the analytic trilinear field of the coarse values at the fine nodes
        truth = RegularGridInterpolator(pos, xc[..., c], method="linear")(points).reshape(shape)
        np.testing.assert_allclose(x[..., c], truth, rtol=0, atol=1e-14)
    r = rng.standard_normal(shape + (3,))
    rc = np.empty(coarse + (3,))
    galerkin.transfer(r, *tables[0], *tables[1], *tables[2], rc, True)
    assert np.isclose(np.sum(rc * xc), np.sum(r * x), rtol=1e-13)


def test_galerkin_coarse_operators_equal_dense_triple_products():
    shape = (5, 4, 3)
    H = _mass_stencil(shape)
    P, coarse = _dense_prolongation(shape)
    M = _dense(lambda v: stencil_matvec(H, v), shape)
    Mc = galerkin.node_stencil(H).coarsened(_transfers(shape), 0).S
    assert Mc.shape == coarse + (14, 3, 3)  # a 27-point stencil stays 27-point
    np.testing.assert_allclose(_dense(lambda v: stencil_matvec(Mc, v), coarse), P.T @ M @ P, rtol=0,
                               atol=2e-7 * np.abs(M).max())  # float32 storage
    for kind in ("tikhonov", "equilibrium-gap"):
        reg = Regularizer(kind, shape, 6.0)
        R = _dense(reg.apply, shape)
        Rc = galerkin.regularizer_stencil(reg).coarsened(_transfers(shape), galerkin.CORE)

        def coarse_apply(v, Rc=Rc):
            y = np.zeros_like(v)
            Rc.matvec_add(1.0, v, y)
            return y

        np.testing.assert_allclose(_dense(coarse_apply, coarse), P.T @ R @ P, rtol=0, atol=1e-12 * np.abs(R).max())


@pytest.mark.parametrize("kind", ["tikhonov", "equilibrium-gap"])
def test_class_stencils_of_a_large_mesh_act_as_R_and_its_galerkin_product(kind):
    """Class stencils (rows shared by interior nodes) on meshes longer than 2·CORE + 1 nodes per axis."""
    shape = (20, 17, 12)
    reg = Regularizer(kind, shape, 8.0)
    R0 = galerkin.regularizer_stencil(reg)
    assert R0.S.shape[:3] == (7, 7, 7)  # probed on 7³ nodes, whatever the mesh
    rng = np.random.default_rng(1)
    v = rng.standard_normal(shape + (3,))
    y = np.zeros_like(v)
    R0.matvec_add(1.0, v, y)
    np.testing.assert_allclose(y, reg.apply(v), rtol=0, atol=1e-12 * np.abs(y).max())
    # coarse: wᵀ R_c v = (P w)ᵀ R (P v), P by scipy's trilinear interpolation
    R1 = R0.coarsened(_transfers(shape), galerkin.CORE)
    pos = [_coarse_positions(n) for n in shape]
    coarse = tuple(len(p) for p in pos)
    points = np.indices(shape).reshape(3, -1).T

    def prolong(xc):
        return np.stack([RegularGridInterpolator(pos, xc[..., c])(points).reshape(shape) for c in range(3)], -1)

    for _ in range(3):
        vc, wc = rng.standard_normal((2,) + coarse + (3,))
        yc = np.zeros_like(vc)
        R1.matvec_add(1.0, vc, yc)
        truth = np.sum(prolong(wc) * reg.apply(prolong(vc)))
        assert np.isclose(np.sum(wc * yc), truth, rtol=1e-11)


@pytest.mark.parametrize("kind", ["tikhonov", "equilibrium-gap"])
def test_vcycle_cg_equals_a_dense_solve_and_is_symmetric(kind, monkeypatch):
    monkeypatch.setattr(galerkin, "COARSEST", 8)  # four levels on 6³ nodes: 6³, 4³, 3³, 2³ (dense)
    shape = (6, 6, 6)
    H = _mass_stencil(shape, seed=2)
    reg = Regularizer(kind, shape, 4.0)
    lam = plane_wave_weight(reg, lambda v: stencil_matvec(H, v), 32 * 4.0)
    solver = StencilSolver(H.copy(), rtol=1e-10, multigrid=True)
    solver.regularize(reg, lam)
    assert [lev.shape for lev in solver._vcycle.levels] == [(6, 6, 6), (4, 4, 4), (3, 3, 3), (2, 2, 2)]
    A = _dense(solver.matvec, shape)
    b = np.random.default_rng(3).standard_normal(shape + (3,))
    x, iterations = solver.solve(b)
    exact = np.linalg.solve(A, b.ravel())
    assert np.abs(x.ravel() - exact).max() < 1e-8 * np.abs(exact).max()
    # the preconditioner B (one V-cycle) is symmetric positive definite, as PCG needs
    B = _dense(solver._vcycle.cycle, shape)
    np.testing.assert_allclose(B, B.T, rtol=0, atol=1e-10 * np.abs(B).max())
    assert np.linalg.eigvalsh(0.5 * (B + B.T)).min() > 0


def test_iterations_do_not_grow_with_the_length():
    """Tikhonov at 32ℓ on 16³ nodes: block-Jacobi CG needs hundreds of iterations, the V-cycle about ten."""
    shape = (16, 16, 16)
    H = _mass_stencil(shape, seed=4)
    reg = Regularizer("tikhonov", shape, 8.0)
    b = np.random.default_rng(5).standard_normal(shape + (3,))
    counts = {}
    for length in (8.0, 256.0):  # ℓ and 32ℓ
        lam = plane_wave_weight(reg, lambda v: stencil_matvec(H, v), length)
        for use in (False, None):
            solver = StencilSolver(H.copy(), rtol=1e-7, multigrid=use)
            solver.regularize(reg, lam)
            counts[length, use] = solver.solve(b)[1]
            if use is None:  # the automatic choice: block-Jacobi at ℓ, the V-cycle at 32ℓ
                assert (solver._vcycle is not None) == (length == 256.0)
    assert counts[256.0, False] > 500  # measured 914 (33 at ℓ)
    assert counts[256.0, None] <= 40  # measured 29 (28 at 32³ nodes, 27 at 48³)
    # the equilibrium gap too, since its null space is 24 fields (the edge term, issue 20):
    # measured at 32ℓ 1 887 block-Jacobi iterations against 70 with the V-cycle (before the
    # edge term: 2 000+ against 2 000+, neither converged)
    reg = Regularizer("equilibrium-gap", shape, 8.0)
    lam = plane_wave_weight(reg, lambda v: stencil_matvec(H, v), 256.0)
    for use in (False, None):
        eq = StencilSolver(H.copy(), rtol=1e-7, multigrid=use)
        eq.regularize(reg, lam)
        counts["eq", use] = eq.solve(b)[1]
    assert eq._vcycle is not None
    assert counts["eq", False] > 1000 and counts["eq", None] <= 100


@pytest.mark.parametrize("shape", [(11, 9, 7), (17, 3, 10), (2, 20, 20)])
def test_slab_coarsening_equals_the_whole(shape):
    """Coarse M built a few z planes at a time: bit-identical to the whole-stencil product."""
    H = np.random.default_rng(1).standard_normal(shape + (14, 3, 3)).astype(np.float32)
    tr = galerkin.level_transfers(shape)
    whole = galerkin.node_stencil(H).coarsened(tr, 0).S
    for slab in (1, 3, 16):
        np.testing.assert_array_equal(galerkin.coarsened_in_slabs(H, tr, slab), whole)
