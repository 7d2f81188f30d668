"""CT imaging of a phase map, slice by slice: projections, noise, rings, FBP, grey change.

Each z-slice is one parallel-beam CT slice (a row of detector pixels):

1. forward projection (Radon) of the slice's attenuation map with Joseph's method (linear
   interpolation along the ray, one sample per row or column) over ``angles`` angles in
   ``[0, pi)``, default the Nyquist number ``ceil(pi/2 * max(ny, nx))``; the detector
   (unit pixels, centred on the slice centre) covers the slice diagonal;
2. Gaussian noise added to every projection sample (homoscedastic, hashed from the scan,
   slice, angle and detector pixel: the reference and the deformed scans get independent
   noise), optional Gaussian detector blur of std ``blur`` pixels applied after the noise
   (scintillator light spread correlates the quantum noise), optional ring offsets
   (one value per detector pixel and row, the same in both scans: rings belong to the
   detector);
3. filtered back-projection: Kak & Slaney's discrete ramp filter (zero padded to at least
   twice the detector), optionally times a Hann window (``filter="hann"``), then linear
   interpolation back-projection, ``(pi / angles) * sum``.

Noise calibration: ``noise`` is the standard deviation of the reconstruction noise as a
fraction of the phase contrast (phase units: contrast 1). With ``g`` the effective
detector kernel (filter x blur) the back-projection of white projection noise of std
``sigma_p`` has, averaged over pixels (linear interpolation at uniformly spread fractional
positions), variance ``sigma_p^2 * pi^2 / angles * (2 c0 + c1) / 3`` with
``c0 = sum g^2`` and ``c1 = sum g[i] g[i+1]`` (:func:`noise_gain`); ``sigma_p`` follows.
Rings are calibrated likewise (``rings`` = RMS of the ring pattern over the slice, as a
fraction of the contrast) by reconstructing a fixed set of random ring patterns
(:func:`ring_gain`).

The back-projector and the Joseph projector are Numba kernels (serial, ``nogil``), chosen
over scikit-image's ``radon``/``iradon``, 10-15x (projection) and 3-5x (FBP) slower at
128^2 and 300^2 slices (measured in docs/synthetic.md).
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass

import numpy as np
from numba import njit

from ..errors import InputError
from .boolean import hash3, stream_key

__all__ = [
    "Imaging",
    "GreyChange",
    "Geometry",
    "radon",
    "fbp",
    "noise_gain",
    "ring_gain",
    "reconstruct_slice",
    "FILTERS",
    "MODES",
]

FILTERS = ("ramp", "hann")
MODES = ("fbp", "local")
CH_NOISE_REF, CH_NOISE_DEF, CH_RINGS = 31, 32, 33
_INV32 = 1.0 / (1 << 32)
_S32 = np.uint64(32)
_MASK32 = np.uint64(0xFFFFFFFF)


def _number(v, name) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        f = float("nan")
    if isinstance(v, bool) or not math.isfinite(f):
        raise InputError(f"{name} must be a finite number, got {v!r}")
    return f


@dataclass(frozen=True)
class Imaging:
    """CT imaging settings.

    Parameters
    ----------
    noise : float
        Std of the reconstruction noise as a fraction of the phase contrast (>= 0),
        default 0.02.
    angles : int or None
        Number of projections over 180 degrees; ``None``: Nyquist, ``ceil(pi/2 n)``
        with ``n = max(ny, nx)``.
    filter : {"ramp", "hann"}
        Reconstruction filter: Ram-Lak ramp (default, sharpest) or ramp x Hann.
    blur : float
        Std of the Gaussian detector blur, detector pixels (>= 0), default 0.
    rings : float
        RMS of the ring pattern as a fraction of the phase contrast (>= 0), default 0.
    mode : {"fbp", "local"}
        ``"fbp"`` (default): projections, noise and filtered back-projection, slice by
        slice (cost per voxel ``∝ N``). ``"local"``: the local stand-in of
        :mod:`chunkdic.synth.ctlocal` (in-plane PSF and ramp-spectrum noise of the same
        std, cost per voxel independent of ``N``); ``angles``, ``filter``, ``blur`` and
        ``rings`` are FBP settings and refused with it.
    """

    noise: float = 0.02
    angles: int | None = None
    filter: str = "ramp"
    blur: float = 0.0
    rings: float = 0.0
    mode: str = "fbp"

    def __post_init__(self):
        for name in ("noise", "blur", "rings"):
            v = _number(getattr(self, name), name)
            if v < 0:
                raise InputError(f"{name} must be >= 0, got {v!r}")
            object.__setattr__(self, name, v)
        if self.angles is not None:
            a = _number(self.angles, "angles")
            if a < 2 or a != int(a):
                raise InputError(f"angles must be an integer >= 2, got {self.angles!r}")
            object.__setattr__(self, "angles", int(a))
        if self.filter not in FILTERS:
            raise InputError(f"filter must be one of {FILTERS}, got {self.filter!r}")
        if self.mode not in MODES:
            raise InputError(f"imaging must be one of {MODES}, got {self.mode!r}")
        if self.mode == "local":
            fbp_only = [n for n, v in (("angles", self.angles is not None), ("filter", self.filter != "ramp"),
                                       ("blur", self.blur != 0), ("rings", self.rings != 0)) if v]
            if fbp_only:
                raise InputError(f"{', '.join(fbp_only)}: only with the FBP imaging (imaging='fbp'), "
                                 "not with imaging='local'")

    def to_json(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class GreyChange:
    """Grey-level change of the deformed scan, applied after reconstruction.

    ``v' = gain * v + offset + drift * (z / (nz - 1) - 1/2)`` in phase units (contrast 1,
    pores 0): ``offset`` is a fraction of the phase contrast, ``drift`` the change over
    the scan height (centred: the mean level is unchanged).
    """

    gain: float = 1.0
    offset: float = 0.0
    drift: float = 0.0

    def __post_init__(self):
        for name in ("gain", "offset", "drift"):
            object.__setattr__(self, name, _number(getattr(self, name), name))
        if self.gain <= 0:
            raise InputError(f"gain must be > 0, got {self.gain!r}")

    @property
    def identity(self) -> bool:
        return self.gain == 1.0 and self.offset == 0.0 and self.drift == 0.0

    def to_json(self) -> dict:
        return asdict(self)

    def apply(self, v: np.ndarray, z: int, nz: int) -> np.ndarray:
        """``v`` (one slice at global index ``z`` of a scan of height ``nz``) changed."""
        t = z / (nz - 1) - 0.5 if nz > 1 else 0.0
        return self.gain * v + (self.offset + self.drift * t)


# --------------------------------------------------------------------------- geometry


@dataclass(frozen=True)
class Geometry:
    """Parallel-beam geometry of one ``(ny, nx)`` slice.

    Angles ``theta_k = k pi / angles``; detector coordinate ``s = x cos + y sin`` with
    ``(y, x)`` relative to the slice centre ``((ny-1)/2, (nx-1)/2)``; ``ndet`` unit pixels
    (odd) centred on ``s = 0``, covering the diagonal.
    """

    ny: int
    nx: int
    angles: int

    @classmethod
    def of(cls, ny: int, nx: int, angles: int | None = None) -> "Geometry":
        if angles is None:
            angles = math.ceil(math.pi / 2 * max(ny, nx))
        return cls(int(ny), int(nx), int(angles))

    @property
    def ndet(self) -> int:
        return 2 * math.ceil(0.5 * math.hypot(self.ny, self.nx) + 1) + 1

    @property
    def theta(self) -> np.ndarray:
        return np.arange(self.angles) * (math.pi / self.angles)

    @property
    def padded(self) -> int:
        from scipy.fft import next_fast_len

        return next_fast_len(2 * self.ndet, real=True)


_TILE = 16  # image rows per tile: the tile and one sinogram row stay in cache


@njit(nogil=True, cache=True)
def _joseph_rows(rows, ctr_row, ctr_col, sel, cos, sin, major_is_cos, ndet, sino):
    """Joseph sums over the rows of ``rows`` (zero-padded by one column each side) for
    the angles ``sel``: one linear-interpolation sample per row and detector pixel."""
    nrows, npad = rows.shape
    n = npad - 2
    cd = 0.5 * (ndet - 1)
    for j0 in range(0, nrows, _TILE):
        for kk in range(sel.size):
            k = sel[kk]
            if major_is_cos:
                a, sr = cos[k], sin[k]
            else:
                a, sr = sin[k], cos[k]
            inv = 1.0 / a
            w = abs(inv)
            srow = sino[k]
            for j in range(j0, min(nrows, j0 + _TILE)):
                # detector t samples padded column u = (t - cd - (j - ctr_row) sr) / a + ctr_col + 1
                u0 = (-cd - (j - ctr_row) * sr) * inv + ctr_col + 1.0
                ta = -u0 * a
                tb = (n + 1.0 - u0) * a  # 0 < u < n + 1: both neighbours inside the padding
                t0 = max(0, int(math.ceil(min(ta, tb))))
                t1 = min(ndet - 1, int(math.floor(max(ta, tb))))
                row = rows[j]
                for t in range(t0, t1 + 1):
                    u = u0 + t * inv
                    i = min(max(int(u), 0), n)
                    f = u - i
                    srow[t] += w * ((1.0 - f) * row[i] + f * row[i + 1])


@njit(nogil=True, cache=True)
def _backproject(q, cos, sin, ny, nx, out):
    """out (ny, nx) += pi/angles * sum_k q_k(x cos + y sin), linear interpolation.

    Tiled over rows so that a tile of ``out`` stays in cache while the angles stream.
    """
    ndet = q.shape[1]
    cy, cx = 0.5 * (ny - 1), 0.5 * (nx - 1)
    cd = 0.5 * (ndet - 1)
    acc = np.zeros((_TILE, nx))
    for j0 in range(0, ny, _TILE):
        nj = min(ny, j0 + _TILE) - j0
        acc[:] = 0.0
        for k in range(cos.size):
            c, s = cos[k], sin[k]
            qk = q[k]
            for jj in range(nj):
                base = (j0 + jj - cy) * s + cd - cx * c
                arow = acc[jj]
                for i in range(nx):
                    t = base + i * c  # in [1, ndet - 2]: the detector covers the diagonal
                    m = int(t)
                    f = t - m
                    arow[i] += (1.0 - f) * qk[m] + f * qk[m + 1]
        scale = math.pi / cos.size
        for jj in range(nj):
            for i in range(nx):
                out[j0 + jj, i] += scale * acc[jj, i]


@njit(nogil=True, cache=True)
def _gaussian_rows(key, z, scale, out):
    """out[k, t] += scale * standard normal from hash (z, k, t, key) (Box-Muller, 2 x 32 bits)."""
    for k in range(out.shape[0]):
        for t in range(out.shape[1]):
            h = hash3(z, k, t, key)
            u1 = (np.float64(h >> _S32) + 1.0) * _INV32  # (0, 1]
            u2 = np.float64(h & _MASK32) * _INV32
            out[k, t] += scale * math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)


def radon(img: np.ndarray, geometry: Geometry | None = None) -> np.ndarray:
    """Parallel-beam projections of one slice (Joseph's method).

    Parameters
    ----------
    img : ndarray, shape (ny, nx), float, attenuation per voxel
    geometry : Geometry, optional
        Default ``Geometry.of(ny, nx)`` (Nyquist angles).

    Returns
    -------
    ndarray, shape (angles, ndet), float64
        Line integrals (attenuation x voxels).
    """
    img = np.asarray(img, np.float64)
    ny, nx = img.shape
    g = geometry or Geometry.of(ny, nx)
    th = g.theta
    cos, sin = np.cos(th), np.sin(th)
    along_y = np.abs(cos) >= np.abs(sin)  # rays mostly along y: one sample per image row
    sino = np.zeros((g.angles, g.ndet))
    pad = np.zeros((ny, nx + 2))
    pad[:, 1:-1] = img
    _joseph_rows(pad, 0.5 * (ny - 1), 0.5 * (nx - 1), np.flatnonzero(along_y), cos, sin, True,
                 g.ndet, sino)
    pad = np.zeros((nx, ny + 2))
    pad[:, 1:-1] = img.T
    _joseph_rows(pad, 0.5 * (nx - 1), 0.5 * (ny - 1), np.flatnonzero(~along_y), cos, sin, False,
                 g.ndet, sino)
    return sino


@functools.lru_cache(maxsize=32)
def _response(ndet: int, padded: int, filt: str, blur: float) -> tuple[np.ndarray, np.ndarray]:
    """(H, B): rfft responses of the discrete ramp (x Hann) and of the detector blur."""
    n = np.zeros(padded)
    n[0] = 0.25
    m = np.arange(1, padded // 2 + 1)
    k = np.where(m % 2 == 1, -1.0 / (np.pi * m) ** 2, 0.0)
    n[1:padded // 2 + 1] = k
    n[padded - m[: (padded - 1) // 2]] = k[: (padded - 1) // 2]  # symmetric kernel
    H = np.real(np.fft.rfft(n))
    f = np.fft.rfftfreq(padded)
    if filt == "hann":
        H = H * 0.5 * (1.0 + np.cos(2 * np.pi * f))
    B = np.exp(-2.0 * (np.pi * blur * f) ** 2)
    return H, B


_FILTER_BLOCK = 64  # projections filtered at a time (bounds the spectra's memory)


def _filter(sino: np.ndarray, geometry: Geometry, filt: str, blur: float, extra=None,
            *, inplace: bool = False) -> np.ndarray:
    """Blur then ramp-filter every row; ``extra`` (ndet,) is added after the blur.

    Rows are filtered in blocks of ``_FILTER_BLOCK`` (into ``sino`` itself if ``inplace``)
    so that the padded spectra never hold the whole sinogram.
    """
    from scipy import fft

    H, B = _response(geometry.ndet, geometry.padded, filt, float(blur))
    hb = H * B
    ex = None if extra is None else fft.rfft(extra, n=geometry.padded) * H
    out = sino if inplace else np.empty_like(sino, dtype=np.float64)
    for k0 in range(0, sino.shape[0], _FILTER_BLOCK):
        spec = fft.rfft(sino[k0:k0 + _FILTER_BLOCK], n=geometry.padded, axis=1, workers=1)
        spec *= hb
        if ex is not None:
            spec += ex
        out[k0:k0 + _FILTER_BLOCK] = fft.irfft(spec, n=geometry.padded, axis=1,
                                               workers=1)[:, : geometry.ndet]
    return out


def fbp(sino: np.ndarray, geometry: Geometry, *, filter: str = "ramp",
        blur: float = 0.0) -> np.ndarray:
    """Filtered back-projection of ``sino`` (angles, ndet) onto the ``(ny, nx)`` slice.

    Returns
    -------
    ndarray, shape (ny, nx), float64, attenuation per voxel
    """
    q = _filter(np.asarray(sino, np.float64), geometry, filter, blur)
    th = geometry.theta
    out = np.zeros((geometry.ny, geometry.nx))
    _backproject(q, np.cos(th), np.sin(th), geometry.ny, geometry.nx, out)
    return out


@functools.lru_cache(maxsize=32)
def noise_gain(geometry: Geometry, filter: str = "ramp", blur: float = 0.0) -> float:
    """Std of the reconstruction per unit std of white projection noise (pixel mean).

    ``sqrt(pi^2 / angles * (2 c0 + c1) / 3)`` with ``c0``, ``c1`` the lag-0 and lag-1
    autocorrelations of the effective detector kernel (module docstring).
    """
    H, B = _response(geometry.ndet, geometry.padded, filter, float(blur))
    g = np.fft.irfft(H * B, n=geometry.padded)
    c0, c1 = float(g @ g), float(g @ np.roll(g, 1))
    return math.sqrt(math.pi ** 2 / geometry.angles * (2 * c0 + c1) / 3)


@functools.lru_cache(maxsize=32)
def ring_gain(geometry: Geometry, filter: str = "ramp") -> float:
    """RMS over the slice of the ring pattern per unit std of the detector offsets.

    Monte Carlo over 8 fixed random offset patterns (a stable calibration: ~3 %).
    """
    key = stream_key(0x5EED, CH_RINGS)
    d = np.zeros((8, geometry.ndet))
    _gaussian_rows(key, 0, 1.0, d)
    ms = 0.0
    th = geometry.theta
    for row in d:
        q = _filter(np.zeros((1, geometry.ndet)), geometry, filter, 0.0, extra=row)
        out = np.zeros((geometry.ny, geometry.nx))
        _backproject(np.ascontiguousarray(np.broadcast_to(q, (geometry.angles, geometry.ndet))),
                     np.cos(th), np.sin(th), geometry.ny, geometry.nx, out)
        ms += float(np.mean(out ** 2))
    return math.sqrt(ms / len(d))


def reconstruct_slice(mu: np.ndarray, z: int, imaging: Imaging, *, seed: int,
                      which: str = "reference", geometry: Geometry | None = None) -> np.ndarray:
    """Simulated CT reconstruction of one slice.

    Parameters
    ----------
    mu : ndarray, shape (ny, nx), float, phase units
        Noise-free attenuation map of the slice.
    z : int
        Global slice index (the detector row: it selects the noise and ring values).
    imaging : Imaging
    seed : int
        Specimen seed (with ``which``, selects the noise stream; rings use the seed only).
    which : {"reference", "deformed"}
        Independent noise streams for the two scans.
    geometry : Geometry, optional
        Default ``Geometry.of(ny, nx, imaging.angles)``.

    Returns
    -------
    ndarray, shape (ny, nx), float64, phase units
    """
    ny, nx = mu.shape
    g = geometry or Geometry.of(ny, nx, imaging.angles)
    sino = radon(mu, g)
    if imaging.noise > 0:
        ch = CH_NOISE_REF if which == "reference" else CH_NOISE_DEF
        _gaussian_rows(stream_key(seed, ch), int(z),
                       imaging.noise / noise_gain(g, imaging.filter, imaging.blur), sino)
    extra = None
    if imaging.rings > 0:
        extra = np.zeros((1, g.ndet))
        _gaussian_rows(stream_key(seed, CH_RINGS), int(z),
                       imaging.rings / ring_gain(g, imaging.filter), extra)
        extra = extra[0]
    q = _filter(sino, g, imaging.filter, imaging.blur, extra, inplace=True)
    th = g.theta
    out = np.zeros((ny, nx))
    _backproject(q, np.cos(th), np.sin(th), ny, nx, out)
    return out
