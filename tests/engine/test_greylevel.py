"""Known answers of the four brightness models (chunkdic.engine.greylevel).

The deformed scan is the reference with a known brightness change and no motion:
``g = a·f + b + c·z``, so ``f = g / a - b / a - (c / a)·z`` exactly, i.e. in the models'
form ``f ≈ gain · g(X + u) + offset (+ drift · (X - X_e))``: gain ``1/a``, offset at an
element's centre ``-(b + c·z_e)/a``, drift ``-c/a`` grey levels per voxel along z. The
low-pass of both scans keeps that relation (a Gaussian maps a linear function of z to
itself), so every model must find it, and the field must stay at zero.
"""

from __future__ import annotations

import numpy as np
import pytest
from textures import smooth_noise

import chunkdic

N, ELL = 48, 12
A, B, C = 1.25, 40.0, 0.5


def _pair(c: float):
    f = smooth_noise((N, N, N), sigma=1.5, seed=4)
    z = np.arange(N, dtype=np.float64)[:, None, None]
    return f.astype(np.float32), (A * f + B + c * z).astype(np.float32)


def _run(f, g, grey):
    return chunkdic.correlate(f, g, element_size=ELL, coarsest=0, grey=grey, regularization="none",
                              tolerance=1e-4)


def _element_centres_z(res) -> np.ndarray:
    """z of each element's centre (voxel coordinates; element k covers o + k ℓ … o + (k + 1) ℓ - 1)."""
    mesh = res.mesh
    return mesh.origin[0] + ELL * np.arange(mesh.shape[0]) + (ELL - 1) / 2


def test_global_model_finds_gain_and_offset():
    f, g = _pair(0.0)
    res = _run(f, g, "global")
    bright = res.info["grey_level"]
    assert res.converged and np.abs(res.displacement).max() < 2e-3
    assert bright["gain"] == pytest.approx(1 / A, rel=1e-4)
    assert bright["offset"] == pytest.approx(-B / A, abs=0.05)
    np.testing.assert_allclose(res.brightness[0], 1 / A, rtol=1e-4)  # one gain for every element


def test_drift_model_finds_gain_drift_and_element_offsets():
    f, g = _pair(C)
    res = _run(f, g, "drift")
    bright = res.info["grey_level"]
    assert res.converged and np.abs(res.displacement).max() < 2e-3
    assert bright["gain"] == pytest.approx(1 / A, rel=1e-4)
    np.testing.assert_allclose(bright["drift"], [-C / A, 0.0, 0.0], atol=2e-4)
    want = -(B + C * _element_centres_z(res)) / A  # per element row along z
    np.testing.assert_allclose(res.brightness[1], np.broadcast_to(want[:, None, None], res.brightness[1].shape),
                               atol=0.05)


def test_element_model_finds_a_gain_and_offset_per_element():
    f, g = _pair(0.0)
    res = _run(f, g, "element")
    assert res.converged and np.abs(res.displacement).max() < 2e-3
    np.testing.assert_allclose(res.brightness[0], 1 / A, rtol=1e-3)
    np.testing.assert_allclose(res.brightness[1], -B / A, atol=0.1)


def test_none_model_keeps_gain_one_and_identical_scans_give_zero_motion():
    f, _ = _pair(0.0)
    res = _run(f, f.copy(), "none")
    bright = res.info["grey_level"]
    assert res.converged and bright["model"] == "none"
    assert bright["gain"] == 1.0 and bright["offset"] == 0.0
    assert np.abs(res.displacement).max() < 1e-5  # identical scans: zero motion to float32 round-off
