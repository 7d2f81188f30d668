"""Results written for other tools: VTK and CSV, voxel-wise fields and corrected images for viewers.

Public names are imported on first use (lazy_loader, as scikit-image does); ``__init__.pyi``
lists them with the module each comes from.
"""

import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
