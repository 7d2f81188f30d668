"""Mean rigid translation on the coarsest level (paper section 5.1, first step).

Phase correlation of the reference ROI with the same box of the deformed image gives the
integer translation however large it is (up to half the box), which Gauss–Newton cannot
do from zero once the shift exceeds the texture's correlation length; the engine then
refines it to sub-voxel precision with the rigid-body restriction of the C8 system.
This runs as one task on a worker: the client never reads voxels.
"""

from __future__ import annotations

import numpy as np

from ..io.handles import ArrayRef

#: largest box edge (voxels) used for phase correlation; a central sub-box beyond that
#: (enough for a mean translation, and it bounds the task's memory to ~100 MB)
MAX_EDGE = 128


def _central_box(roi: tuple[slice, slice, slice]) -> tuple[slice, slice, slice]:
    out = []
    for s in roi:
        n = s.stop - s.start
        if n > MAX_EDGE:
            start = s.start + (n - MAX_EDGE) // 2
            out.append(slice(start, start + MAX_EDGE))
        else:
            out.append(s)
    return tuple(out)


def phase_correlation(f: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Translation ``t`` such that ``g(x) ≈ f(x - t)``, i.e. ``f(X) = g(X + t)``.

    Parameters
    ----------
    f, g : ndarray, shape (nz, ny, nx)
        Two boxes of the same shape.

    Returns
    -------
    t : ndarray, shape (3,), float64, voxels
        Integer peak refined by a parabola through its neighbours on each axis.
    """
    hann = [np.hanning(n + 2)[1:-1].astype(np.float32) for n in f.shape]
    window = hann[0][:, None, None] * hann[1][None, :, None] * hann[2][None, None, :]
    F = np.fft.rfftn((f - f.mean()) * window)
    G = np.fft.rfftn((g - g.mean()) * window)
    del window
    cross = G * np.conj(F)
    # a floor above zero: a constant block (all-zero spectrum) gives no peak, not 0/0 and a
    # RuntimeWarning line before the refusal that follows ("the reference is constant")
    cross /= np.maximum(np.abs(cross), max(1e-12 * float(np.abs(cross).max()), np.finfo(np.float32).tiny))
    corr = np.fft.irfftn(cross, s=f.shape, axes=(0, 1, 2))
    peak = np.array(np.unravel_index(np.argmax(corr), corr.shape))
    t = peak.astype(np.float64)
    for axis, n in enumerate(f.shape):
        if n < 3:
            continue
        idx_m, idx_p = list(peak), list(peak)
        idx_m[axis] = (peak[axis] - 1) % n
        idx_p[axis] = (peak[axis] + 1) % n
        c_m, c_0, c_p = corr[tuple(idx_m)], corr[tuple(peak)], corr[tuple(idx_p)]
        denom = c_m - 2 * c_0 + c_p
        if denom < 0:
            t[axis] += float(np.clip(0.5 * (c_m - c_p) / denom, -0.5, 0.5))
    sizes = np.array(f.shape)
    return (t + sizes / 2) % sizes - sizes / 2


def translation_task(f_ref: ArrayRef, g_ref: ArrayRef, roi: tuple[slice, slice, slice]) -> np.ndarray:
    """Task: read the ROI box of ``f`` and the same box of ``g``, return ``t`` (voxels)."""
    box = _central_box(roi)
    f = f_ref.read(box).astype(np.float32)
    g = np.zeros(f.shape, dtype=np.float32)
    # the same box of g, clipped to g (zeros where g does not reach)
    src, dst = [], []
    for s, n in zip(box, g_ref.shape):
        a, b = max(s.start, 0), min(s.stop, n)
        if b <= a:
            return np.zeros(3)
        src.append(slice(a, b))
        dst.append(slice(a - s.start, b - s.start))
    g[tuple(dst)] = g_ref.read(tuple(src))
    return phase_correlation(f, g)
