"""Local CT imaging (``imaging="local"``, :mod:`chunkdic.synth.ctlocal`): noise level and
spectrum against the requested law, the PSF's transfer function, chunk independence."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from chunkdic.cli.app import main
from chunkdic.errors import InputError
from chunkdic.synth import ctlocal
from chunkdic.synth.ctpair import CTSpecimen, as_dask_ct, render_ct
from chunkdic.synth.fields import Translation

SHAPE = (6, 128, 128)


@pytest.fixture(scope="module")
def noises():
    kw = dict(specimen="grains", seed=4, dtype="float32", imaging="local")
    clean = render_ct(SHAPE, noise=0.0, **kw).astype(np.float64)
    ref = render_ct(SHAPE, noise=0.03, **kw) - clean
    dfm = render_ct(SHAPE, noise=0.03, which="deformed", **kw) - clean
    return ref, dfm


def test_noise_std_is_the_requested_fraction_of_the_contrast_and_independent(noises):
    ref, dfm = noises
    for n in (ref, dfm):
        assert abs(n.std() / 0.03 - 1) < 0.03  # exact calibration: sum(kernel^2) = 1
        assert abs(n.mean()) < 0.002
    assert abs(np.corrcoef(ref.ravel(), dfm.ravel())[0, 1]) < 0.03  # independent scans
    # independent between slices (FBP slices are)
    assert abs(np.corrcoef(ref[:-1].ravel(), ref[1:].ravel())[0, 1]) < 0.03


def test_noise_power_spectrum_follows_the_ramp_law(noises):
    """NPS ∝ |k| exp(-4 pi^2 s^2 k^2) in each slice: the ratio to the law is flat."""
    ref, _ = noises
    n = SHAPE[1]
    nps = np.mean([np.abs(np.fft.fft2(s)) ** 2 for s in ref], axis=0)
    f = np.fft.fftfreq(n)
    k = np.hypot(f[:, None], f[None, :])
    law = k * np.exp(-4 * math.pi ** 2 * ctlocal.NOISE_SIGMA ** 2 * k ** 2)
    ratios = []
    for lo in np.arange(0.08, 0.46, 0.06):
        ring = (k >= lo) & (k < lo + 0.06)
        ratios.append(nps[ring].mean() / law[ring].mean())
    ratios = np.array(ratios) / np.mean(ratios)
    assert np.all(np.abs(ratios - 1) < 0.12), ratios
    # and not white: the law gives 2.8x more power at 0.4 cycle/voxel than at 0.05
    lowk, highk = (k > 0.03) & (k < 0.07), (k > 0.38) & (k < 0.42)
    assert nps[highk].mean() / nps[lowk].mean() > 2


def test_psf_transfer_function_and_unit_gain():
    ker = ctlocal.psf_kernel()
    assert abs(ker.sum() - 1) < 1e-12  # the mean grey level is kept
    h = ker.shape[0] // 2
    grid = np.zeros((128, 128))
    grid[:2 * h + 1, :2 * h + 1] = ker
    H = np.fft.fft2(np.roll(grid, (-h, -h), axis=(0, 1))).real
    f = np.fft.fftfreq(128)
    k = np.hypot(f[:, None], f[None, :])
    for kk in (0.1, 0.25, 0.4):
        ring = np.abs(k - kk) < 0.02
        want = math.exp(-2 * math.pi ** 2 * ctlocal.PSF_SIGMA ** 2 * kk ** 2)
        assert abs(H[ring].mean() - want) < 0.02


def test_values_do_not_depend_on_the_chunking():
    spec = CTSpecimen.build("concrete", (20, 150, 140), seed=2, noise=0.02, imaging="local",
                            field=Translation((0.3, -0.7, 1.2)), dtype="uint16", gain=1.1, drift=0.02)
    for which in ("reference", "deformed"):
        a = as_dask_ct(spec, which, chunks=(7, 64, 48)).compute(scheduler="sync")
        b = as_dask_ct(spec, which, chunks=128).compute(scheduler="sync")
        assert np.array_equal(a, b)
        # a box rendered alone equals the same box of the whole
        box = spec.block(which, ((5, 9), (100, 150), (3, 131)))
        assert np.array_equal(box, b[5:9, 100:150, 3:131])


def test_fbp_settings_are_refused_with_local_imaging():
    for kw in (dict(angles=100), dict(filter="hann"), dict(blur=1.0), dict(rings=0.01)):
        with pytest.raises(InputError, match="only with the FBP"):
            CTSpecimen.build("grains", (8, 32, 32), imaging="local", **kw)
    with pytest.raises(InputError, match="imaging"):
        CTSpecimen.build("grains", (8, 32, 32), imaging="radon")


def test_cli_local_imaging_writes_its_metadata(tmp_path, capsys):
    out = tmp_path / "p"
    assert main(["synth", str(out), "--shape", "32", "--specimen", "grains", "--imaging", "local",
                 "--case", "shift"]) == 0
    meta = json.loads((out / "field.json").read_text())
    assert meta["imaging"]["mode"] == "local" and meta["geometry"]["psf_sigma"] == ctlocal.PSF_SIGMA
    assert main(["synth", str(tmp_path / "q"), "--shape", "32", "--imaging", "local"]) == 2  # foam
    assert "CT specimens" in capsys.readouterr().err
