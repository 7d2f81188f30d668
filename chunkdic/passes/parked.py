"""Mesh-sized arrays kept on the scratch disk while a level in node blocks does not read them.

With a level's mesh data in node blocks the client holds, besides a solve's vectors, the
Gauss–Newton state: the current field, the best field met, the element fields of the pass
that measured each, and the pass's ``b`` while it is solved for. Only the current field and a
solve's vectors are read at every pass; the rest is read when the level ends (the best field
when it is returned, the element fields by the result), by a checkpoint or by the
regularisation's choice. :class:`Parked` keeps such an array in a ``.npy`` file under the
level's scratch and reads it back whole when asked (``np.asarray``), so that the client
holds it in memory only then (docs/distributed.md, "What stays in the client"). The file
goes with the last reference to its :class:`Parked`.
"""

from __future__ import annotations

import itertools
import os
import weakref
from pathlib import Path

import numpy as np

__all__ = ["Parked"]

_NAMES = itertools.count()


class Parked:
    """An array written to a file of its own in ``directory``, read back whole by ``np.asarray``.

    Parameters
    ----------
    array : ndarray, or list of ndarray
        Any shape and dtype, or its rows along a first axis (arrays of one shape, some
        perhaps broadcast): written row by row, so that no stacked copy is ever made.
    directory : Path
        Made if missing; the file is ``<pid>-<n>.npy`` in it, removed when the object goes.
    """

    def __init__(self, array, directory: Path):
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        self.path = directory / f"{os.getpid()}-{next(_NAMES)}.npy"
        if isinstance(array, np.ndarray):
            self.shape, self.dtype = tuple(array.shape), np.dtype(array.dtype)
        else:
            self.shape, self.dtype = (len(array),) + np.shape(array[0]), np.result_type(*array)
        with open(self.path, "wb") as fh:
            np.lib.format.write_array_header_2_0(fh, {"descr": np.lib.format.dtype_to_descr(self.dtype),
                                                      "fortran_order": False, "shape": self.shape})
            for row in array:  # a row at a time: its copy, if any, is a row's
                np.ascontiguousarray(np.broadcast_to(row, self.shape[1:]), dtype=self.dtype).tofile(fh)
        weakref.finalize(self, _remove, self.path)

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        out = np.load(self.path, allow_pickle=False)
        return out if dtype is None else out.astype(dtype, copy=False)

    def __getitem__(self, key) -> np.ndarray:
        """A part, read from the file alone (a copy in memory)."""
        return np.array(np.load(self.path, mmap_mode="r", allow_pickle=False)[key])

    def __repr__(self) -> str:
        return f"Parked(shape={self.shape}, dtype={self.dtype}, path={str(self.path)!r})"


def _remove(path: Path) -> None:
    try:
        path.unlink()
    except OSError:  # the scratch already removed with the run's
        pass
