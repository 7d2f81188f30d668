"""Local CT imaging: what a reconstruction does to a phase map, at a cost per voxel that does
not grow with the slice size (``--imaging local``).

The slice-by-slice simulation of :mod:`chunkdic.synth.ctsim` (projections, noise, filtered
back-projection) costs ``O(N)`` per voxel (``angles ∝ N``): a 2048³ pair would take about
two days on 2 cores. This model keeps what DVC sees of it, measured on the FBP at 128²
(docs/synthetic.md, "Local imaging"), and computes each voxel from a small neighbourhood:

- **System blur (PSF)**: the FBP of a noise-free phase map (Joseph projection and linear
  back-projection, two linear interpolations) is the map seen through a radial transfer
  function close to a Gaussian of std ``PSF_SIGMA`` = 0.53 voxel in the slice (measured
  MTF 0.83 / 0.54 / 0.16 at 0.18 / 0.33 / 0.58 cycle per voxel; the Gaussian: 0.84 / 0.54 /
  0.15). Slices are independent (no blur along z), as in the FBP model.
- **Reconstruction noise**: FBP noise is ramp-filtered white projection noise; its
  power spectrum in a slice is ``∝ |k| exp(-4 pi^2 NOISE_SIGMA^2 k^2)`` (the ramp times the
  interpolations' roll-off, fitted on the FBP's measured spectrum: ``NOISE_SIGMA`` = 0.41),
  independent between slices. Here: white Gaussian noise hashed from (scan, z, y, x)
  filtered in the slice by a compact kernel (radius ``NOISE_HALO``) of that amplitude
  response, normalised so that its output std is exactly ``noise`` (a fraction of the phase
  contrast, the meaning ``--noise`` has for the FBP imaging). Beyond ``|k| = 0.5`` (outside
  the detector's Nyquist disc) the power falls further by ``exp(-(|k| - 0.5) / 0.15)``, as
  measured on the FBP. Reference and deformed scans use independent streams.

Chunk independence: the slice plane is cut into a fixed global grid of ``TILE`` x ``TILE``
tiles; a tile's values are computed from its own halo-extended patch, slice by slice (one
2-D FFT of a fixed size each), whatever Dask block asks for it; a block computes the tiles
it overlaps and crops. The values are hence a function of the seed, the scan and the voxel
index alone: bit for bit the same for any chunking (tested). Both kernels are compact
(support within the halo), so the tiles' circular convolutions are the linear ones and
tiles join without seams.

Not modelled here (use the FBP imaging): streaks, the anisotropy of FBP noise along the
projection angles, rings, detector blur, other filters, a different number of angles.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit

from .boolean import hash3, stream_key

__all__ = ["PSF_SIGMA", "NOISE_SIGMA", "TILE", "noise_kernel", "psf_kernel", "local_block"]

PSF_SIGMA = 0.60     # voxel: in-plane transfer function exp(-2 pi^2 s^2 k^2) matched to the FBP's measured one (128^2, ramp)
NOISE_SIGMA = 0.41   # voxel: roll-off of the FBP noise spectrum |k| exp(-4 pi^2 s^2 k^2)
CORNER_DECAY = 0.15  # cycle/voxel: e-folding of the noise power beyond |k| = 0.5
TILE = 128           # in-plane tile edge of the global grid the values are computed on
PSF_HALO = 6         # radius of the compact PSF kernel
NOISE_HALO = 16      # radius of the compact noise kernel
CH_LOCAL_REF, CH_LOCAL_DEF = 41, 42
_OFFSET = 1 << 24    # global indices shifted positive before hashing (halo at -16)
_INV32 = 1.0 / (1 << 32)
_S32 = np.uint64(32)
_MASK32 = np.uint64(0xFFFFFFFF)


@njit(nogil=True, cache=True)
def _white(key, z, y0, x0, out):
    """out[j, i] = standard normal hashed from (z, y0 + j, x0 + i) and ``key`` (Box-Muller)."""
    for j in range(out.shape[0]):
        for i in range(out.shape[1]):
            h = hash3(z, y0 + j, x0 + i, key)
            u1 = (np.float64(h >> _S32) + 1.0) * _INV32  # (0, 1]
            u2 = np.float64(h & _MASK32) * _INV32
            out[j, i] = math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)


def _compact_kernel(amp: np.ndarray, halo: int) -> np.ndarray:
    """Kernel of radius ``halo`` with (about) the radial amplitude response ``amp`` (512² DFT
    grid): the ideal kernel, cut with a cosine taper over its outer half."""
    m = amp.shape[0]
    ker = np.fft.fftshift(np.real(np.fft.ifft2(amp)))
    c = m // 2
    ker = ker[c - halo:c + halo + 1, c - halo:c + halo + 1]
    yy, xx = np.mgrid[-halo:halo + 1, -halo:halo + 1]
    r = np.hypot(yy, xx) / halo
    taper = np.where(r <= 0.5, 1.0, np.where(r < 1.0, np.cos(math.pi * (r - 0.5)) ** 2, 0.0))
    return ker * taper


def _radial_frequency(m: int = 512) -> np.ndarray:
    f = np.fft.fftfreq(m)
    return np.hypot(f[:, None], f[None, :])


@functools.lru_cache(maxsize=4)
def noise_kernel(halo: int = NOISE_HALO, sigma: float = NOISE_SIGMA) -> np.ndarray:
    """Compact in-plane kernel ``(2 halo + 1)²`` whose power response is ``∝ |k| exp(-4 pi² sigma² k²)``.

    The ideal kernel (amplitude ``sqrt(|k|) exp(-2 pi² sigma² k²)``) decays as ``r^-2.5``;
    it is cut to radius ``halo`` with a cosine taper over its outer half, then scaled so
    that ``sum(kernel²) = 1``: filtered unit white noise has std 1 exactly.
    """
    k = _radial_frequency()
    amp = np.sqrt(k) * np.exp(-2 * math.pi ** 2 * sigma ** 2 * k ** 2)
    # beyond the detector's Nyquist disc (|k| > 0.5, the slice's corners in frequency) the
    # FBP's noise power falls by a further exp(-(|k| - 0.5) / 0.15) (measured: 0.61, 0.43,
    # 0.33 of the law at 0.575, 0.625, 0.675)
    amp = amp * np.exp(-np.maximum(k - 0.5, 0.0) / (2 * CORNER_DECAY))
    ker = _compact_kernel(amp, halo)
    return ker / math.sqrt(float(np.sum(ker ** 2)))


@functools.lru_cache(maxsize=4)
def psf_kernel(halo: int = PSF_HALO, sigma: float = PSF_SIGMA) -> np.ndarray:
    """In-plane PSF ``(2 halo + 1)²`` of radial transfer function ``exp(-2 pi² sigma² k²)``, sum 1.

    Built from the transfer function (not by sampling a Gaussian of std ``sigma``: at
    ``sigma`` ~ 0.5 voxel the sampled Gaussian passes twice as much at Nyquist).
    """
    k = _radial_frequency()
    ker = _compact_kernel(np.exp(-2 * math.pi ** 2 * sigma ** 2 * k ** 2), halo)
    return ker / float(np.sum(ker))


@functools.lru_cache(maxsize=8)
def _spectrum(which: str, size: int) -> np.ndarray:
    """rfft2 of a kernel embedded (centred at 0, wrapped) in a ``size²`` grid."""
    ker = noise_kernel() if which == "noise" else psf_kernel()
    h = ker.shape[0] // 2
    grid = np.zeros((size, size))
    grid[:2 * h + 1, :2 * h + 1] = ker
    grid = np.roll(grid, (-h, -h), axis=(0, 1))
    return np.fft.rfft2(grid)


def _convolve_tile(patch: np.ndarray, which: str, halo: int) -> np.ndarray:
    """Linear convolution of a ``(TILE + 2 halo)²`` patch with the kernel, interior ``TILE²``."""
    from scipy import fft

    spec = fft.rfft2(patch, workers=1) * _spectrum(which, patch.shape[0])
    return fft.irfft2(spec, s=patch.shape, workers=1)[halo:halo + TILE, halo:halo + TILE]


def local_tile(params, field, noise: float, seed: int, which: str, z: int, ty: int, tx: int) -> np.ndarray:
    """One slice of one tile, phase units: blurred phase map plus reconstruction noise.

    Returns
    -------
    ndarray, shape (TILE, TILE), float64; tile ``(ty, tx)`` covers ``y in [ty TILE, (ty+1) TILE)``.
    """
    from .microstructure import render_phantom

    y0, x0 = ty * TILE, tx * TILE
    n = TILE + 2 * PSF_HALO
    mu = render_phantom(params, (1, n, n), origin=(z, y0 - PSF_HALO, x0 - PSF_HALO), field=field)[0]
    v = _convolve_tile(mu.astype(np.float64), "psf", PSF_HALO)
    if noise > 0:
        key = stream_key(seed, CH_LOCAL_REF if which == "reference" else CH_LOCAL_DEF)
        w = np.empty((TILE + 2 * NOISE_HALO,) * 2)
        _white(key, z + _OFFSET, y0 - NOISE_HALO + _OFFSET, x0 - NOISE_HALO + _OFFSET, w)
        v += noise * _convolve_tile(w, "noise", NOISE_HALO)
    return v


def local_block(params, field, noise: float, seed: int, which: str, box) -> np.ndarray:
    """Voxels ``box = ((z0, z1), (y0, y1), (x0, x1))`` of one scan, phase units (float64).

    Computes every tile the box overlaps, slice by slice, and crops: the values do not
    depend on the box (module docstring).
    """
    (z0, z1), (y0, y1), (x0, x1) = box
    out = np.empty((z1 - z0, y1 - y0, x1 - x0))
    for ty in range(y0 // TILE, -(-y1 // TILE)):
        for tx in range(x0 // TILE, -(-x1 // TILE)):
            ya, yb = max(y0, ty * TILE), min(y1, (ty + 1) * TILE)
            xa, xb = max(x0, tx * TILE), min(x1, (tx + 1) * TILE)
            for z in range(z0, z1):
                t = local_tile(params, field, noise, seed, which, z, ty, tx)
                out[z - z0, ya - y0:yb - y0, xa - x0:xb - x0] = t[ya - ty * TILE:yb - ty * TILE,
                                                                  xa - tx * TILE:xb - tx * TILE]
    return out
