"""OME-NGFF 0.5 metadata of a scan group: units, voxel sizes, ``multiscales``.

Units are stored with their OME-NGFF (UDUNITS-2) names (``"um"`` is accepted and becomes
``"micrometer"``). The group's ``multiscales`` list only the complete levels ``0..k``; the
voxel size is read back from ``attrs["chunkdic"]``, else from the NGFF scale transforms of
a group written by another tool.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..mesh import level0_position
from .ownership import final_name

# OME-NGFF space units (UDUNITS-2 names) and the spellings users type.
_SPACE_UNITS = {
    "angstrom", "attometer", "centimeter", "decimeter", "exameter", "femtometer", "foot",
    "gigameter", "hectometer", "inch", "kilometer", "megameter", "meter", "micrometer",
    "mile", "millimeter", "nanometer", "parsec", "petameter", "picometer", "terameter",
    "yard", "yoctometer", "yottameter", "zeptometer", "zettameter",
}
_UNIT_ALIASES = {
    "um": "micrometer", "µm": "micrometer", "μm": "micrometer", "micron": "micrometer",
    "microns": "micrometer", "micrometre": "micrometer", "mm": "millimeter",
    "millimetre": "millimeter", "nm": "nanometer", "nanometre": "nanometer",
    "cm": "centimeter", "m": "meter", "metre": "meter", "a": "angstrom", "å": "angstrom",
    "pm": "picometer",
}


def normalize_unit(unit) -> str | None:
    """Return the OME-NGFF spelling of ``unit`` (``"um"`` -> ``"micrometer"``)."""
    if unit is None:
        return None
    u = str(unit).strip()
    if not u:
        return None
    low = u.lower()
    low = _UNIT_ALIASES.get(low, low)
    if low not in _SPACE_UNITS:
        raise InputError(
            f"unknown length unit {unit!r}: use an OME-NGFF unit such as micrometer, "
            "millimeter or nanometer (um, mm, nm also accepted)"
        )
    return low


def normalize_voxel_size(voxel_size) -> tuple[float, float, float] | None:
    """``4.9`` or ``(vz, vy, vx)`` -> a tuple of 3 positive floats (or ``None``)."""
    if voxel_size is None:
        return None
    if isinstance(voxel_size, str):
        voxel_size = [v for v in voxel_size.replace(" ", ",").split(",") if v]
    try:
        values = [float(v) for v in np.atleast_1d(np.asarray(voxel_size, dtype=object))]
    except (TypeError, ValueError):
        raise InputError(f"voxel size {voxel_size!r} is not a number or 3 numbers (z,y,x)") from None
    if len(values) == 1:
        values = values * 3
    if len(values) != 3 or not all(np.isfinite(v) and v > 0 for v in values):
        raise InputError(f"voxel size {voxel_size!r} must be one positive number or 3 (z,y,x)")
    return tuple(values)


def level_frame(scale0, shift0, level: int) -> tuple[list[float], list[float]]:
    """Scale and translation of pyramid level ``level`` of a grid whose level 0 has
    ``scale0``, ``shift0``: ``scale0 * 2^s`` and ``shift0 + scale0 (2^s - 1) / 2``
    (the voxel-centre offset of shared/DESIGN.md)."""
    f = 2**int(level)
    return [v * f for v in scale0], [o + v * float(level0_position(0.0, f)) for o, v in zip(shift0, scale0)]


def multiscales(name: str, levels, scale0, shift0, unit, *, kind: str, description: str, method: str,
                channels: bool = False) -> dict:
    """OME-NGFF 0.5 ``ome`` attributes of a pyramid: one ``multiscales`` entry.

    Parameters
    ----------
    name : str
        The image's name (the store's final name).
    levels : sequence of int
        The levels listed (array paths ``"s"``); level ``s`` is placed by :func:`level_frame`.
    scale0, shift0 : sequence of 3 float
        Level-0 scale and translation ``(z, y, x)``, in ``unit``.
    unit : str or None
        The space axes' unit (None: no unit written).
    kind, description, method : str
        The ``type`` and ``metadata`` of the pyramid (``"sum"``, ``"mean"``).
    channels : bool, keyword-only
        A leading channel axis ``c`` (scale 1, translation 0).
    """
    axes = [{"name": "c", "type": "channel"}] if channels else []
    axes += [{"name": a, "type": "space", **({"unit": unit} if unit else {})} for a in "zyx"]
    lead = [1.0] if channels else []
    datasets = []
    for s in levels:
        scale, shift = level_frame(scale0, shift0, s)
        datasets.append({"path": str(s), "coordinateTransformations": [
            {"type": "scale", "scale": lead + scale},
            {"type": "translation", "translation": [0.0] * len(lead) + shift},
        ]})
    return {"version": "0.5", "multiscales": [{
        "name": name, "axes": axes, "datasets": datasets, "type": kind,
        "metadata": {"description": description, "method": method},
    }]}


def ngff_attrs(levels, voxel_size, unit, name) -> dict:
    """:func:`multiscales` of a scan group: the ``2^s`` sum pyramid, level 0 at the voxel
    size (1 without one, and then no unit) and origin 0."""
    vs = [float(v) for v in voxel_size] if voxel_size is not None else [1.0] * 3
    return multiscales(
        name, levels, vs, [0.0] * 3, unit if voxel_size is not None else None, kind="sum",
        description="level s is the sum over 2^s voxels per axis of level 0 (odd trailing voxels trimmed); "
                    "voxel centre of level s at level-0 coordinate 2^s*j + (2^s-1)/2",
        method="chunkdic.io.coarsen.coarsen_sum")


def image_attrs(name: str, scale0, shift0, unit, n_levels: int, channels, windows, description: str,
                method: str = "chunkdic.export.images.coarsen_task") -> dict:
    """OME-NGFF 0.5 ``ome`` attributes of a float image for viewers (fields, corrected image):
    axes ``c, z, y, x``, levels ``0..n_levels-1`` on the frame of level 0 (``scale0``,
    ``shift0``: the scan's own pyramid frame), NaN-aware means, and ``omero`` channels
    labelled ``channels`` with their contrast windows ``(start, end, min, max)``."""
    ome = multiscales(name, range(n_levels), scale0, shift0, unit, kind="mean", description=description,
                      method=method, channels=True)
    ome["omero"] = omero(windows, channels, name=name)
    return ome


def complete_levels(group) -> list[int]:
    out = []
    for name in sorted((k for k in group.array_keys() if k.isdigit()), key=int):
        info = group[name].attrs.get("chunkdic") or {}
        if info.get("complete") is True:
            out.append(int(name))
    return out


def update_group_metadata(path: str) -> None:
    """Rewrite the NGFF ``multiscales`` of group ``path`` to list its complete levels 0..k."""
    import zarr

    g = zarr.open_group(store=path, mode="r+")
    info = dict(g.attrs.get("chunkdic") or {})
    complete = complete_levels(g)
    levels = []
    for s in complete:
        if s != len(levels):
            break
        levels.append(s)
    vs = info.get("voxel_size")
    attrs = {"chunkdic": info}
    if levels:
        attrs["ome"] = ngff_attrs(levels, tuple(vs) if vs else None, info.get("unit"), final_name(path))
        if info.get("display_window") and len(levels) > 1:
            # the level-0 window (chunkdic.io.display): what a viewer uses on every level
            attrs["ome"]["omero"] = omero([info["display_window"]])
    else:
        attrs["ome"] = {"version": "0.5"}
    g.update_attributes(attrs)


def voxel_from_group_attrs(attrs) -> tuple:
    info = attrs.get("chunkdic") or {}
    if "voxel_size" in info:
        vs = info.get("voxel_size")
        return (tuple(float(v) for v in vs) if vs else None), info.get("unit")
    ome = attrs.get("ome") or {}
    ms = ome.get("multiscales") or attrs.get("multiscales")
    if not ms:
        return None, None
    try:
        m = ms[0]
        scale = np.ones(3)
        for t in m["datasets"][0].get("coordinateTransformations", []):
            if t.get("type") == "scale":
                scale = scale * np.asarray(t["scale"], float)[-3:]
        for t in m.get("coordinateTransformations", []) or []:
            if t.get("type") == "scale":
                scale = scale * np.asarray(t["scale"], float)[-3:]
        units = {a.get("unit") for a in m.get("axes", [])[-3:] if isinstance(a, dict)}
        unit = units.pop() if len(units) == 1 else None
        return tuple(float(v) for v in scale), unit
    except (KeyError, IndexError, TypeError, ValueError):
        return None, None


def omero(windows, labels=("grey",), name: str | None = None) -> dict:
    """OME-NGFF ``omero`` metadata of grey channels ``labels`` with their ``windows``
    ``[start, end, min, max]`` (the first channel active)."""
    channels = [{"label": label, "active": i == 0, "color": "FFFFFF", "coefficient": 1.0, "family": "linear",
                 "inverted": False, "window": {"start": lo, "end": hi, "min": vmin, "max": vmax}}
                for i, (label, (lo, hi, vmin, vmax)) in enumerate(zip(labels, windows))]
    out = {} if name is None else {"name": name}
    return {**out, "channels": channels, "rdefs": {"model": "greyscale", "defaultZ": 0}}
