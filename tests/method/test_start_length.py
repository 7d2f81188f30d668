"""The regularisation length a level starts with (:func:`chunkdic.method.length.start_length`)
and the autocorrelation length it reads (:mod:`chunkdic.kernels.autocorrelation`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from chunkdic.kernels.autocorrelation import autocorrelation_length, lag_sums
from chunkdic.method.length import mean_gradient, start_length
from chunkdic.passes.texture import sample_boxes
from textures import smooth_noise


@pytest.mark.parametrize("sigma", [1.5, 3.0, 5.0])
def test_autocorrelation_length_of_gaussian_filtered_noise(sigma):
    """White noise low-passed by a Gaussian of std σ has the autocorrelation exp(-k² / 4σ²):
    it falls to 1/e at k = 2σ. One 64³ realisation reads it within 20 % on every axis and within
    12 % in the median."""
    acl = np.array(autocorrelation_length(lag_sums(smooth_noise((64, 64, 64), sigma=sigma, seed=3), 32)))
    assert acl == pytest.approx(np.full(3, 2 * sigma), rel=0.2)
    assert np.median(acl) == pytest.approx(2 * sigma, rel=0.12)


def test_autocorrelation_length_along_one_axis_only():
    """A cosine of period 24 along x over 20 periods: along z and y perfectly correlated (no
    crossing: inf); along x its autocorrelation is cos(2πk / 24), 0.5 at lag 4 and 0.259 at
    lag 5, the crossing of 1/e interpolated between them 4.548 (by hand; the finite sums read
    within 0.05). A constant block has none (NaN)."""
    x = np.arange(480)
    block = np.broadcast_to(np.cos(2 * np.pi * x / 24), (6, 8, 480))
    acl = autocorrelation_length(lag_sums(block, 12))
    assert math.isinf(acl[0]) and math.isinf(acl[1])
    assert acl[2] == pytest.approx(4 + (0.5 - 1 / math.e) / (0.5 - math.cos(5 * math.pi / 12)), abs=0.05)
    assert all(math.isnan(a) for a in autocorrelation_length(lag_sums(np.ones((8, 8, 8)), 4)))


def test_start_length_grows_as_the_square_of_the_texture_scale_under_a_large_deformation():
    """2ℓ (A/ℓ')² with ℓ' = max(ℓ, 8), rounded geometrically to the candidates ℓ·2^(k/2) from
    2ℓ to 32ℓ (by hand): A ≤ ℓ' or unknown: 2ℓ; A/ℓ' = 1.44: 4.13 → 4; 2.5: 12.5 → 8√2
    (11.3); 30/8: 28.1 → 32; below ℓ = 8 the ratio is to 8 voxels (a fine texture keeps 2ℓ).
    A small deformation (mean gradient below 0.02) keeps 2ℓ on any texture."""
    assert start_length(8, 6.0) == 16.0
    assert start_length(8, math.nan) == 16.0
    assert start_length(4, 7.9) == 8.0
    assert start_length(8, 11.5) == 32.0
    assert start_length(6, 11.5) == 24.0
    assert start_length(8, 20.0) == pytest.approx(8 * 8 * math.sqrt(2))
    assert start_length(6, 30.0) == 192.0
    assert start_length(6, 30.0, gradient=0.019) == 12.0
    assert start_length(6, 30.0, gradient=0.02) == 192.0


def test_mean_gradient_of_an_affine_field():
    """u_z = -0.2 z, u_x = 0.06 x on a 5 × 4 × 3 node grid of ℓ = 8: 0.2 (by hand), a translation 0."""
    z, y, x = np.meshgrid(*(8.0 * np.arange(n) for n in (5, 4, 3)), indexing="ij")
    u = np.stack([-0.2 * z + 3.0, np.zeros_like(y), 0.06 * x])
    assert mean_gradient(u, 8) == pytest.approx(0.2)
    assert mean_gradient(np.ones((3, 5, 4, 3)), 8) == 0.0


def test_sample_boxes_lie_in_the_roi():
    """Boxes of 64³ on a large ROI, at its quarters where an axis holds two, never outside it."""
    roi = ((10, 210), (0, 100), (5, 45))
    boxes = sample_boxes(None, 64, 8, within=roi)
    assert len(boxes) == 2 * 1 * 1
    for box in boxes:
        for (a, b), (lo, hi), edge in zip(box, roi, (64, 64, 40)):
            assert lo <= a and b <= hi and b - a == edge
    assert [b[0][0] for b in boxes] == [28, 128]  # centred on 10 + 50 and 10 + 150: the quarters
