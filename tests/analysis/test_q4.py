"""2-D Q4-DIC and the paper's cut check (issue 13, item 1; paper section 5.3)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from textures import fourier_shift, smooth_noise

import chunkdic
from chunkdic.analysis.crosscheck import correlation_length
from chunkdic.analysis.q4 import correlate2d
from chunkdic.analysis.q4mesh import Mesh2D, read_image
from chunkdic.cli.app import main
from chunkdic.synth import foam, synthetic

# --------------------------------------------------------------------------- mesh


def test_mesh_conventions_by_hand():
    mesh = Mesh2D((3, 5), 4, (2, 3))
    ys, xs = mesh.node_axes()
    assert ys.tolist() == [2.5, 6.5, 10.5] and xs.tolist() == [4.5, 8.5, 12.5, 16.5]  # o + k ell - 0.5
    phi = mesh.shape_matrix().toarray()
    assert phi.shape == (8 * 12, 3 * 4)
    np.testing.assert_allclose(phi.sum(axis=1), 1.0)
    # ROI pixel (0, 0) = image pixel (3, 5): xi = 1/8 on both axes, node (0, 0) weight (7/8)^2
    assert phi[0, 0] == pytest.approx(49 / 64) and phi[0, 1] == pytest.approx(7 / 64)
    # a bilinear field is reproduced exactly at pixel centres and by evaluate
    Y, X = mesh.node_coords()
    u = np.stack([0.3 + 0.01 * Y - 0.02 * X, -0.1 + 0.03 * Y])
    py, px = np.meshgrid(np.arange(3, 11.0), np.arange(5, 17.0), indexing="ij")
    truth = np.stack([0.3 + 0.01 * py - 0.02 * px, -0.1 + 0.03 * py])
    np.testing.assert_allclose((phi @ u.reshape(2, -1).T).T.reshape(truth.shape), truth, atol=1e-12)
    np.testing.assert_allclose(mesh.evaluate(u, np.stack([py, px])), truth, atol=1e-12)


# --------------------------------------------------------------------------- Q4-DIC


def test_identical_images_give_exactly_zero_motion():
    f = smooth_noise((96, 96), sigma=1.2, seed=1)
    res = correlate2d(f, f, element_size=16)
    assert res.converged
    assert np.abs(res.displacement).max() < 1e-9


@pytest.fixture(scope="module")
def shifted():
    f = smooth_noise((256, 256), sigma=1.2, seed=7)
    return f, fourier_shift(f, (0.3, -0.45))  # g(x) = f(x - t): f(X) = g(X + t), exact


@pytest.mark.parametrize("ell, std_bound", [(16, 0.01), (8, 0.03)])
def test_fourier_subpixel_translation(shifted, ell, std_bound):
    """The 3-D engine's bounds (tests/engine/test_engine.py: bias < 0.005, std 0.01 / 0.03)."""
    f, g = shifted
    res = correlate2d(f, g, element_size=ell)
    assert res.converged
    u = res.displacement.reshape(2, -1)
    bias = np.abs(u.mean(axis=1) - (0.3, -0.45))
    assert bias.max() < 0.005, bias  # measured 0.0016
    assert u.std(axis=1).max() < std_bound  # measured 0.001 (16), 0.003 (8)
    assert res.levels[0] > 0 and res.gap < res.initial_gap / 10


def test_affine_field_on_procedural_texture():
    """1 % compression, 0.8 % stretch and shear, the deformed image rendered at the exact
    pre-images (no interpolation): the engine's bound, RMS < 0.03 pixel."""
    n, z = 160, 40.0
    A = np.array([[-0.01, 0.005], [0.003, 0.008]])
    c, t = np.array([n / 2, n / 2]), np.array([0.3, -0.2])  # u(X) = A (X - c) + t
    Y, X = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    f = foam.texture(z, Y, X, seed=2)
    x = np.stack([Y, X]).reshape(2, -1)
    pre = np.linalg.solve(np.eye(2) + A, x - t[:, None] + (A @ c)[:, None]).reshape(2, n, n)
    g = foam.texture(z, pre[0], pre[1], seed=2)  # g(X + u(X)) = f(X)
    res = correlate2d(f, g, element_size=12)
    assert res.converged
    truth = np.einsum("ij,j...->i...", A, res.node_coords - c[:, None, None]) + t[:, None, None]
    rms = np.sqrt(((res.displacement - truth) ** 2).mean())
    assert rms < 0.03, rms  # measured 0.006


def test_large_translation_through_the_pyramid():
    f = smooth_noise((128, 128), sigma=1.5, seed=4)
    res = correlate2d(f, np.roll(f, (9, -7), axis=(0, 1)), element_size=16)
    assert res.converged and res.levels[0] > 0
    assert np.abs(res.displacement - np.array([9.0, -7.0])[:, None, None]).max() < 1e-3


