"""CT-like specimens: microstructure geometry, partial volume, CT imaging, pairs, CLI."""

from __future__ import annotations

import math

import numpy as np
import pytest

from chunkdic.errors import InputError
from chunkdic.synth import boolean as B
from chunkdic.synth import ctsim as C
from chunkdic.synth import microstructure as M
from chunkdic.synth import synthetic as S
from chunkdic.synth.ctpair import (
    CTSpecimen,
    as_dask_ct,
    quantise,
    render_ct,
    standard_field,
)

BAND = S.Band(center_z=15.5, width=6.0, strain=-0.08, lateral=0.3, center_y=20.0, center_x=18.0)
FIELDS = {
    "translation": S.Translation((0.5, 0.5, 0.5)),
    "affine": S.Affine(((-0.02, 0.0, 0.01), (0.0, 0.01, 0.0), (0.01, 0.0, 0.005)),
                       center=(16.0, 20.0, 18.0), translation=(0.3, -0.7, 1.2)),
    "band": BAND,
}


# --------------------------------------------------------------------------- partial volume


def test_cube_fraction_known_values():
    s = np.linspace(-1.0, 1.0, 41)
    # plane normal to an axis: the occupied fraction is a linear ramp of one voxel
    np.testing.assert_allclose(B.cube_fraction(s, [0.0, 0.0, 1.0]), np.clip(0.5 - s, 0, 1), atol=1e-12)
    # normal (1, 1, 0)/sqrt 2: n.U = (U1 + U2)/sqrt 2, U1 + U2 triangular on [-1, 1]
    n = np.array([1.0, 1.0, 0.0]) / math.sqrt(2)
    a = -math.sqrt(2) * s
    tri = np.where(a < 0, (1 + np.clip(a, -1, 0)) ** 2 / 2, 1 - (1 - np.clip(a, 0, 1)) ** 2 / 2)
    np.testing.assert_allclose(B.cube_fraction(s, n), tri, atol=1e-9)
    # any normal: complementary halves and the value at the centre
    rng = np.random.default_rng(1)
    for _ in range(20):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        np.testing.assert_allclose(B.cube_fraction(s, n) + B.cube_fraction(-s, n), 1.0, atol=1e-9)
        assert abs(B.cube_fraction(0.0, n) - 0.5) < 1e-9
    # a Monte Carlo check of the three-uniform CDF for a generic normal
    n = np.array([0.3, -0.5, 0.8124])
    n /= np.linalg.norm(n)
    u = rng.random((400_000, 3)) - 0.5
    proj = u @ n
    for sv in (-0.4, -0.1, 0.2, 0.55):
        assert abs(B.cube_fraction(sv, n) - np.mean(proj < -sv)) < 0.003  # 4 sigma of MC


def _isolated(sp, lo, hi, gap):
    c, r = sp["center"], sp["radius"]
    for i in range(len(r)):
        d = np.linalg.norm(c - c[i], axis=1)
        d[i] = np.inf
        if np.all(d > r + r[i] + gap) and np.all(c[i] > lo + 15) and np.all(c[i] < hi - 15):
            yield i


def test_isolated_sphere_volume_and_edges():
    """Voxel sum of an isolated grain = its analytic volume 4/3 pi r^3.

    The planar (tangent-plane) rule alone overestimates it by pi r / 3 (>= 3.1 voxel^3 for
    r >= 3, module docstring); with the effective radius the residual is the lattice-sum
    error, measured <= 0.13 voxel^3 for r in [3, 10]: tolerance 0.5 voxel^3.
    """
    P = M.GrainsParams(seed=5, solid_fraction=0.03, radius_sigma=0.5)
    sp = M.spheres(P, "grains", (0, 0, 0), (160, 160, 160))
    done = []
    for i in _isolated(sp, 0, 160, 7.0):
        c, r, g = sp["center"][i], sp["radius"][i], sp["grey"][i]
        lo, hi = np.floor(c - r - 2), np.ceil(c + r + 2)
        z, y, x = np.meshgrid(*[np.arange(a, b + 1.0) for a, b in zip(lo, hi)], indexing="ij")
        v = M.phantom(P, z, y, x).astype(np.float64) / g
        assert abs(v.sum() - 4 / 3 * math.pi * r ** 3) < 0.5, (r, v.sum())
        done.append(r)
        if len(done) == 1 or r < 3.6:
            # per voxel, against 12^3 supersampling of the true sphere: the tangent-plane
            # sag is <= 3/(8r) voxel; measured max 0.012 at r = 3.2
            o = (np.arange(12) + 0.5) / 12 - 0.5
            ex = np.zeros_like(v)
            for a in o:
                for b in o:
                    ex += (((z + a - c[0]) ** 2 + (y + b - c[1]) ** 2)[..., None]
                           + (x[..., None] + o - c[2]) ** 2 < r * r).mean(axis=-1)
            ex /= 144
            assert np.abs(v - ex).max() < 3 / (8 * r)
    assert len(done) >= 10 and min(done) < 4.0 and max(done) > 6.0


