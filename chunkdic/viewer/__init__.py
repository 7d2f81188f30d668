"""napari view of chunkdic's outputs: layers of a result, a loading series or a fields image.

The npe2 plugin of this package (``napari.yaml`` beside this file, declared in
``pyproject.toml`` under ``napari.manifest``): a reader contribution that opens a result,
a series or a fields image as napari layer-data tuples, with no viewer and no Qt needed to
read; ``chunkdic view`` opens them in a napari window. napari is an optional dependency
(``pip install 'chunkdic[napari]'``), imported only by :mod:`chunkdic.viewer.launch`.

Public names are imported on first use (lazy_loader, as scikit-image does); ``__init__.pyi``
lists them with the module each comes from.
"""

import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