# --------------------------------------------------------------------------- cut check


def test_correlation_length_of_known_fields():
    rng = np.random.default_rng(0)
    white = rng.standard_normal((2, 32, 32))
    assert correlation_length(white, 8.0) < 8.0  # 1 at lag 0, ~0 at lag 1: crosses before one node
    y = np.arange(32.0)
    ramp = np.stack([np.broadcast_to(y[:, None], (32, 32)), np.broadcast_to(y[None, :], (32, 32))])
    assert correlation_length(ramp, 8.0) > 5 * 8.0
    assert correlation_length(np.ones((2, 8, 8)), 8.0) == 0.0


N, ELL = 64, 8


@pytest.fixture(scope="module")
def synthetic_result(tmp_path_factory):
    """A converged 64³ result of an affine field (exact renders), and a copy of it with a
    deliberate 1 % dilatation error added to the displacement."""
    d = tmp_path_factory.mktemp("cutcheck")
    field = synthetic.Affine(matrix=((-0.01, 0.0, 0.005), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
                             center=(N / 2,) * 3, translation=(1.3, -0.4, 0.7))
    pair = synthetic.synthesize(d / "pair", (N,) * 3, field=field, seed=3, dtype="float32")
    res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=ELL, output=d / "good.zarr")
    assert res.converged
    wrong = chunkdic.open_result(d / "good.zarr")
    centre = wrong.node_coords.mean(axis=(1, 2, 3))[:, None, None, None]
    wrong.displacement = wrong.displacement + 0.01 * (wrong.node_coords - centre)
    wrong.strain = None
    wrong.save(d / "wrong.zarr")
    return d


def test_cutcheck_passes_a_converged_result(synthetic_result):
    d = synthetic_result
    cuts = chunkdic.cutcheck(d / "good.zarr", d / "good-check")
    assert [c.axis for c in cuts] == ["z", "y", "x"]
    for c in cuts:
        assert c.status == "converged"
        assert c.mean < 0.02 and c.std < 0.02, c  # measured mean <= 0.0015, std 0.008-0.010
        assert c.max < 0.05, c  # measured 0.030-0.037 (3-4 std over 49 nodes)
        assert c.correlation_length < ELL, c  # white-noise-like: measured ~4 pixels
        assert c.passed
    assert (d / "good-check" / "cutcheck.png").stat().st_size > 10_000
    stored = json.loads((d / "good-check" / "cutcheck.json").read_text())
    assert [s["axis"] for s in stored] == ["z", "y", "x"] and stored[0]["std"] == pytest.approx(cuts[0].std)


def test_cutcheck_flags_a_wrong_field(synthetic_result):
    """A 1 % dilatation error: in every cut plane it is the in-plane field 0.01 (X - c),
    which the 2-D correlation must find with the opposite sign, smooth and large."""
    d = synthetic_result
    good = chunkdic.cutcheck(d / "good.zarr")
    res = chunkdic.open_result(d / "wrong.zarr")
    from chunkdic.analysis.crosscheck import check_cut
    from chunkdic.results.scans import level_refs
    from chunkdic.scheduler import open_runner
    from chunkdic.export import correction
    from chunkdic.plot.figures import mid_planes

    with level_refs(res) as (f, g), open_runner(None) as runner:
        for normal, axis in enumerate("zyx"):
            idx = mid_planes(res)[axis]
            planes = correction.planes(res, f, g, normal, idx, runner)
            cut, q = check_cut(planes["prepared"], planes["corrected"], ELL, normal, idx)
            ok = good[normal]
            assert not cut.passed
            assert cut.std > 10 * ok.std and cut.max > 5 * ok.max, (cut, ok)
            assert cut.correlation_length > 3 * ok.correlation_length and cut.correlation_length > 2 * ELL
            # the truth: v(X) = -(0.01 (X - c)) in the plane (f(X) = h(X + v) with h(x) = g(x + u + e))
            others = [a for a in range(3) if a != normal]
            roi = res.mesh.roi
            centre = [(roi[a].start + roi[a].stop - 1) / 2 for a in others]
            coords = [q.node_coords[i] + roi[a].start for i, a in enumerate(others)]
            truth = np.stack([-0.01 * (x - c0) / 1.01 for x, c0 in zip(coords, centre)])
            assert np.sqrt(((q.displacement - truth) ** 2).mean()) < 0.02


# --------------------------------------------------------------------------- CLI


