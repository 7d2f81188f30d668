"""The robust reweighting of the Tikhonov penalty (issue 20: the band and the slip at ℓ = 8).

Truths: the penalty of hand-built nodal fields (a kink of known second difference, a random
field's squared differences by ``np.diff``), the dense operator probed column by column, a
dense solve, and which terms a field of known shape must free (a kink's plane, nothing for
a wave or for noise).
"""

from __future__ import annotations

import numpy as np
import pytest

from chunkdic.mesh import LOCAL_NODES, STENCIL_OFFSETS
from chunkdic.solve import galerkin
from chunkdic.solve.cg import StencilSolver
from chunkdic.solve.penalty import NO_FREED, TERM_KINDS, add_weighted
from chunkdic.solve.regularizer import Regularizer, plane_wave_weight
from chunkdic.solve.reweighting import robust_freed
from chunkdic.solve.stencil import stencil_matvec

ZZ, ZY = TERM_KINDS.index("zz"), TERM_KINDS.index("zy")


def _kept_penalty(x: np.ndarray, freed: np.ndarray) -> float:
    """``xᵀ R_w x`` by hand: Σ kept second differences² + 2 Σ kept mixed differences²
    (``np.diff``), a term kept unless its bit is set at its anchor node."""
    total = 0.0
    for c in range(3):
        u = x[..., c]
        for a in range(3):  # second differences along axis a, anchored at their centre node
            d = np.diff(u, n=2, axis=a)
            mid = [slice(None)] * 3
            mid[a] = slice(1, -1)
            kept = (freed[tuple(mid) + (a,)] >> c) & 1 == 0
            total += float(np.sum(d[kept] ** 2))
        for t, (a, b) in zip((3, 4, 5), ((0, 1), (0, 2), (1, 2))):  # mixed, anchored at the first corner
            d = np.diff(np.diff(u, axis=a), axis=b)
            first = [slice(None)] * 3
            first[a] = first[b] = slice(0, -1)
            kept = (freed[tuple(first) + (t,)] >> c) & 1 == 0
            total += 2.0 * float(np.sum(d[kept] ** 2))
    return total


def test_a_freed_kink_costs_nothing_and_the_plain_penalty_its_hand_computed_value():
    """``u_x = |z − 2|`` on 5 × 4 × 4 nodes: one second difference of 2 per (y, x) column at
    z = 2, nothing else (a function of z alone has no mixed differences), so the plain
    penalty is 16 × 2² = 64 and ``(R u)_x`` is (2, −4, 2) at z = 1, 2, 3; with those 16 terms
    of component x freed the penalty and ``R u`` vanish, and the other components' terms
    still act."""
    shape = (5, 4, 4)
    u = np.zeros(shape + (3,))
    u[..., 2] = np.abs(np.arange(5) - 2.0)[:, None, None]
    plain = Regularizer("tikhonov", shape, 8.0)
    r = plain.apply(u)
    np.testing.assert_array_equal(r[1:4, :, :, 2], np.broadcast_to(np.array([2.0, -4.0, 2.0])[:, None, None],
                                                                   (3, 4, 4)))
    assert float(np.sum(u * r)) == 64.0
    freed = np.zeros(shape + (6,), np.uint8)
    freed[2, :, :, ZZ] = 1 << 2  # component x (bit 2) of the zz terms centred on z = 2
    weighted = Regularizer("tikhonov", shape, 8.0, freed)
    assert not weighted.apply(u).any()
    v = u[..., ::-1].copy()  # the same kink in component z: its terms are not freed
    np.testing.assert_array_equal(weighted.apply(v), plain.apply(v))


