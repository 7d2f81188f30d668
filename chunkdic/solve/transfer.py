"""What a measured C8 field keeps of a sine: the transfer of the C8 basis and of the penalty.

A sine of period ``T`` imposed on the specimen comes out of a correlation attenuated twice:
by the C8 basis (the L2 projection onto trilinear elements of edge ``ℓ``, read between the
nodes as a viewer shows it: :func:`c8_ratio`, derived in docs/engine.md, "Spatial
resolution") and by the regularisation, whose plane-wave normalisation penalises it
``(ℓ_reg / T)^4`` times its image term (:func:`chunkdic.solve.regularizer.plane_wave_weight`),
so that it keeps ``1 / (1 + (ℓ_reg / T)^4)`` of it. :func:`nominal_l10` is the period at
which the product first reaches 0.9 (the DIC Challenge 2.0 definition of the spatial
resolution). It is a lower bound: the low-pass of the scans and the noise attenuate
further; ``chunkdic resolution`` measures the real one on a star (measured 2.0-3.1× the
length where this model gives about 1.7-2×).
"""

from __future__ import annotations


import numpy as np

#: the amplitude ratio that defines the spatial resolution (DIC Challenge 2.0)
THRESHOLD = 0.9


def c8_ratio(period, ell):
    """Amplitude ratio of the unregularised C8 field of a sine of ``period``, read between the nodes.

    The L2 projection of ``sin(k z)`` onto linear elements of edge ``ell`` (a trilinear C8
    field of a function of ``z`` alone is the 1-D projection along z) has nodal values
    ``G(θ) sin(k z_j)`` with ``θ = k ℓ`` and ``G = 3 sinc²(θ/2) / (2 + cos θ)``; its
    interpolant's component at ``k`` is ``sinc²(θ/2)`` of that (docs/engine.md,
    "Spatial resolution"): ``R(θ) = 3 sinc⁴(θ/2) / (2 + cos θ)``, ``sinc x = sin x / x``.

    Parameters
    ----------
    period : float or ndarray, voxels
    ell : float, voxels

    Returns
    -------
    float or ndarray
    """
    th = 2.0 * np.pi * ell / np.asarray(period, np.float64)
    return 3.0 * np.sinc(th / (2.0 * np.pi)) ** 4 / (2.0 + np.cos(th))


def c8_l10(ell: float) -> float:
    """The period at which :func:`c8_ratio` equals 0.9: ``2.767 ℓ`` (θ = 2.2704)."""
    th = _root(lambda t: 3.0 * np.sinc(t / (2 * np.pi)) ** 4 / (2.0 + np.cos(t)) - THRESHOLD, 0.1, 3.0)
    return float(2.0 * np.pi * ell / th)


def _root(fn, lo: float, hi: float) -> float:
    """The root of ``fn`` between ``lo`` and ``hi`` (of opposite signs there), by bisection
    to the last bit: scipy's ``brentq`` did the same, but importing ``scipy.optimize`` for it
    cost 0.1 s of every run's summary (``nominal_l10``)."""
    f_lo = fn(lo)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        f_mid = fn(mid)
        if (f_mid < 0) == (f_lo < 0):
            lo, f_lo = mid, f_mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def nominal_l10(ell: float, length: float | None) -> float:
    """The spatial resolution ``l10 %`` of a C8 field of element edge ``ell`` regularised over
    ``length`` (both voxels of one level; ``None`` or 0: unregularised), from the two
    transfers of the module: the period at which ``c8_ratio(T) / (1 + (length / T)^4)``
    rises through 0.9. Unregularised: :func:`c8_l10`; a long length: ``9^(1/4) length``.

    Examples
    --------
    >>> round(nominal_l10(8, None) / 8, 3)
    2.767
    >>> round(nominal_l10(8, 800) / 800, 3)
    1.732
    """
    if not length:
        return c8_l10(ell)

    def short(period):
        return float(c8_ratio(period, ell)) / (1.0 + (length / period) ** 4) - THRESHOLD

    lo = c8_l10(ell)  # neither transfer reaches 0.9 below the C8 one
    hi = max(lo, 9.0 ** 0.25 * length) * 4.0
    return _root(short, lo, hi) if short(lo) < 0 else lo


__all__ = ["THRESHOLD", "c8_ratio", "c8_l10", "nominal_l10"]