def test_cli_cutcheck_figure_format_and_resolution(synthetic_result, tmp_path, capsys):
    """``cutcheck --format/--dpi``, as ``report``: the PNG's width is the figure's 15 inches
    (3 panels of 5) times the dpi; ``--overwrite`` with another format replaces the PNG."""
    from PIL import Image

    out = tmp_path / "check"
    good = str(synthetic_result / "good.zarr")
    assert main(["cutcheck", good, "-o", str(out), "--dpi", "40"]) == 0
    assert Image.open(out / "cutcheck.png").size[0] == 15 * 40
    assert main(["cutcheck", good, "-o", str(out), "--format", "svg", "--overwrite"]) == 0
    assert (out / "cutcheck.svg").read_text().lstrip().startswith("<?xml")
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == ["cutcheck.json", "cutcheck.svg"]
    capsys.readouterr()



def test_cli_correlate2d_on_image_files(tmp_path, shifted, capsys):
    import tifffile
    from PIL import Image

    f, g = shifted
    np.save(tmp_path / "a.npy", f.astype(np.float32))
    tifffile.imwrite(tmp_path / "b.tif", g.astype(np.float32))
    assert main(["correlate2d", str(tmp_path / "a.npy"), str(tmp_path / "b.tif"), "-l", "16", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["status"] == "converged"
    assert s["mean"]["y"] == pytest.approx(0.3, abs=0.005) and s["mean"]["x"] == pytest.approx(-0.45, abs=0.005)
    # 8-bit PNGs (grey saved as RGB too), integer translation
    q = np.rint(255 * (f - f.min()) / (f.max() - f.min())).astype(np.uint8)
    Image.fromarray(q).save(tmp_path / "a.png")
    Image.fromarray(np.repeat(np.roll(q, 2, axis=1)[..., None], 3, axis=2)).save(tmp_path / "b.png")
    assert main(["correlate2d", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "-l", "16"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("converged") and "<Ux> +2.00" in out
    assert read_image(tmp_path / "b.png").shape == q.shape


def test_cli_bad_input_is_one_line_and_writes_nothing(tmp_path, synthetic_result, capsys):
    a = tmp_path / "a.npy"
    np.save(a, smooth_noise((64, 64), seed=2))
    for argv in (["correlate2d", str(a), str(tmp_path / "missing.npy"), "-l", "16"],
                 ["correlate2d", str(a), str(a), "-l", "0"],
                 ["correlate2d", str(a), str(a), "-l", "200"],
                 ["cutcheck", str(tmp_path / "missing.zarr"), "-o", str(tmp_path / "out")],
                 ["cutcheck", str(a), "-o", str(tmp_path / "out")],
                 ["cutcheck", str(synthetic_result / "good.zarr"), "-o", str(tmp_path / "out"),
                  "--ref", str(tmp_path / "missing.zarr")],
                 ["cutcheck", str(synthetic_result / "good.zarr"), "-o", str(tmp_path / "out"), "--dpi", "5"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("chunkdic: error:") and err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npy"]
    rgb = np.zeros((8, 8, 3), np.uint8)
    rgb[..., 0] = 200
    from PIL import Image

    Image.fromarray(rgb).save(tmp_path / "colour.png")
    with pytest.raises(chunkdic.InputError, match="colour image"):
        read_image(tmp_path / "colour.png")
    with pytest.raises(chunkdic.InputError, match="2-D image"):
        correlate2d(np.zeros((8, 8, 3)), np.zeros((8, 8)), element_size=4)


def test_cli_cutcheck_json_and_exit_status(synthetic_result, capsys):
    d = synthetic_result
    assert main(["cutcheck", str(d / "good.zarr"), "-o", str(d / "cli-good"), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["axis"] for r in rows] == ["z", "y", "x"]
    assert all({"axis", "mean", "std", "max", "correlation_length"} <= set(r) for r in rows)
    assert all(r["max"] < 0.05 and r["std"] < 0.02 for r in rows)
    assert main(["cutcheck", str(d / "wrong.zarr"), "-o", str(d / "cli-wrong")]) == 1
    assert "FAILED" in capsys.readouterr().out


def test_increments_at_the_noise_level_end_converged_not_max_iterations():
    """Two noisy copies of one image (5 % of its range, independent): no motion to find, and
    with an unreachable tolerance the increments stay at the noise level. The 2-D check uses
    the 3-D engine's rule (chunkdic.method.stopping): converged at the noise level (before:
    max-iterations with the very same field). Measured: RMS 0.44 px, 39 passes."""
    f = smooth_noise((1, 96, 96), sigma=1.5, seed=3)[0]
    rng = np.random.default_rng(1)
    a, b = f + rng.normal(0, 5.0, f.shape), f + rng.normal(0, 5.0, f.shape)
    res = correlate2d(a.astype(np.float32), b.astype(np.float32), element_size=8, tolerance=1e-6, coarsest=0)
    assert res.status == "converged"
    assert float(np.sqrt(np.mean(res.displacement**2))) < 0.6
