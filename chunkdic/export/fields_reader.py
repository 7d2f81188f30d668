"""Reading a fields image written by :func:`chunkdic.export.fields_image.write_fields`:
its level arrays, or one level as an xarray Dataset.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .voxel_values import CHANNELS

__all__ = ["open_fields", "open_levels"]


def open_levels(path):
    """Open an image written by :func:`write_fields`: ``(levels, attrs)``, the level arrays
    (lazily read Zarr arrays, ``(7, nz, ny, nx)``) and the group's attributes; an
    incomplete one is refused. :func:`open_fields` gives one level as an xarray Dataset."""
    import zarr

    try:
        g = zarr.open_group(str(path), mode="r")
        attrs = g.attrs.asdict()
        meta = attrs["chunkdic"]
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"{path} is not a fields image ({exc.__class__.__name__})") from None
    if meta.get("kind") != "fields" or not meta.get("complete"):
        raise InputError(f"{path} is not a complete fields image")
    datasets = attrs["ome"]["multiscales"][0]["datasets"]
    return [g[d["path"]] for d in datasets], attrs


def open_fields(path, level: int = 0):
    """One level of a fields image (:func:`write_fields`) as an :class:`xarray.Dataset`.

    ``xarray.open_zarr`` cannot read the image group itself: its levels share the dimension
    names ``c, z, y, x`` with different sizes (an OME-NGFF pyramid, "conflicting sizes for
    dimension 'z'"); this opens one level, lazily (Dask, the image's chunks).

    Parameters
    ----------
    path : path
        The image (``chunkdic export RESULT --fields fields.zarr``).
    level : int
        Pyramid level of the image (0: its finest, on the scan's level-``grid_level`` grid, see
        ``attrs["chunkdic"]["grid_level"]``; ``t``: the 2^t mean).

    Returns
    -------
    xarray.Dataset
        One variable per channel (:data:`CHANNELS`: ``Uz``, ``Uy``, ``Ux``, ``|U|``, ``eps_zz``,
        ``eps_eq``, ``residual``), float32 on ``(z, y, x)``, NaN outside the ROI; coordinates
        ``z, y, x`` are the voxel centres in the scan's physical unit (OME-NGFF scale and
        translation of that level; voxels without a voxel size), ``units`` in their attributes;
        the Dataset's attributes hold the image's ``chunkdic`` metadata (result, element size,
        displacement unit, strain measure).

    Examples
    --------
    >>> ds = chunkdic.open_fields("fields.zarr")  # doctest: +SKIP
    >>> ds["eps_zz"].sel(z=500.0, method="nearest").plot()  # doctest: +SKIP
    """
    try:
        import xarray as xr
    except ImportError:
        raise ImportError("open_fields needs xarray: pip install xarray") from None
    import dask.array as da

    levels, attrs = open_levels(path)
    if int(level) != level or not 0 <= level < len(levels):
        raise InputError(f"{path} has levels 0 to {len(levels) - 1}, not {level!r}")
    level = int(level)
    ms = attrs["ome"]["multiscales"][0]
    scale, shift = [1.0] * 4, [0.0] * 4
    for t in ms["datasets"][level].get("coordinateTransformations", []):
        if t.get("type") == "scale":
            scale = [float(v) for v in t["scale"]]
        elif t.get("type") == "translation":
            shift = [float(v) for v in t["translation"]]
    axes = {a["name"]: a for a in ms.get("axes", []) if isinstance(a, dict)}
    arr = levels[level]
    data = da.from_zarr(arr)
    meta = attrs.get("chunkdic", {})
    coords = {}
    for i, name in enumerate("zyx", start=1):
        unit = axes.get(name, {}).get("unit") or "voxel"
        coords[name] = (name, shift[i] + scale[i] * np.arange(arr.shape[i]), {"units": unit})
    names = meta.get("channels") or list(CHANNELS)
    units = {"Uz": meta.get("displacement_unit"), "Uy": meta.get("displacement_unit"),
             "Ux": meta.get("displacement_unit"), "|U|": meta.get("displacement_unit"), "eps_zz": "1",
             "eps_eq": "1", "residual": "grey level"}
    data_vars = {name: (("z", "y", "x"), data[k], {"units": units.get(name) or "1"}) for k, name in enumerate(names)}
    return xr.Dataset(data_vars, coords=coords, attrs={**{k: v for k, v in meta.items() if v is not None and
                                                          isinstance(v, (str, int, float, bool))},
                                                       "level": level, "path": str(path)})
