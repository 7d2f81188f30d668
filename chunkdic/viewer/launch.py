"""Open chunkdic's outputs in a napari window (``chunkdic view``).

The one module that imports napari (an optional dependency: ``pip install
'chunkdic[napari]'``). Before anything is read it checks that napari is installed, that a
Qt binding is, and (on Linux) that there is a display, and refuses in one line otherwise
(:class:`~chunkdic.errors.InputError`: exit 2 from the CLI).
"""

from __future__ import annotations

import importlib
import os
import sys

from ..errors import InputError
from .layers import MAX_VECTORS, layers_of

__all__ = ["view", "check_napari"]

INSTALL = "pip install 'chunkdic[napari]'"


def check_napari():
    """napari, importable and able to open a window here; else a one-line InputError."""
    try:
        import napari
    except ImportError:
        raise InputError(f"napari is not installed: {INSTALL}, or read the layers headless with "
                         "chunkdic.viewer.layers_of") from None
    try:
        importlib.import_module("qtpy")  # napari's windows need a Qt binding
    except Exception:  # noqa: BLE001 - qtpy raises its own error when no binding is found
        raise InputError(f"napari has no Qt binding to open a window: {INSTALL} (it brings PyQt5)") from None
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise InputError("no display to open napari on (DISPLAY is not set): run it on a desktop, or over "
                         "ssh -X, or read the layers headless with chunkdic.viewer.layers_of")
    return napari


def view(paths, *, fields=None, scan: bool = True, max_vectors: int = MAX_VECTORS, block: bool = True):
    """Open results, series or fields images in a new napari window.

    Parameters
    ----------
    paths : path or list of paths
        What :func:`chunkdic.viewer.layers.layers_of` reads.
    fields : path, optional
        The fields image of the (single) result, when it is not beside it.
    scan, max_vectors
        As in :func:`~chunkdic.viewer.layers.layers_of`.
    block : bool, keyword-only
        Run napari's event loop until the window is closed.

    Returns
    -------
    napari.Viewer
    """
    napari = check_napari()
    paths = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if fields is not None and len(paths) != 1:
        raise InputError("--fields goes with one result")
    layers = [layer for p in paths for layer in layers_of(p, fields=fields, scan=scan, max_vectors=max_vectors)]
    from napari.layers import Layer

    viewer = napari.Viewer(title="chunkdic: " + ", ".join(str(p) for p in paths))
    for data, kwargs, kind in layers:
        viewer.add_layer(Layer.create(data, kwargs, kind))
    units = {kw.get("units", (None,))[-1] for _, kw, _ in layers}
    viewer.scale_bar.visible = True
    if len(units) == 1 and None not in units:
        viewer.scale_bar.unit = units.pop()
    if block:
        napari.run()
    return viewer
