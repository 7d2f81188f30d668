"""``M`` kept in the output while a run is incomplete: a resumed level reads it instead of a pass.

``M`` is built once per level by a pass over every voxel of the level (:meth:`chunkdic.passes.level.LevelPasses.assemble_m`):
563 s at 2048³ level 0, about two Gauss–Newton passes. So that a run killed during that level
does not build it again on resume, the level's ``M`` (the client's half stencil, shape
``(nz, ny, nx, 14, 3, 3)`` float32, 504 bytes per node: 1 056 964 608 bytes = 0.98 GiB for
the 128³ nodes of 2048³ at ℓ = 16), the noise-correlation sums of its pass, the element
activity of a mask and the reference's range are written into the output's checkpoint group
once built, and a resumed run whose level matches reads them back (``key``: level, mesh,
blocks, the 16-bit grid of the haloed ``f`` and a hash of the field ``M`` was built at; the
output's fingerprint — inputs, their contents, settings — is checked before, by
:class:`chunkdic.engine.checkpoint.Checkpoint`).

Layout in ``OUT.zarr``: arrays ``checkpoint/matrix_stencil``, ``checkpoint/matrix_lags`` and
``checkpoint/matrix_active`` (with a mask), and ``attrs["chunkdic"]["matrix"] = {"key": …,
"fmin": …, "fmax": …, "complete": true}``. Writing removes the record first, writes the
arrays, then the record: a kill while ``M`` is written leaves no record, and the resumed run
builds ``M`` again. The record of a level is removed once the level's end is recorded
(:func:`chunkdic.engine.coarse_to_fine.solve_one_level`), and the whole checkpoint group goes when the
result replaces it: a complete result holds no ``M``.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from ..method.operator import Assembled

#: array names in the checkpoint group (no trailing digit: never one of a checkpoint slot's ``<name><k>``)
ARRAYS = ("matrix_stencil", "matrix_lags", "matrix_active", "matrix_cells")
#: bytes of one chunk of the stored stencil (whole node planes along z)
CHUNK_BYTES = 64 * 2**20
#: bytes per node of the stored half stencil: 14 blocks of 3 x 3 float32
BYTES_PER_NODE = 14 * 9 * 4


def cells_bytes(elements_shape, cell: int) -> int:
    """Bytes of the brightness cells' couplings (:attr:`Assembled.cells`) of a mesh of
    ``elements_shape`` elements with cells of ``cell³`` elements (0 for ``cell`` 1: none):
    ``(cell + 1)³ × 12`` float32 per cell, 162 B per node at ``cell`` 2, 94 at 4."""
    k = int(cell)
    if k <= 1:
        return 0
    return int(np.prod([-(-int(n) // k) for n in elements_shape])) * (k + 1) ** 3 * 12 * 4


def stored_bytes(nodes_shape, cell: int = 1) -> int:
    """Bytes of ``M`` kept in the output for a level of ``nodes_shape`` nodes: the stencil and,
    with brightness cells of ``cell³`` elements, their couplings (:func:`cells_bytes`)."""
    return int(np.prod(nodes_shape)) * BYTES_PER_NODE + cells_bytes([n - 1 for n in nodes_shape], cell)


def field_hash(u: np.ndarray) -> str:
    """A hash of the field ``M`` is built at (float64 bytes): a resumed level's key."""
    return hashlib.sha256(np.ascontiguousarray(u, dtype=np.float64).tobytes()).hexdigest()[:32]


class StoredMatrix:
    """The ``M`` of the level being solved, in the output group at ``path``."""

    def __init__(self, path):
        self.path = Path(path)

    def _root(self, mode: str):
        import zarr

        return zarr.open_group(str(self.path), mode=mode)

    def _set_record(self, root, record: dict | None) -> None:
        attrs = dict(root.attrs["chunkdic"])
        if record is None:
            attrs.pop("matrix", None)
        else:
            attrs["matrix"] = record
        root.attrs["chunkdic"] = attrs

    def record(self) -> dict | None:
        """The complete record, or None."""
        try:
            rec = dict(self._root("r").attrs["chunkdic"]).get("matrix")
        except Exception:  # noqa: BLE001 - an unreadable group has no M to give
            return None
        return rec if isinstance(rec, dict) and rec.get("complete") else None

    def level(self) -> int | None:
        """The level whose ``M`` is kept (None: none)."""
        rec = self.record()
        return None if rec is None else rec["key"].get("level")

    def load(self, key: dict) -> Assembled | None:
        """The kept ``M`` when its key equals ``key`` (a JSON-able dict), else None."""
        rec = self.record()
        if rec is None or rec.get("key") != json.loads(json.dumps(key)):
            return None
        try:
            group = self._root("r")["checkpoint"]
            stencil = group["matrix_stencil"][...]
            lags = group["matrix_lags"][...]
            active = group["matrix_active"][...].astype(bool) if rec.get("active") else None
            cells = group["matrix_cells"][...] if rec.get("cells") else None
        except Exception:  # noqa: BLE001 - arrays gone or damaged: build M again
            return None
        nodes = tuple(key["nodes"])
        if stencil.shape != nodes + (14, 3, 3) or stencil.dtype != np.float32:
            return None
        return Assembled(stencil, lags, active, float(rec["fmin"]), float(rec["fmax"]), cells)

    def save(self, key: dict, m: Assembled) -> None:
        """Keep ``m`` under ``key``: the old record removed, the arrays written, the record last."""
        root = self._root("r+")
        self._set_record(root, None)
        group = root.require_group("checkpoint")
        stencil = m.stencil
        plane = max(1, int(np.prod(stencil.shape[1:])) * stencil.itemsize)
        chunks = (max(1, min(stencil.shape[0], CHUNK_BYTES // plane)),) + stencil.shape[1:]
        group.create_array("matrix_stencil", data=stencil, chunks=chunks, compressors=None, overwrite=True,
                           dimension_names=("z", "y", "x", "offset", "row", "column"))
        group.create_array("matrix_lags", data=np.asarray(m.lags, np.float64), overwrite=True,
                           dimension_names=("axis", "lag"))
        if m.active is not None:
            group.create_array("matrix_active", data=np.asarray(m.active, np.uint8), overwrite=True,
                               dimension_names=("z", "y", "x"))
        elif "matrix_active" in group:
            del group["matrix_active"]
        if m.cells is not None:
            group.create_array("matrix_cells", data=m.cells, compressors=None, overwrite=True,
                               chunks=(max(1, min(m.cells.shape[0], CHUNK_BYTES // max(1, m.cells[0].nbytes))),)
                               + m.cells.shape[1:],
                               dimension_names=("z", "y", "x", "node_z", "node_y", "node_x", "axis", "offset"))
        elif "matrix_cells" in group:
            del group["matrix_cells"]
        self._set_record(root, {"key": key, "fmin": float(m.fmin), "fmax": float(m.fmax),
                                "active": m.active is not None, "cells": m.cells is not None, "complete": True})

    def drop(self) -> None:
        """Remove the kept ``M`` (record first, then its arrays)."""
        root = self._root("r+")
        self._set_record(root, None)
        if "checkpoint" in root:
            group = root["checkpoint"]
            for name in ARRAYS:
                if name in group:
                    del group[name]