def test_sphere_process_statistics():
    """Sphere centres form a Poisson process of the intended intensity and the radii follow
    the truncated lognormal law (expected r^3 by numerical integration of the density)."""
    from scipy import integrate

    P = M.GrainsParams(seed=11)
    sp = M.spheres(P, "grains", (0, 0, 0), (599, 599, 599))
    L = sp["cell"]
    lo, hi = -L, (math.floor(599 / L) + 2) * L  # the cells listed
    n = len(sp["radius"])
    lam = -math.log(1 - P.solid_fraction)
    mu, s = math.log(P.radius_median), P.radius_sigma

    def pdf(r):
        return math.exp(-0.5 * ((math.log(r) - mu) / s) ** 2) / r

    z = integrate.quad(pdf, P.radius_min, P.radius_max)[0]
    er3 = integrate.quad(lambda r: r ** 3 * pdf(r), P.radius_min, P.radius_max)[0] / z
    er6 = integrate.quad(lambda r: r ** 6 * pdf(r), P.radius_min, P.radius_max)[0] / z
    expected_n = lam / (4 / 3 * math.pi * er3) * (hi - lo) ** 3
    assert abs(n - expected_n) < 4 * math.sqrt(expected_n)
    r = sp["radius"]
    assert r.min() >= P.radius_min and r.max() <= P.radius_max
    assert abs(np.mean(r ** 3) - er3) < 4 * math.sqrt((er6 - er3 ** 2) / n)
    assert np.all((sp["center"] >= lo) & (sp["center"] < hi))


def test_union_volume_fraction():
    """Mean of the noise-free phantom = expected solid fraction 1 - exp(-lam E[V]).

    For a Boolean model Var(phi_hat) <= phi (1 - phi) E[V^2] / (E[V] |W|) (convexity of
    exp on [0, lam E[V]]); 4 independent 96^3 windows, tolerance 4 sigma of that bound.
    """
    from scipy import integrate

    vals = []
    P = M.GrainsParams(seed=0, grain_spread=0.0)
    for k in range(4):
        vals.append(M.render_phantom(P, (96, 96, 96), origin=(0, 1000 * k, 0)).mean(dtype=np.float64))
    phi = P.solid_fraction
    mu, s = math.log(P.radius_median), P.radius_sigma

    def mom(k):
        f = lambda r: r ** k * math.exp(-0.5 * ((math.log(r) - mu) / s) ** 2) / r  # noqa: E731
        return integrate.quad(f, P.radius_min, P.radius_max)[0]

    ratio = 4 / 3 * math.pi * mom(6) / mom(3)  # E[V^2] / E[V]
    sigma = math.sqrt(phi * (1 - phi) * ratio / 96 ** 3 / len(vals))
    assert abs(np.mean(vals) - phi) < 4 * sigma, (vals, sigma)


def test_concrete_phases():
    P = M.ConcreteParams(seed=2, texture_contrast=0.0, aggregate_spread=0.0)
    v = M.render_phantom(P, (64, 96, 96))
    # pure phases sit at their levels; the pore and aggregate fractions are near the
    # expected ones (loose: one window of a few aggregates)
    assert np.isclose(np.mean(np.abs(v - 0.5) < 1e-6), (1 - 0.4) * (1 - 0.04), atol=0.12)
    assert np.isclose(np.mean(v > 1 - 1e-6), 0.4 * 0.96, atol=0.12)
    assert 0.005 < np.mean(v < 1e-6) < 0.06
    t = M.render_phantom(M.ConcreteParams(seed=2), (8, 96, 96))
    m = np.abs(v[:8] - 0.5) < 1e-6
    assert 0.015 < np.std(t[m]) < 0.04  # the matrix texture (amplitude 0.08 peak)


