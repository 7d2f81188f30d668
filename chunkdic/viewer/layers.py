"""napari layers of what chunkdic wrote: a result, a loading series, a fields image.

One idea: from a path to napari's *layer-data tuples* ``(data, kwargs, layer_type)``, the
form npe2 reader contributions return. Nothing here imports napari (or Qt): the tuples are
arrays and plain keyword arguments, so they are built, and tested, without a viewer
(:mod:`chunkdic.viewer.reader` hands them to napari, :mod:`chunkdic.viewer.launch` to a window).

Every layer is placed in the reference scan's **physical frame** (shared/DESIGN.md): the
scan's level-0 scale and translation from its OME-NGFF metadata (its voxel size and origin
0 without any; 1 voxel without a voxel size), so level-0 voxel ``i`` sits at
``shift + scale * i``. A pyramid level ``s`` voxel ``j`` has its centre at level-0
coordinate ``2^s j + (2^s - 1)/2`` (:func:`chunkdic.mesh.level0_position`), which places
the nodes (``o + k ell - 0.5`` in voxels of the result's level) and element centres.

Layers of a **result** (bottom to top, napari draws later layers on top):

- ``reference``: the reference scan (recorded in the result, if on disk) as a multiscale
  image, lazily read; pyramid level ``s`` is shown as its mean (the stored sum over
  ``8^s`` voxels, divided), so one contrast window (the scan's level-0 ``display_window``)
  fits every level;
- from an ``export --fields`` image (given, or found beside the result): ``|U|``,
  ``eps_zz``, ``eps_eq`` and ``residual``, multiscale, each with its stored window;
  without one, the mesh-sized ``|U| (nodes)`` (on the node grid) and ``eps_zz (elements)``
  (constant per element, the result's element strain);
- ``mask`` (Labels): the specimen mask file the result records, else its active elements;
- ``displacement`` (Vectors): the nodal field, sub-sampled by a stride per axis to at
  most :data:`MAX_VECTORS` nodes, coloured by ``|U|`` (feature ``|U|``, in the scan's unit
  with a voxel size), drawn with a length factor (``metadata["length"]``) that makes the
  longest vector 0.8 of the shown node spacing (sub-voxel fields are invisible at scale 1);
- ``weak nodes (k)`` (Points): the ``k`` nodes the engine flagged weak (``FLAG_WEAK`` of
  :attr:`chunkdic.results.result.Result.flags`: poorly textured, regularised, or not settled
  at the noise level; the flag the VTU and CSV exports carry), at their level-0 positions;
  no layer when no node is flagged.

A **loading series** adds a leading time axis ``t`` = scan index (0 the reference): the
scans stacked (when they share a shape; else the reference alone), the cumulative fields
``u_0→t`` as 4-D vectors, ``|U| (nodes)`` and ``eps_zz (elements)`` (zero at ``t = 0``).

The mesh-sized layers (vectors, weak nodes, node and element values, the mask's elements) are
:mod:`chunkdic.viewer.mesh_layers`'s.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..analysis.loadseries import open_series
from ..errors import InputError
from ..io.display import sample_step
from ..io.kinds import kind_of
from ..io.scan import open_scan
from ..results.scans import as_result, input_scan
from ..export.voxel_values import CHANNELS
from ..export.fields_reader import open_levels
from ..export.images import scan_frame
from .mesh_layers import (
    MAX_VECTORS,
    Frame,
    Layer,
    contrast_window,
    element_strain_layer,
    mask_layer,
    nodes_norm_layer,
    vector_layer,
    weak_layer,
)

__all__ = ["layers_of", "result_layers", "series_layers", "fields_layers", "find_fields"]


#: channels of a fields image shown as layers (Uz, Uy, Ux are the vectors)
FIELD_LAYERS = ("|U|", "eps_zz", "eps_eq", "residual")
_COLORMAPS = {"|U|": "viridis", "eps_zz": "bwr", "eps_eq": "magma", "residual": "gray"}
#: a window from at most this many sampled voxels (the client reads no more of a scan)
_SAMPLE = 1_000_000


def layers_of(path, *, fields=None, scan: bool = True, max_vectors: int = MAX_VECTORS) -> list[Layer]:
    """The layers of a chunkdic result, loading series or fields image at ``path``.

    Parameters
    ----------
    path : str or Path
        A result group (also a series step, ``series.zarr/steps/002-cumulative``), a
        series group, or a fields image (``export --fields``).
    fields : str or Path, optional
        A result's fields image (default: one found beside the result, :func:`find_fields`).
    scan : bool, keyword-only
        Include the reference scan(s).
    max_vectors : int, keyword-only
        Bound on the displacement vectors per time step.

    Returns
    -------
    list of (data, kwargs, layer_type)
        napari layer-data tuples, bottom layer first.

    Raises
    ------
    InputError
        Not one of chunkdic's outputs above, or an incomplete one.
    """

    kind, complete = kind_of(path)
    if kind not in ("result", "series", "fields"):
        raise InputError(f"{path} is not a chunkdic result, loading series or fields image")
    if not complete:
        raise InputError(f"{path} is an incomplete {kind} (the run that wrote it was interrupted)")
    if kind == "fields":
        return fields_layers(path)
    if kind == "series":
        return series_layers(path, scan=scan, max_vectors=max_vectors)
    return result_layers(path, fields=fields, scan=scan, max_vectors=max_vectors)


def result_layers(result, *, fields=None, scan: bool = True, max_vectors: int = MAX_VECTORS) -> list[Layer]:
    """Layers of one result (module docstring): reference, fields, mask, displacement, weak nodes.

    Parameters
    ----------
    result : Result or path
    fields, scan, max_vectors
        As in :func:`layers_of`.
    """

    res = as_result(result)
    ref = _reference(res) if scan else None
    frame = _frame(ref, res.info)
    out = [] if ref is None else [scan_layer([ref], frame, "reference")]
    fields = fields if fields is not None else find_fields(res)
    if fields is not None:
        out += fields_layers(fields)
    else:
        out += [nodes_norm_layer([res], frame), element_strain_layer([res], frame)]
    mask = mask_layer(res, frame)
    if mask is not None:
        out.append(mask)
    out.append(vector_layer([res], frame, max_vectors))
    weak = weak_layer([res], frame)
    if weak is not None:
        out.append(weak)
    return out


def _reference(res):
    """The result's reference scan (recorded path), or None when it is not on disk."""

    try:
        return input_scan(res, "reference", optional=True)
    except InputError:
        return None


