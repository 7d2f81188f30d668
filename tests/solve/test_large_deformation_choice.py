"""The length choice's no-feature test under a large deformation, on misfit curves measured on
100³ CT-like pairs (the first choice's misfit increase over the shortest candidate, for the
candidates ℓ·2^(k/2), k = 0 … 10, in noise budgets; validation/scripts/bench_vs_aldvc.py and
bench_large_strain.py pairs). Which of them is a feature is known from the best fixed length:
the longest candidate is best on the compressions, a length of 2–4ℓ on the bands."""

from __future__ import annotations

import numpy as np
import pytest

from chunkdic.solve.regchoice import large_deformation_tolerance, no_feature

# 10 % compression with 3 % lateral expansion, grains at texture scale 4: the longest candidate
# is best (ℓ = 16: 0.0039 voxel against 0.109 at 16 voxels)
COMPRESSION_L16 = [0.0, 1.325, 2.428, 3.176, 3.674, 3.971, 4.117, 4.181, 4.203, 4.21, 4.211]
COMPRESSION_L12 = [0.0, 0.616, 1.303, 1.83, 2.14, 2.302, 2.379, 2.413, 2.428, 2.433, 2.435]
# the −8 % band 6 voxels wide, concrete at texture scale 4: 23 voxels are best at ℓ = 4 and 8
BAND_L4 = [0.0, 0.141, 0.268, 0.365, 0.435, 0.492, 0.545, 0.619, 0.741, 0.907, 1.081]
BAND_L8 = [0.0, 0.181, 0.356, 0.534, 0.744, 1.08, 1.664, 2.477, 3.319, 3.951, 4.252]
# −20 % over a band 48 voxels wide, grains at texture scale 4.5, ℓ = 8: within 1.22 budgets,
# but its steps grow 2.7× (16 voxels read 0.41 voxel, the longest 0.95)
WIDE_BAND_L8 = [0.0, 0.02, 0.05, 0.07, 0.1, 0.13, 0.2, 0.39, 0.74, 1.06, 1.22]


def says_no_feature(curve, ell: float) -> bool:
    c = np.asarray(curve)
    return no_feature(lambda i: c[i], len(c) - 1, 1.0, ell)


def test_tolerance_grows_as_the_square_of_the_element():
    assert large_deformation_tolerance(8) == 2.5
    assert large_deformation_tolerance(16) == pytest.approx(10.0)
    assert large_deformation_tolerance(4) == pytest.approx(0.625)


@pytest.mark.parametrize("curve, ell", [(COMPRESSION_L16, 16), (COMPRESSION_L12, 12)])
def test_a_compression_on_a_coarse_texture_is_no_feature(curve, ell):
    assert says_no_feature(curve, ell)
    if ell == 16:  # beyond ℓ = 8's tolerance: taken for a feature with it
        assert not says_no_feature(curve, 8)


@pytest.mark.parametrize("curve, ell", [(BAND_L4, 4), (BAND_L8, 8), (WIDE_BAND_L8, 8)])
def test_a_band_is_a_feature(curve, ell):
    assert not says_no_feature(curve, ell)


def test_a_band_at_small_elements_is_told_by_the_tolerance_alone():
    # its steps never double: with ℓ = 8's tolerance it would pass for no feature
    assert says_no_feature(BAND_L4, 8)
