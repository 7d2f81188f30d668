"""A-priori uncertainty (paper 4.2), out-of-core Fourier shift, power-law fit, ZOI sweep (issue 4)."""

from __future__ import annotations

import argparse
import csv

import numpy as np
import pytest
import zarr

from chunkdic.analysis import metrology, zoisweep
from chunkdic.analysis.metrology import PowerLaw, fit_power_law
from chunkdic.cli import report_commands as _cli_report
from chunkdic.errors import InputError
from chunkdic.io.handles import ArrayRef
from chunkdic.results.result import open_result
from chunkdic.synth import foam, fourier_shift, synthetic


def _parser():
    parser = argparse.ArgumentParser(prog="chunkdic")
    _cli_report.register(parser.add_subparsers(dest="command", required=True))
    return parser


# --------------------------------------------------------------------------- power law


def test_power_law_fit_recovers_known_parameters():
    ell = np.array([6, 8, 12, 16])
    law = fit_power_law(ell, PowerLaw(2.4, 1.07)(ell))
    assert law.A == pytest.approx(2.4, rel=1e-9) and law.alpha == pytest.approx(1.07, rel=1e-9)
    rng = np.random.default_rng(0)
    noisy = PowerLaw(1.3, 1.8)(ell) * np.exp(rng.normal(scale=0.01, size=4))
    law = fit_power_law(ell, noisy)
    assert law.A == pytest.approx(1.3, rel=0.05) and law.alpha == pytest.approx(1.8, abs=0.05)


@pytest.mark.parametrize("ell, sigma", [([8], [0.1]), ([8, 8], [0.1, 0.2]), ([8, 16], [0.1, 0.0])])
def test_power_law_fit_refuses_degenerate_data(ell, sigma):
    with pytest.raises(InputError):
        fit_power_law(ell, sigma)


# --------------------------------------------------------------------------- Fourier shift


def _stored(tmp_path, a):
    z = zarr.create_array(str(tmp_path / "src.zarr"), shape=a.shape, chunks=(16, 16, 16), dtype=a.dtype)
    z[...] = a
    return ArrayRef("zarr", str(tmp_path / "src.zarr"), "", a.shape, a.dtype.name)


def test_pencil_fourier_shift_of_a_mirror_symmetric_cosine_product_is_exact(tmp_path, monkeypatch):
    """Analytic truth: ``Π cos(π k_a (x_a + ½) / n_a)`` is a DCT-II mode, so with the
    half-sample mirror extension (period ``2n``) the shift ``f(x - t)`` is that product at
    ``x - t``, to round-off, whatever ``t``. Several pencils per pass, partial ones at the ends."""
    monkeypatch.setattr(fourier_shift, "PENCIL_EDGE", 16)
    shape, k, t = (40, 48, 36), (3, 5, 2), (0.5, -0.3, 0.25)

    def product(shift):
        axes = np.meshgrid(*[np.arange(n, dtype=np.float64) for n in shape], indexing="ij")
        out = np.ones(shape)
        for x, n, ka, ta in zip(axes, shape, k, shift):
            out *= np.cos(np.pi * ka * (x - ta + 0.5) / n)
        return out

    f = (1000.0 + 500.0 * product((0, 0, 0))).astype(np.float32)
    out = fourier_shift.fourier_shift_scan(_stored(tmp_path, f), tmp_path / "g.zarr", t)
    g = out.read((slice(None),) * 3)
    err = np.abs(g - (1000.0 + 500.0 * product(t))).max() / 1000.0
    assert err < 2e-6, err  # measured 5.1e-7 (float32 storage); the opposite shift is 0.12 away
    assert zarr.open_array(str(tmp_path / "g.zarr")).attrs["chunkdic"]["complete"] is True
    assert not (tmp_path / "g.zarr.passes").exists()


def test_fourier_shift_sign_and_integer_shift(tmp_path):
    f = foam.render((32, 32, 32), seed=4)
    out = fourier_shift.fourier_shift_scan(_stored(tmp_path, f), tmp_path / "g.zarr", (2, 0, -1))
    g = out.read((slice(None),) * 3)
    # g(x) = f(x - t): away from the mirrored borders an integer shift is a plain roll
    expect = np.roll(f, (2, 0, -1), axis=(0, 1, 2))
    assert np.abs(g - expect)[2:, :, :-1].max() < 1e-4


# --------------------------------------------------------------------------- uncertainty + sweep


@pytest.fixture(scope="module")
def affine_pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("pair")
    field = synthetic.Affine(matrix=((-0.01, 0, 0), (0, 0, 0), (0, 0, 0.004)), center=(32, 32, 32),
                             translation=(0.6, -0.3, 0.2))
    return synthetic.synthesize(d, (64, 64, 64), field=field, seed=5, dtype="uint8")


@pytest.fixture(scope="module")
def uncertainty_dir(affine_pair, tmp_path_factory):
    out = tmp_path_factory.mktemp("unc") / "u"
    args = _parser().parse_args(["uncertainty", affine_pair["reference"], "--element-sizes", "16", "8",
                                 "-o", str(out)])
    assert args.func(args) == 0
    return out


