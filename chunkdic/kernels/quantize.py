"""Float data onto a 16-bit grid and back, in one sweep (numba).

The scratch stores keep prepared scans as ``uint16`` on a grid ``offset + step · q``
(:func:`chunkdic.passes.prefilter.prepared_grid`). Written as NumPy expressions, a block's
quantisation made four to six float temporaries of the region (a 130³ block of the haloed
``f``: 8.7 ms in float64, then 3 ms to read it back as float32), about a tenth of the ``M``
pass's time per block; one loop makes both the stored values and the float32 ones the
passes will read back, with the same arithmetic, so the stored values are unchanged.
"""

from __future__ import annotations

import numpy as np

from .interp import jit

__all__ = ["quantize_u16"]


def quantize_u16(data: np.ndarray, offset: float, step: float, *, wide: bool) -> tuple[np.ndarray, np.ndarray]:
    """``data`` on the grid ``offset + step · q``: ``(q, back)``.

    Parameters
    ----------
    data : ndarray, 3-D, float32 or any real dtype
    offset, step : float
        The grid (``step`` > 0).
    wide : bool, keyword-only
        Round ``(data - offset) / step`` computed in float64 (the haloed ``f``,
        :class:`chunkdic.passes.haloed.HaloedBlocks`), else ``(data - offset) · (1 / step)`` in
        float32 (the prepared ``g``, :func:`chunkdic.passes.prefilter.quantize`).

    Returns
    -------
    q : ndarray, data's shape, uint16
        Rounded to the nearest (half to even) and clipped to ``[0, 65535]``.
    back : ndarray, data's shape, float32
        ``offset + step · q`` in float32, as :func:`chunkdic.passes.prefilter.dequantize` reads it.

    >>> q, back = quantize_u16(np.array([[[-1.0, 0.24, 0.26, 1e9]]], np.float32), 0.0, 0.5, wide=True)
    >>> q.tolist(), back.tolist()
    ([[[0, 0, 1, 65535]]], [[[0.0, 0.0, 0.5, 32767.5]]])
    """
    src = np.ascontiguousarray(data)
    q = np.empty(src.shape, np.uint16)
    back = np.empty(src.shape, np.float32)
    _quantize(src.reshape(-1), float(offset), float(step), bool(wide), q.reshape(-1), back.reshape(-1))
    return q, back


@jit
def _quantize(x, offset, step, wide, q, back):
    o32 = np.float32(offset)
    s32 = np.float32(step)
    inv32 = np.float32(1.0 / step)
    for i in range(x.size):
        if wide:
            v = np.rint((np.float64(x[i]) - offset) / step)
        else:
            # the float32 product, rounded in float64 (exact: numba's float32 rint is slow)
            v = np.rint(np.float64((np.float32(x[i]) - o32) * inv32))
        if v < 0.0:
            v = 0.0
        elif v > 65535.0:
            v = 65535.0
        k = np.uint16(v)
        q[i] = k
        back[i] = np.float32(k) * s32 + o32
