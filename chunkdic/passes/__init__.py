"""The passes over the voxels of a level: the ``M`` and ``b`` passes out of core, block by block, and a dense twin.

What the method (:mod:`chunkdic.method`) asks of the voxels, through
:class:`chunkdic.method.protocol.Passes`: tasks that read their block of ``f`` and the
window of ``g`` they need from the stores and return mesh-sized partials, the scratch
stores they read (the haloed ``f``, the prepared ``g``), ``M`` kept for a resumed run,
specimen masks and the phase-correlation translation.

Public names are imported on first use (lazy_loader, as scikit-image does); ``__init__.pyi``
lists them with the module each comes from.
"""

import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
