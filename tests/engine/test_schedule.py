"""The texture-dependent start of the schedule (:mod:`chunkdic.engine.schedule`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from chunkdic.engine.schedule import autocorrelation_length, sample_boxes, start_length
from textures import smooth_noise


@pytest.mark.parametrize("sigma", [1.5, 3.0, 5.0])
def test_autocorrelation_length_of_gaussian_filtered_noise(sigma):
    """White noise low-passed by a Gaussian of std σ has the autocorrelation exp(-k² / 4σ²):
    it falls to 1/e at k = 2σ. One 64³ realisation reads it within 20 % on every axis (a
    sample's scatter: ±15 % at 2σ = 10 over four seeds) and within 12 % in the median."""
    acl = autocorrelation_length(smooth_noise((64, 64, 64), sigma=sigma, seed=3))
    assert acl == pytest.approx(np.full(3, 2 * sigma), rel=0.2)
    assert np.median(acl) == pytest.approx(2 * sigma, rel=0.12)


def test_autocorrelation_length_along_one_axis_only():
    """A texture that varies along x only (a cosine of period 24 over 20 periods) is perfectly
    correlated along z and y (the bound n / 2 of a block of n voxels); along x its
    autocorrelation is cos(2πk / 24), 0.5 at lag 4 and 0.259 at lag 5: the crossing of 1/e
    interpolated between them is 4.548 (by hand; the sums over 480 voxels read 4.518). A
    constant block has none."""
    x = np.arange(480)
    block = np.broadcast_to(np.cos(2 * np.pi * x / 24), (6, 8, 480))
    acl = autocorrelation_length(block)
    assert acl[:2].tolist() == [3.0, 4.0]
    assert acl[2] == pytest.approx(4 + (0.5 - 1 / math.e) / (0.5 - math.cos(5 * math.pi / 12)), abs=0.05)
    assert np.isnan(autocorrelation_length(np.ones((8, 8, 8)))).all()


def test_start_length_grows_as_the_square_of_the_texture_scale_in_elements():
    """2ℓ (A/ℓ')² with ℓ' = max(ℓ, 8), rounded geometrically to the candidates ℓ·2^(k/2) from
    2ℓ to 32ℓ (by hand): A ≤ ℓ' or unknown: 2ℓ; A/ℓ' = 1.44: 4.13 → 4; 2.5: 12.5 → 8√2
    (11.3); 30/8: 28.1 → 32; below ℓ = 8 the ratio is to 8 voxels (a fine texture keeps 2ℓ)."""
    assert start_length(8, 6.0) == 16.0
    assert start_length(8, math.nan) == 16.0
    assert start_length(4, 7.9) == 8.0
    assert start_length(8, 11.5) == 32.0
    assert start_length(6, 11.5) == 24.0
    assert start_length(8, 20.0) == pytest.approx(8 * 8 * math.sqrt(2))
    assert start_length(6, 30.0) == 192.0


def test_sample_boxes_lie_in_the_roi():
    """Eight blocks of 64³ on a large ROI, one on a small one, never outside it."""
    roi = (slice(10, 210), slice(0, 100), slice(5, 45))
    boxes = sample_boxes(roi)
    assert len(boxes) == 2 * 2 * 1
    for box in boxes:
        for s, r, edge in zip(box, roi, (64, 64, 40)):
            assert r.start <= s.start and s.stop <= r.stop and s.stop - s.start == edge
    assert [b[0].start for b in boxes[::2]] == [28, 128]  # centred on 10 + 50 and 10 + 150: the quarters