# --------------------------------------------------------------------------- geometry, chunks


def test_phantom_chunks_and_points_agree():
    P = M.ConcreteParams(seed=4)
    whole = M.render_phantom(P, (20, 30, 26), origin=(5, -7, 100), field=BAND)
    part = M.render_phantom(P, (7, 11, 9), origin=(5 + 6, -7 + 13, 100 + 4), field=BAND)
    assert np.array_equal(part, whole[6:13, 13:24, 4:13])
    rng = np.random.default_rng(0)
    idx = [rng.integers(0, n, 200) for n in whole.shape]
    X = BAND.inverse(idx[0] + 5.0, idx[1] - 7.0, idx[2] + 100.0)
    assert np.array_equal(M.phantom(P, *X), whole[tuple(idx)])


@pytest.mark.parametrize("name", sorted(FIELDS))
def test_deformed_phantom_is_advected(name):
    """Deformed phantom at x = reference phase at X(x), at random points; and the forward
    map X + u(X) lands on x (fields' displacement, independent of their inverse)."""
    fld = FIELDS[name]
    P = M.GrainsParams(seed=3)
    g = M.render_phantom(P, (32, 40, 36), field=fld)
    rng = np.random.default_rng(1)
    idx = [rng.integers(0, n, 300).astype(float) for n in g.shape]
    X = fld.inverse(*idx)
    np.testing.assert_allclose(X + fld.displacement(*X), np.stack(idx), atol=1e-9)
    assert np.array_equal(M.phantom(P, *X), g[tuple(i.astype(int) for i in idx)])


def test_rigid_parts_of_a_band_are_shifted_copies():
    """Far from a band of strain -0.25 and width 8 the material moves by -/+1 voxel along
    z: the deformed phantom is the reference shifted by one voxel there (known answer)."""
    P = M.GrainsParams(seed=8)
    fld = S.Band(center_z=40.0, width=8.0, strain=-0.25, lateral=0.0)
    f = M.render_phantom(P, (80, 24, 24))
    g = M.render_phantom(P, (80, 24, 24), field=fld)
    np.testing.assert_allclose(g[1:21], f[0:20], atol=1e-5)  # below: u = +1, g(X + 1) = f(X)
    np.testing.assert_allclose(g[60:78], f[61:79], atol=1e-5)  # above: u = -1
    assert not np.allclose(g[1:21], f[1:21], atol=0.1)


# --------------------------------------------------------------------------- CT imaging


def _disc(n, r, cy, cx, ss=8):
    o = (np.arange(ss) + 0.5) / ss - 0.5
    yy, xx = np.mgrid[0:n, 0:n].astype(float)
    img = np.zeros((n, n))
    for a in o:
        for b in o:
            img += (yy + a - cy) ** 2 + (xx + b - cx) ** 2 < r * r
    return img / ss ** 2, yy, xx


def test_radon_and_fbp_of_a_disc():
    """Projections of a disc against 2 sqrt(r^2 - s^2) (within 0.2 % RMS of the peak); FBP
    of its noise-free projections
    against the disc: error bounds measured at 128^2 (interior RMS 0.0023, edge band RMS
    0.092: the error lives at the edges, where the interpolations blur the step)."""
    n, r = 128, 40.3
    cy, cx = (n - 1) / 2 + 3.3, (n - 1) / 2 - 5.1
    img, yy, xx = _disc(n, r, cy, cx)
    g = C.Geometry.of(n, n)
    assert g.angles == math.ceil(math.pi / 2 * n)
    sino = C.radon(img, g)
    s = np.arange(g.ndet) - (g.ndet - 1) / 2
    s0 = (cx - (n - 1) / 2) * np.cos(g.theta)[:, None] + (cy - (n - 1) / 2) * np.sin(g.theta)[:, None]
    exact = 2 * np.sqrt(np.clip(r * r - (s[None] - s0) ** 2, 0, None))
    # away from the disc's tangent rays (where the voxel footprint smooths the sqrt edge)
    # measured at 0.8 r: RMS 0.077, max 0.32 (45-degree rays), mean -0.007; peak 80.6
    inner = np.abs(s[None] - s0) < 0.8 * r
    err = (sino - exact)[inner]
    assert np.sqrt(np.mean(err ** 2)) < 0.15 and np.abs(err).max() < 0.5 and abs(err.mean()) < 0.02
    assert np.abs(sino - exact)[np.abs(s[None] - s0) > r + 2].max() < 1e-12
    rec = C.fbp(sino, g)
    d2 = (yy - cy) ** 2 + (xx - cx) ** 2
    inside, outside = d2 < (r - 2) ** 2, d2 > (r + 2) ** 2
    edge = ~inside & ~outside
    err = rec - img
    assert np.sqrt(np.mean(err[inside] ** 2)) < 0.004
    assert np.sqrt(np.mean(err[outside] ** 2)) < 0.006
    assert 0.03 < np.sqrt(np.mean(err[edge] ** 2)) < 0.12
    assert abs(err.mean()) < 1e-3


