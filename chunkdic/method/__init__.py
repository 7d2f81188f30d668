"""The method on mesh-sized data: modified Gauss–Newton, its start, stopping rule, length choice, brightness and noise.

C8-DIC of Roux, Hild, Viot, Bernard (sections 3–5) as functions of a level's state, which
go in and come out; the voxels are reached only through the passes of
:class:`chunkdic.method.protocol.Passes` (out of core: :mod:`chunkdic.passes`).

Public names are imported on first use (lazy_loader, as scikit-image does); ``__init__.pyi``
lists them with the module each comes from.
"""

import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
