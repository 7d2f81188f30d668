"""Opening each scan format: checks, metadata, and the reader of the file.

One idea: from what the user passed (a folder of 2-D TIFF slices, a 3-D TIFF, an HDF5
dataset ``file.h5:/path``, a ``.npy``, a raw binary file with its shape and dtype, or a
Zarr store) to a :mod:`chunkdic.io.formats.readers` reader, the voxel size and unit found in the
metadata (ImageJ / OME-XML, HDF5 attributes), and the input path. Only headers are read
here; inconsistent or truncated inputs are refused with one :class:`InputError` line.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np

from ...errors import InputError
from ..ngff import normalize_unit, normalize_voxel_size
from .readers import H5Reader, NpyReader, RawReader, TiffSlicesReader, TiffVolumeReader, tiff_as_zarr

log = logging.getLogger(__name__)

__all__ = ["natural_key", "open_source", "open_tiff_file", "WHOLE_VOLUME_TIFF_LIMIT"]

_TIFF = (".tif", ".tiff")
_HDF5 = (".h5", ".hdf5", ".hdf", ".he5", ".nxs")
_RAW_DTYPES = ("uint8", "uint16", "int16", "uint32", "int32", "float32", "float64")


def natural_key(name: str):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _tiff_unit(u) -> str | None:
    if not u:
        return None
    u = str(u).replace("\\u00B5", "µ").replace("\\u00b5", "µ")
    try:
        return normalize_unit(u)
    except InputError:
        return None


def _tiff_voxel_size(tif) -> tuple[tuple | None, str | None]:
    """Voxel size from ImageJ or OME-XML metadata (None when absent or meaningless)."""
    try:
        ij = tif.imagej_metadata or {}
        unit = _tiff_unit(ij.get("unit"))
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
            unit = _tiff_unit(m.group(1) if m else "µm")
            if "X" in vals and unit:
                return (vals.get("Z", vals["X"]), vals.get("Y", vals["X"]), vals["X"]), unit
    except Exception as e:  # noqa: BLE001 - metadata is a convenience
        log.debug("TIFF metadata unreadable: %s", e)
    return None, None


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

    files = sorted((f for f in folder.iterdir() if f.is_file() and f.suffix.lower() in _TIFF),
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
WHOLE_VOLUME_TIFF_LIMIT = 256 * 2**20


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


def _split_h5(src: str, dataset):
    if dataset is not None:
        return Path(src), str(dataset)
    if os.path.exists(src):
        return Path(src), None
    for m in re.finditer(":", src):
        head = src[: m.start()]
        if os.path.isfile(head):
            return Path(head), src[m.start() + 1:] or None
    return Path(src), None


def _h5_datasets(f) -> list[str]:
    import h5py

    found = []

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset) and obj.ndim == 3:
            found.append("/" + name)

    f.visititems(visit)
    return found


def _open_hdf5(path: Path, dataset):
    import h5py

    try:
        f = h5py.File(path, "r")
    except Exception as e:  # noqa: BLE001
        raise InputError(f"{path}: not a readable HDF5 file ({e})".splitlines()[0]) from None
    with f:
        candidates = _h5_datasets(f)
        if dataset is None:
            if len(candidates) != 1:
                raise InputError(f"{path}: name the dataset as {path}:/path/to/dataset (3-D datasets: "
                                 f"{', '.join(candidates[:6]) or 'none'})")
            dataset = candidates[0]
        if dataset not in f or not isinstance(f[dataset], h5py.Dataset):
            raise InputError(f"{path}: no dataset {dataset!r} (3-D datasets: {', '.join(candidates[:6]) or 'none'})")
        d = f[dataset]
        if d.ndim != 3:
            raise InputError(f"{path}:{dataset} has shape {d.shape}; a scan must be 3-D (z, y, x)")
        if d.dtype.kind not in "uif":
            raise InputError(f"{path}:{dataset}: unsupported dtype {d.dtype}")
        vs = unit = None
        attrs = d.attrs
        if "element_size_um" in attrs:
            vs, unit = attrs["element_size_um"], "micrometer"
        else:
            for k in ("voxel_size", "pixel_size", "voxel_size_um"):
                if k in attrs:
                    vs = attrs[k]
                    u = attrs.get("unit", attrs.get("units", "micrometer" if k.endswith("_um") else None))
                    unit = _tiff_unit(u.decode() if isinstance(u, bytes) else u)
                    break
        try:
            vs = normalize_voxel_size(np.asarray(vs, float).tolist()) if vs is not None else None
        except (InputError, TypeError, ValueError):
            vs, unit = None, None
        return H5Reader(str(path), dataset, d.shape, d.dtype), vs, unit


def _parse_shape(shape) -> tuple[int, int, int]:
    if isinstance(shape, str):
        shape = [s for s in re.split(r"[,x ]+", shape.strip()) if s]
    try:
        out = tuple(int(s) for s in shape)
    except (TypeError, ValueError):
        raise InputError(f"shape {shape!r} must be 3 integers Z,Y,X") from None
    if len(out) != 3 or min(out) < 1:
        raise InputError(f"shape {shape!r} must be 3 positive integers Z,Y,X")
    return out


def _open_raw(path: Path, shape, dtype, byte_order, offset):
    if shape is None or dtype is None:
        raise InputError(f"{path}: raw binary input needs --shape Z,Y,X and --dtype ({'|'.join(_RAW_DTYPES)})")
    shape = _parse_shape(shape)
    name = np.dtype(dtype).name if not isinstance(dtype, str) else dtype.strip().lower()
    if name not in _RAW_DTYPES:
        raise InputError(f"raw dtype {dtype!r} not supported: use one of {', '.join(_RAW_DTYPES)}")
    order = {"little": "<", "big": ">", "<": "<", ">": ">", "le": "<", "be": ">"}.get(str(byte_order).lower())
    if order is None:
        raise InputError(f"byte order {byte_order!r}: use little or big")
    offset = int(offset or 0)
    if offset < 0:
        raise InputError(f"header offset must be >= 0, got {offset}")
    fdtype = np.dtype(name).newbyteorder(order)
    size = path.stat().st_size
    expected = offset + int(np.prod(shape)) * fdtype.itemsize
    if size != expected:
        hint = ""
        payload = size - offset
        if payload > 0:
            fits = [d for d in _RAW_DTYPES if payload == int(np.prod(shape)) * np.dtype(d).itemsize and d != name]
            if fits:
                hint = f"; the size matches --dtype {fits[0]}"
            elif size > expected and offset == 0:
                hint = f"; a {size - expected}-byte header? pass --offset {size - expected}"
        raise InputError(f"{path}: file has {size} bytes but shape {shape} {name} + offset {offset} needs "
                         f"{expected}{hint}")
    return RawReader(str(path), shape, fdtype, offset), None, None


def _open_npy(path: Path):
    try:
        a = np.load(path, mmap_mode="r")
    except Exception as e:  # noqa: BLE001
        raise InputError(f"{path}: not a readable .npy file ({e})".splitlines()[0]) from None
    if a.ndim != 3:
        raise InputError(f"{path}: array has shape {a.shape}; a scan must be 3-D (z, y, x)")
    if a.dtype.kind not in "uif":
        raise InputError(f"{path}: unsupported dtype {a.dtype}")
    return NpyReader(str(path), a.shape, a.dtype), None, None


def open_source(src, *, shape, dtype, byte_order, offset, dataset):
    """Reader, voxel size and unit from the metadata, input path (for overlap checks)."""
    s = str(src)
    h5path, ds = _split_h5(s, dataset)
    if h5path.suffix.lower() in _HDF5 or ds is not None:
        if not h5path.exists():
            raise InputError(f"input {h5path} does not exist")
        return (*_open_hdf5(h5path, ds), h5path)
    p = Path(s)
    if not p.exists():
        raise InputError(f"input {p} does not exist")
    if p.is_dir():
        if (p / "zarr.json").exists() or (p / ".zarray").exists() or (p / ".zgroup").exists():
            return None, None, None, p  # Zarr: handled by open_scan
        return (*_open_tiff_folder(p), p)
    suffix = p.suffix.lower()
    if shape is not None:
        return (*_open_raw(p, shape, dtype, byte_order, offset), p)
    if suffix in _TIFF:
        return (*open_tiff_file(p), p)
    if suffix == ".npy":
        return (*_open_npy(p), p)
    import h5py

    if h5py.is_hdf5(p):
        return (*_open_hdf5(p, None), p)
    return (*_open_raw(p, shape, dtype, byte_order, offset), p)