def test_uncertainty_command_on_synthetic_texture(uncertainty_dir):
    with open(uncertainty_dir / "uncertainty.csv", newline="") as fh:
        rows = {int(r["element_size"]): r for r in csv.DictReader(fh)}
    assert set(rows) == {16, 8}
    for c in "zyx":
        assert abs(float(rows[16][f"bias_{c}"])) < 0.02
    assert float(rows[16]["sigma_u"]) < float(rows[8]["sigma_u"]) < 0.05
    assert 0 <= float(rows[16]["delta_eps"]) < 5e-3
    md = (uncertainty_dir / "uncertainty.md").read_text()
    assert "A =" in md and "α =" in md and "| 16 |" in md
    png = (uncertainty_dir / "uncertainty.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert (uncertainty_dir / "result-ell16.zarr").is_dir()
    # the DVC Challenge 2.0 u_rms: the RMS error over the nodes and components, from the result itself
    err = open_result(uncertainty_dir / "result-ell16.zarr").displacement - 0.5
    assert float(rows[16]["u_rms"]) == pytest.approx(float(np.sqrt(np.mean(err**2))), rel=1e-9)
    assert float(rows[16]["bias"]) == pytest.approx(float(np.sqrt(np.mean(err.mean(axis=(1, 2, 3)) ** 2))), rel=1e-9)


def test_uncertainty_refuses_bad_input(affine_pair, tmp_path):
    with pytest.raises(InputError):
        metrology.uncertainty(affine_pair["reference"], [1], tmp_path / "x")
    with pytest.raises(InputError):
        _cli_report._shift("0.5,0.5")


def test_sweep_table(affine_pair, uncertainty_dir, tmp_path):
    out = zoisweep.sweep(affine_pair["reference"], affine_pair["deformed"], [16, 8], tmp_path / "sweep",
                         uncertainty_from=uncertainty_dir)
    rows = out["rows"]
    assert [r["element_size"] for r in rows] == [16, 8]
    with open(uncertainty_dir / "uncertainty.csv", newline="") as fh:  # what `uncertainty` measured per ell
        measured = {int(r["element_size"]): float(r["delta_eps"]) for r in csv.DictReader(fh)}
    for r in rows:
        assert r["status"] == "converged"
        # measured: eps_zz within 3.7e-5 of the truth, tr within 5.8e-5 (bounds about 3x that)
        assert r["eps_zz"] == pytest.approx(-0.01, abs=1e-4)
        assert r["volume_change"] == pytest.approx(-0.006, abs=2e-4)  # -1 % along z, +0.4 % along x
        assert r["delta_eps"] == pytest.approx(measured[r["element_size"]], rel=1e-12) and r["delta_eps"] > 0
        # the nodes are centred on the ROI's centre, voxel 31.5 on every axis: u there is the
        # translation plus the affine part at -0.5 voxel from the field's centre (measured within 6e-4)
        assert r["mean_ux"] == pytest.approx(0.2 + 0.004 * -0.5, abs=2e-3)
        assert r["mean_uy"] == pytest.approx(-0.3, abs=2e-3)
        assert r["mean_uz"] == pytest.approx(0.6 - 0.01 * -0.5, abs=2e-3)
    md = (tmp_path / "sweep" / "zoi_table.md").read_text()
    assert "⟨Uz⟩" in md and "δε" in md and md.count("\n| ") >= 3
    with open(tmp_path / "sweep" / "zoi_table.csv", newline="") as fh:
        assert len(list(csv.DictReader(fh))) == 2
    # the same table from the existing results (`chunkdic table`)
    args = _parser().parse_args(["table", *(r["result"] for r in rows), "--uncertainty", str(uncertainty_dir),
                                 "-o", str(tmp_path / "table")])
    assert args.func(args) == 0
    assert (tmp_path / "table" / "zoi_table.md").read_text() == md


def test_studies_take_settings_like_correlate():
    """``sweep``/``uncertainty``/``resolution(settings=..., **options)``: the template's fields
    reach every correlation (its element size replaced per size), keyword options still
    override them; without a template the paper's analysis runs unregularised."""
    import inspect

    from chunkdic.analysis.metrology import PAPER_SETTINGS, study_settings
    from chunkdic.analysis.resolution import resolution
    from chunkdic.method.settings import Settings

    template = Settings(element_size=99, level=1, interpolation="linear", smoothing=0.0, regularization="tikhonov")
    given = study_settings(template, {"tolerance": 1e-4, "smoothing": 0.5}, PAPER_SETTINGS)
    assert (given["level"], given["interpolation"]) == (1, "linear")
    assert "element_size" not in given and given["regularization"] == "tikhonov"
    assert given["smoothing"] == 0.5 and given["tolerance"] == 1e-4
    assert study_settings(None, {"level": 2}, PAPER_SETTINGS) == {"regularization": "none", "level": 2}
    for fn in (zoisweep.sweep, metrology.uncertainty, resolution):
        params = inspect.signature(fn).parameters
        assert "settings" in params and params["options"].kind is inspect.Parameter.VAR_KEYWORD
