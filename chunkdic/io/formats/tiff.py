"""TIFF scans: a folder of 2-D slices, or one 3-D file (ImageJ hyperstack, OME-TIFF, tiled).

Opening reads the headers only: slices of one shape and dtype, no truncated image data, a
voxel size from ImageJ or OME-XML metadata. The readers read a slab's pages, slices or
tiles inside the task (a compressed volumetric file through tifffile's chunked store, so a
slab decodes only the tiles it overlaps).
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np

from ...errors import InputError
from .base import Layout, Reader, Source, metadata_unit, natural_key

log = logging.getLogger(__name__)

SUFFIXES = (".tif", ".tiff")


class TiffFolder:
    """A folder of 2-D TIFF slices, one per z, in natural order (``slice2`` before ``slice10``)."""

    name = "tiff-folder"

    def can_open(self, path: Path, layout: Layout) -> bool:
        return path.is_dir()

    def open(self, path: Path, layout: Layout) -> Source:
        reader, vs, unit = _open_tiff_folder(path)
        return Source(path, reader, vs, unit)


class TiffVolume:
    """One 3-D TIFF file."""

    name = "tiff"

    def can_open(self, path: Path, layout: Layout) -> bool:
        return path.is_file() and path.suffix.lower() in SUFFIXES

    def open(self, path: Path, layout: Layout) -> Source:
        reader, vs, unit = open_tiff_file(path)
        return Source(path, reader, vs, unit)


def is_slice_folder(path: Path) -> bool:
    """A folder holding TIFF slices (and not a Zarr store)."""
    return path.is_dir() and any(f.suffix.lower() in SUFFIXES for f in path.iterdir())


def _tiff_voxel_size(tif) -> tuple[tuple | None, str | None]:
    """Voxel size from ImageJ or OME-XML metadata (None when absent or meaningless)."""
    try:
        ij = tif.imagej_metadata or {}
        unit = metadata_unit(ij.get("unit"))
        page = tif.pages[0]
        if unit:
            def size(tag):
                t = page.tags.get(tag)
                if t is None:
                    return None
                num, den = t.value
                return den / num if num else None

            px, py = size("XResolution"), size("YResolution")
            if px:
                py = py or px
                pz = float(ij.get("spacing") or px)
                return (pz, py, px), unit
        ome = tif.ome_metadata
        if ome:
            vals = {}
            for ax in "XYZ":
                m = re.search(rf'PhysicalSize{ax}="([0-9.eE+-]+)"', ome)
                if m:
                    vals[ax] = float(m.group(1))
            m = re.search(r'PhysicalSizeXUnit="([^"]+)"', ome)
            unit = metadata_unit(m.group(1) if m else "µm")
            if "X" in vals and unit:
                return (vals.get("Z", vals["X"]), vals.get("Y", vals["X"]), vals["X"]), unit
    except Exception as e:  # noqa: BLE001 - metadata is a convenience
        log.debug("TIFF metadata unreadable: %s", e)
    return None, None


#: a compressed page (a slice, decoded whole) or tile larger than this is refused from its
#: tags, before anything is decoded: a few MB of deflate data declaring a 60 000² page would
#: allocate 3.4 GiB per reading thread (an 11 585² uint16 slice is 256 MiB; an uncompressed
#: one of any size is memory-mapped instead)
TIFF_DECODE_LIMIT = 256 * 2**20


def _check_decode_size(path, page) -> None:
    """Refuse a compressed TIFF page whose decoded page or tile its tags declare larger than
    :data:`TIFF_DECODE_LIMIT` (an uncompressed one is memory-mapped, never decoded whole)."""
    if page.is_memmappable:
        return
    item = np.dtype(page.dtype).itemsize
    for what, shape in (("page", page.shape), ("tile or strip", getattr(page, "chunks", page.shape))):
        nbytes = int(np.prod([int(n) for n in shape], dtype=object)) * item
        if nbytes > TIFF_DECODE_LIMIT:
            raise InputError(f"{path}: a compressed {what} of {' x '.join(str(int(n)) for n in shape)} {page.dtype} "
                             f"({nbytes / 2**30:.1f} GiB) would be decoded whole, more than "
                             f"{TIFF_DECODE_LIMIT / 2**20:g} MiB: save the scan uncompressed, or with smaller slices or "
                             "tiles")


def _check_tiff_extent(path, tif, pages) -> None:
    """Refuse a TIFF whose image data end beyond the end of the file (truncated copy)."""
    size = os.path.getsize(path)
    end = 0
    for page in pages:
        offsets, counts = getattr(page, "dataoffsets", ()), getattr(page, "databytecounts", ())
        if offsets and counts:
            end = max(end, max(int(o) + int(c) for o, c in zip(offsets, counts)))
    if end > size:
        raise InputError(f"{path}: truncated TIFF: its image data end at byte {end} but the file has {size} bytes")


def _open_tiff_folder(folder: Path):
    import tifffile

    files = sorted((f for f in folder.iterdir() if f.is_file() and f.suffix.lower() in SUFFIXES),
                   key=lambda f: natural_key(f.name))
    if not files:
        raise InputError(f"{folder}: no .tif/.tiff slices in this folder")
    ref_shape = ref_dtype = None
    memmappable = True
    vs = unit = None
    for i, f in enumerate(files):
        try:
            with tifffile.TiffFile(f) as tif:
                npages = len(tif.pages)
                page = tif.pages[0]
                shape, dtype = tuple(page.shape), np.dtype(page.dtype)
                _check_tiff_extent(f, tif, [page])
                _check_decode_size(f, page)
                if i == 0:
                    vs, unit = _tiff_voxel_size(tif)
                    memmappable = bool(page.is_memmappable)
        except InputError:
            raise
        except Exception as e:  # noqa: BLE001
            raise InputError(f"{f}: not a readable TIFF ({type(e).__name__}: {e})".splitlines()[0]) from None
        if npages != 1:
            raise InputError(f"{f}: slice file has {npages} pages; a slice folder needs one 2-D image per file")
        if len(shape) != 2:
            raise InputError(f"{f}: slice has shape {shape}; slices must be 2-D grey-level images")
        if ref_shape is None:
            ref_shape, ref_dtype = shape, dtype
        elif shape != ref_shape or dtype != ref_dtype:
            raise InputError(f"{f.name}: slice is {shape} {dtype} but {files[0].name} is {ref_shape} {ref_dtype}: "
                             "mixed shapes or dtypes in the folder")
    if vs is not None and len(files) > 1:
        log.info("voxel size from the first slice's metadata (z spacing assumed equal to x): %s %s", vs, unit)
    shape3 = (len(files),) + ref_shape
    return TiffSlicesReader([str(f) for f in files], shape3, ref_dtype, memmappable), vs, unit


#: a compressed TIFF whose smallest decodable unit (tile or strip) spans every slice is
#: refused above this size: each slab task would decode the whole volume
WHOLE_VOLUME_TIFF_LIMIT = TIFF_DECODE_LIMIT


def _check_tiff_chunking(path: Path, shape, dtype) -> None:
    import tifffile

    with tifffile.TiffFile(path) as tif:
        arr = tiff_as_zarr(tif, 0)
        depth = [c for c, n in zip(arr.chunks, arr.shape) if n != 1][0]
    nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
    if depth >= shape[0] and nbytes > WHOLE_VOLUME_TIFF_LIMIT:
        raise InputError(f"{path}: compressed volumetric TIFF stored as one block of {nbytes / 2**30:.1f} GiB: "
                         "every slab would decode the whole file; save it as one page per slice, tiled, "
                         "or uncompressed (e.g. tifffile.imwrite(..., tile=(64, 256, 256), volumetric=True))")


def open_tiff_file(path: Path):
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            series = tif.series[0]
            shape = tuple(int(n) for n in series.shape if n != 1)  # squeeze (1, Z, 1, Y, X) layouts
            dtype = np.dtype(series.dtype)
            vs, unit = _tiff_voxel_size(tif)
            pages = len(series.pages) if hasattr(series, "pages") else 0
            try:
                memmappable = series.dataoffset is not None
            except Exception:  # noqa: BLE001
                memmappable = False
            page_shape = tuple(n for n in series.pages[0].shape if n != 1) if pages else ()
            _check_decode_size(path, tif.pages[0])
            if memmappable:
                end = int(series.dataoffset) + int(np.prod(series.shape)) * dtype.itemsize
                if end > os.path.getsize(path):
                    raise InputError(f"{path}: truncated TIFF: its image data end at byte {end} but the file has "
                                     f"{os.path.getsize(path)} bytes")
            else:
                _check_tiff_extent(path, tif, [p for p in tif.pages[-1:] if p is not None])
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001
        raise InputError(f"{path}: not a readable TIFF ({type(e).__name__}: {e})".splitlines()[0]) from None
    if len(shape) != 3:
        raise InputError(f"{path}: TIFF holds an image of shape {tuple(series.shape)}; a scan must be 3-D "
                         "(for a folder of 2-D slices pass the folder)")
    if dtype.kind not in "uif":
        raise InputError(f"{path}: unsupported TIFF sample type {dtype}")
    by_pages = pages == shape[0] and page_shape == shape[1:]
    if not memmappable and not by_pages:
        _check_tiff_chunking(path, shape, dtype)
    return TiffVolumeReader(str(path), shape, dtype, 0, memmappable, by_pages), vs, unit



class TiffSlicesReader(Reader):
    def __init__(self, files: list[str], shape, dtype, memmappable: bool):
        self.files, self.shape, self.memmappable = list(files), tuple(shape), bool(memmappable)
        self.dtype = np.dtype(dtype).newbyteorder("=")
        self.label = str(Path(files[0]).parent)

    def describe(self, z: int) -> str:
        return f"slice z={z} (file {Path(self.files[z]).name})"

    def _read_plane(self, path: str, ys, xs):
        import tifffile

        if self.memmappable:
            try:
                return np.array(tifffile.memmap(path, mode="r")[ys, xs])
            except ValueError:
                pass
        return tifffile.imread(path)[ys, xs]

    def _read(self, region):
        zs, ys, xs = region
        zr = range(*zs.indices(self.shape[0]))
        out = np.empty((len(zr),) + tuple(len(range(*r.indices(n))) for r, n in zip((ys, xs), self.shape[1:])),
                       self.dtype)
        for i, z in enumerate(zr):
            try:
                plane = self._read_plane(self.files[z], ys, xs)
            except Exception as e:  # noqa: BLE001 - name the slice file
                raise InputError(f"{self.files[z]}: cannot read slice z={z} ({type(e).__name__}: {e}"
                                 .splitlines()[0] + "); the file is damaged or truncated") from None
            if plane.shape != out.shape[1:]:
                raise InputError(f"{self.files[z]}: slice changed shape to {plane.shape} while reading")
            out[i] = plane
        return out


class TiffVolumeReader(Reader):
    def __init__(self, path: str, shape, dtype, series: int, memmappable: bool, by_pages: bool):
        self.path, self.shape, self.series = path, tuple(shape), int(series)
        self.dtype = np.dtype(dtype).newbyteorder("=")
        self.memmappable, self.by_pages = bool(memmappable), bool(by_pages)
        self.label = path

    def describe(self, z: int) -> str:
        return f"page z={z}"

    def _read(self, region):
        import tifffile

        zs, ys, xs = region
        if self.memmappable:
            m = tifffile.memmap(self.path, series=self.series, mode="r").reshape(self.shape)
            return np.array(m[region], dtype=self.dtype)
        with tifffile.TiffFile(self.path) as tif:
            if self.by_pages:
                z0, z1, step = zs.indices(self.shape[0])
                data = tif.asarray(key=range(z0, z1, step), series=self.series)
                data = data.reshape((-1,) + self.shape[1:])
                return np.asarray(data[:, ys, xs], dtype=self.dtype)
            # compressed volumetric page(s): through tifffile's chunked store, so that a slab
            # decodes only the tiles / strips it overlaps, not the whole series
            arr = tiff_as_zarr(tif, self.series)
            return np.asarray(arr[_unsqueezed(arr.shape, region)], dtype=self.dtype)


def tiff_as_zarr(tif, series: int):
    import zarr

    return zarr.open_array(tif.aszarr(series=series), mode="r")


def _unsqueezed(shape, region) -> tuple:
    """``region`` over the squeezed 3-D shape as an index of the stored ``shape`` (singleton axes 0)."""
    it = iter(region)
    return tuple(0 if n == 1 else next(it) for n in shape)