@pytest.mark.parametrize("imaging", [dict(noise=0.05), dict(noise=0.03, filter="hann", blur=0.8)])
def test_noise_level_and_independence(imaging):
    """Reconstruction noise (scan minus the same scan without noise) has the requested std
    within 10 % (measured within 1 %), and the two scans' noises are independent."""
    shape = (12, 48, 48)
    kw = dict(specimen="grains", seed=6, dtype="float32", **{k: v for k, v in imaging.items() if k != "noise"})
    clean = render_ct(shape, noise=0.0, **kw).astype(np.float64)
    nr = render_ct(shape, noise=imaging["noise"], **kw) - clean
    nd = render_ct(shape, noise=imaging["noise"], which="deformed", **kw) - clean
    for n in (nr, nd):
        assert abs(n.std() / imaging["noise"] - 1) < 0.1
    rho = np.corrcoef(nr.ravel(), nd.ravel())[0, 1]
    assert abs(rho) < 0.03  # 12 * 48^2 samples, spatially correlated: sigma(rho) ~ 0.01


def test_rings_fixed_to_the_detector():
    shape = (16, 48, 48)
    kw = dict(specimen="grains", seed=6, dtype="float32", noise=0.0)
    clean = render_ct(shape, **kw).astype(np.float64)
    f = render_ct(shape, rings=0.03, **kw) - clean
    g = render_ct(shape, rings=0.03, which="deformed", **kw) - clean
    assert np.array_equal(f, g)  # the same detector in both scans
    assert abs(np.sqrt(np.mean(f ** 2)) / 0.03 - 1) < 0.25  # 16 slices of random rings


def test_grey_change_applied_exactly():
    shape = (10, 32, 32)
    kw = dict(specimen="concrete", seed=1, dtype="float32", noise=0.02, field=BAND, which="deformed")
    base = render_ct(shape, **kw).astype(np.float64)
    changed = render_ct(shape, gain=1.1, offset=0.05, drift=-0.03, **kw).astype(np.float64)
    z = np.arange(10)[:, None, None]
    np.testing.assert_allclose(changed, 1.1 * base + 0.05 - 0.03 * (z / 9 - 0.5), atol=1e-6)
    ref = render_ct(shape, gain=1.1, **{**kw, "which": "reference"})
    assert np.array_equal(ref, render_ct(shape, **{**kw, "which": "reference"}))


def test_quantise_map():
    v = np.array([-0.6, -0.5, 0.0, 0.5, 1.0, 1.5, 1.7])
    np.testing.assert_array_equal(quantise(v, "uint16"), [0, 0, 16384, 32768, 49151, 65535, 65535])
    np.testing.assert_array_equal(quantise(v, "uint8"), [0, 0, 64, 128, 191, 255, 255])
    assert quantise(v, "float32").dtype == np.float32


def test_ct_slabs_agree_with_whole_render():
    shape = (20, 36, 30)
    kw = dict(specimen="grains", seed=9, field=FIELDS["affine"], noise=0.03, rings=0.01,
              gain=0.95, offset=0.02, drift=0.04)
    for which in ("reference", "deformed"):
        whole = render_ct(shape, which=which, **kw)
        parts = [render_ct(shape, which=which, z_range=zr, **kw) for zr in ((0, 7), (7, 8), (8, 20))]
        assert np.array_equal(np.concatenate(parts), whole)
        spec = CTSpecimen.build("grains", shape, seed=9, field=FIELDS["affine"], noise=0.03,
                                rings=0.01, gain=0.95, offset=0.02, drift=0.04)
        assert np.array_equal(as_dask_ct(spec, which).compute(scheduler="threads"), whole)


# --------------------------------------------------------------------------- pairs and CLI


