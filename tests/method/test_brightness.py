"""Known answers of the four brightness models (chunkdic.method.brightness).

The deformed scan is the reference with a known brightness change and no motion:
``g = a·f + b + c·z``, so ``f = g / a - b / a - (c / a)·z`` exactly, i.e. in the models'
form ``f ≈ gain · g(X + u) + offset (+ drift · (X - X_e))``: gain ``1/a``, offset at an
element's centre ``-(b + c·z_e)/a``, drift ``-c/a`` grey levels per voxel along z. The
low-pass of both scans keeps that relation (a Gaussian maps a linear function of z to
itself), so every model must find it, and the field must stay at zero.
"""

from __future__ import annotations

import numpy as np
import pytest
from textures import smooth_noise

import chunkdic

N, ELL = 48, 12
A, B, C = 1.25, 40.0, 0.5


def _pair(c: float):
    f = smooth_noise((N, N, N), sigma=1.5, seed=4)
    z = np.arange(N, dtype=np.float64)[:, None, None]
    return f.astype(np.float32), (A * f + B + c * z).astype(np.float32)


def _run(f, g, grey):
    return chunkdic.correlate(f, g, element_size=ELL, coarsest=0, grey=grey, regularization="none",
                              tolerance=1e-4)


def _element_centres_z(origin: int, ell: int, count: int) -> np.ndarray:
    """z of each element's centre (voxel coordinates; element k covers o + k ℓ … o + (k + 1) ℓ - 1)."""
    return origin + ell * np.arange(count) + (ell - 1) / 2


def test_global_model_finds_gain_and_offset():
    f, g = _pair(0.0)
    res = _run(f, g, "global")
    bright = res.info["grey_level"]
    assert res.converged and np.abs(res.displacement).max() < 2e-3
    assert bright["gain"] == pytest.approx(1 / A, rel=1e-4)
    assert bright["offset"] == pytest.approx(-B / A, abs=0.05)
    np.testing.assert_allclose(res.brightness[0], 1 / A, rtol=1e-4)  # one gain for every element


def test_drift_model_finds_gain_drift_and_element_offsets():
    f, g = _pair(C)
    res = _run(f, g, "drift")
    bright = res.info["grey_level"]
    assert res.converged and np.abs(res.displacement).max() < 2e-3
    assert bright["gain"] == pytest.approx(1 / A, rel=1e-4)
    np.testing.assert_allclose(bright["drift"], [-C / A, 0.0, 0.0], atol=2e-4)
    want = -(B + C * _element_centres_z(res.mesh.origin[0], ELL, res.mesh.shape[0])) / A  # per element row along z
    np.testing.assert_allclose(res.brightness[1], np.broadcast_to(want[:, None, None], res.brightness[1].shape),
                               atol=0.05)


def test_element_model_finds_a_gain_and_offset_per_element():
    f, g = _pair(0.0)
    res = _run(f, g, "element")
    assert res.converged and np.abs(res.displacement).max() < 2e-3
    np.testing.assert_allclose(res.brightness[0], 1 / A, rtol=1e-3)
    np.testing.assert_allclose(res.brightness[1], -B / A, atol=0.1)


def test_none_model_keeps_gain_one_and_identical_scans_give_zero_motion():
    f, _ = _pair(0.0)
    res = _run(f, f.copy(), "none")
    bright = res.info["grey_level"]
    assert res.converged and bright["model"] == "none"
    assert bright["gain"] == 1.0 and bright["offset"] == 0.0
    assert np.abs(res.displacement).max() < 1e-5  # identical scans: zero motion to float32 round-off


# ---------------------------------------------------------------- offsets per cell of elements