def _frame(scan, info: dict) -> Frame:

    scale, shift, unit = scan_frame(scan, info)
    return Frame(tuple(scale), tuple(shift), unit)


def find_fields(res) -> Path | None:
    """A complete fields image written from ``res`` beside it (the newest), or None."""
    if not res.path:
        return None
    here = Path(res.path).resolve()
    found = []
    for p in here.parent.iterdir():
        meta = _store_meta(p)
        if meta.get("kind") != "fields" or not meta.get("complete") or not meta.get("result"):
            continue
        source = Path(meta["result"])
        candidates = [source] if source.is_absolute() else [Path.cwd() / source, p.parent / source]
        if any(c.resolve() == here for c in candidates):
            found.append((p.stat().st_mtime, p))
    return max(found)[1] if found else None


def _store_meta(path: Path) -> dict:
    """``attrs["chunkdic"]`` of a Zarr v3 group (its ``zarr.json`` read directly: cheap)."""
    try:
        return json.loads((path / "zarr.json").read_text())["attributes"]["chunkdic"] or {}
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def scan_layer(scans, frame: Frame, name: str) -> Layer:
    """A scan (or scans stacked along ``t``) as a multiscale image of level means.

    Levels are the scan's stored pyramid levels ``0..k`` (the reference's, when stacked);
    level ``s`` is divided by ``8^s`` (lazily: nothing is read here but a window sample).
    """
    import dask.array as da

    levels = _contiguous(scans[0].stored_levels()) or [0]
    data = []
    for s in levels:
        per_scan = [sc.level(s) for sc in scans]
        if s:
            per_scan = [(a.astype(np.float64) / 8.0**s).astype(np.float32) for a in per_scan]
        data.append(per_scan[0] if len(scans) == 1 else da.stack(per_scan))
    window = _scan_window(scans[0], data[-1] if len(scans) == 1 else data[-1][0])
    kw = {"name": name, "colormap": "gray", "blending": "translucent", "contrast_limits": window,
          "metadata": {"paths": [sc.path for sc in scans], "levels": levels}, **frame.kwargs(time=len(scans) > 1)}
    if len(data) > 1:
        kw["multiscale"] = True
    return (data if len(data) > 1 else data[0]), kw, "image"


def _contiguous(levels) -> list[int]:
    out = []
    for s in sorted(levels):
        if s != len(out):
            break
        out.append(s)
    return out