def test_weighted_operator_is_the_sum_of_the_kept_squared_terms_and_symmetric():
    shape = (6, 5, 7)
    rng = np.random.default_rng(0)
    freed = (rng.random(shape + (6,)) < 0.3) * rng.integers(1, 8, shape + (6,))
    freed = freed.astype(np.uint8)
    reg = Regularizer("tikhonov", shape, 6.0, freed)
    x, y = rng.standard_normal((2,) + shape + (3,))
    assert float(np.sum(x * reg.apply(x))) == pytest.approx(_kept_penalty(x, reg.freed), rel=1e-12)
    assert float(np.sum(y * reg.apply(x))) == pytest.approx(float(np.sum(x * reg.apply(y))), rel=1e-12)
    # the numba product of the CG and the V-cycle's fine level is the same operator
    out = np.zeros_like(x)
    add_weighted(*reg.numba_args(), 0.5, x, out)
    np.testing.assert_allclose(out, 0.5 * reg.apply(x), rtol=1e-13, atol=1e-13)
    # nothing freed: the plain operator, and an all-zero mask is dropped
    assert Regularizer("tikhonov", shape, 6.0, np.zeros(shape + (6,), np.uint8)).freed is None
    plain = Regularizer("tikhonov", shape, 6.0)
    assert plain.numba_args()[-1] is NO_FREED
    assert float(np.sum(x * plain.apply(x))) == pytest.approx(_kept_penalty(x, np.zeros_like(freed)), rel=1e-12)


def test_diagonal_blocks_of_the_weighted_operator_are_its_dense_diagonal():
    shape = (9, 8, 10)  # more than the probed 7 nodes per axis: the class blocks mapped back
    rng = np.random.default_rng(1)
    freed = ((rng.random(shape + (6,)) < 0.2) * rng.integers(1, 8, shape + (6,))).astype(np.uint8)
    reg = Regularizer("tikhonov", shape, 4.0, freed)
    dense = np.zeros(shape + (3,))
    for c in range(3):
        for idx in np.ndindex(shape):
            e = np.zeros(shape + (3,))
            e[idx + (c,)] = 1.0
            dense[idx + (c,)] = reg.apply(e)[idx + (c,)]
    blocks = reg.diagonal_blocks()
    np.testing.assert_array_equal(np.diagonal(blocks, axis1=-2, axis2=-1), dense)
    assert not (blocks - np.diagonal(blocks, axis1=-2, axis2=-1)[..., None] * np.eye(3)).any()
    np.testing.assert_array_equal(reg.diagonal_blocks(slice(3, 6)), blocks[3:6])  # a slab of planes
    # the normalisation is the plain penalty's: one length, one weight
    H = _mass_stencil(shape)
    matvec = lambda v: stencil_matvec(H, v)  # noqa: E731
    assert plane_wave_weight(reg, matvec, 20.0) == plane_wave_weight(reg.plain(), matvec, 20.0)


def test_robust_reweighting_frees_the_kink_and_nothing_of_a_wave_or_of_noise():
    """A kink of 0.4 voxel per node in slope (second difference 0.8) under noise of 0.01 voxel
    (a second difference's σ ≈ 0.025): only the zz terms of u_x on the kink's plane lie beyond
    6 robust σ. A wave of amplitude 0.5 and period 6 nodes: its second differences are
    the wave itself, their robust spread its amplitude: no term beyond 6 σ; pure noise neither."""
    shape = (11, 9, 8)
    rng = np.random.default_rng(2)
    z = np.arange(shape[0], dtype=np.float64)[:, None, None]
    kink = 0.01 * rng.standard_normal(shape + (3,))
    kink[..., 2] += 0.4 * np.abs(z - 5.0)
    freed = robust_freed(kink)
    expected = np.zeros(shape + (6,), np.uint8)
    expected[5, :, :, ZZ] = 1 << 2
    np.testing.assert_array_equal(freed, expected)
    wave = 0.01 * rng.standard_normal(shape + (3,))
    wave[..., 2] += 0.5 * np.sin(2 * np.pi * z / 6.0 + 0.3)
    assert not robust_freed(wave).any()
    assert not robust_freed(0.01 * rng.standard_normal(shape + (3,))).any()



