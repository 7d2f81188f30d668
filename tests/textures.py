"""Textures with exactly known deformations, for the tests."""

from __future__ import annotations

import math

import numpy as np

from chunkdic.synth.fields import Affine
from chunkdic.synth.foam import render


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


def cylinder_pair(n=64, radius=24.0, *, field=None, noise=0.0, seed=7):
    """Foam cylinder (axis z) in air, -2 % axial / +0.6 % lateral strain, partial-volume edges.

    The edge is a one-voxel linear ramp of the material weight, evaluated at ``X`` in the
    reference and at the undeformed position ``field.inverse(x)`` in the deformed scan, so
    the edge moves with the material (a binary edge would jump by whole voxels).
    ``field``: another motion (a :class:`chunkdic.synth.fields.Field`); ``noise``: the std
    of independent white noise added to each scan, as a fraction of the foam's grey range
    (the air is then noise alone, as in a CT scan).
    """
    if field is None:
        field = Affine(matrix=((-0.02, 0, 0), (0, 0.006, 0), (0, 0, 0.006)), center=(n / 2,) * 3)
    f0 = render((n,) * 3, seed=3, cell_size=5.0)
    g0 = render((n,) * 3, seed=3, cell_size=5.0, field=field, which="deformed")
    Z, Y, X = np.indices((n,) * 3).astype(float)
    c = (n - 1) / 2

    def weight(y, x):
        return np.clip(radius + 0.5 - np.hypot(y - c, x - c), 0.0, 1.0)

    back = field.inverse(Z, Y, X)
    wf, wg = weight(Y, X), weight(back[1], back[2])
    air = 0.05
    f = wf * f0 + (1 - wf) * air
    g = wg * g0 + (1 - wg) * air
    if noise:
        rng = np.random.default_rng(seed)
        span = float(f0.max() - f0.min())
        f = f + noise * span * rng.standard_normal(f.shape)
        g = g + noise * span * rng.standard_normal(g.shape)
    return f.astype(np.float32), g.astype(np.float32), wf, field


def fft_autocorrelation_length(v: np.ndarray) -> list[float]:
    """1/e lag per axis of the whole volume's autocorrelation (3-D FFT, mean removed, each lag
    divided by its number of pairs), linear between lags: the independent estimate."""
    v = v.astype(np.float64) - v.mean()
    shape = [2 * n for n in v.shape]
    acov = np.fft.irfftn(np.abs(np.fft.rfftn(v, s=shape, axes=(0, 1, 2))) ** 2, s=shape, axes=(0, 1, 2))
    pairs = np.fft.irfftn(np.abs(np.fft.rfftn(np.ones(v.shape), s=shape, axes=(0, 1, 2))) ** 2, s=shape,
                          axes=(0, 1, 2))
    rho = acov / np.maximum(pairs, 1.0)
    rho /= rho[0, 0, 0]
    out = []
    for ax in range(3):
        line = np.moveaxis(rho, ax, 0)[: v.shape[ax] // 2, 0, 0]
        j = int(np.flatnonzero(line < 1 / math.e)[0])
        out.append(j - 1 + (line[j - 1] - 1 / math.e) / (line[j - 1] - line[j]))
    return out
