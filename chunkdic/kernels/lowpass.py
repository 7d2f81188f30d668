"""Gaussian low-pass and cubic B-spline prefilter of a window, one sweep per axis (numba).

Both filters are separable and linear, so along each axis the Gaussian (a finite impulse
response, ``mode="mirror"``, truncated at ``TRUNCATE`` σ as :func:`scipy.ndimage.gaussian_filter`)
and the B-spline prefilter (the recursive filter of :func:`scipy.ndimage.spline_filter1d`,
``order=3, mode="mirror"``: gain 6, pole ``z = √3 − 2``, causal then anti-causal) can be
applied line after line while the line is in cache: three sweeps of the window instead of
scipy's six (three per filter), and the lines along z and y are filtered a whole plane at
a time so that the inner loops run over contiguous x (vectorised). Measured on 192³
windows (one thread): 2.6× faster than scipy's two calls (:mod:`chunkdic.passes.prefilter`
chooses this kernel; docs/engine.md, "Image preparation").

Results equal scipy's to float32 round-off: the causal initialisation of the recursive
filter sums the mirrored line over ``HORIZON`` samples (``|z|^HORIZON < 1e-9``) where scipy
sums the whole line.
"""

from __future__ import annotations

import math

import numpy as np

from .interp import jit, jit_sums

#: the Gaussian is truncated at this many standard deviations (scipy's ``truncate``)
TRUNCATE = 4.0
#: pole of the cubic B-spline prefilter
POLE = math.sqrt(3.0) - 2.0
#: samples of the causal initial sum (|POLE|^HORIZON < 1e-9: below float32 round-off)
HORIZON = 16


def gaussian_weights(sigma: float) -> np.ndarray:
    """The normalised 1-D Gaussian taps of scipy.ndimage (radius ``int(TRUNCATE σ + 0.5)``), float64."""
    radius = int(TRUNCATE * float(sigma) + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (x / float(sigma)) ** 2)
    return w / w.sum()


def lowpass_bspline(window: np.ndarray, sigma: float, cubic: bool) -> np.ndarray:
    """Low-pass (``sigma`` > 0) and, if ``cubic``, B-spline coefficients of a 3-D window.

    Parameters
    ----------
    window : ndarray, shape (nz, ny, nx), any real dtype
        Grey levels; the boundary of every axis is mirrored (``d c b | a b c d | c b a``).
    sigma : float
        Gaussian standard deviation, voxels; 0: no low-pass.
    cubic : bool
        Also apply the cubic B-spline prefilter (interpolation coefficients).

    Returns
    -------
    ndarray, shape (nz, ny, nx), float32
    """
    out = np.array(window, dtype=np.float32, order="C", copy=True)
    if out.size == 0:
        return out
    taps = gaussian_weights(sigma).astype(np.float32) if sigma > 0 else np.ones(1, np.float32)
    _filter_axes(out, taps, sigma > 0, bool(cubic), np.float32(POLE))
    return out


@jit
def _mirror(i, n):
    """Index ``i`` reflected into ``[0, n)`` without repeating the edge sample (scipy "mirror")."""
    if n == 1:
        return 0
    period = 2 * n - 2
    i = abs(i) % period
    return period - i if i >= n else i


@jit_sums
def _filter_axes(a, taps, lowpass, cubic, z):
    nz, ny, nx = a.shape
    r = (taps.size - 1) // 2
    # along z: whole (y, x) planes at a time
    if lowpass and nz > 1:
        src = a.copy()
        for i in range(nz):
            for y in range(ny):
                for x in range(nx):
                    a[i, y, x] = 0.0
            for t in range(taps.size):
                k = _mirror(i + t - r, nz)
                w = taps[t]
                for y in range(ny):
                    for x in range(nx):
                        a[i, y, x] += w * src[k, y, x]
    if cubic and nz > 1:
        _recursive_planes(a, z)
    # along y: for each z plane, whole x rows at a time
    line = np.empty((ny, nx), np.float32)
    for i in range(nz):
        plane = a[i]
        if lowpass and ny > 1:
            for j in range(ny):
                for x in range(nx):
                    line[j, x] = plane[j, x]
            for j in range(ny):
                for x in range(nx):
                    plane[j, x] = 0.0
                for t in range(taps.size):
                    k = _mirror(j + t - r, ny)
                    w = taps[t]
                    for x in range(nx):
                        plane[j, x] += w * line[k, x]
        if cubic and ny > 1:
            _recursive_rows(plane, z)
    # along x: one contiguous row at a time
    row = np.empty(nx + 2 * r, np.float32)
    for i in range(nz):
        for j in range(ny):
            v = a[i, j]
            if lowpass and nx > 1:
                for x in range(-r, nx + r):
                    row[x + r] = v[_mirror(x, nx)]
                for x in range(nx):
                    s = np.float32(0.0)
                    for t in range(taps.size):
                        s += taps[t] * row[x + t]
                    v[x] = s
            if cubic and nx > 1:
                _recursive_line(v, z)


@jit
def _recursive_line(c, z):
    """The cubic B-spline prefilter of one line in place (mirror boundary)."""
    n = c.size
    for i in range(n):
        c[i] *= 6.0
    # causal initial value: the mirrored line's sum weighted by z^k
    s = c[0]
    zk = z
    for k in range(1, HORIZON):
        s += zk * c[_mirror(k, n)]
        zk *= z
    c[0] = s
    for i in range(1, n):
        c[i] += z * c[i - 1]
    c[n - 1] = (z / (z * z - 1.0)) * (c[n - 1] + z * c[n - 2])
    for i in range(n - 2, -1, -1):
        c[i] = z * (c[i + 1] - c[i])


@jit
def _recursive_rows(p, z):
    """The prefilter along the first axis of a 2-D array ``p`` (ny, nx), rows at a time."""
    n, nx = p.shape
    for i in range(n):
        for x in range(nx):
            p[i, x] *= 6.0
    init = np.zeros(nx, np.float32)
    zk = np.float32(1.0)
    for k in range(HORIZON):
        m = _mirror(k, n)
        for x in range(nx):
            init[x] += zk * p[m, x]
        zk *= z
    for x in range(nx):
        p[0, x] = init[x]
    for i in range(1, n):
        for x in range(nx):
            p[i, x] += z * p[i - 1, x]
    g = z / (z * z - 1.0)
    for x in range(nx):
        p[n - 1, x] = g * (p[n - 1, x] + z * p[n - 2, x])
    for i in range(n - 2, -1, -1):
        for x in range(nx):
            p[i, x] = z * (p[i + 1, x] - p[i, x])


@jit
def _recursive_planes(a, z):
    """The prefilter along the first axis of a 3-D array, (y, x) planes at a time."""
    for j in range(a.shape[1]):
        _recursive_rows(a[:, j, :], z)