def test_synthesize_ct_pair(tmp_path):
    from chunkdic.io.scan import open_scan

    shape = (24, 32, 32)
    fld, fourier = standard_field("band", shape)
    assert not fourier and fld.strain == -0.08 and fld.width == 6.0
    res = S.synthesize(tmp_path / "p", shape, specimen="concrete", field=fld, seed=2, chunks=16,
                       noise=0.02, gain=1.1, offset=0.05, drift=0.03)
    for which in ("reference", "deformed"):
        lvl0 = np.asarray(open_scan(res[which]).level(0))
        assert lvl0.dtype == np.uint16
        expect = render_ct(shape, specimen="concrete", seed=2, field=fld, which=which,
                           noise=0.02, gain=1.1, offset=0.05, drift=0.03)
        assert np.array_equal(lvl0, expect)
    assert S.load_field(tmp_path / "p") == fld
    assert S.load_specimen(tmp_path / "p") == M.ConcreteParams(seed=2)
    meta = S.load_metadata(tmp_path / "p")
    assert meta["grey_change"] == {"gain": 1.1, "offset": 0.05, "drift": 0.03}
    assert meta["imaging"]["noise"] == 0.02 and meta["intensity_map"] == [-0.5, 1.5]
    with pytest.raises(InputError):
        S.load_texture(tmp_path / "p")


def test_synthesize_fourier_shift_pair(tmp_path):
    from chunkdic.io.scan import open_scan

    shape = (16, 24, 24)
    fld, fourier = standard_field("fourier-shift", shape)
    res = S.synthesize(tmp_path / "f", shape, specimen="grains", field=fld, fourier_shift=fourier,
                       seed=1, chunks=8, dtype="float32")
    f = np.asarray(open_scan(res["reference"]).level(0)).astype(np.float64)
    g = np.asarray(open_scan(res["deformed"]).level(0)).astype(np.float64)
    # whole-volume twin: per axis, mirror-extend, phase shift (real Nyquist factor), crop
    e = f
    for axis in range(3):
        n = e.shape[axis]
        ext = np.concatenate([e, np.flip(e, axis)], axis=axis)
        k = np.fft.fftfreq(2 * n)
        ph = np.exp(-2j * np.pi * k * 0.5)
        ph[n] = np.cos(np.pi * 0.5)
        shp = [1, 1, 1]
        shp[axis] = 2 * n
        e = np.real(np.fft.ifft(np.fft.fft(ext, axis=axis) * ph.reshape(shp), axis=axis))
        e = np.take(e, np.arange(n), axis=axis)
    np.testing.assert_allclose(g, e, atol=2e-5)
    assert not np.allclose(g, f, atol=0.05)
    assert not (tmp_path / "f" / "def.fourier.tmp.zarr").exists()
    assert "fourier" in S.load_metadata(tmp_path / "f")["deformed"]


@pytest.mark.parametrize("opts", [
    ["--specimen", "grains", "--noise", "-0.1"],
    ["--specimen", "grains", "--gain", "0"],
    ["--specimen", "grains", "--gain", "-1"],
    ["--specimen", "grains", "--blur", "-1"],
    ["--specimen", "grains", "--rings", "-0.01"],
    ["--specimen", "grains", "--angles", "1"],
    ["--specimen", "grains", "--offset", "nan"],
    ["--specimen", "grains", "--cell-size", "6"],
    ["--gain", "1.1"],
    ["--case", "fourier-shift"],
    ["--noise", "-1"],
])
def test_cli_bad_options(tmp_path, capsys, opts):
    from chunkdic.cli.app import main

    out = tmp_path / "bad"
    assert main(["synth", str(out), "--shape", "16", *opts]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) >= 1 and err[-1].startswith("chunkdic: error:")
    assert not out.exists()


def test_cli_ct_case(tmp_path, capsys):
    from chunkdic.cli.app import main

    out = tmp_path / "band"
    assert main(["synth", str(out), "--shape", "24,32,32", "--specimen", "grains", "--case", "band",
                 "--noise", "0.03", "--gain", "1.05", "--offset", "0.02", "--drift", "0.01",
                 "--chunks", "16"]) == 0
    meta = S.load_metadata(out)
    assert meta["field"]["type"] == "band" and meta["field"]["strain"] == -0.08
    assert meta["imaging"]["noise"] == 0.03 and meta["grey_change"]["gain"] == 1.05
    assert meta["dtype"] == "uint16"
