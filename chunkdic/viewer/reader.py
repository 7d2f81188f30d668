"""The npe2 reader contribution: chunkdic's outputs as napari layer-data tuples.

``napari_get_reader(path)`` answers the reader's question of npe2: a function that reads
``path`` when it is a complete chunkdic result, loading series or fields image (recognised
by its ``zarr.json`` attributes, :func:`chunkdic.io.kinds.kind_of`), None otherwise so
that napari tries its other readers. The layers are :func:`chunkdic.viewer.layers.layers_of`'s;
napari is not imported here.
"""

from __future__ import annotations

from pathlib import Path

from ..io.kinds import kind_of
from .layers import layers_of

__all__ = ["napari_get_reader", "read"]

#: what the reader opens
KINDS = ("result", "series", "fields")


def napari_get_reader(path):
    """npe2 ``get_reader``: :func:`read` when every path is a chunkdic output it opens, else None.

    Parameters
    ----------
    path : str or list of str
    """

    paths = path if isinstance(path, (list, tuple)) else [path]
    if not paths or any(kind_of(Path(str(p).rstrip("/")))[0] not in KINDS for p in paths):
        return None
    return read


def read(path) -> list[tuple]:
    """Layer-data tuples ``(data, kwargs, layer_type)`` of one path or a list of paths."""

    paths = path if isinstance(path, (list, tuple)) else [path]
    return [layer for p in paths for layer in layers_of(str(p).rstrip("/"))]
