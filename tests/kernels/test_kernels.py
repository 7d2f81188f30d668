"""Known-answer and oracle tests of the per-block kernels (chunkdic/kernels_*.py).

Truths used: a hand-computed element matrix, ``np.gradient`` of the whole volume,
``scipy.ndimage.map_coordinates`` on the whole volume, integer translations (exact
answers), analytic counts of voxels leaving ``g``; the numba kernels are checked against
their NumPy twins.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.ndimage as ndi

from chunkdic.kernels import warp as kernels_warp
from chunkdic.kernels.b import b_block, b_sums
from chunkdic.kernels.blocks import LAGS, gradient_block, voxel_xi
from chunkdic.kernels.jit import warmup
from chunkdic.kernels.m import m_block
from chunkdic.kernels.twins import nodal_field
from chunkdic.kernels.warp import warp_block
from chunkdic.kernels.window import IMPLEMENTATIONS, g_window, prepare_window
from chunkdic.mesh import LOCAL_NODES, STENCIL_OFFSETS, shape_table

INTERPS = ("linear", "cubic")


def _rng(seed=0):
    return np.random.default_rng(seed)


def _smooth_volume(shape, seed=0, sigma=1.5):
    """Random texture with a range of about 0..255, float32."""
    v = ndi.gaussian_filter(_rng(seed).random(shape), sigma)
    v = (v - v.min()) / (v.max() - v.min()) * 255.0
    return v.astype(np.float32)


def _block(vol, e0, e1, ell, origin=(0, 0, 0)):
    """Region of `vol` for the block of elements [e0, e1) with its clipped 1-voxel halo."""
    c0 = [origin[i] + e0[i] * ell for i in range(3)]
    c1 = [origin[i] + e1[i] * ell for i in range(3)]
    lo = tuple(1 if c0[i] > 0 else 0 for i in range(3))
    hi = tuple(1 if c1[i] < vol.shape[i] else 0 for i in range(3))
    sl = tuple(slice(c0[i] - lo[i], c1[i] + hi[i]) for i in range(3))
    return vol[sl], lo, hi, tuple(c0), tuple(c1[i] - c0[i] for i in range(3))


def _smooth_nodes(n_nodes, amp, seed=0):
    """A random smooth nodal field (3, *n_nodes): low-order polynomial plus small noise."""
    rng = _rng(seed)
    grids = np.meshgrid(*[np.linspace(-1, 1, n) for n in n_nodes], indexing="ij")
    u = np.empty((3,) + tuple(n_nodes))
    for c in range(3):
        a = rng.normal(size=7)
        u[c] = (a[0] + a[1] * grids[0] + a[2] * grids[1] + a[3] * grids[2]
                + a[4] * grids[0] * grids[1] + a[5] * grids[2] ** 2)
        u[c] += 0.1 * rng.normal(size=n_nodes)
    return amp * u / np.abs(u).max()


def _voxel_positions(u_nodes, ell, core_origin):
    """X + u(X) with u = sum_a N_a u_a from mesh.shape_table (independent of kernels)."""
    N = shape_table(ell)
    ne = [n - 1 for n in u_nodes.shape[1:]]
    core = tuple(e * ell for e in ne)
    u = np.zeros((3,) + core)
    for ez, ey, ex in np.ndindex(*ne):
        sl = tuple(slice(e * ell, (e + 1) * ell) for e in (ez, ey, ex))
        for a, d in enumerate(LOCAL_NODES):
            un = u_nodes[:, ez + d[0], ey + d[1], ex + d[2]]
            u[(slice(None),) + sl] += N[..., a][None] * un[:, None, None, None]
    grids = np.meshgrid(*[np.arange(n) for n in core], indexing="ij")
    return np.stack([core_origin[i] + grids[i] + u[i] for i in range(3)])


def _dense(S):
    """Dense (3 n_nodes)^2 matrix of a stencil, unknowns ordered (node, component)."""
    off = STENCIL_OFFSETS
    nn = np.array(S.shape[:3])
    nnode = int(np.prod(nn))
    M = np.zeros((nnode * 3, nnode * 3))
    for n in np.ndindex(*S.shape[:3]):
        for k in range(27):
            m = np.array(n) + off[k]
            if np.any(m < 0) or np.any(m >= nn):
                continue
            i = np.ravel_multi_index(n, nn)
            j = np.ravel_multi_index(tuple(m), nn)
            M[3 * i:3 * i + 3, 3 * j:3 * j + 3] = S[n][k]
    return M


# ---------------------------------------------------------------------------- (1) M by hand


@pytest.mark.parametrize("impl", ["numba", "numpy"])
def test_element_matrix_by_hand(impl):
    # ell = 2: xi in {1/4, 3/4}; per axis sum phi_0^2 = sum phi_1^2 = 9/16 + 1/16 = 5/8 and
    # sum phi_0 phi_1 = 3/16 + 3/16 = 3/8, so sum_X N_a N_b = (5/8)^same (3/8)^(3 - same).
    # f = c . X has the constant centred gradient c, hence M_(a,i),(b,j) = c_i c_j sum N_a N_b.
    c = np.array([2.0, -1.0, 3.0])
    X = np.meshgrid(*[np.arange(4.0)] * 3, indexing="ij")
    f = (c[0] * X[0] + c[1] * X[1] + c[2] * X[2] + 10.0).astype(np.float32)
    S, fmin, fmax = m_block(f, (1, 1, 1), (1, 1, 1), 2, impl=impl)
    assert S.shape == (2, 2, 2, 27, 3, 3)
    core = f[1:3, 1:3, 1:3]
    assert (fmin, fmax) == (core.min(), core.max())
    cc = np.outer(c, c)
    # self term, any node: 125/512
    np.testing.assert_allclose(S[0, 0, 0, 13], cc * 125 / 512, rtol=1e-14)
    # opposite corner (1, 1, 1) from node 0 -> k = 26: 27/512
    np.testing.assert_allclose(S[0, 0, 0, 26], cc * 27 / 512, rtol=1e-14)
    # edge neighbour along x, k = 14: (5/8)^2 (3/8) = 75/512
    np.testing.assert_allclose(S[0, 0, 0, 14], cc * 75 / 512, rtol=1e-14)
    # face diagonal in (y, x), k = 17: 45/512
    np.testing.assert_allclose(S[0, 0, 0, 17], cc * 45 / 512, rtol=1e-14)
    # node (1, 1, 1) to node 0 -> k = 0
    np.testing.assert_allclose(S[1, 1, 1, 0], cc * 27 / 512, rtol=1e-14)
    # all other stencil entries of node 0 point outside the element -> 0
    off = STENCIL_OFFSETS
    outside = np.any(off < 0, axis=1)
    assert np.all(S[0, 0, 0][outside] == 0)
    # the whole matrix sums to c c^T times the number of voxels (sum_a N_a = 1)
    np.testing.assert_allclose(S.sum(axis=(0, 1, 2, 3)), cc * 8, rtol=1e-14)


# ---------------------------------------------------------------------------- (2) gradient


def test_gradient_block_matches_whole_volume():
    vol = _rng(1).integers(0, 256, size=(13, 14, 15)).astype(np.uint8)
    ref = np.stack(np.gradient(vol.astype(np.float32)))
    step = (6, 7, 5)  # blocks touching every boundary, incl. a 1-voxel-thick one in z
    for c0 in itertools.product(range(0, 13, 6), range(0, 14, 7), range(0, 15, 5)):
        c1 = tuple(min(c0[i] + step[i], vol.shape[i]) for i in range(3))
        lo = tuple(1 if c0[i] > 0 else 0 for i in range(3))
        hi = tuple(1 if c1[i] < vol.shape[i] else 0 for i in range(3))
        f = vol[tuple(slice(c0[i] - lo[i], c1[i] + hi[i]) for i in range(3))]
        g = gradient_block(f, lo, hi)
        assert g.dtype == np.float32
        want = ref[(slice(None),) + tuple(slice(c0[i], c1[i]) for i in range(3))]
        np.testing.assert_array_equal(g, want)


# ---------------------------------------------------------------------------- (3) twins


@pytest.mark.parametrize("block", [((0, 0, 0), (2, 2, 3)), ((1, 1, 0), (3, 3, 2)),
                                   ((0, 2, 1), (1, 3, 3))])
def test_m_block_numba_equals_numpy(block):
    vol = _smooth_volume((12, 12, 12), seed=2)
    f, lo, hi, _, _ = _block(vol, *block, ell=4)
    S1, a1, b1 = m_block(f, lo, hi, 4, impl="numba")
    S2, a2, b2 = m_block(f, lo, hi, 4, impl="numpy")
    np.testing.assert_allclose(S1, S2, rtol=0, atol=1e-10 * np.abs(S2).max())
    assert (a1, b1) == (a2, b2)


@pytest.mark.parametrize("interpolation", INTERPS)
@pytest.mark.parametrize("block", [((0, 0, 0), (2, 2, 2)), ((1, 1, 1), (3, 3, 3)),
                                   ((0, 1, 2), (2, 3, 3))])
def test_b_block_numba_equals_numpy(interpolation, block):
    ell = 4
    f_vol = _smooth_volume((12, 12, 12), seed=3)
    g_vol = _smooth_volume((12, 12, 12), seed=4).astype(np.uint8)  # any dtype for g
    f, lo, hi, c0, core = _block(f_vol, *block, ell=ell)
    u = _smooth_nodes(tuple(n // ell + 1 for n in core), amp=2.5, seed=5)
    win = g_window(c0, core, u, g_vol.shape, interpolation=interpolation, halo=3)
    g = g_vol[win]
    g_origin = tuple(s.start for s in win)
    out = {impl: b_block(f, lo, hi, ell, u, c0, g, g_origin, g_vol.shape,
                           interpolation=interpolation, impl=impl) for impl in IMPLEMENTATIONS}
    b1, r1, n1, x1 = out["numba"]
    b2, r2, n2, x2 = out["numpy"]
    assert (n1, x1) == (n2, x2)
    assert n1 + x1 == np.prod(core) and n1 > 0
    np.testing.assert_allclose(b1, b2, rtol=0, atol=1e-10 * np.abs(b2).max())
    np.testing.assert_allclose(r1, r2, rtol=1e-10)
    # every element sum the brightness models use (d, g', 1, element-centred coordinates)
    sums = {impl: b_sums(f, lo, hi, ell, u, c0, g, g_origin, g_vol.shape, interpolation=interpolation,
                           impl=impl, center=100.0, margin=1) for impl in IMPLEMENTATIONS}
    np.testing.assert_allclose(sums["numba"].B, sums["numpy"].B, rtol=0,
                               atol=1e-10 * np.abs(sums["numpy"].B).max())
    np.testing.assert_allclose(sums["numba"].gram, sums["numpy"].gram, rtol=1e-10,
                               atol=1e-10 * np.abs(sums["numpy"].gram).max())
    assert sums["numba"].n_excluded == sums["numpy"].n_excluded
    w1, m1 = warp_block(ell, u, c0, core, g, g_origin, g_vol.shape,
                          interpolation=interpolation, impl="numba")
    w2, m2 = warp_block(ell, u, c0, core, g, g_origin, g_vol.shape,
                          interpolation=interpolation, impl="numpy")
    np.testing.assert_array_equal(m1, m2)
    np.testing.assert_allclose(w1[m1], w2[m2], rtol=1e-6, atol=1e-4)
    assert np.isnan(w1[~m1]).all()


@pytest.mark.parametrize("interpolation", INTERPS)
def test_fast_and_general_paths_agree_with_whole_volume(interpolation):
    # The numba kernels take a flat, check-free path for element rows whose taps all lie
    # inside the window and the volume, and the general (clamping / mirroring) path for
    # the others. Both must give map_coordinates on the whole volume to float64 round-off:
    # blocks in the interior (fast path only) and at the volume faces (both paths), fields
    # that fold elements (|u_a - u_b| > ell along x) and send voxels out of g.
    ell = 8
    vol = _smooth_volume((40, 40, 48), seed=20, sigma=1.2)
    coef = ndi.spline_filter(vol, order=3, mode="mirror", output=np.float32)
    gv = coef if interpolation == "cubic" else vol
    order = 3 if interpolation == "cubic" else 1
    cases = [((1, 1, 1), (4, 4, 5), 3.0), ((0, 0, 0), (2, 3, 3), 4.0),
             ((3, 2, 4), (5, 5, 6), 4.0), ((1, 1, 1), (3, 3, 3), 12.0)]
    for k, (e0, e1, amp) in enumerate(cases):
        f, lo, hi, c0, core = _block(vol, e0, e1, ell)
        u = _smooth_nodes(tuple(n // ell + 1 for n in core), amp=amp, seed=30 + k)
        for halo in (12, 0):
            win = g_window(c0, core, u, vol.shape, interpolation=interpolation, halo=halo)
            go = tuple(w.start for w in win)
            w1, m1 = warp_block(ell, u, c0, core, gv[win], go, vol.shape,
                                  interpolation=interpolation, prefiltered=True)
            pos = _voxel_positions(u, ell, c0)
            want_mask = np.all((pos >= 0) & (pos <= np.array(vol.shape)[:, None, None, None]
                                              - 1), axis=0)
            np.testing.assert_array_equal(m1, want_mask)
            assert m1.any()
            if halo == 12:  # the window's own mirror differs from the volume's without halo
                want = ndi.map_coordinates(gv.astype(np.float64), pos[:, m1], order=order,
                                           mode="mirror", prefilter=False)
                # warp output is float32
                np.testing.assert_allclose(w1[m1], want, rtol=0, atol=1e-6 * 255)
            out = {impl: b_block(f, lo, hi, ell, u, c0, gv[win], go, vol.shape,
                                   interpolation=interpolation, impl=impl, prefiltered=True)
                   for impl in IMPLEMENTATIONS}
            b1, r1, n1, x1 = out["numba"]
            b2, r2, n2, x2 = out["numpy"]
            assert (n1, x1) == (n2, x2) == (int(m1.sum()), int((~m1).sum()))
            np.testing.assert_allclose(b1, b2, rtol=0, atol=1e-10 * np.abs(b2).max())
            np.testing.assert_allclose(r1, r2, rtol=1e-10)


@pytest.mark.parametrize("interpolation", INTERPS)
def test_nan_displacement_excludes_voxels_in_kernel(interpolation):
    # b_block / warp_block exclude a whole block when u has a NaN (g_window is empty); the
    # kernels themselves must still treat NaN positions as invalid, in both paths
    ell = 4
    vol = _smooth_volume((16, 16, 16), seed=21)
    c0, core = (4, 4, 4), (8, 8, 8)
    u = _smooth_nodes((3, 3, 3), amp=1.0, seed=22)
    ok = u.copy()
    u[1, 2, 1, 0] = np.nan  # a node of the 2 elements (ez, ey, ex) = (1, 0|1, 0)
    win = g_window(c0, core, ok, vol.shape, interpolation=interpolation, halo=12)
    go = tuple(w.start for w in win)
    cubic = interpolation == "cubic"
    gw = prepare_window(vol[win], interpolation)
    args = (ell, 2, 2, 2, voxel_xi(ell))
    w, m = kernels_warp._warp_kernel(*args, u, *c0, gw, *go, *vol.shape, 0.0, cubic)
    w_ok, m_ok = kernels_warp._warp_kernel(*args, ok, *c0, gw, *go, *vol.shape, 0.0, cubic)
    bad = np.zeros(core, bool)
    bad[4:, :, :4] = True
    assert m_ok.all()
    np.testing.assert_array_equal(m, ~bad)
    assert np.isnan(w[bad]).all()
    np.testing.assert_array_equal(w[~bad], w_ok[~bad])


def test_prefiltered_window_equals_prefilter_inside():
    ell = 4
    vol = _smooth_volume((20, 20, 20), seed=23)
    f, lo, hi, c0, core = _block(vol, (1, 1, 1), (3, 4, 3), ell)
    u = _smooth_nodes((3, 4, 3), amp=2.0, seed=24)
    win = g_window(c0, core, u, vol.shape, interpolation="cubic", halo=12)
    go = tuple(w.start for w in win)
    coef = prepare_window(vol[win], "cubic")  # the kernel's own prefilter, given ready-made
    a = b_block(f, lo, hi, ell, u, c0, vol[win], go, vol.shape, interpolation="cubic")
    b = b_block(f, lo, hi, ell, u, c0, coef, go, vol.shape, interpolation="cubic",
                  prefiltered=True)
    np.testing.assert_array_equal(a[0], b[0])
    assert a[1:] == b[1:]


def test_nodal_field_is_sum_of_shape_functions():
    u = _smooth_nodes((3, 2, 4), amp=3.0, seed=6)
    pos = _voxel_positions(u, 5, (0, 0, 0))
    grids = np.meshgrid(*[np.arange(n) for n in pos.shape[1:]], indexing="ij")
    np.testing.assert_allclose(nodal_field(u, 5), pos - np.stack(grids), atol=1e-13)


# ---------------------------------------------------------------------------- (4) translation


@pytest.mark.parametrize("impl", ["numba", "numpy"])
@pytest.mark.parametrize("interpolation", INTERPS)
def test_integer_translation_gives_zero_residual(impl, interpolation):
    ell = 4
    V = _smooth_volume((24, 24, 24), seed=7)
    s = np.array([3, -2, 1])  # f(X) = g(X + s)
    n = 16
    a = np.array([4, 4, 4])
    f_vol = V[a[0]:a[0] + n, a[1]:a[1] + n, a[2]:a[2] + n]
    # g[x] = V[x + a - s], so g(X + s) = V[X + a] = f(X)
    g_vol = V[a[0] - s[0]:a[0] - s[0] + n, a[1] - s[1]:a[1] - s[1] + n,
              a[2] - s[2]:a[2] - s[2] + n]
    f, lo, hi, c0, core = _block(f_vol, (1, 1, 1), (3, 3, 3), ell)
    u = np.broadcast_to(s[:, None, None, None], (3, 3, 3, 3)).astype(np.float64)
    win = g_window(c0, core, u, g_vol.shape, interpolation=interpolation, halo=12)
    g_origin = tuple(w.start for w in win)
    b, ssr, nv, nx = b_block(f, lo, hi, ell, u, c0, g_vol[win], g_origin, g_vol.shape,
                               interpolation=interpolation, impl=impl)
    assert (nv, nx) == (8 * 8 * 8, 0)
    warped, mask = warp_block(ell, u, c0, core, g_vol[win], g_origin, g_vol.shape,
                                interpolation=interpolation, impl=impl)
    fc = f[1:-1, 1:-1, 1:-1]
    assert mask.all()
    if interpolation == "linear":
        assert ssr == 0.0 and np.all(b == 0.0)
        np.testing.assert_array_equal(warped, fc)
    else:
        # the spline reproduces samples to float32 precision (intensity range 255)
        assert np.abs(warped - fc).max() < 1e-5 * 255
        assert np.sqrt(ssr / nv) < 1e-5 * 255
        S, _, _ = m_block(f, lo, hi, ell)
        scale = np.sqrt(np.abs(S).max() * nv)  # |b| <= |grad f| |r| sums
        assert np.abs(b).max() < 1e-5 * scale


# ---------------------------------------------------------------------------- (5) cubic window


@pytest.mark.parametrize("impl", ["numba", "numpy"])
def test_cubic_window_prefilter_equals_whole_volume(impl):
    ell = 4
    g_vol = _smooth_volume((40, 36, 44), seed=8, sigma=1.0)
    f_vol = g_vol  # only the warp is checked here
    rng_range = float(g_vol.max() - g_vol.min())
    whole = lambda pos: ndi.map_coordinates(g_vol.astype(np.float64), pos.reshape(3, -1),
                                            order=3, mode="mirror").reshape(pos.shape[1:])
    # blocks in the interior and touching each face of the volume
    blocks = [((3, 3, 3), (6, 6, 6)), ((0, 0, 0), (2, 3, 2)), ((8, 7, 9), (10, 9, 11)),
              ((0, 6, 9), (3, 9, 11))]
    for k, (e0, e1) in enumerate(blocks):
        f, lo, hi, c0, core = _block(f_vol, e0, e1, ell)
        u = _smooth_nodes(tuple(n // ell + 1 for n in core), amp=3.0, seed=10 + k)
        win = g_window(c0, core, u, g_vol.shape, interpolation="cubic", halo=12)
        g_origin = tuple(w.start for w in win)
        warped, mask = warp_block(ell, u, c0, core, g_vol[win], g_origin, g_vol.shape,
                                    interpolation="cubic", impl=impl)
        pos = _voxel_positions(u, ell, c0)
        want_mask = np.all((pos >= 0) & (pos <= np.array(g_vol.shape)[:, None, None, None] - 1),
                           axis=0)
        np.testing.assert_array_equal(mask, want_mask)
        err = np.abs(warped[mask] - whole(pos)[mask]).max() / rng_range
        # float32 coefficients: ~1e-7 of the range (a 6-voxel halo gives ~1e-6)
        assert err < 3e-7, (k, err)
    # sanity: without the halo the interior window differs visibly (the test has teeth)
    f, lo, hi, c0, core = _block(f_vol, *blocks[0], ell)
    u = np.zeros((3, 4, 4, 4))
    win = g_window(c0, core, u, g_vol.shape, interpolation="cubic", halo=0)
    warped, _ = warp_block(ell, u + 0.5, c0, core, g_vol[win], tuple(w.start for w in win),
                             g_vol.shape, interpolation="cubic", impl=impl)
    pos = _voxel_positions(u + 0.5, ell, c0)
    assert np.abs(warped - whole(pos)).max() / rng_range > 1e-4


# ---------------------------------------------------------------------------- (6) exclusion


@pytest.mark.parametrize("impl", ["numba", "numpy"])
@pytest.mark.parametrize("interpolation", INTERPS)
def test_voxels_leaving_g_are_excluded_and_counted(impl, interpolation):
    ell = 4
    vol = _smooth_volume((12, 12, 16), seed=11)
    # whole volume as one block: u_x = -2.5 sends x = 0, 1, 2 below 0 (excluded) and x = 3
    # to 0.5 (half a voxel inside: weight 0.5, the boundary taper); u_z = +1 sends z = 10
    # onto the last sample (on the boundary: weight 0) and z = 11 beyond; u_y = 0 puts
    # y = 0 and y = 11 on the boundary (weight 0). Every other voxel has weight 1.
    f, lo, hi, c0, core = _block(vol, (0, 0, 0), (3, 3, 4), ell)
    u = np.zeros((3, 4, 4, 5))
    u[0] = 1.0
    u[2] = -2.5
    weight = np.ones((12, 12, 16))
    weight[10:] = 0.0
    weight[:, [0, 11]] = 0.0
    weight[:, :, :3] = 0.0
    weight[:, :, 3] *= 0.5
    expected_bad = int((weight == 0).sum())
    win = g_window(c0, core, u, vol.shape, interpolation=interpolation, halo=12)
    g_origin = tuple(w.start for w in win)
    b, ssr, nv, nx = b_block(f, lo, hi, ell, u, c0, vol[win], g_origin, vol.shape,
                               interpolation=interpolation, impl=impl)
    assert nx == expected_bad
    assert nv == 12 * 12 * 16 - expected_bad
    if interpolation == "linear":
        # r = f(z, y, x) - (g(z+1, y, x-3) + g(z+1, y, x-2)) / 2, by hand, weighted
        g = vol.astype(np.float64)
        r = vol[:11, :, 3:] - 0.5 * (g[1:, :, :-3] + g[1:, :, 1:-2])
        np.testing.assert_allclose(ssr, np.sum(weight[:11, :, 3:] * r * r), rtol=1e-12)
    # entirely outside: empty window, every voxel excluded, b = 0
    u_far = np.full((3, 4, 4, 5), 100.0)
    win = g_window(c0, core, u_far, vol.shape, interpolation=interpolation, halo=12)
    assert all(w.stop - w.start == 0 for w in win)
    b, ssr, nv, nx = b_block(f, lo, hi, ell, u_far, c0, vol[win], (0, 0, 0), vol.shape,
                               interpolation=interpolation, impl=impl)
    assert (nv, nx, ssr) == (0, 12 * 12 * 16, 0.0) and not b.any()


def test_g_window_bounds_and_refusal():
    u = np.zeros((3, 2, 2, 2))
    u[0, 1] = 2.3
    u[2, 0] = -1.7
    w = g_window((10, 10, 10), (4, 4, 4), u, (30, 30, 30), interpolation="linear")
    # z: [10, 13 + 2.3] -> floor 10 .. floor(15.3) + 1 = 16; x: [8.3, 13] -> 8 .. 14
    assert w == (slice(10, 17), slice(10, 15), slice(8, 15))
    # a halo (for a window the task low-passes itself) grows it on every side, clipped
    w = g_window((10, 10, 10), (4, 4, 4), u, (30, 30, 30), interpolation="linear", halo=12)
    assert w == (slice(0, 29), slice(0, 27), slice(0, 27))
    w = g_window((10, 10, 10), (4, 4, 4), u, (30, 30, 30), interpolation="cubic", halo=2)
    assert w == (slice(7, 20), slice(7, 18), slice(5, 18))
    w = g_window((0, 0, 26), (4, 4, 4), u, (30, 30, 30), interpolation="cubic", halo=12)
    # z: [0, 5.3] -> 0 .. 5 + 2 + 13 = 20; x: [24.3, 29] -> 24 - 13 = 11 .. clipped 30
    assert w == (slice(0, 20), slice(0, 18), slice(11, 30))
    f = np.zeros((5, 5, 5), np.float32)
    with pytest.raises(ValueError, match="does not cover"):
        b_block(f, (1, 0, 0), (0, 1, 1), 4, u, (10, 10, 10), np.zeros((3, 3, 3)),
                  (10, 10, 10), (30, 30, 30), interpolation="linear")
    with pytest.raises(ValueError, match="multiple"):
        m_block(np.zeros((6, 6, 6)), (0, 0, 0), (0, 0, 0), 4)


# ---------------------------------------------------------------------------- (7) symmetry


@pytest.mark.parametrize("impl", ["numba", "numpy"])
def test_stencil_symmetry(impl):
    vol = _smooth_volume((12, 8, 12), seed=12)
    f, lo, hi, _, _ = _block(vol, (0, 0, 1), (3, 2, 3), 4)
    S, _, _ = m_block(f, lo, hi, 4, impl=impl)
    off = STENCIL_OFFSETS
    nn = np.array(S.shape[:3])
    n_checked = 0
    for n in np.ndindex(*S.shape[:3]):
        for k in range(27):
            m = np.array(n) + off[k]
            if np.any(m < 0) or np.any(m >= nn):
                assert not S[n][k].any()
                continue
            np.testing.assert_allclose(S[n][k], S[tuple(m)][26 - k].T, rtol=1e-13, atol=0)
            n_checked += 1
    assert n_checked > 0
    # M is positive semi-definite: check via the assembled dense matrix
    M = _dense(S)
    np.testing.assert_allclose(M, M.T, rtol=1e-13, atol=0)
    assert np.linalg.eigvalsh(M).min() > -1e-9 * np.abs(M).max()


# ---------------------------------------------------------------------------- engine contracts


@pytest.mark.parametrize("interpolation", INTERPS)
def test_block_partials_add_up_to_whole(interpolation):
    # the engine sums block partials on shared nodes: the result must not depend on blocks
    ell = 4
    f_vol = _smooth_volume((12, 16, 12), seed=13)
    g_vol = _smooth_volume((12, 16, 12), seed=14)
    ne = (3, 4, 3)
    u = _smooth_nodes(tuple(e + 1 for e in ne), amp=2.0, seed=15)
    S_all = np.zeros(tuple(e + 1 for e in ne) + (27, 3, 3))
    b_all = np.zeros(tuple(e + 1 for e in ne) + (3,))
    ssr_all, nv_all, nx_all = 0.0, 0, 0
    splits = [(0, 1, 3), (0, 2, 4), (0, 2, 3)]
    for iz, iy, ix in itertools.product(range(2), range(2), range(2)):
        e0 = (splits[0][iz], splits[1][iy], splits[2][ix])
        e1 = (splits[0][iz + 1], splits[1][iy + 1], splits[2][ix + 1])
        f, lo, hi, c0, core = _block(f_vol, e0, e1, ell)
        nodes = tuple(slice(e0[i], e1[i] + 1) for i in range(3))
        S, _, _ = m_block(f, lo, hi, ell)
        S_all[nodes] += S
        un = u[(slice(None),) + nodes]
        win = g_window(c0, core, un, g_vol.shape, interpolation=interpolation, halo=12)
        b, ssr, nv, nx = b_block(f, lo, hi, ell, un, c0, g_vol[win],
                                   tuple(w.start for w in win), g_vol.shape,
                                   interpolation=interpolation)
        b_all[nodes] += b
        ssr_all += ssr
        nv_all += nv
        nx_all += nx
    f, lo, hi, c0, core = _block(f_vol, (0, 0, 0), ne, ell)
    S, _, _ = m_block(f, lo, hi, ell)
    win = g_window(c0, core, u, g_vol.shape, interpolation=interpolation, halo=12)
    b, ssr, nv, nx = b_block(f, lo, hi, ell, u, c0, g_vol[win], tuple(w.start for w in win),
                               g_vol.shape, interpolation=interpolation)
    np.testing.assert_allclose(S_all, S, rtol=0, atol=1e-12 * np.abs(S).max())
    # cubic: per-window prefilters agree to float32 precision only
    tol = 1e-12 if interpolation == "linear" else 1e-5
    np.testing.assert_allclose(b_all, b, rtol=0, atol=tol * np.abs(b).max())
    np.testing.assert_allclose(ssr_all, ssr, rtol=tol)
    assert (nv_all, nx_all) == (nv, nx) and nx > 0


def _shifted_pair(n, s, sigma, seed):
    """Periodic band-limited texture f and g(x) = f(x - s), exact (Fourier shift theorem).

    Both share one intensity scale (range ~0..200), so f(X) = g(X + s) holds exactly.
    """
    rng = _rng(seed)
    k = np.meshgrid(*[2 * np.pi * np.fft.fftfreq(n)] * 3, indexing="ij")
    F = np.fft.fftn(rng.normal(size=(n,) * 3))
    F *= np.exp(-0.5 * sigma**2 * (k[0] ** 2 + k[1] ** 2 + k[2] ** 2))
    f = np.fft.ifftn(F).real
    g = np.fft.ifftn(F * np.exp(-1j * (k[0] * s[0] + k[1] * s[1] + k[2] * s[2]))).real
    lo, scale = f.min(), 200.0 / (f.max() - f.min())
    return ((f - lo) * scale).astype(np.float32), ((g - lo) * scale).astype(np.float32)


@pytest.mark.parametrize("interpolation", INTERPS)
def test_gauss_newton_recovers_subvoxel_translation(interpolation):
    # sign convention end to end: with r = f - g(X + u) and b = sum N grad f r, solving
    # M da = b and adding da converges to the translation s with f(X) = g(X + s)
    n, ell = 32, 16
    s = np.array([0.4, -0.7, 0.25])
    f_vol, g_vol = _shifted_pair(n, s, sigma=2.0, seed=16)
    f, lo, hi, c0, core = _block(f_vol, (0, 0, 0), (1, 1, 1), ell, origin=(8, 8, 8))
    S, _, _ = m_block(f, lo, hi, ell)
    M = _dense(S)
    u = np.zeros((3, 2, 2, 2))
    ssr = []
    for _ in range(6):
        win = g_window(c0, core, u, g_vol.shape, interpolation=interpolation, halo=12)
        b, r2, nv, nx = b_block(f, lo, hi, ell, u, c0, g_vol[win],
                                  tuple(w.start for w in win), g_vol.shape,
                                  interpolation=interpolation)
        ssr.append(r2)
        da = np.linalg.solve(M, b.reshape(-1))  # unknowns (node, component)
        u += da.reshape(2, 2, 2, 3).transpose(3, 0, 1, 2)
    assert nx == 0
    err = u - s[:, None, None, None]
    if interpolation == "cubic":
        assert ssr[-1] < 1e-4 * ssr[0]
        assert np.abs(err).max() < 5e-3
    else:
        # trilinear interpolation blurs g; on a single element the blur leaks into the
        # non-uniform modes (known interpolation bias), the mean stays close
        assert ssr[-1] < 0.05 * ssr[0]
        assert np.abs(err.mean(axis=(1, 2, 3))).max() < 0.05
        assert np.abs(err).max() < 0.3


def test_warmup_compiles_every_kernel_it_names():
    """After ``warmup`` every numba kernel of the block passes has machine code for the
    dtypes a run uses (float32 images, float64 fields), so no task compiles."""
    from chunkdic.kernels import b, m, warp

    warmup()
    for kernel in (b.b_kernel, m.m_kernel, warp._warp_kernel):
        assert kernel.signatures, kernel
    assert any("float32" in str(sig) for sig in b.b_kernel.signatures)


def _lag_sums_over_blocks(f_vol, g_vol, u_all, ell, cut, impl="numba"):
    """The ``M`` and ``b`` passes' lag sums of a level cut into blocks of ``cut`` elements along z
    and y (whole rows along x), added over the blocks as the passes' reductions add them."""
    elems = tuple(n // ell for n in f_vol.shape)
    m_lags, b_lags = 0.0, 0.0
    for e0z in range(0, elems[0], cut[0]):
        for e0y in range(0, elems[1], cut[1]):
            e0, e1 = (e0z, e0y, 0), (min(e0z + cut[0], elems[0]), min(e0y + cut[1], elems[1]), elems[2])
            f, lo, hi, c0, core = _block(f_vol, e0, e1, ell)
            u = np.ascontiguousarray(u_all[:, e0[0]:e1[0] + 1, e0[1]:e1[1] + 1, :])
            m_lags = m_lags + m_block(f, lo, hi, ell, impl=impl, u_nodes=u, core_origin=c0, g_shape=g_vol.shape,
                                      with_lags=True)[3]
            win = g_window(c0, core, u, g_vol.shape, interpolation="linear", halo=3)
            sums = b_sums(f, lo, hi, ell, u, c0, g_vol[win], tuple(s.start for s in win), g_vol.shape,
                          interpolation="linear", impl=impl)
            b_lags = b_lags + sums.lags
    return m_lags, b_lags


def test_the_noise_lag_sums_do_not_depend_on_how_the_level_is_cut_into_blocks():
    # every row carries them (one row in eight counted within each block took other rows for
    # every cut): a level cut into blocks of 2×3, 3×2 or 6×6 elements along z and y sums the
    # same pairs (the numba kernels and their NumPy twins alike)
    ell = 4
    f_vol = _smooth_volume((24, 24, 12), seed=7)
    g_vol = _smooth_volume((24, 24, 12), seed=8)
    u_all = _smooth_nodes((7, 7, 4), amp=0.8, seed=9)
    whole = _lag_sums_over_blocks(f_vol, g_vol, u_all, ell, (6, 6))
    assert np.all(whole[0][:, 0] > 0) and np.all(whole[1][1] > 0)
    for impl, cut in itertools.product(("numba", "numpy"), ((2, 3), (3, 2), (6, 6))):
        m_lags, b_lags = _lag_sums_over_blocks(f_vol, g_vol, u_all, ell, cut, impl)
        np.testing.assert_allclose(m_lags, whole[0], rtol=1e-9)
        np.testing.assert_allclose(b_lags, whole[1], rtol=1e-9, atol=1e-9 * np.abs(whole[1]).max())


def test_every_lag_sums_the_same_voxels_so_that_narrow_blocks_do_not_bias_the_correlation():
    # a row of n voxels gives each lag the pairs that start on its first n - LAGS: with a
    # constant gradient every sensitivity lag equals lag 0 whatever the block's width (summed
    # over n - k voxels, lag k read (n - k) / n of it: 0.83 at lag 4 for a 24-voxel block)
    ramp = np.broadcast_to(np.arange(30, dtype=np.float32)[:, None, None] * 3.0, (30, 16, 24)).copy()
    for nx in (8, 24):
        f, lo, hi, c0, _ = _block(ramp, (1, 1, 0), (3, 3, nx // 4), 4)
        lags = m_block(f, lo, hi, 4, with_lags=True)[3]
        assert lags[0, 0] > 0
        np.testing.assert_allclose(lags[0], np.full(LAGS + 1, lags[0, 0]), rtol=1e-12)
