"""CT-like scan pairs: a microstructure imaged slice by slice, as lazy Dask arrays.

A scan of a CT specimen is computed in slabs of whole z-slices (each slice is one CT
reconstruction, :mod:`chunkdic.synth.ctsim`), from the phase map of :mod:`chunkdic.synth.microstructure`
(reference: ``phase(x)``; deformed: ``phase(field.inverse(x))``). Each slab is one Dask
task of ``SLAB`` slices; :func:`chunkdic.io.scanwrite.write_scan` regroups slabs into whole Zarr
chunks (every writing task owns whole chunks). Memory per task: the slab in the output
dtype plus one slice's working set (phase map and its coordinates, projections filtered
in place, reconstruction: measured peak ``48 N^2`` bytes for an ``N x N`` slice); the
writer holds the slabs of one chunk row, ``chunk_z x N^2`` samples of the output dtype. At
2048^2 slices with uint16 and 128-voxel chunks: 134 MB per slab task, ~200 MB of working
set, ~1.1 GB for a chunk row.

Grey levels: reconstructions are in phase units (pores 0, grains/aggregates 1). Integer
dtypes map ``[-0.5, 1.5]`` linearly to the whole range (``uint16``: 0..65535, the phase
contrast spans 32768 levels; ``uint8``: 128 levels), rounded and clipped: the half-contrast
margins hold the FBP overshoot at edges (up to ~0.2) and noise (at noise 0.02 a voxel
clips only 14 sigma beyond the worst overshoot). ``float32`` keeps phase units.

With ``imaging="local"`` (:mod:`chunkdic.synth.ctlocal`) a scan is computed per Zarr chunk
instead (any box, from global in-plane tiles with halos; cost per voxel independent of the
slice size), see :meth:`CTSpecimen.block`.

The deformed scan of a ``fourier_shift`` pair is not rendered: it is the stored reference
translated by a Fourier phase shift (:func:`chunkdic.synth.fourier_shift.fourier_shift_scan`, the
paper's section 4.2 test), rounded to the reference's dtype.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..io.handles import ArrayRef
from ..io.owntree import remove
from . import ctlocal
from .ctsim import Geometry, GreyChange, Imaging, reconstruct_slice
from .fields import Band, Field, Translation
from .fourier_shift import fourier_shift_scan
from .microstructure import (
    ConcreteParams,
    GrainsParams,
    render_phantom,
    specimen_params,
)

__all__ = ["CTSpecimen", "INTENSITY_RANGE", "SLAB", "render_ct", "as_dask_ct", "quantise",
           "standard_field", "STANDARD_CASES"]

INTENSITY_RANGE = (-0.5, 1.5)  # phase units mapped to the whole integer range
SLAB = 16  # z-slices per Dask task
IMAGING_KEYS = ("noise", "angles", "filter", "blur", "rings", "mode")
GREY_KEYS = ("gain", "offset", "drift")
STANDARD_CASES = ("fourier-shift", "shift", "band")


def quantise(v: np.ndarray, dtype) -> np.ndarray:
    """Phase units to ``dtype`` (integer: ``INTENSITY_RANGE`` to the whole range)."""
    dt = np.dtype(dtype)
    if dt.kind == "f":
        return v.astype(dt)
    top = float(np.iinfo(dt).max)
    lo, hi = INTENSITY_RANGE
    return np.clip(np.rint((v - lo) * (top / (hi - lo))), 0, top).astype(dt)


@dataclass(frozen=True)
class CTSpecimen:
    """Everything that defines a CT-like pair except the output store.

    Parameters
    ----------
    params : GrainsParams or ConcreteParams
    imaging : Imaging
    grey : GreyChange
        Applied to the deformed scan only.
    shape : tuple of 3 int
    dtype : str
    field : Field or None
    fourier_shift : bool
        Deformed scan = Fourier phase shift of the stored reference by ``field.t``
        (``field`` must be a :class:`~chunkdic.synth.fields.Translation`).
    """

    params: GrainsParams | ConcreteParams
    imaging: Imaging
    grey: GreyChange
    shape: tuple[int, int, int]
    dtype: str
    field: Field | None = None
    fourier_shift: bool = False

    @classmethod
    def build(cls, specimen, shape, *, seed=0, field=None, dtype=None, fourier_shift=False,
              **kw) -> "CTSpecimen":
        """Validate options (``Imaging``, ``GreyChange`` and specimen keywords mixed)."""
        img = {k: kw.pop(k) for k in IMAGING_KEYS if k in kw}
        if "imaging" in kw:  # the API's and the CLI's name of Imaging.mode
            img["mode"] = kw.pop("imaging")
        grey = {k: kw.pop(k) for k in GREY_KEYS if k in kw}
        img = {k: v for k, v in img.items() if v is not None}  # None: the default
        grey = {k: v for k, v in grey.items() if v is not None}
        params = specimen_params(specimen, seed, **kw)
        dt = np.dtype("uint16" if dtype is None else dtype)
        if dt.kind not in "uif" or dt.itemsize > 8:
            raise InputError(f"unsupported dtype {dtype!r} (use uint8, uint16, float32)")
        if fourier_shift and not isinstance(field, Translation):
            raise InputError("a Fourier-shift pair needs a translation field")
        if field is not None and not isinstance(field, Field):
            raise InputError(f"field must be a chunkdic.synth.fields.Field, got {type(field).__name__}")
        return cls(params, Imaging(**img), GreyChange(**grey), tuple(int(s) for s in shape),
                   dt.name, field, bool(fourier_shift))

    def metadata(self) -> dict:
        """JSON metadata (``attrs["chunkdic"]["synthetic"]`` and ``field.json``)."""
        lo, hi = INTENSITY_RANGE
        if self.imaging.mode == "local":
            geometry = {"model": "local: in-plane Gaussian PSF and ramp-spectrum noise (chunkdic.synth.ctlocal)",
                        "psf_sigma": ctlocal.PSF_SIGMA, "noise_sigma": ctlocal.NOISE_SIGMA,
                        "tile": ctlocal.TILE}
        else:
            geometry = {"angles": Geometry.of(*self.shape[1:], self.imaging.angles).angles,
                        "detector_pixels": Geometry.of(*self.shape[1:]).ndet,
                        "beam": "parallel, one CT slice per z"}
        return {
            "specimen": self.params.to_json(),
            "imaging": self.imaging.to_json(),
            "geometry": geometry,
            "grey_change": self.grey.to_json(),
            "deformed": "fourier_shift of the reference" if self.fourier_shift
            else "rendered from the deformed geometry",
            "intensity_map": None if np.dtype(self.dtype).kind == "f" else [lo, hi],
        }

    def block(self, which: str, box) -> np.ndarray:
        """Voxels ``box = ((z0, z1), (y0, y1), (x0, x1))`` of one scan, ``dtype``.

        Local imaging: any box (:func:`chunkdic.synth.ctlocal.local_block`); FBP: whole
        slices only (``box`` must span y and x).
        """
        (z0, z1), (y0, y1), (x0, x1) = box
        if self.imaging.mode != "local":
            if (y0, y1, x0, x1) != (0, self.shape[1], 0, self.shape[2]):
                raise ValueError("the FBP imaging computes whole slices only")
            return self.slab(which, z0, z1)
        fld = self.field if which == "deformed" and not self.fourier_shift else None
        v = ctlocal.local_block(self.params, fld, self.imaging.noise, self.params.seed, which, box)
        if which == "deformed" and not self.grey.identity:
            for k, z in enumerate(range(z0, z1)):
                v[k] = self.grey.apply(v[k], z, self.shape[0])
        return quantise(v, self.dtype)

    def slab(self, which: str, z0: int, z1: int) -> np.ndarray:
        """Slices ``z0 <= z < z1`` of the reference or the deformed scan, ``dtype``."""
        nz, ny, nx = self.shape
        if self.imaging.mode == "local":
            return self.block(which, ((z0, z1), (0, ny), (0, nx)))
        geo = Geometry.of(ny, nx, self.imaging.angles)
        fld = self.field if which == "deformed" and not self.fourier_shift else None
        out = np.empty((z1 - z0, ny, nx), self.dtype)
        for z in range(z0, z1):
            mu = render_phantom(self.params, (1, ny, nx), origin=(z, 0, 0), field=fld)[0]
            v = reconstruct_slice(mu, z, self.imaging, seed=self.params.seed, which=which,
                                  geometry=geo)
            if which == "deformed" and not self.grey.identity:
                v = self.grey.apply(v, z, nz)
            out[z - z0] = quantise(v, self.dtype)
        return out


def render_ct(shape, *, specimen="grains", which: str = "reference", z_range=None,
              seed: int = 0, field: Field | None = None, dtype=None, **kw) -> np.ndarray:
    """Render (part of) one CT-like scan in memory.

    Parameters
    ----------
    shape : tuple of 3 int
        Shape of the whole scan ``(nz, ny, nx)`` (the grey drift refers to its height).
    specimen : str or GrainsParams or ConcreteParams
    which : {"reference", "deformed"}
    z_range : tuple (z0, z1), optional
        Slices to render (default all).
    seed, field, dtype
        As in :func:`chunkdic.synth.synthetic.synthesize` (``dtype`` default uint16).
    **kw
        Specimen parameters, :class:`~chunkdic.synth.ctsim.Imaging` and
        :class:`~chunkdic.synth.ctsim.GreyChange` keywords.

    Returns
    -------
    ndarray, shape ``(z1 - z0, ny, nx)``, ``dtype``

    Examples
    --------
    >>> f = render_ct((4, 32, 32), specimen="grains", noise=0.02, dtype="float32")
    >>> f.shape
    (4, 32, 32)
    """
    if which not in ("reference", "deformed"):
        raise InputError(f"which must be 'reference' or 'deformed', got {which!r}")
    sp = CTSpecimen.build(specimen, shape, seed=seed, field=field, dtype=dtype, **kw)
    if sp.fourier_shift:
        raise InputError("render_ct renders from geometry; use synthesize for a Fourier-shift pair")
    z0, z1 = (0, sp.shape[0]) if z_range is None else (int(z_range[0]), int(z_range[1]))
    return sp.slab(which, z0, z1)


def _slab_block(*, spec, which, block_info=None):
    return spec.block(which, block_info[None]["array-location"])


def as_dask_ct(spec: CTSpecimen, which: str, chunks=None):
    """One scan as a lazy Dask array: ``SLAB``-slice blocks of whole xy slices (FBP), or
    blocks of the Zarr chunk shape ``chunks`` (local imaging: default 128).

    Returns
    -------
    dask.array.Array, shape ``spec.shape``, ``spec.dtype``
    """
    import dask.array as da
    from dask.base import tokenize

    nz, ny, nx = spec.shape
    zc = tuple(min(SLAB, nz - z) for z in range(0, nz, SLAB))
    blocks = (zc, (ny,), (nx,))
    if spec.imaging.mode == "local":
        from ..io.store import chunk_shape_for

        c = chunk_shape_for(spec.shape, chunks)
        blocks = tuple(tuple(min(e, n - a) for a in range(0, n, e)) for e, n in zip(c, spec.shape))
    dt = np.dtype(spec.dtype)
    return da.map_blocks(_slab_block, chunks=blocks, dtype=dt,
                         meta=np.empty((0, 0, 0), dt), spec=spec, which=which,
                         name=f"chunkdic-ct-{which}-" + tokenize(repr(spec), which))


def fourier_deformed(ref_scan_path: str, out_dir: str, spec: CTSpecimen, scheduler=None):
    """The deformed scan of a Fourier-shift pair, as a Dask array over a scratch array.

    Returns ``(array, scratch_path)``; remove ``scratch_path`` once written.
    """
    import dask.array as da
    import zarr

    scratch = os.path.join(out_dir, "def.fourier.tmp.zarr")
    remove(scratch)
    src = ArrayRef("zarr", ref_scan_path, "0", spec.shape, spec.dtype)
    fourier_shift_scan(src, scratch, spec.field.t, scheduler=scheduler, overwrite=True)
    arr = da.from_zarr(zarr.open_array(store=scratch, mode="r"))
    dt = np.dtype(spec.dtype)
    if dt.kind != "f":
        top = float(np.iinfo(dt).max)
        arr = da.clip(da.round(arr), 0, top)
    return arr.astype(dt), scratch


def standard_field(case: str, shape, *, shift=(0.5, 0.5, 0.5), strain: float = -0.08,
                   width: float = 6.0, lateral: float = 0.05) -> tuple[Field, bool]:
    """Field of one of the standard test cases and whether it is a Fourier shift.

    ``"fourier-shift"``: the paper's section 4.2 test, deformed = reference shifted by
    ``shift`` with a Fourier phase shift; ``"shift"``: the same translation rendered from
    the geometry (independent noise); ``"band"``: a compression band normal to z at
    mid-height (``strain`` peak, ``width`` voxels, lateral expansion ``lateral``, axis
    through the slice centre).

    The lateral factor 0.05 keeps the band one that a mesh of 8-12 voxel elements can
    follow: with 0.3 the lateral displacement jumps by up to 1.2 voxels across the 6-voxel
    band (a 40 % shear), and the best C8 fit of the exact field (its L2 projection) already
    misses it by 0.13 / 0.06 voxel RMS at the nodes for ℓ = 12 / 8 (0.029 / 0.026 with
    0.05), far above any measurement error.
    """
    nz, ny, nx = shape
    if case == "fourier-shift":
        return Translation(shift), True
    if case == "shift":
        return Translation(shift), False
    if case == "band":
        return Band(center_z=(nz - 1) / 2, width=width, strain=strain, lateral=lateral,
                    center_y=(ny - 1) / 2, center_x=(nx - 1) / 2), False
    raise InputError(f"unknown standard case {case!r} (known: {', '.join(STANDARD_CASES)})")
