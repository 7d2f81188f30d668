"""Synthetic specimens: point-wise texture, exact deformed scans, stored fields."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from chunkdic.errors import InputError
from chunkdic.synth import foam, foam_kernels
from chunkdic.synth import synthetic as S

FIELDS = {
    "translation": S.Translation((2.3, -1.4, 0.7)),
    "affine": S.Affine(((-0.01, 0.0, 0.005), (0.0, 0.003, 0.0), (0.005, 0.0, 0.003)),
                       center=(20.0, 24.0, 28.0), translation=(0.4, -0.3, 1.1)),
    "band": S.Band(center_z=20.0, width=12.0, strain=-0.05, lateral=0.3, center_y=24.0,
                   center_x=28.0),
    # a sliding crack, then 10 % compression about the centre
    "crack-then-compression": S.Composed(
        S.Crack(normal=(1.0, 0.0, 0.0), point=(23.5, 0.0, 0.0), sliding=(0.0, 0.0, 0.6)),
        S.Affine(((-0.10, 0.0, 0.0), (0.0, 0.03, 0.0), (0.0, 0.0, 0.03)), center=(24.0, 24.0, 24.0))),
}


def test_texture_point_wise_equals_grid():
    f = foam.render((12, 13, 14), origin=(-5, 3, 100), seed=7)
    z, y, x = np.meshgrid(np.arange(-5, 7.0), np.arange(3, 16.0), np.arange(100, 114.0),
                          indexing="ij")
    assert np.array_equal(foam.texture(z, y, x, seed=7), f)
    # broadcasting and arbitrary visiting order
    rng = np.random.default_rng(0)
    idx = rng.permutation(f.size)[:300]
    zi, yi, xi = np.unravel_index(idx, f.shape)
    v = foam.texture(zi - 5.0, yi + 3.0, xi + 100.0, seed=7)
    assert np.array_equal(v, f[zi, yi, xi])


def test_caches_do_not_change_values():
    """The kernels cache features along a scan; each value must still be a function of
    its point alone: compare with points evaluated one per call (fresh caches) and with
    the grid visited in random order."""
    shape, origin = (24, 26, 28), (-40, 17, 3)
    kw = dict(seed=13, cell_size=6.0, bead_size=24.0)
    f = foam.render(shape, origin=origin, **kw)
    rng = np.random.default_rng(2)
    for _ in range(150):
        i = tuple(int(rng.integers(0, n)) for n in shape)
        v = foam.texture(*(float(i[a] + origin[a]) for a in range(3)), **kw)
        assert v == f[i]
    idx = rng.permutation(f.size)
    zi, yi, xi = np.unravel_index(idx, shape)
    v = foam.texture(zi + float(origin[0]), yi + float(origin[1]), xi + float(origin[2]), **kw)
    assert np.array_equal(v, f[zi, yi, xi])
    for _ in range(6):
        o = [int(rng.integers(0, n - 4)) for n in shape]
        s = [int(rng.integers(1, n - oo)) for n, oo in zip(shape, o)]
        part = foam.render(s, origin=[a + b for a, b in zip(origin, o)], **kw)
        assert np.array_equal(part, f[o[0]:o[0] + s[0], o[1]:o[1] + s[1], o[2]:o[2] + s[2]])


_MASK = (1 << 64) - 1


def _mix(h):
    h ^= h >> 30
    h = (h * 0xBF58476D1CE4E5B9) & _MASK
    h ^= h >> 27
    h = (h * 0x94D049BB133111EB) & _MASK
    return h ^ (h >> 31)


def _hash3(i, j, k, key):
    return _mix(_mix(_mix(key ^ (i & _MASK)) ^ (j & _MASK)) ^ (k & _MASK))


def _wall_reference(q, key, r):
    """Plain-Python twin of the cellular wall weight (no caches, no pruning)."""
    c = [int(np.floor(v)) for v in q]
    feats = []
    for dz in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                cell = (c[0] + dz, c[1] + dy, c[2] + dx)
                h = _hash3(*cell, key)
                u = [((h >> s) & ((1 << 21) - 1)) / (1 << 21) for s in (43, 22, 1)]
                feats.append((np.array([cell[a] + 0.5 + 0.8 * (u[a] - 0.5) for a in range(3)]), h))
    d = [float(np.sum((q - f) ** 2)) for f, _ in feats]
    ia = int(np.argmin(d))
    a = feats[ia][0]
    prod = 1.0
    for n, (b, _) in enumerate(feats):
        if n != ia:
            dist = (d[n] - d[ia]) / (2 * np.linalg.norm(b - a))
            if dist < r:
                prod *= 1 - (1 - dist ** 2 / r ** 2) ** 4
    return 1 - prod, feats[ia][1]


def _unit(h):
    return (_mix(h ^ 0x9E3779B97F4A7C15) >> 11) / 2.0 ** 53


def _texture_reference(p, tp):
    """Plain-Python twin of the texture formula at one point (smooth noise off)."""
    fwhm = 2 * np.sqrt(1 - 0.5 ** 0.25)
    keys = [int(foam_kernels.channel_key(tp.seed, ch)) for ch in (1, 2)]
    wc, hc = _wall_reference(p / tp.cell_size, keys[0], tp.wall_width / fwhm / tp.cell_size)
    wb, hb = _wall_reference(p / tp.bead_size, keys[1], tp.skin_width / fwhm / tp.bead_size)
    interior = 0.08 + 0.22 * _unit(hc)
    wall = 0.60 + 0.20 * _unit(hb)
    return (1 - wb) * ((1 - wc) * interior + wc * wall) + wb * 0.95


def test_texture_matches_plain_python_twin():
    tp = foam.TextureParams(seed=21, cell_size=7.0, bead_size=20.0, noise_amplitude=0.0)
    rng = np.random.default_rng(5)
    pts = rng.uniform(-60.0, 60.0, size=(3, 60))
    v = foam.texture(*pts, seed=tp)
    ref = [_texture_reference(pts[:, i], tp) for i in range(pts.shape[1])]
    np.testing.assert_allclose(v, ref, rtol=0, atol=2e-6)
    walls = np.array(ref)
    assert walls.max() > 0.6 and walls.min() < 0.35  # points in walls and in cells


def test_chunks_agree_with_larger_render():
    big = foam.render((40, 44, 48), seed=3, origin=(10, -20, 5))
    part = foam.render((17, 9, 23), seed=3, origin=(10 + 11, -20 + 30, 5 + 7))
    assert np.array_equal(part, big[11:28, 30:39, 7:30])
    fld = FIELDS["band"]
    bigd = foam.render((40, 44, 48), seed=3, field=fld, which="deformed", dtype="uint16")
    partd = foam.render((13, 20, 9), seed=3, field=fld, which="deformed", dtype="uint16",
                        origin=(5, 21, 33))
    assert np.array_equal(partd, bigd[5:18, 21:41, 33:42])


@pytest.mark.parametrize("which", ["reference", "deformed"])
def test_as_dask_equals_render(which):
    fld = FIELDS["affine"]
    kw = dict(field=fld, seed=11, which=which, dtype="uint8", noise=0.02)
    one = foam.render((37, 30, 33), **kw)
    for chunks in [(16, 16, 16), (10, 30, 7), 37]:
        arr = foam.as_dask((37, 30, 33), chunks=chunks, **kw)
        assert np.array_equal(arr.compute(scheduler="threads"), one)
    # the graph carries parameters only
    assert all(not isinstance(v, np.ndarray) for v in dict(arr.dask).values())


@pytest.mark.parametrize("name", sorted(FIELDS))
def test_deformed_matches_reference_exactly(name):
    fld = FIELDS[name]
    rng = np.random.default_rng(1)
    X = rng.uniform(0.0, 48.0, size=(3, 2000))
    u = fld.displacement(*X)
    assert u.shape == (3, 2000)
    x = X + u
    back = fld.inverse(*x)
    assert np.abs(back - X).max() < 1e-6
    f = foam.texture(*X, seed=5)
    g = foam.texture(*fld.inverse(*x), seed=5)  # deformed scan evaluated at x = X + u(X)
    np.testing.assert_allclose(g, f, rtol=0, atol=1e-6)
    # and on the grid: render(deformed) at integer x equals texture at inverse(x)
    gd = foam.render((8, 9, 10), seed=5, field=fld, which="deformed", origin=(12, 14, 16))
    zz, yy, xx = np.meshgrid(np.arange(12, 20.0), np.arange(14, 23.0), np.arange(16, 26.0),
                             indexing="ij")
    assert np.array_equal(gd, foam.texture(*fld.inverse(zz, yy, xx), seed=5))


def test_translation_and_affine_inverse_exact():
    t = FIELDS["translation"]
    np.testing.assert_array_equal(t.displacement(1.0, 2.0, np.zeros((2, 3)))[:, 0, 0], t.t)
    a = FIELDS["affine"]
    X = np.array([3.0, -7.0, 50.0])
    A = np.asarray(a.matrix)
    np.testing.assert_allclose(a.displacement(*X), A @ (X - a.center) + a.translation,
                               atol=1e-13)
    # the inverses: the deformed position x = X + u(X) maps back to X, to round-off
    rng = np.random.default_rng(3)
    Xs = rng.uniform(-20, 120, size=(3, 50))
    for field in (t, a):
        x = Xs + field.displacement(*Xs)
        np.testing.assert_allclose(field.inverse(*x), Xs, atol=1e-10)
    # not the first-order x - u(x): an inverse that ignored the strain would fail above
    assert np.abs(a.inverse(*Xs) - (Xs - a.displacement(*Xs))).max() > 1e-4


def test_composed_affines_are_the_product_of_their_maps():
    """Two affine motions about one centre compose as ``x - c = (I + B)(I + A)(X - c)``."""
    c = (10.0, -4.0, 7.0)
    A = np.array([[-0.10, 0.02, 0.0], [0.0, 0.03, -0.01], [0.04, 0.0, 0.03]])
    B = np.array([[0.0, -0.17, 0.0], [0.17, 0.0, 0.0], [0.0, 0.0, 0.05]])
    both = S.Composed(S.Affine(tuple(map(tuple, A)), center=c), S.Affine(tuple(map(tuple, B)), center=c))
    one = S.Affine(tuple(map(tuple, (np.eye(3) + B) @ (np.eye(3) + A) - np.eye(3))), center=c)
    X = np.random.default_rng(4).uniform(-30, 60, size=(3, 40))
    np.testing.assert_allclose(both.displacement(*X), one.displacement(*X), atol=1e-12)
    np.testing.assert_allclose(both.inverse(*X), one.inverse(*X), atol=1e-10)
    # the order matters: A then B is not B then A
    swapped = S.Composed(both.then, both.first)
    assert np.abs(swapped.displacement(*X) - both.displacement(*X)).max() > 1e-2
    with pytest.raises(InputError):
        S.Composed(both.first, "affine")


def test_band_shape():
    b = S.Band(center_z=50.0, width=20.0, strain=-0.05, lateral=0.4, center_y=10.0,
               center_x=10.0)
    z = np.linspace(0.0, 100.0, 2001)
    u = b.displacement(z, 10.0, 10.0)
    # rigid shift of strain * width / 2 on each side, compression in between
    np.testing.assert_allclose(u[0, 0], 0.05 * 10.0, rtol=1e-3)
    np.testing.assert_allclose(u[0, -1], -0.05 * 10.0, rtol=1e-3)
    dudz = np.gradient(u[0], z)
    assert dudz.min() == pytest.approx(-0.05, rel=1e-3) and dudz.max() <= 1e-12
    assert np.allclose(u[1:], 0.0)  # on the axis no lateral motion
    ul = b.displacement(50.0, 20.0, 0.0)  # lateral expansion in the band
    np.testing.assert_allclose(ul[1:], [0.4 * 0.05 * 10.0, -0.4 * 0.05 * 10.0], rtol=1e-3)


def test_texture_is_rich_and_smooth():
    f = foam.render((64, 64, 64), seed=0).astype(np.float64)
    assert 0.15 < f.std() < 0.4
    assert 0.3 < f.mean() < 0.7
    wall = (f > 0.55).mean()
    assert 0.15 < wall < 0.85
    g = np.gradient(f)
    energy = np.mean(sum(c * c for c in g))
    assert energy > 1e-2  # texture at the cell scale
    # smooth, not aliased: the finest differences are not larger than first differences
    d1 = np.diff(f, axis=2)
    d2 = np.diff(f, 2, axis=2)
    assert np.mean(d2 ** 2) < 1.5 * np.mean(d1 ** 2)
    # power spectrum falls off towards Nyquist
    spec = np.abs(np.fft.rfft(f - f.mean(), axis=2)) ** 2
    p = spec.mean(axis=(0, 1))
    assert p[-1] < 0.05 * p[1:8].max()
    # different seeds give different specimens
    assert not np.array_equal(foam.render((8, 8, 8), seed=1), foam.render((8, 8, 8), seed=2))


def test_integer_dtypes_and_noise():
    v = foam.render((16, 16, 16), seed=2)
    q = foam.render((16, 16, 16), seed=2, dtype="uint8")
    assert q.dtype == np.uint8
    np.testing.assert_array_equal(q, np.clip(np.rint(20 + v.astype(np.float64) * 215), 0, 255))
    n = foam.render((16, 16, 16), seed=2, noise=0.05)
    assert 0.04 < np.std(n - v) < 0.06
    nd = foam.render((16, 16, 16), seed=2, noise=0.05, which="deformed")
    assert not np.array_equal(n, nd)  # independent acquisition noise in the two scans


def test_field_json_round_trip():
    for fld in FIELDS.values():
        d = json.loads(json.dumps(fld.to_json()))
        assert S.Field.from_json(d) == fld
    with pytest.raises(InputError):
        S.Field.from_json({"type": "spiral"})
    with pytest.raises(InputError):
        S.Field.from_json({"type": "translation", "shift": [1, 2, 3]})
    with pytest.raises(InputError):
        S.Affine(matrix=((-1.0, 0, 0), (0, 0, 0), (0, 0, 0)))
    with pytest.raises(InputError):
        S.Band(width=-1.0)


def test_synthesize_writes_pair(tmp_path):
    from chunkdic.io.scan import open_scan

    fld = FIELDS["band"]
    out = tmp_path / "pair"
    res = S.synthesize(out, (24, 20, 28), field=fld, seed=4, dtype="uint8", chunks=8,
                       voxel_size=4.91, unit="micrometer", levels=1)
    for which, key in (("reference", "reference"), ("deformed", "deformed")):
        scan = open_scan(res[key])
        lvl0 = np.asarray(scan.level(0))
        np.testing.assert_array_equal(
            lvl0, foam.render((24, 20, 28), field=fld, seed=4, which=which, dtype="uint8"))
    assert S.load_field(out) == fld
    assert S.load_field(res["deformed"]) == fld
    assert S.load_field(os.path.join(out, "field.json")) == fld
    assert S.load_texture(out) == foam.TextureParams(seed=4)
    with pytest.raises(InputError):
        S.synthesize(out, (8, 8, 8))  # exists, no overwrite
    S.synthesize(out, (8, 8, 8), overwrite=True, chunks=8)
    assert S.load_field(out) is None


def test_cli_synth(tmp_path):
    import argparse

    from chunkdic.cli import synth_commands as _cli_synth

    parser = argparse.ArgumentParser()
    _cli_synth.register(parser.add_subparsers(dest="command"))
    out = tmp_path / "cli"
    args = parser.parse_args(["synth", str(out), "--shape", "16,16,24", "--field", "affine",
                              "--chunks", "8", "--seed", "3"])
    assert args.func(args) == 0
    fld = S.load_field(out)
    assert isinstance(fld, S.Affine)
    np.testing.assert_allclose(np.asarray(fld.matrix)[0, 0], -0.01)
    bad = parser.parse_args(["synth", str(out), "--shape", "16,16"])
    with pytest.raises(InputError):
        bad.func(bad)
