"""chunkdic: out-of-core global C8 digital volume correlation over Zarr with Dask.

Method: Roux, Hild, Viot, Bernard, *Three dimensional image correlation from X-ray
computed tomography of solid foam* (C8-DIC). Conventions: shared/DESIGN.md and
docs/architecture.md.
"""

from . import config as _config  # noqa: F401  (registers the chunkdic.* dask.config defaults)

# Public names, imported on first use (PEP 562) so that ``import chunkdic`` stays light
# (numba, distributed and zarr load only when needed).
_EXPORTS = {
    "ArrayRef": "volume",
    "InputError": "errors",
    "Mesh": "mesh",
    "PoorTextureWarning": "solve",
    "Result": "result",
    "Scan": "volume",
    "Settings": "engine",
    "build_pyramid": "pyramid",
    "write_display": "display",
    "correlate": "engine",
    "correlate2d": "q4",
    "series": "loadseries",
    "open_series": "loadseries",
    "SeriesResult": "loadseries",
    "cutcheck": "crosscheck",
    "ingest": "formats",
    "open_result": "result",
    "open_scan": "volume",
    "write_scan": "scanwrite",
    "element_strain": "strain",
    "mean_strain": "strain",
    "uncertainty": "metrology",
    "sweep": "zoisweep",
    "zoi_table": "zoisweep",
    "fit_power_law": "metrology",
    "score_displacement": "scoring",
    "write_corrected": "corrected",
    "write_fields": "fields_export",
    "write_vtk": "export",
}


def __getattr__(name):
    if name in _EXPORTS:
        import importlib

        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'chunkdic' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))


__version__ = "0.1.0"

__all__ = [
    "ArrayRef",
    "build_pyramid",
    "write_display",
    "correlate",
    "correlate2d",
    "cutcheck",
    "element_strain",
    "fit_power_law",
    "ingest",
    "InputError",
    "mean_strain",
    "Mesh",
    "open_result",
    "open_scan",
    "open_series",
    "PoorTextureWarning",
    "Result",
    "Scan",
    "score_displacement",
    "series",
    "SeriesResult",
    "Settings",
    "show_versions",
    "sweep",
    "uncertainty",
    "write_corrected",
    "write_fields",
    "write_scan",
    "write_vtk",
    "zoi_table",
]


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
