"""Textures with exactly known deformations, for the tests."""

from __future__ import annotations

import numpy as np


def smooth_noise(shape, *, sigma: float = 1.5, seed: int = 0) -> np.ndarray:
    """Periodic Gaussian-filtered white noise (filtered in Fourier space), float64.

    Periodic and smooth, so that a Fourier phase shift translates it *exactly*
    (the paper's a-priori test, section 4.2).
    """
    rng = np.random.default_rng(seed)
    white = rng.standard_normal(shape)
    freqs = np.meshgrid(*[np.fft.fftfreq(n) for n in shape], indexing="ij", sparse=True)
    k2 = sum(f**2 for f in freqs)
    out = np.fft.ifftn(np.fft.fftn(white) * np.exp(-2 * (np.pi * sigma) ** 2 * k2)).real
    out -= out.min()
    return 100.0 * out / out.max()


def fourier_shift(volume: np.ndarray, t) -> np.ndarray:
    """``g(x) = f(x - t)`` for a periodic ``f``, by a phase shift: then ``f(X) = g(X + t)``."""
    freqs = np.meshgrid(*[np.fft.fftfreq(n) for n in volume.shape], indexing="ij", sparse=True)
    phase = sum(f * ti for f, ti in zip(freqs, t))
    return np.fft.ifftn(np.fft.fftn(volume) * np.exp(-2j * np.pi * phase)).real
