"""The displacement field as an OME-NGFF 0.6 ``displacements`` coordinate transformation.

OME-NGFF 0.6 stores a displacement field as a multiscale image with one axis of type
``displacement`` (discrete, the vector's components) before the spatial axes, and a
``displacements`` transformation that names it by ``path`` and says between which two
coordinate systems it maps (a point ``X`` of the input goes to ``X + u(X)``). The field
of a correlation maps the **reference** scan's physical frame onto the **deformed** scan's
(``f(X) = g(X + u(X))``), so :func:`write_displacements` writes an OME-Zarr *scene*: ::

    OUT.zarr/                                   ome.scene: coordinate systems "reference" and
                                                "deformed" (z, y, x, space, the scan's unit) and
                                                the transformation reference -> deformed,
                                                type displacements, interpolation linear
    OUT.zarr/coordinateTransformations/displacement/
                                                the field: a multiscale image, axes
                                                c (displacement), z, y, x; arrays "0", "1", …

Level 0 of the field is the C8 mesh's nodes: scale ``ℓ 2^s`` level-0 voxels (times the voxel
size) and translation the first node's position (level-0 voxel centres, DESIGN.md), so linear
interpolation between its samples — the transformation's ``interpolation`` — *is* the C8 field
(trilinear shape functions), exactly, with no voxel-sized array. Level ``t`` holds the
NaN-aware means of ``2^t`` nodes per axis, placed at their centroid (scale ``2^t`` times level
0's, translation ``+ scale₀ (2^t − 1) / 2``, the scans' own pyramid rule), down to two
samples per axis. Values are in the coordinate systems' unit: the scan's physical unit when it
has a voxel size (``units="physical"``, the default then), else level-0 voxels (no ``unit``).
NaN where a node was not measured.

The store is written through :mod:`chunkdic.io.outputs` (staged, renamed into place) and
carries ``attrs["chunkdic"] = {"kind": "displacements", ...}``. ngff-zarr (0.50) reads the
scene and the field back, validated against the 0.6 schemas (tests/export/test_ngff_displacements.py).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..io.outputs import Outputs
from ..mesh import level0_position
from ..results.result import jsonable
from ..results.scans import as_result

__all__ = ["write_displacements", "write_displacements_store", "NGFF_VERSION", "FIELD_PATH"]

#: the OME-NGFF version written
NGFF_VERSION = "0.6"
#: where the field image sits in the store (the spec's "coordinateTransformations" group)
FIELD_PATH = "coordinateTransformations/displacement"


def _levels(u: np.ndarray) -> list[np.ndarray]:
    """The field and its NaN-aware 2×2×2 mean levels, down to two samples per axis."""
    levels = [u]
    while min(levels[-1].shape[1:]) >= 4:
        a = levels[-1]
        n = tuple(k // 2 for k in a.shape[1:])
        b = a[:, :2 * n[0], :2 * n[1], :2 * n[2]].reshape(3, n[0], 2, n[1], 2, n[2], 2)
        finite = np.isfinite(b)
        count = finite.sum(axis=(2, 4, 6))
        with np.errstate(invalid="ignore", divide="ignore"):
            levels.append(np.where(finite, b, 0.0).sum(axis=(2, 4, 6)) / count)
    return levels


def _frame(result, units: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, str | None]:
    """Metric per axis (level-0 voxel -> output unit), node spacing, first node, unit."""
    if units == "physical":
        if result.voxel_size is None:
            raise InputError("this result has no voxel size: export the displacements in voxels, or give the scans "
                             "a voxel size")
        metric, unit = np.asarray(result.voxel_size, np.float64), result.unit
    elif units == "voxels":
        metric, unit = np.ones(3), None
    else:
        raise InputError(f"units must be 'voxels' or 'physical', got {units!r}")
    spacing = float(result.info["element_size"]) * result.scale * metric
    first = level0_position(result.node_coords[:, 0, 0, 0], result.scale) * metric
    return metric, spacing, first, unit


def _axes(unit: str | None) -> list[dict]:
    return [{"name": a, "type": "space", **({"unit": unit} if unit else {})} for a in "zyx"]


def field_metadata(n_levels: int, spacing, first, unit: str | None) -> dict:
    """``ome`` attributes of the field image: its intrinsic system (c, z, y, x) and per-level frames."""
    datasets = []
    for t in range(n_levels):
        scale = spacing * 2**t
        shift = first + spacing * (2**t - 1) / 2
        datasets.append({"path": str(t), "coordinateTransformations": [{
            "type": "sequence", "input": {"path": str(t)}, "output": {"name": "reference"},
            "transformations": [{"type": "scale", "scale": [1.0, *map(float, scale)]},
                                {"type": "translation", "translation": [0.0, *map(float, shift)]}]}]})
    return {"version": NGFF_VERSION, "multiscales": [{
        "name": "displacement",
        "coordinateSystems": [{"name": "reference",
                               "axes": [{"name": "c", "type": "displacement", "discrete": True}, *_axes(unit)]}],
        "datasets": datasets,
        "type": "mean",
        "metadata": {"description": "level 0: the C8 nodes (linear interpolation between them is the measured "
                                    "field); level t: NaN-aware means of 2^t nodes per axis"}}]}


def scene_metadata(unit: str | None) -> dict:
    """``ome`` attributes of the store: the scene joining the two scans' frames by the field."""
    return {"version": NGFF_VERSION, "scene": {
        "coordinateSystems": [{"name": "reference", "axes": _axes(unit)}, {"name": "deformed", "axes": _axes(unit)}],
        "coordinateTransformations": [{
            "type": "displacements", "name": "correlation", "path": FIELD_PATH, "interpolation": "linear",
            "input": {"name": "reference"}, "output": {"name": "deformed"}}]}}


