"""``chunkdic texture`` / :func:`chunkdic.texture`: autocorrelation length, weak elements, predicted noise.

Truths: the autocorrelation of Gaussian-filtered white noise (``exp(-r²/4σ²)``: 1/e at ``2σ``)
and the same volume's autocorrelation by a whole-volume 3-D FFT; a checkerboard of textured and
flat blocks whose weakly textured elements are counted by hand; the engine's own scatter on a
translated pair with known white noise.
"""

from __future__ import annotations

import inspect
import math
import warnings

import numpy as np
import pytest
from scipy.ndimage import fourier_shift, gaussian_filter

import chunkdic
from chunkdic.engine.texture_check import ElementSizeWarning, check_texture
from chunkdic.io.scan import open_scan
from chunkdic.mesh import Mesh
from chunkdic.method.settings import Settings
from chunkdic.scheduler import open_runner
from textures import fft_autocorrelation_length


def test_autocorrelation_length_matches_an_fft_of_the_whole_volume_and_the_gaussian_truth():
    """Gaussian-filtered white noise of σ = 4 voxels on 96³ (periodic; 1/e at 2σ = 8 voxels):
    the report samples eight 48³ boxes (tasks, never the volume); the whole volume's 3-D
    FFT and the analytic value agree within 15 %."""
    v = gaussian_filter(np.random.default_rng(3).standard_normal((96, 96, 96)), 4.0, mode="wrap")
    v = (1000.0 * v / v.std()).astype(np.float32)
    report = chunkdic.texture(v, [], noise=1.0, edge=48)
    assert report.stats.boxes == 8 and report.stats.box_edge == 48
    reference = fft_autocorrelation_length(v)
    for measured, independent in zip(report.acl, reference):
        assert measured == pytest.approx(independent, rel=0.15)
        assert measured == pytest.approx(8.0, rel=0.15)