def _scan_window(scan, coarsest) -> list[float]:
    """The scan's stored level-0 window (``display_window``), else 1st/99th percentiles of
    a strided sample of its coarsest level (as means)."""

    stored = _store_meta(Path(scan.path)).get("display_window") if scan.path else None
    if stored:
        return [float(stored[0]), float(stored[1])]
    step = sample_step(coarsest.shape, _SAMPLE)
    sample = np.asarray(coarsest[::step, ::step, ::step], dtype=np.float64)
    return contrast_window(sample)


def fields_layers(path) -> list[Layer]:
    """The channels :data:`FIELD_LAYERS` of a fields image (``export --fields``) as
    multiscale images on their stored frame, each with its stored contrast window; only
    ``|U|`` visible. The residual only when it was computed."""
    import dask.array as da

    levels, attrs = open_levels(path)
    meta = attrs["chunkdic"]
    frame = _ngff_frame(attrs["ome"]["multiscales"][0])
    windows = {c["label"]: c["window"] for c in (attrs["ome"].get("omero") or {}).get("channels", [])}
    out = []
    for label in FIELD_LAYERS:
        if label == "residual" and not meta.get("residual"):
            continue
        i = CHANNELS.index(label)
        data = [da.from_zarr(a)[i] for a in levels]
        w = windows.get(label) or {}
        limits = [float(w.get("start", 0.0)), float(w.get("end", 1.0))]
        if label in ("eps_zz", "residual"):
            limits = contrast_window(np.asarray(limits), symmetric=True)
        elif not limits[1] > limits[0]:
            limits = contrast_window(np.asarray(limits))
        kw = {"name": label, "colormap": _COLORMAPS[label], "contrast_limits": limits, "visible": label == "|U|",
              "opacity": 0.6, "blending": "translucent",
              "metadata": {"path": str(path), "channel": label,
                           "unit": meta.get("displacement_unit") if label == "|U|" else None},
              **frame.kwargs()}
        if len(data) > 1:
            kw["multiscale"] = True
        out.append(((data if len(data) > 1 else data[0]), kw, "image"))
    return out


def _ngff_frame(multiscale: dict) -> Frame:
    """Level-0 scale, translation and unit of an OME-NGFF multiscale (its space axes)."""
    scale, shift = [1.0] * 3, [0.0] * 3
    for t in multiscale["datasets"][0].get("coordinateTransformations", []):
        if t.get("type") == "scale":
            scale = [float(v) for v in t["scale"][-3:]]
        elif t.get("type") == "translation":
            shift = [float(v) for v in t["translation"][-3:]]
    units = {a.get("unit") for a in multiscale.get("axes", [])[-3:]}
    return Frame(tuple(scale), tuple(shift), units.pop() if len(units) == 1 else None)


def series_layers(path, *, scan: bool = True, max_vectors: int = MAX_VECTORS) -> list[Layer]:
    """Layers of a loading series with a time axis ``t`` = scan index (module docstring).

    The fields are the cumulative ``u_0→t`` (the cumulative correlation, else the composed
    field) at the reference mesh's nodes; ``t = 0`` is the reference (zero field).
    """

    sr = open_series(path)
    steps = [sr.cumulative[k] for k in sorted(sr.cumulative)]
    if not steps:
        raise InputError(f"series {path} holds no step")
    scans = _series_scans(path, steps[0]) if scan else []
    frame = _frame(scans[0] if scans else None, steps[0].info)
    out = []
    if scans:
        stackable = len({(sc.shape(0), sc.dtype(0)) for sc in scans}) == 1 and len(scans) == len(steps) + 1
        out.append(scan_layer(scans if stackable else scans[:1], frame, "scans" if stackable else "reference"))
    same_mesh = len({(r.mesh, r.level) for r in steps}) == 1
    groups = [steps] if same_mesh else [[r] for r in steps[-1:]]
    out += [nodes_norm_layer(groups[0], frame), element_strain_layer(groups[0], frame)]
    mask = mask_layer(steps[0], frame)
    if mask is not None:
        out.append(mask)
    out.append(vector_layer(groups[0], frame, max_vectors))
    weak = weak_layer(groups[0], frame)
    if weak is not None:
        out.append(weak)
    for _, kw, _ in out:
        kw.setdefault("metadata", {})["series"] = str(path)
    return out


def _series_scans(path, first) -> list:
    """The scans of a series (recorded paths), or only its reference; [] when not on disk."""

    paths = _store_meta(Path(path)).get("scans") or []
    try:
        return [open_scan(p) for p in paths] if paths and all(Path(p).exists() for p in paths) else (
            [r] if (r := _reference(first)) is not None else [])
    except InputError:
        return []