def write_displacements(result, out, *, units: str | None = None, overwrite: bool = False) -> dict:
    """Write a result's displacement field as an OME-NGFF 0.6 scene (module docstring).

    Parameters
    ----------
    result : Result or path
    out : path
        The Zarr v3 store to create.
    units : {"physical", "voxels"}, optional
        Coordinates and displacements in the scan's unit (default when it has a voxel size)
        or in level-0 voxels (default otherwise).
    overwrite : bool
        Replace a displacement store chunkdic wrote (nothing else).

    Returns
    -------
    dict
        ``path``, ``levels`` (shapes, ``(3, nz, ny, nx)`` each), ``unit`` (None: level-0 voxels).

    Examples
    --------
    >>> chunkdic.write_displacements("result.zarr", "displacement.zarr")  # doctest: +SKIP
    """
    result = as_result(result)
    result.check_displacement()
    _frame(result, units or _default_units(result))  # a bad unit refused before anything is written
    plan = Outputs(inputs=[result.path] if result.path else [], overwrite=overwrite)
    entry = plan.add(out, "displacements")
    with plan:
        done = write_displacements_store(result, entry.work, units=units)
    return {**done, "path": str(out)}


def _default_units(result) -> str:
    return "physical" if result.voxel_size is not None else "voxels"


def write_displacements_store(result, work, *, units: str | None = None) -> dict:
    """:func:`write_displacements` into ``work`` (outputs checked by the caller, e.g. ``chunkdic
    export``, which stages several outputs in one :class:`~chunkdic.io.outputs.Outputs`)."""
    import zarr

    units = units or _default_units(result)
    metric, spacing, first, unit = _frame(result, units)
    u = result.displacement * result.scale * metric[:, None, None, None]
    levels = _levels(u)
    root = zarr.open_group(str(work), mode="w", zarr_format=3)
    meta = {"kind": "displacements", "complete": False, "result": result.path, "units": units,
            "element_size": result.info["element_size"], "level": result.level,
            "rigid_removed": result.info.get("rigid_removed")}
    root.attrs.update({"chunkdic": jsonable(meta), "ome": scene_metadata(unit)})
    field = root.require_group("coordinateTransformations").create_group("displacement")
    for t, a in enumerate(levels):
        field.create_array(str(t), data=np.ascontiguousarray(a), dimension_names=["c", "z", "y", "x"],
                           fill_value=np.nan)
    field.attrs["ome"] = field_metadata(len(levels), spacing, first, unit)
    root.attrs["chunkdic"] = jsonable({**meta, "complete": True})
    return {"path": str(work), "levels": [a.shape for a in levels], "unit": unit}
