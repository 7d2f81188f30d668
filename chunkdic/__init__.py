"""chunkdic: out-of-core global C8 digital volume correlation over Zarr with Dask.

Method: Roux, Hild, Viot, Bernard, *Three dimensional image correlation from X-ray
computed tomography of solid foam* (C8-DIC). Conventions: shared/DESIGN.md and
docs/architecture.md.
"""

# Public names, imported on first use (PEP 562 through lazy_loader, as scikit-image does) so
# that ``import chunkdic`` stays light: numba, distributed and zarr load only when needed.
# ``__init__.pyi`` is the one list of them, with the module each comes from.
import importlib as _importlib

import lazy_loader as _lazy

_importlib.import_module(f"{__name__}.config")  # registers the chunkdic.* dask.config defaults

__getattr__, _, _lazy_all = _lazy.attach_stub(__name__, __file__)

__version__ = "0.1.0"

__all__ = [*_lazy_all, "show_versions"]


def __dir__():
    return sorted([*__all__, "__version__"])


def show_versions() -> str:
    """Versions of chunkdic and its dependencies, for bug reports."""
    import platform
    from importlib.metadata import PackageNotFoundError, version

    lines = [f"python: {platform.python_version()} ({platform.platform()})", f"chunkdic: {__version__}"]
    for name in ("numpy", "scipy", "dask", "distributed", "zarr", "numcodecs", "numba", "tifffile", "h5py", "matplotlib", "meshio"):
        try:
            lines.append(f"{name}: {version(name)}")
        except PackageNotFoundError:
            lines.append(f"{name}: not installed")
    return "\n".join(lines)
