"""Zarr stores (an array, or a scan group with its pyramid): opened by :func:`chunkdic.open_scan`
itself, so the source carries no reader."""

from __future__ import annotations

from pathlib import Path

from .base import Layout, Source

MARKERS = ("zarr.json", ".zarray", ".zgroup")


class Zarr:
    name = "zarr"

    def can_open(self, path: Path, layout: Layout) -> bool:
        return path.is_dir() and any((path / m).exists() for m in MARKERS)

    def open(self, path: Path, layout: Layout) -> Source:
        return Source(path)
