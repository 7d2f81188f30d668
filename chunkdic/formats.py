"""Ingest the scan formats users bring into a stored scan (Zarr v3 group, OME-NGFF 0.5).

Formats: a folder of 2-D TIFF slices (natural sort: ``slice_2`` before ``slice_10``), a
3-D / multi-page TIFF, a raw binary file (``shape``, ``dtype``, byte order, header
offset), an HDF5 dataset (``file.h5:/path/to/dataset``), a ``.npy`` file, or an existing
Zarr array / scan group (rechunked, recompressed copy).

Nothing is read whole: a small picklable *reader* (a path and a layout) is wrapped in a
Dask array whose blocks are slabs of whole Zarr chunks (``chunk`` slices deep, full rows
if they fit ``chunkdic.ingest-slab-bytes``, 32 MiB by default); each task opens the file
by path, reads its slab (page range, ``pread`` rows, HDF5 hyperslab, memory map) and
writes it with :func:`chunkdic.scanwrite.write_scan`. Float input is checked for NaN and
infinity slab by slab during the write; a failure removes the half-written output.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Callable
from pathlib import Path

import dask.config
import numpy as np

from .errors import InputError
from .inputs import check_finite
from .ngff import normalize_unit, normalize_voxel_size
from .store import chunk_shape_for
from .scanwrite import write_scan
from .volume import Scan, open_scan

log = logging.getLogger(__name__)

_TIFF = (".tif", ".tiff")
_HDF5 = (".h5", ".hdf5", ".hdf", ".he5", ".nxs")
_RAW_DTYPES = ("uint8", "uint16", "int16", "uint32", "int32", "float32", "float64")
_DEFAULT_SLAB_BYTES = 32 * 2**20


# --------------------------------------------------------------------------------------
# Readers: small picklable objects; every task opens the file by path
# --------------------------------------------------------------------------------------


class _Reader:
    """Array-like for ``dask.array.from_array``: ``shape``, ``dtype``, ``[z, y, x]``."""

    ndim = 3
    shape: tuple[int, int, int]
    dtype: np.dtype
    label: str

    def __getitem__(self, region):
        try:
            return self._read(region)
        except InputError:
            raise
        except Exception as e:  # noqa: BLE001 - a damaged or truncated file: one line naming it
            z = region[0].indices(self.shape[0])[0]
            raise InputError(f"{self.label}: cannot read {self.describe(z)} onwards ({type(e).__name__}: {e}"
                             .splitlines()[0] + "); the file is damaged or truncated") from None

    def _read(self, region):
        raise NotImplementedError

    def describe(self, z: int) -> str:
        return f"slice z={z}"

    def _token_fields(self) -> tuple:
        return tuple(sorted((k, repr(v)) for k, v in vars(self).items()))

    def __dask_tokenize__(self):
        return (type(self).__name__, self._token_fields())


class _RawReader(_Reader):
    def __init__(self, path: str, shape, dtype: np.dtype, offset: int):
        self.path, self.shape, self.file_dtype, self.offset = path, tuple(shape), np.dtype(dtype), int(offset)
        self.dtype = self.file_dtype.newbyteorder("=")
        self.label = path

    def _read(self, region):
        nz, ny, nx = self.shape
        zs, ys, xs = (r.indices(n) for r, n in zip(region, self.shape))
        row = nx * self.file_dtype.itemsize
        y0, y1 = ys[0], max(ys[0], ys[1])
        zr = range(*zs)
        out = np.empty((len(zr), y1 - y0, nx), self.file_dtype)
        with open(self.path, "rb", buffering=0) as f:
            fd = f.fileno()
            for i, z in enumerate(zr):
                start = self.offset + (z * ny + y0) * row
                want = (y1 - y0) * row
                buf = memoryview(out[i]).cast("B")
                got = 0
                while got < want:
                    n = os.preadv(fd, [buf[got:]], start + got)
                    if n <= 0:
                        raise InputError(f"{self.path}: unexpected end of file at z={z}")
                    got += n
        out = out[:, slice(None, None, ys[2]) if ys[2] != 1 else slice(None), slice(*xs)]
        return out.astype(self.dtype, copy=False)


class _NpyReader(_Reader):
    def __init__(self, path: str, shape, dtype):
        self.path, self.shape, self.file_dtype = path, tuple(shape), np.dtype(dtype)
        self.dtype = self.file_dtype.newbyteorder("=")
        self.label = path

    def _read(self, region):
        a = np.load(self.path, mmap_mode="r")
        return np.array(a[region], dtype=self.dtype)


class _H5Reader(_Reader):
    def __init__(self, path: str, dataset: str, shape, dtype):
        self.path, self.dataset, self.shape = path, dataset, tuple(shape)
        self.dtype = np.dtype(dtype).newbyteorder("=")
        self.label = f"{path}:{dataset}"

    def _read(self, region):
        import h5py

        with h5py.File(self.path, "r") as f:
            return np.asarray(f[self.dataset][region], dtype=self.dtype)


class _TiffSlicesReader(_Reader):
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


class _TiffVolumeReader(_Reader):
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
            arr = _tiff_as_zarr(tif, self.series)
            return np.asarray(arr[_unsqueezed(arr.shape, region)], dtype=self.dtype)


def _tiff_as_zarr(tif, series: int):
    import zarr

    return zarr.open_array(tif.aszarr(series=series), mode="r")


def _unsqueezed(shape, region) -> tuple:
    """``region`` over the squeezed 3-D shape as an index of the stored ``shape`` (singleton axes 0)."""
    it = iter(region)
    return tuple(0 if n == 1 else next(it) for n in shape)


# --------------------------------------------------------------------------------------
# Opening each format
# --------------------------------------------------------------------------------------


def _natural_key(name: str):
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
                   key=lambda f: _natural_key(f.name))
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
    return _TiffSlicesReader([str(f) for f in files], shape3, ref_dtype, memmappable), vs, unit


#: a compressed TIFF whose smallest decodable unit (tile or strip) spans every slice is
#: refused above this size: each slab task would decode the whole volume
WHOLE_VOLUME_TIFF_LIMIT = 256 * 2**20


def _check_tiff_chunking(path: Path, shape, dtype) -> None:
    import tifffile

    with tifffile.TiffFile(path) as tif:
        arr = _tiff_as_zarr(tif, 0)
        depth = [c for c, n in zip(arr.chunks, arr.shape) if n != 1][0]
    nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
    if depth >= shape[0] and nbytes > WHOLE_VOLUME_TIFF_LIMIT:
        raise InputError(f"{path}: compressed volumetric TIFF stored as one block of {nbytes / 2**30:.1f} GiB: "
                         "every slab would decode the whole file; save it as one page per slice, tiled, "
                         "or uncompressed (e.g. tifffile.imwrite(..., tile=(64, 256, 256), volumetric=True))")


def _open_tiff_file(path: Path):
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
    return _TiffVolumeReader(str(path), shape, dtype, 0, memmappable, by_pages), vs, unit


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
        return _H5Reader(str(path), dataset, d.shape, d.dtype), vs, unit


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
    return _RawReader(str(path), shape, fdtype, offset), None, None


def _open_npy(path: Path):
    try:
        a = np.load(path, mmap_mode="r")
    except Exception as e:  # noqa: BLE001
        raise InputError(f"{path}: not a readable .npy file ({e})".splitlines()[0]) from None
    if a.ndim != 3:
        raise InputError(f"{path}: array has shape {a.shape}; a scan must be 3-D (z, y, x)")
    if a.dtype.kind not in "uif":
        raise InputError(f"{path}: unsupported dtype {a.dtype}")
    return _NpyReader(str(path), a.shape, a.dtype), None, None


def _open_source(src, *, shape, dtype, byte_order, offset, dataset):
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
        return (*_open_tiff_file(p), p)
    if suffix == ".npy":
        return (*_open_npy(p), p)
    import h5py

    if h5py.is_hdf5(p):
        return (*_open_hdf5(p, None), p)
    return (*_open_raw(p, shape, dtype, byte_order, offset), p)


# --------------------------------------------------------------------------------------
# Streaming into write_scan
# --------------------------------------------------------------------------------------


def _slab_chunks(shape, dtype, chunk_shape):
    """Dask chunks: whole Zarr chunks, ``cz`` deep, full rows while under the slab budget."""
    budget = int(dask.config.get("chunkdic.ingest-slab-bytes", default=_DEFAULT_SLAB_BYTES))
    nz, ny, nx = shape
    cz, cy, cx = chunk_shape
    item = np.dtype(dtype).itemsize
    row = cz * nx * item
    if row * ny <= budget:
        ey, ex = ny, nx
    elif row * cy <= budget:
        ey, ex = cy * max(1, budget // (row * cy)), nx
    else:
        ey, ex = cy, cx * max(1, budget // (cz * cy * cx * item))
    return tuple(min(e, n) for e, n in zip((cz, ey, ex), shape))


def _check_finite(block: np.ndarray, reader=None, block_info=None) -> np.ndarray:
    origin = tuple(r[0] for r in block_info[0]["array-location"])
    check_finite(block, origin, reader.label, where=reader.describe)
    return block


def ingest(src, out, *, voxel_size=None, unit=None, chunks=None, shape=None, dtype=None,
           byte_order: str = "little", offset: int = 0, dataset: str | None = None,
           overwrite: bool = False, levels: int = 0, parents: bool = True,
           progress: Callable[[float], None] | None = None) -> Scan:
    """Convert a scan file or folder into a stored scan group (Zarr v3, OME-NGFF 0.5).

    Parameters
    ----------
    src : str or Path
        Folder of 2-D TIFF slices, 3-D TIFF, raw binary file (with ``shape``/``dtype``),
        ``file.h5:/path/to/dataset``, ``.npy``, or a Zarr array / scan group.
    out : str or Path
        Group to create, e.g. ``"scan.zarr"``.
    voxel_size : float or tuple of 3 float, optional
        Level-0 voxel size ``(z, y, x)``; default from TIFF (ImageJ / OME) or HDF5
        (``element_size_um``, ``voxel_size``) metadata, else none.
    unit : str, optional
        Length unit of ``voxel_size`` (``"micrometer"``, ``"um"``, ``"mm"``, ...).
    chunks : int or tuple of 3 int, optional
        Zarr chunk edge; default ``chunkdic.chunk-size`` (128).
    shape : tuple of 3 int or "Z,Y,X", optional
        Raw input only: array shape.
    dtype : {"uint8", "uint16", "float32", "int16", "uint32", "int32", "float64"}, optional
        Raw input only: sample type.
    byte_order : {"little", "big"}
        Raw input only.
    offset : int
        Raw input only: header bytes to skip.
    dataset : str, optional
        HDF5 dataset path (alternative to ``file.h5:/dataset``).
    overwrite : bool
        Replace an existing Zarr store at ``out``.
    levels : int
        Pyramid levels to build after level 0 (2 = the paper's 4^3 compression).
    parents : bool
        Create missing parent directories of ``out`` (default; like ``mkdir -p``, never
        inside an input or a Zarr store; removed again if the run fails).
    progress : callable(float), optional
        Called with the fraction done.

    Returns
    -------
    Scan

    Raises
    ------
    InputError
        Unreadable or inconsistent input (size mismatch, mixed slices, missing dataset,
        not 3-D, NaN/inf in float data), existing output; nothing is left at ``out``.

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> d = tempfile.mkdtemp()
    >>> np.arange(4 * 5 * 6, dtype=np.uint16).reshape(4, 5, 6).byteswap().tofile(os.path.join(d, "v.raw"))
    >>> s = ingest(os.path.join(d, "v.raw"), os.path.join(d, "v.zarr"), shape=(4, 5, 6), dtype="uint16",
    ...            byte_order="big", voxel_size=2.5, unit="um")
    >>> int(s.level(0)[3, 4, 5].compute()), s.voxel_size
    (119, (2.5, 2.5, 2.5))
    """
    import dask.array as da

    user_vs = normalize_voxel_size(voxel_size)
    user_unit = normalize_unit(unit)
    if user_unit is not None and user_vs is None:
        raise InputError("a unit was given without a voxel size: pass both (--voxel-size 4.91 --unit micrometer)")
    reader, meta_vs, meta_unit, in_path = _open_source(src, shape=shape, dtype=dtype, byte_order=byte_order,
                                                       offset=offset, dataset=dataset)
    out_p = Path(out)
    if reader is None:  # a Zarr array or group
        scan = open_scan(in_path)
        data = scan.level(0)
        meta_vs, meta_unit = scan.voxel_size, scan.unit
        label = str(in_path)
    else:
        label = reader.label
        cshape = chunk_shape_for(reader.shape, chunks)
        slab = _slab_chunks(reader.shape, reader.dtype, cshape)
        name = "ingest-" + dask.base.tokenize(reader, slab, _mtime(in_path))
        data = da.from_array(reader, chunks=slab, name=name, asarray=False,
                             meta=np.empty((0, 0, 0), reader.dtype))
        if reader.dtype.kind == "f":
            data = data.map_blocks(_check_finite, reader=reader, dtype=reader.dtype,
                                   meta=np.empty((0, 0, 0), reader.dtype))
    vs = user_vs if user_vs is not None else meta_vs
    unit_out = user_unit if user_vs is not None else meta_unit
    log.info("ingesting %s: shape %s %s, voxel size %s %s", label, data.shape, data.dtype, vs, unit_out)
    return write_scan(out_p, data, voxel_size=vs, unit=unit_out, chunks=chunks, overwrite=overwrite,
                      levels=levels, progress=progress, inputs=[in_path], parents=parents)


def _mtime(p: Path) -> int:
    try:
        return p.stat().st_mtime_ns
    except OSError:
        return 0