def _block_sums(d, gp, grad, w, ell):
    """:class:`ElementSums` of one block formed voxel by voxel (the kernels' definition:
    ``B[e, q, a, i] = Σ w N_a ∂_i f v_q``, ``gram = Σ w v vᵀ``, ``v = (d, g', 1, z~, y~, x~)``)."""
    from chunkdic.kernels.blocks import ElementSums

    ez, ey, ex = (n // ell for n in d.shape)
    xi = (np.arange(ell) + 0.5) / ell
    lz, ly, lx = np.meshgrid(xi, xi, xi, indexing="ij")
    N = np.stack([(lz if a >> 2 & 1 else 1 - lz) * (ly if a >> 1 & 1 else 1 - ly) * (lx if a & 1 else 1 - lx)
                  for a in range(8)]).reshape(8, -1)
    B = np.zeros((ez, ey, ex, 6, 8, 3))
    G = np.zeros((ez, ey, ex, 6, 6))
    for e in np.ndindex(ez, ey, ex):
        sl = tuple(slice(k * ell, (k + 1) * ell) for k in e)
        v = np.stack([d[sl].ravel(), gp[sl].ravel(), np.ones(ell**3), (lz - .5).ravel(), (ly - .5).ravel(),
                      (lx - .5).ravel()])
        ww = w[sl].ravel()
        gr = grad[(slice(None),) + sl].reshape(3, -1)
        B[e] = np.einsum("qn,an,in->qai", v * ww, N, gr)
        G[e] = (v * ww) @ v.T
    return ElementSums(B, G, 0), N


@pytest.mark.parametrize("k", [1, 2, 3])
def test_cell_offsets_are_the_least_squares_fit_over_the_voxels(k):
    """The ``drift`` model against a direct weighted least-squares fit over the voxels: with
    cells of ``k³`` elements (partial cells at the block's end), a gain and an affine offset
    per cell (``k = 1``: a gain, one drift and one offset per element). Same residual, same
    ``b`` at every node, same offset at each element's centre, same gain; the drift is the
    global one (``k = 1``) or the weighted least-squares plane through the element-centre
    offsets (float64 round-off)."""
    from chunkdic.method.brightness import combine, reduce_block
    from chunkdic.kernels.b import element_to_nodes

    ell, shape_e = 3, (4, 5, 3)
    rng = np.random.default_rng(7)
    shape = tuple(n * ell for n in shape_e)
    d, gp = rng.standard_normal(shape), rng.standard_normal(shape)
    grad = rng.standard_normal((3,) + shape)
    w = rng.uniform(0.2, 1.0, shape) * (rng.uniform(size=shape) > 0.1)
    sums, N = _block_sums(d, gp, grad, w, ell)
    part = reduce_block(sums, "drift", k)
    fit = combine("drift", part.nodal, part.scalars, part.elements, 0.0, float(ell))

    Z = np.indices(shape, dtype=np.float64)
    cell = np.ravel_multi_index(tuple((Z[a] // ell // k).astype(int) for a in range(3)),
                                tuple(-(-n // k) for n in shape_e))
    cells = range(cell.max() + 1)
    ones = [(cell.ravel() == c).astype(float) for c in cells]
    if k == 1:  # gain, drift, offsets
        cols = [gp.ravel(), *(Z[a].ravel() / ell for a in range(3)), *ones]
    else:  # gain, then per cell the offset and its three slopes
        cols = [gp.ravel()] + [col for c in cells for col in (ones[c], *(ones[c] * Z[a].ravel() / ell
                                                                          for a in range(3)))]
    A = np.stack(cols, 1)
    sw = np.sqrt(w.ravel())
    theta = np.linalg.lstsq(A * sw[:, None], d.ravel() * sw, rcond=None)[0]
    r = (d.ravel() - A @ theta).reshape(shape)
    assert fit.ssr == pytest.approx(float(np.sum(w * r * r)), rel=1e-9)
    E = np.zeros(shape_e + (8, 3))
    for e in np.ndindex(*shape_e):
        sl = tuple(slice(q * ell, (q + 1) * ell) for q in e)
        E[e] = np.einsum("an,in,n->ai", N, grad[(slice(None),) + sl].reshape(3, -1), (w * r)[sl].ravel())
    np.testing.assert_allclose(fit.b, element_to_nodes(E), atol=1e-9 * np.abs(fit.b).max())
    assert fit.gain.ravel()[0] == pytest.approx(1 + theta[0], rel=1e-9)
    centres = [(np.arange(n) * ell + (ell - 1) / 2) / ell for n in shape_e]
    ce = np.meshgrid(*centres, indexing="ij")
    cell_e = np.ravel_multi_index(np.meshgrid(*(np.arange(n) // k for n in shape_e), indexing="ij"),
                                  tuple(-(-n // k) for n in shape_e))
    if k == 1:
        np.testing.assert_allclose(fit.drift, theta[1:4] / ell, rtol=1e-8)
        want = theta[4:][cell_e] + sum(theta[1 + a] * ce[a] for a in range(3))
    else:
        per_cell = theta[1:].reshape(-1, 4)  # offset, then slopes along z, y, x (per element length)
        want = per_cell[cell_e, 0] + sum(per_cell[cell_e, 1 + a] * ce[a] for a in range(3))
        # the drift: the plane through the element-centre offsets, weighted by each element's Σ w
        we = np.sqrt(w.reshape(shape_e[0], ell, shape_e[1], ell, shape_e[2], ell).sum(axis=(1, 3, 5)).ravel())
        P = np.stack([*(c.ravel() for c in ce), np.ones(we.size)], 1)
        plane = np.linalg.lstsq(P * we[:, None], want.ravel() * we, rcond=None)[0]
        np.testing.assert_allclose(fit.drift, plane[:3] / ell, rtol=1e-8)
    np.testing.assert_allclose(fit.offset, want, atol=1e-9 * np.abs(want).max())


def test_cell_offsets_follow_a_drift_that_bends_under_a_subvoxel_translation():
    """A smooth texture Fourier-shifted by a sub-voxel translation (exact); the deformed scan
    ×1.25, +40, and a drift along z of 0.2 grey level per voxel below mid-height, 0.8 above
    (continuous; texture range 0-100). Cells of 32 voxels (, 4 elements: the mesh's
    7 elements from voxel 4 make 2 cells per axis) hold one affine piece each when the bend
    sits on their boundary (voxel 36 of the reference), so the model is exact: the
    translation within 0.015 voxel at every node (measured 0.0129; 0.0135 without any
    brightness change), the gain 1/1.25, the offset at each element's centre that of the
    truth, the drift reported the least-squares line through those offsets. One offset per element with a single drift cannot bend: on the
    same pair it misses the translation by more than 0.1 voxel (measured 0.52)."""
    from textures import fourier_shift

    n, ell, t = 64, 8, (0.4, -0.3, 0.25)
    f = smooth_noise((n, n, n), sigma=1.5, seed=5)
    bend = 4 + 4 * ell - 0.5 + t[0]  # the cells' boundary (mesh origin 4), seen in the deformed scan

    def bright(z):  # the change of the deformed scan at its own coordinate z
        return B + np.where(z < bend, 0.2 * (z - bend), 0.8 * (z - bend))

    z = np.arange(n, dtype=np.float64)[:, None, None]
    g = (A * fourier_shift(f, t) + bright(z)).astype(np.float32)
    kw = dict(element_size=ell, coarsest=0, regularization="none", tolerance=1e-4, smoothing=0)  # a low-pass rounds the bend
    res = chunkdic.correlate(f.astype(np.float32), g, grey_cell=32, **kw)
    assert res.info["settings"]["grey_cell"] == 32.0 and res.converged and res.mesh.origin[0] == 4
    assert np.abs(res.displacement - np.asarray(t)[:, None, None, None]).max() < 0.015
    got = res.info["grey_level"]
    assert got["gain"] == pytest.approx(1 / A, rel=2e-3)  # measured 0.80095 (no low-pass: interpolation)
    # f(X) = g(X + t) / A - bright(z + t_z) / A: the offset at the element's centre
    centres = _element_centres_z(res.mesh.origin[0], ell, res.mesh.shape[0])
    want = -bright(centres + t[0]) / A
    # the drift reported: the least-squares line through those offsets (every element full)
    np.testing.assert_allclose(got["drift"], [np.polyfit(centres, want, 1)[0], 0.0, 0.0], atol=2e-3)
    # within 0.15 grey level: the gain's 1e-3 (interpolation, no low-pass) times the texture's ~100
    np.testing.assert_allclose(res.brightness[1], np.broadcast_to(want[:, None, None], res.brightness[1].shape),
                               atol=0.15)
    old = chunkdic.correlate(f.astype(np.float32), g, grey_cell=0, **kw)
    assert np.abs(old.displacement - np.asarray(t)[:, None, None, None]).max() > 0.1


def test_cell_offsets_lower_the_noise_of_a_ct_translation(tmp_path):
    """Independent CT noise in each scan of a 64³ concrete pair translated by (0.5, 0.5, 0.5)
    (``standard_case("shift")``), ℓ = 8 at the regularisation length the star reads at ℓ = 8
    (16 voxels): with cells of 32 voxels σ between the nodes is 0.00826 voxel, with one offset
    per element 0.00923 (1.12×; grains 0.00549 / 0.00607, 1.10×). Each offset takes the
    information of the texture's mean gradient over its support from the field, and there
    are 64 times fewer with one per cell of 4³ elements (docs/engine.md, "Brightness")."""
    from chunkdic.analysis.scoring import score_between_nodes
    from chunkdic.synth import synthetic

    n = 64
    pair = synthetic.standard_case(tmp_path / "shift", "shift", n, specimen="concrete", noise=0.02)
    sigma = {}
    for cell in (32.0, 0.0):
        res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=8, regularization_length=16.0,
                                 grey_cell=cell)
        assert res.converged
        axes = [np.unique(c) for c in res.node_coords]
        sigma[cell] = score_between_nodes(axes, res.displacement, pair["field"], (n,) * 3, 8).sigma
    assert sigma[32.0] < 0.009 and sigma[0.0] > 1.06 * sigma[32.0], sigma