def _checkerboard(n: int = 128, block: int = 16) -> np.ndarray:
    """Blocks of ``block``³ voxels alternately textured and flat, white noise of std 1
    everywhere. A textured block holds white noise of std 20 windowed by ``sin²`` along each
    axis (zero at the block's faces), so that no texture leaks into the flat blocks through
    the engine's low-pass: there the mean squared gradient is the noise's alone."""
    rng = np.random.default_rng(7)
    idx = np.indices((n, n, n))
    textured = ((idx // block).sum(axis=0) % 2) == 0
    w = np.sin(np.pi * ((np.arange(n) % block) + 0.5) / block) ** 2
    window = w[:, None, None] * w[None, :, None] * w[None, None, :]
    return (np.where(textured, 20.0 * window * rng.standard_normal((n, n, n)), 0.0)
            + rng.standard_normal((n, n, n))).astype(np.float32)


def test_weak_elements_of_a_checkerboard_are_counted_as_by_hand():
    """Textured and flat 16³ blocks: elements of 8 and 16 voxels (aligned with the blocks,
    the boxes starting at 0 and 64) are half weak; 4-voxel ones more than half (those in a
    textured block's corners, where its window is near 0, too); every larger size holds a
    textured block (the unaligned 20 and 24 too): the smallest size the texture supports is
    20 voxels. The noise (std 1) is given."""
    report = chunkdic.texture(_checkerboard(), [], noise=1.0, edge=64)
    weak = report.stats.weak_fraction
    for ell in (8, 16):
        assert weak[ell] == pytest.approx(0.5, abs=1e-9)
    assert weak[4] > 0.5
    assert all(weak[e] == 0.0 for e in (20, 24, 32, 48, 64))
    assert report.smallest == 20
    text = "\n".join(report.lines())
    assert "smallest element size the texture supports: 20 voxels" in text


def test_a_coarse_texture_without_weak_elements_is_judged_by_its_predicted_noise(tmp_path):
    """A coarse Gaussian texture (σ = 5 voxels, autocorrelation length about 10, std 100) holds
    far more gradient than the noise in every element of every size: no element is weak, so
    the weak elements alone would support ℓ = 4 whatever the noise. With noise of std 1 the
    predicted σ_u at ℓ = 4 is below SIGMA_LIMIT and 4 is supported; with std 10 it is above
    (σ_u ∝ noise), and the smallest supported size is the first of the ladder whose predicted
    median is within the limit. ``correlate``'s check warns at ℓ = 4 and names that noise."""
    from chunkdic.passes.texture import LADDER, SIGMA_LIMIT

    rng = np.random.default_rng(0)
    base = gaussian_filter(rng.standard_normal((64, 64, 64)), 5.0, mode="wrap")
    base = base / base.std() * 100.0
    quiet = chunkdic.texture((base + rng.standard_normal(base.shape)).astype(np.float32), [], noise=1.0, edge=64)
    assert all(w == 0.0 for w in quiet.stats.weak_fraction.values())
    assert quiet.stats.sigma_u[4][0] <= SIGMA_LIMIT and quiet.smallest == 4
    noisy = (base + 10.0 * rng.standard_normal(base.shape)).astype(np.float32)
    report = chunkdic.texture(noisy, [], noise=10.0, edge=64)
    assert all(w == 0.0 for w in report.stats.weak_fraction.values())
    sigma = {e: s[0] for e, s in report.stats.sigma_u.items()}
    assert sigma[4] > SIGMA_LIMIT
    assert report.smallest == min(e for e in LADDER if e in sigma and sigma[e] <= SIGMA_LIMIT) > 4
    ref = open_scan(noisy).refs([0], tmp_path)[0]
    with open_runner() as runner, pytest.warns(ElementSizeWarning, match=r"predicted noise without regularisation is"):
        check_texture(ref, Mesh((0, 0, 0), 4, (16, 16, 16)), Settings(element_size=4), runner)


def test_predicted_noise_is_the_engines_scatter_on_a_translated_pair():
    """A Gaussian texture (σ = 2 voxels, std 100) translated by a Fourier shift, white noise of
    std 5 added to each scan independently: the unregularised engine's scatter at the inner
    nodes (pooled σ) at ℓ = 8 and 12 is what the report predicts from the reference alone
    (measured 0.025 / 0.0125 voxel, predicted median 0.031 / 0.015: the engine's model
    overestimates by ~20 %, docs/engine.md "Per-node uncertainty"); within 0.8–1.5×."""
    rng = np.random.default_rng(0)
    base = gaussian_filter(rng.standard_normal((80, 80, 80)), 2.0)
    base = base / base.std() * 100
    moved = np.real(np.fft.ifftn(fourier_shift(np.fft.fftn(base), (0.4, 0.3, 0.2))))
    f = (base + 5.0 * rng.standard_normal(base.shape)).astype(np.float32)
    g = (moved + 5.0 * rng.standard_normal(base.shape)).astype(np.float32)
    report = chunkdic.texture(f, [8, 12], noise=5.0)
    for ell in (8, 12):
        res = chunkdic.correlate(f, g, element_size=ell, regularization="none", coarsest=0)
        u = res.displacement[:, 1:-1, 1:-1, 1:-1].reshape(3, -1)
        measured = math.sqrt(np.mean(np.var(u, axis=1)))
        assert 0.8 < report.stats.sigma_u[ell][0] / measured < 1.5


def test_correlate_warns_in_one_line_when_the_element_size_is_below_what_the_texture_supports(tmp_path):
    """The checkerboard (flat blocks of 16³) at ℓ = 8: one ElementSizeWarning naming the smallest
    supported size; a 32-voxel element size: none (the check alone, from the runner's tasks)."""
    f = _checkerboard(96)
    with pytest.warns(ElementSizeWarning, match=r"element size 8 voxels is below the smallest .* \(\d+ voxels\)"):
        res = chunkdic.correlate(f, f, element_size=8, coarsest=0, regularization_length=16.0)
    assert res.converged
    ref = open_scan(f).refs([0], tmp_path)[0]
    with open_runner() as runner, warnings.catch_warnings():
        warnings.simplefilter("error", ElementSizeWarning)
        length = check_texture(ref, Mesh((0, 0, 0), 32, (3, 3, 3)), Settings(element_size=32), runner)
    assert 0 < length < 16


def test_cli_prints_the_report_and_refuses_bad_sizes_in_one_line(tmp_path, capsys):
    from chunkdic.cli.app import main

    path = tmp_path / "ref.npy"
    np.save(path, _checkerboard(64))
    assert main(["texture", str(path), "-l", "8", "--noise", "1"]) == 0
    out = capsys.readouterr().out
    assert "autocorrelation length (z, y, x)" in out and "smallest element size" in out
    assert main(["texture", str(path), "-l", "1"]) == 2
    err = capsys.readouterr().err
    assert err.strip().count("\n") == 0 and "error: --element-sizes must be >= 2" in err


def test_a_flat_or_pure_noise_reference_supports_no_element_size(tmp_path):
    """A constant reference holds no texture, and white noise none above its noise: neither
    supports any element size. The report says none, and why, in its text and its JSON, with
    the noise estimated (0 for the constant scan) or given; correlate's check warns that no
    size is supported and names none."""
    flat = np.full((48, 48, 48), 100.0, np.float32)
    noise = (100.0 + 10.0 * np.random.default_rng(1).standard_normal((48, 48, 48))).astype(np.float32)
    for f, given in ((flat, None), (flat, 1.0), (noise, None)):
        report = chunkdic.texture(f, [8], noise=given)
        assert report.smallest is None and not report.stats.textured
        assert "supports: none of 4, 5, 6, 8" in report.lines()[-1]
        assert "no texture above the noise" in report.lines()[-1]
        assert report.to_json()["smallest"] is None and "no texture" in report.to_json()["why_unsupported"]
    ref = open_scan(flat).refs([0], tmp_path)[0]
    with open_runner() as runner, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_texture(ref, Mesh((0, 0, 0), 8, (6, 6, 6)), Settings(element_size=8), runner)
    [w] = [w for w in caught if w.category is ElementSizeWarning]
    assert "supports no element size of 8–12 voxels (no texture above the noise" in str(w.message)
    assert "below the smallest" not in str(w.message)


def test_a_coarse_texture_too_noisy_at_every_measured_size_supports_none_rather_than_an_unmeasured_one(tmp_path):
    """A coarse Gaussian texture (σ = 8 voxels, std 100, noise std 20) in boxes of 24³ voxels:
    sub-meshes of three elements fit up to ℓ = 8 only, and the predicted σ_u is above
    SIGMA_LIMIT at every one of 4, 5, 6 and 8 (σ_u falls as ℓ grows, too slowly here). The
    sizes 10-24 (their weak elements counted, none weak) have no predicted noise: nothing says
    they are supported, and the report supports none. With boxes of 64³ the same scan's
    10 voxels is measured, within the limit and supported; correlate's check at ℓ = 4 on a
    48³ ROI (boxes of 24³) names no size."""
    from chunkdic.passes.texture import SIGMA_LIMIT

    rng = np.random.default_rng(0)
    base = gaussian_filter(rng.standard_normal((64, 64, 64)), 8.0, mode="wrap")
    f = (base / base.std() * 100.0 + 20.0 * rng.standard_normal(base.shape)).astype(np.float32)
    small = chunkdic.texture(f, [], noise=20.0, edge=24)
    assert sorted(small.stats.sigma_u) == [4, 5, 6, 8]
    assert all(s[0] > SIGMA_LIMIT for s in small.stats.sigma_u.values())
    assert all(w == 0.0 for w in small.stats.weak_fraction.values()) and small.stats.textured
    assert small.smallest is None
    assert "predicted σ_u median is above 0.7 voxel at every size measured" in small.lines()[-1]
    large = chunkdic.texture(f, [], noise=20.0, edge=64)
    assert large.smallest == 10 and large.stats.sigma_u[10][0] <= SIGMA_LIMIT
    ref = open_scan(f).refs([0], tmp_path)[0]
    with open_runner() as runner, pytest.warns(ElementSizeWarning, match=r"supports no element size of 4–12 voxels "
                                                                         r"\(the predicted σ_u median is above"):
        check_texture(ref, Mesh((8, 8, 8), 4, (12, 12, 12)), Settings(element_size=4), runner)


def test_the_element_size_warning_names_the_users_call():
    """``chunkdic.correlate(...)`` called here: the warning's file and line are this call's,
    not a line of chunkdic (where a fixed stacklevel left it)."""
    f = _checkerboard(64)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        line = inspect.currentframe().f_lineno + 1
        chunkdic.correlate(f, f, element_size=8, coarsest=0, regularization_length=16.0)
    [w] = [w for w in caught if w.category is ElementSizeWarning]
    assert (w.filename, w.lineno) == (__file__, line)


def test_the_report_does_not_depend_on_which_box_task_finishes_first(tmp_path):
    """The same eight boxes reduced by tasks that finish in the boxes' order or in the reverse
    one (as a cluster's may): the same report to the last bit (the noise factor is solved on
    the first box's sub-mesh, the sums added in one order)."""
    from chunkdic.passes.texture import measure_texture

    v = gaussian_filter(np.random.default_rng(5).standard_normal((64, 64, 64)), 1.5)
    ref = open_scan((1000.0 * v / v.std()).astype(np.float32)).refs([0], tmp_path)[0]

    def in_order(fn, args):
        return [fn(*a) for a in args]

    def reversed_order(fn, args):
        return in_order(fn, args)[::-1]

    forward = measure_texture(ref, in_order, element_sizes=(4,), edge=32, max_lag=16)
    backward = measure_texture(ref, reversed_order, element_sizes=(4,), edge=32, max_lag=16)
    assert forward.boxes == 8 and forward.sigma_u and forward == backward


def test_the_noise_model_is_built_for_the_sizes_read_only_and_reads_the_same(monkeypatch, tmp_path):
    """Eight boxes of 48³, correlate's ladder from ℓ up. A fine texture (Gaussian σ = 1.5,
    noise std 1) supports ℓ = 8: the sub-meshes' M are built for 8 alone (8 boxes, 8 M; not
    for 10, 12 and 16 too, which nothing reads). A coarser, noisier one (σ = 4, noise std 10)
    does not support ℓ = 4: the other sizes' M are built by a second round of tasks, and
    their predicted σ_u is the one measured when the sizes are asked for (the same boxes,
    every M built in the first round)."""
    import chunkdic.passes.texture as tex

    built = []
    m_block = tex.m_block
    monkeypatch.setattr(tex, "m_block", lambda prepared, lo, hi, ell, **kw: built.append(ell) or
                        m_block(prepared, lo, hi, ell, **kw))

    def serial(fn, args):
        return [fn(*a) for a in args]

    rng = np.random.default_rng(2)
    for sigma, noise, ell in ((1.5, 1.0, 8), (4.0, 10.0, 4)):
        v = gaussian_filter(rng.standard_normal((96, 96, 96)), sigma, mode="wrap")
        v = 100.0 * v / v.std() + noise * rng.standard_normal(v.shape)
        ref = open_scan(v.astype(np.float32)).refs([0], tmp_path / str(ell))[0]
        built.clear()
        stats = tex.measure_texture(ref, serial, noise=noise, edge=48, max_lag=0,
                                    ladder=tuple(e for e in tex.LADDER if ell <= e <= 24))
        if ell == 8:
            assert stats.smallest == 8 and built == [8] * 8
        else:
            assert stats.sigma_u[4][0] > tex.SIGMA_LIMIT and stats.smallest > 4 and len(stats.sigma_u) > 1
            asked = tex.measure_texture(ref, serial, element_sizes=tuple(stats.sigma_u), noise=noise, edge=48,
                                        max_lag=0, ladder=())
            assert asked.boxes == 8 and asked.sigma_u == stats.sigma_u
