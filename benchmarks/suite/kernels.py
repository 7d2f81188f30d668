"""The per-block kernels on one core: the M and b passes (paper section 3, M_ij and b_i)."""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
import scipy.ndimage as ndi  # noqa: E402

from .common import textured_volume  # noqa: E402

BLOCK = 96
PAD = 16


class Kernels:
    """One 96³ block inside a 128³ volume with its one-voxel halo; a smooth nodal field."""

    params = ([16, 8],)
    param_names = ["ell"]
    repeat = (1, 5, 20.0)
    timeout = 300

    def setup(self, ell):
        from chunkdic.kernels.jit import warmup
        from chunkdic.kernels.window import g_window

        n = BLOCK
        shape = (n + 2 * PAD,) * 3
        vol = textured_volume(shape)
        self.f = vol[PAD - 1:PAD + n + 1, PAD - 1:PAD + n + 1, PAD - 1:PAD + n + 1].copy()
        g = np.roll(vol, (1, -2, 1), axis=(0, 1, 2))
        self.shape, self.c0, self.core, self.lo = shape, (PAD,) * 3, (n,) * 3, (1, 1, 1)
        ne = n // ell + 1
        grid = np.meshgrid(*[np.linspace(-1, 1, ne)] * 3, indexing="ij")
        self.u = np.stack([1.3 + 0.8 * grid[1], -2.2 + 0.5 * grid[0] * grid[2], 0.7 - 0.6 * grid[2]])
        coef = ndi.spline_filter(g, order=3, mode="mirror", output=np.float32)
        win = g_window(self.c0, self.core, self.u, shape, interpolation="cubic", halo=12)
        self.coef, self.g_origin = coef[win], tuple(w.start for w in win)
        warmup()

    def time_m_pass(self, ell):
        from chunkdic.kernels.m import m_block

        m_block(self.f, self.lo, self.lo, ell)

    def time_b_pass_cubic(self, ell):
        from chunkdic.kernels.b import b_block

        b_block(self.f, self.lo, self.lo, ell, self.u, self.c0, self.coef, self.g_origin, self.shape,
                interpolation="cubic", prefiltered=True)
