"""Pairs made from a stored scan: its own texture, a known field, independent noise in each scan.

One idea: what :func:`chunkdic.analysis.resolution.resolution` needs to measure a user's
scan, written out of core. From a stored reference ``f`` (any size) a task per pencil of
whole x-lines (a ``PENCIL_EDGE`` tile in ``(z, y)``) reads its lines, optionally moves
them, adds Gaussian noise hashed from the global voxel index and a stream key (so the
noise is chunk independent and independent between the scans written with different
keys), and writes whole chunks of a float32 Zarr array (every writing task owns its
chunks). Moves:

- none: a noisy copy of the reference;
- a :class:`~chunkdic.synth.fields.Star` field, which moves every x-line ``(z, y)`` as a
  whole by ``Ux(z, y)``: each line is phase-shifted along x by its own amount
  (:func:`chunkdic.synth.fourier_shift.fourier_shift_rows`, mirror-extended, exact for a
  band-limited line), i.e. ``g(x) = f(X(x))`` with the field's explicit inverse, as the
  synthetic specimens render their deformed scans.

A uniform sub-voxel translation goes through :func:`~chunkdic.synth.fourier_shift.fourier_shift_scan`
first (three passes), then through a noisy copy.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..io.handles import ArrayRef, forget_open_arrays
from ..io.owntree import remove
from .fields import Star
from .foam_kernels import add_gaussian_noise
from .fourier_shift import PENCIL_EDGE, fourier_shift_rows

__all__ = ["NOISE_KEYS", "grey_moments", "moved_copy"]

#: hash streams of the noises of the scans a resolution measurement writes
NOISE_KEYS = {"reference": 0x52E5_0001, "translated": 0x52E5_0002, "star": 0x52E5_0003}


def _tiles(shape, edge: int = PENCIL_EDGE):
    for z0 in range(0, shape[0], edge):
        for y0 in range(0, shape[1], edge):
            yield (slice(z0, min(z0 + edge, shape[0])), slice(y0, min(y0 + edge, shape[1])),
                   slice(0, shape[2]))


def _moments_task(src: ArrayRef, region) -> tuple[float, float, int]:
    a = src.read(region).astype(np.float64)
    return float(a.sum()), float((a * a).sum()), int(a.size)


def grey_moments(src: ArrayRef, runner) -> tuple[float, float]:
    """Mean and standard deviation of a stored volume's grey levels, by tasks over pencils."""
    s = s2 = 0.0
    n = 0
    for a, b, c in runner.map_unordered(_moments_task, [(src, r) for r in _tiles(src.shape)]):
        s, s2, n = s + a, s2 + b, n + c
    mean = s / n
    return mean, float(np.sqrt(max(s2 / n - mean * mean, 0.0)))


def _moved_task(src: ArrayRef, out_path: str, region, star: dict | None, key: int, std: float) -> int:
    import zarr

    a = src.read(region)
    if star is not None:
        fld = Star(**star)
        z = np.arange(region[0].start, region[0].stop, dtype=np.float64)[:, None]
        y = np.arange(region[1].start, region[1].stop, dtype=np.float64)[None, :]
        a = fourier_shift_rows(a, fld.displacement(z, y, 0.0)[2])
    a = np.ascontiguousarray(a, dtype=np.float32)
    if std > 0:
        add_gaussian_noise(a, region[0].start, region[1].start, region[2].start, np.uint64(key), float(std))
    arr = zarr.open_array(store=out_path, mode="r+")
    arr.with_config({"write_empty_chunks": True})[region] = a  # every chunk stored (integrity.py)
    return int(a.size)


def moved_copy(src: ArrayRef, out, *, runner, noise: float = 0.0, key: int = NOISE_KEYS["reference"],
               star: Star | None = None, attrs: dict | None = None,
               progress: Callable[[float], None] | None = None) -> ArrayRef:
    """Write ``src`` moved by ``star`` (or not moved) plus hashed Gaussian noise, out of core.

    Parameters
    ----------
    src : ArrayRef
        Stored volume, shape ``(nz, ny, nx)``, any real dtype.
    out : path
        Zarr v3 array to create (float32, ``PENCIL_EDGE``³ chunks); ``chunkdic.complete``
        is set in its attributes last.
    runner
        An open runner (:func:`chunkdic.scheduler.open_runner`).
    noise : float
        Standard deviation of the added noise, grey levels of ``src``.
    key : int
        Hash stream of the noise (different keys: independent noises).
    star : Star, optional
        Field moving each x-line by ``Ux(z, y)`` (module docstring).
    attrs : dict, optional
        More ``attrs["chunkdic"]`` entries.

    Returns
    -------
    ArrayRef
    """
    import zarr

    out = Path(out)
    shape = tuple(int(n) for n in src.shape)
    meta = {"kind": "shifted", "complete": False, **(attrs or {})}
    try:
        zarr.create_array(store=str(out), shape=shape, chunks=tuple(min(PENCIL_EDGE, n) for n in shape),
                          dtype="float32", compressors=None, zarr_format=3, overwrite=True,
                          attributes={"chunkdic": meta})
        tiles = list(_tiles(shape))
        sj = None if star is None else star._json_fields()
        for i, _ in enumerate(runner.map_unordered(
                _moved_task, [(src, str(out), r, sj, int(key), float(noise)) for r in tiles])):
            if progress is not None:
                progress((i + 1) / len(tiles))
        arr = zarr.open_array(store=str(out), mode="r+")
        arr.update_attributes({"chunkdic": {**meta, "complete": True}})
    except BaseException:
        remove(out)
        raise

    forget_open_arrays()
    return ArrayRef("zarr", str(out), "", shape, "float32")