def test_spanning_reweighting_frees_a_surface_and_not_a_streak():
    """With ``spanning`` (the engine's choice on coarse textures) only sets that span the mesh
    along two axes are freed: the kink's plane of zz terms of u_x (11 × 9 × 8 nodes, the plane
    z = 5 whole) is; a streak of outliers along one line of nodes (u_y 1 voxel off along the
    y line at z = 3, x = 2: its zz terms at z = 2, 3, 4 over all of y, one axis spanned), the
    signature of a weakly textured feature, is not. Without ``spanning`` both are freed."""
    shape = (11, 9, 8)
    rng = np.random.default_rng(2)
    z = np.arange(shape[0], dtype=np.float64)[:, None, None]
    x = 0.01 * rng.standard_normal(shape + (3,))
    x[..., 2] += 0.4 * np.abs(z - 5.0)
    x[3, :, 2, 1] += 1.0
    kink = np.zeros(shape + (6,), np.uint8)
    kink[5, :, :, ZZ] = 1 << 2
    np.testing.assert_array_equal(robust_freed(x, spanning=0.5), kink)
    streak = robust_freed(x, spanning=0.0) & (1 << 1)
    assert streak[2:5, :, 2, ZZ].all()

@pytest.mark.parametrize("compression", [0.0, -0.5])
def test_spanning_reweighting_keeps_a_jump_and_not_a_mismatch_bent_both_ways(compression):
    """A slip of 1 voxel in u_x across z = 5 (11 × 12 × 12 nodes: −0.5 up to z = 4, 0 at 5,
    +0.5 from 6): its zz terms at z = 4 and 6 bend opposite ways, but the slope across them has
    one sign. Beside it, u_z bent on the same plane as a coarse texture's mismatch bends it: a
    bump of ±0.4 voxel at z = 5 whose sign alternates in 3 × 3-node patches along the sheet,
    as large as the slip's curvature and spanning the mesh as a sheet too, but bent both ways
    and its slope across the plane of both signs. With ``spanning`` only u_x's sheets are
    freed, also under a uniform compression of u_z (−0.5 voxel per node, 6 % at ℓ = 8: the slope
    less its median); without it, every term beyond the threshold, u_z's included."""
    shape = (11, 12, 12)
    rng = np.random.default_rng(3)
    z = np.arange(shape[0], dtype=np.float64)
    x = 0.01 * rng.standard_normal(shape + (3,))
    x[..., 2] += np.clip(z - 5.0, -1.0, 1.0)[:, None, None] * 0.5
    patches = np.kron((np.indices((4, 4)).sum(0) % 2) * 2.0 - 1.0, np.ones((3, 3)))
    x[5, :, :, 0] += 0.4 * patches
    x[..., 0] += compression * z[:, None, None]
    jump = np.zeros(shape + (6,), np.uint8)
    jump[[4, 6], :, :, ZZ] = 1 << 2
    np.testing.assert_array_equal(robust_freed(x, spanning=0.5), jump)
    everything = robust_freed(x, spanning=0.0)
    assert (everything[4:7, :, :, ZZ] & 1).all()  # u_z's bump: freed without the spanning rule


def _mass_stencil(nodes, seed=0):
    """Half stencil (float32) of ``Σ_e m ⊗ T_e``: the C8 mass matrix ``m`` times a random SPD 3×3
    per element (as tests/solve/test_multigrid.py)."""
    rng = np.random.default_rng(seed)
    elements = tuple(n - 1 for n in nodes)
    G = rng.standard_normal(elements + (3, 3))
    T = G @ np.swapaxes(G, -1, -2) + 0.1 * np.eye(3)
    m1 = np.array([[2.0, 1.0], [1.0, 2.0]]) / 6.0
    H = np.zeros(tuple(nodes) + (14, 3, 3))
    for da in LOCAL_NODES:
        for db in LOCAL_NODES:
            k = int(np.flatnonzero((STENCIL_OFFSETS == np.subtract(db, da)).all(axis=1))[0])
            if k < 13:
                continue
            mab = m1[da[0], db[0]] * m1[da[1], db[1]] * m1[da[2], db[2]]
            sl = tuple(slice(d, d + e) for d, e in zip(da, elements))
            H[sl + (k - 13,)] += mab * T
    return H.astype(np.float32)


