"""The autocorrelation length of grey levels: lag sums of a block, and the 1/e lag of their total.

The size of a texture's features, as pyALDVC's texture analysis reports it: per axis, the
lag at which the autocorrelation of the grey levels (mean removed) first falls below 1/e,
linearly interpolated between lags. A task reduces each sampled block of a scan to its lag
sums (:func:`lag_sums`: ``Σ f(x) f(x + k)``, ``Σ f(x)``, ``Σ f(x + k)`` and the pair count
per axis and lag); the sums of every block are added and read once
(:func:`autocorrelation_length`), so that the mean removed is the blocks' common mean and the
variation between blocks counts as texture, as it does in the whole scan. Used by the
texture report (:mod:`chunkdic.passes.texture`) and by the start of the regularisation
length (:func:`chunkdic.method.length.start_length`).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["lag_sums", "autocorrelation_length"]


def lag_sums(f: np.ndarray, max_lag: int) -> np.ndarray:
    """Per axis and lag ``k`` the sums over the pairs of voxels inside ``f`` that ``k`` apart.

    Parameters
    ----------
    f : ndarray, shape (nz, ny, nx), any real dtype, grey levels
    max_lag : int
        Largest lag, voxels (clipped to each axis's length minus one).

    Returns
    -------
    ndarray, shape (3, 4, max_lag + 1), float64
        ``[axis, 0, k]`` ``Σ f(x) f(x + k)`` (by a zero-padded FFT along the axis),
        ``[axis, 1, k]`` ``Σ f(x)``, ``[axis, 2, k]`` ``Σ f(x + k)``, ``[axis, 3, k]`` the
        number of pairs; zero beyond the axis's length.
    """
    f = np.asarray(f, dtype=np.float64)
    out = np.zeros((3, 4, max_lag + 1))
    for ax in range(3):
        n = f.shape[ax]
        k = min(max_lag, n - 1)
        spec = np.fft.rfft(f, n=2 * n, axis=ax)
        prod = np.fft.irfft(np.abs(spec) ** 2, n=2 * n, axis=ax)
        other = tuple(a for a in range(3) if a != ax)
        out[ax, 0, :k + 1] = prod.sum(axis=other)[:k + 1]
        plane = f.sum(axis=other)
        c = np.concatenate([[0.0], np.cumsum(plane)])
        lags = np.arange(k + 1)
        out[ax, 1, :k + 1] = c[n - lags]  # f(x), x < n - k
        out[ax, 2, :k + 1] = c[n] - c[lags]  # f(x + k)
        out[ax, 3, :k + 1] = (n - lags) * (f.size // n)
    return out


def autocorrelation_length(lags: np.ndarray) -> tuple[float, float, float]:
    """Per axis, the lag where the autocorrelation of the (summed) :func:`lag_sums` first
    falls below 1/e.

    Parameters
    ----------
    lags : ndarray, shape (3, 4, K + 1), float64
        :func:`lag_sums` of one block, or their sum over blocks.

    Returns
    -------
    tuple of 3 float, voxels
        ``(z, y, x)``, linear between lags; ``inf`` where it stays above 1/e up to lag ``K``,
        NaN for constant grey levels.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.arange(240)
    >>> f = np.broadcast_to(np.cos(2 * np.pi * x / 24), (4, 4, 240))  # cos(2πk/24) falls to 1/e at 4.55
    >>> [round(a, 2) for a in autocorrelation_length(lag_sums(f, 8))]
    [inf, inf, 4.49]
    """
    out = []
    for s in np.asarray(lags, dtype=np.float64):
        ok = s[3] > 0
        n = s[3][ok]
        cov = s[0][ok] / n - (s[1][ok] / n) * (s[2][ok] / n)
        if not cov[0] > 0:
            out.append(math.nan)
            continue
        rho = cov / cov[0]
        below = np.flatnonzero(rho < 1.0 / math.e)
        if below.size == 0:
            out.append(math.inf)
            continue
        j = int(below[0])
        out.append(float(j - 1 + (rho[j - 1] - 1.0 / math.e) / (rho[j - 1] - rho[j])))
    return tuple(out)
