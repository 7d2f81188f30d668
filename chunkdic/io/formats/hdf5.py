"""HDF5 scans: a 3-D dataset, named as ``file.h5:/path/to/dataset`` when the file holds several.

The voxel size comes from the dataset's attributes (``element_size_um``, ``voxel_size``,
``pixel_size`` with ``unit``); the reader reads a hyperslab per task.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from ...errors import InputError
from ..ngff import normalize_voxel_size
from .base import Layout, Reader, Source, metadata_unit

SUFFIXES = (".h5", ".hdf5", ".hdf", ".he5", ".nxs")


class Hdf5:
    """An HDF5 file (by suffix, a ``:dataset`` part, or its signature)."""

    name = "hdf5"

    def can_open(self, path: Path, layout: Layout) -> bool:
        import h5py

        return path.suffix.lower() in SUFFIXES or layout.dataset is not None or (path.is_file() and h5py.is_hdf5(path))

    def open(self, path: Path, layout: Layout) -> Source:
        reader, vs, unit = _open_hdf5(path, layout.dataset)
        return Source(path, reader, vs, unit)


def split_dataset(src: str, dataset):
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
        d = _dataset(f, path, dataset, candidates)
        _check_storage(path, d)
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
                    unit = metadata_unit(u.decode() if isinstance(u, bytes) else u)
                    break
        try:
            vs = normalize_voxel_size(np.asarray(vs, float).tolist()) if vs is not None else None
        except (InputError, TypeError, ValueError):
            vs, unit = None, None
        return H5Reader(str(path), dataset, d.shape, d.dtype), vs, unit


def _dataset(f, path: Path, dataset: str, candidates: list[str]):
    """The dataset ``dataset`` of the open file ``f``, refused in one line when it is not one:
    absent, a group, or a link that leads nowhere (an external link to a missing file, a loop
    of soft links: h5py raises KeyError or RuntimeError from deep inside HDF5)."""
    import h5py

    try:
        d = f[dataset] if dataset in f else None
    except Exception as exc:  # noqa: BLE001 - HDF5's own error: name the link
        raise InputError(f"{path}:{dataset} cannot be opened ({type(exc).__name__}: {exc}".splitlines()[0][:200]
                         + "): a link to a missing file or a loop of links?") from None
    if not isinstance(d, h5py.Dataset):
        raise InputError(f"{path}: no dataset {dataset!r} (3-D datasets: {', '.join(candidates[:6]) or 'none'})")
    return d


def _check_storage(path: Path, d) -> None:
    """Refuse (one line) a dataset whose data live where reading them would hang or lie: an
    external storage file that is not a regular file (a FIFO blocks the reader for ever, a
    device never ends) or is missing, and a virtual dataset with a source file or dataset
    missing (HDF5 reads its part as the fill value, without a word)."""
    for name, offset, size in d.external or ():
        name = os.fsdecode(name)
        where = _located(path, name)
        if where is None:
            raise InputError(f"{path}:{d.name}: its external storage file {name} does not exist")
        if not where.is_file():
            raise InputError(f"{path}:{d.name}: its external storage file {where} is not a regular file (a FIFO, "
                             "a device?): refusing to read it")
        if size != 0xFFFFFFFFFFFFFFFF and where.stat().st_size < offset + size:  # H5F_UNLIMITED: to the end
            raise InputError(f"{path}:{d.name}: its external storage file {where} holds "
                             f"{where.stat().st_size} bytes, fewer than the {offset + size} it should")
    if getattr(d, "is_virtual", False):
        import h5py

        for source in d.virtual_sources():
            name = source.file_name
            where = path if name == "." else _located(path, name)
            if where is None or not where.is_file():
                raise InputError(f"{path}:{d.name}: virtual dataset whose source file {name} is missing: its "
                                 "part would read as the fill value")
            try:
                with h5py.File(where, "r") as src:
                    ok = isinstance(src.get(source.dset_name), h5py.Dataset)
            except Exception:  # noqa: BLE001 - unreadable: as missing
                ok = False
            if not ok:
                raise InputError(f"{path}:{d.name}: virtual dataset whose source {name}:{source.dset_name} is "
                                 "missing: its part would read as the fill value")


def _located(path: Path, name: str) -> Path | None:
    """Where HDF5 finds the file ``name`` that ``path`` refers to: absolute, or relative to
    ``path``'s directory, then to the current directory; None when in neither."""
    for candidate in (Path(name),) if os.path.isabs(name) else (path.parent / name, Path(name)):
        if candidate.exists() or candidate.is_symlink():
            return candidate
    return None


class H5Reader(Reader):
    def __init__(self, path: str, dataset: str, shape, dtype):
        self.path, self.dataset, self.shape = path, dataset, tuple(shape)
        self.dtype = np.dtype(dtype).newbyteorder("=")
        self.label = f"{path}:{dataset}"

    def _read(self, region):
        import h5py

        with h5py.File(self.path, "r") as f:
            return np.asarray(f[self.dataset][region], dtype=self.dtype)