def _plane_freed(shape, z0):
    """The terms a band on the plane z = z0 frees: zz of u_z there, zy and zx of u_y and u_x beside it."""
    freed = np.zeros(shape + (6,), np.uint8)
    freed[z0, :, :, ZZ] |= 1 << 0
    freed[z0 - 1:z0 + 1, :, :, ZY] |= 1 << 1
    freed[z0 - 1:z0 + 1, :, :, TERM_KINDS.index("zx")] |= 1 << 2
    return freed


def test_vcycle_with_the_plain_coarse_operators_still_solves_the_weighted_system(monkeypatch):
    """The V-cycle keeps the plain penalty's Galerkin coarse operators (their class stencils
    assume one stencil away from the faces): it stays symmetric positive definite (the
    smoother and the coarse solve are) and PCG solves the weighted system exactly (against a
    dense solve). On these 6³ nodes a third of the z planes carry freed terms: 114 iterations
    at rtol 1e-10 against 93 for the plain penalty (the larger meshes: next test)."""
    monkeypatch.setattr(galerkin, "COARSEST", 8)
    shape = (6, 6, 6)
    H = _mass_stencil(shape, seed=2)
    plain = Regularizer("tikhonov", shape, 4.0)
    lam = plane_wave_weight(plain, lambda v: stencil_matvec(H, v), 32 * 4.0)
    b = np.random.default_rng(3).standard_normal(shape + (3,))
    counts = {}
    for name, reg in (("plain", plain), ("weighted", plain.with_freed(_plane_freed(shape, 3)))):
        solver = StencilSolver(H.copy(), rtol=1e-10, multigrid=True)
        solver.regularize(reg, lam)
        A = np.zeros((b.size, b.size))
        for j in range(b.size):
            e = np.zeros(b.size)
            e[j] = 1.0
            A[:, j] = solver.matvec(e.reshape(b.shape)).ravel()
        x, counts[name] = solver.solve(b)
        exact = np.linalg.solve(A, b.ravel())
        assert np.abs(x.ravel() - exact).max() < 1e-8 * np.abs(exact).max()
        B = np.array([solver._vcycle.cycle(e.reshape(b.shape).copy()).ravel() for e in np.eye(b.size)]).T
        np.testing.assert_allclose(B, B.T, rtol=0, atol=1e-10 * np.abs(B).max())
        assert np.linalg.eigvalsh(0.5 * (B + B.T)).min() > 0
    assert counts["weighted"] <= 1.3 * counts["plain"]


@pytest.mark.parametrize("multigrid, length", [(False, 16.0), (True, 256.0)])
def test_weighted_solve_converges_on_a_larger_mesh(multigrid, length):
    """16³ nodes, a band's freed terms on one plane: block-Jacobi CG at 2ℓ (the plain diagonal
    classes as preconditioner) and the V-cycle at 32ℓ (plain coarse operators) solve the
    weighted system, in about as many iterations as the plain one. Measured (rtol 1e-7,
    plain / weighted): block-Jacobi 28 / 28 at 2ℓ, 190 / 190 at 8ℓ; V-cycle 11 / 11, 24 / 24,
    31 / 36 at 2ℓ, 8ℓ, 32ℓ (24³ nodes: 11 / 11, 24 / 24, 30 / 34)."""
    shape = (16, 16, 16)
    H = _mass_stencil(shape, seed=4)
    plain = Regularizer("tikhonov", shape, 8.0)
    weighted = plain.with_freed(_plane_freed(shape, 8))
    lam = plane_wave_weight(plain, lambda v: stencil_matvec(H, v), length)
    b = np.random.default_rng(5).standard_normal(shape + (3,))
    counts = {}
    for name, reg in (("plain", plain), ("weighted", weighted)):
        solver = StencilSolver(H.copy(), rtol=1e-7, multigrid=multigrid)
        solver.regularize(reg, lam)
        x, counts[name] = solver.solve(b)
        assert np.linalg.norm(b - solver.matvec(x)) <= 1.01e-7 * np.linalg.norm(b)
    assert counts["weighted"] <= 1.25 * counts["plain"] + 2, counts
