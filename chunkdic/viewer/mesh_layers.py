"""napari layers of a result's mesh-sized data: its nodes and elements, in the scan's physical frame.

The displacement vectors (sub-sampled to at most :data:`MAX_VECTORS` nodes), the weak nodes
as points, ``|U|`` on the node grid and ``eps_zz`` per element when no fields image is at
hand, the mask's active elements as labels; a loading series stacks each along a leading
time axis. :mod:`chunkdic.viewer.layers` composes them with the scans and fields images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.formats.anyscan import open_any
from ..mesh import level0_position
from ..results.result import FLAG_WEAK


#: the most displacement vectors one layer shows per time step (a stride per axis keeps it under)
Layer = tuple  # (data, kwargs, layer_type)

MAX_VECTORS = 4000
#: the longest vector is drawn this fraction of the shown node spacing
VECTOR_FILL = 0.8
#: a weak node's marker: this fraction of the element edge across (level-0 voxels)
WEAK_MARKER = 0.4


def contrast_window(values: np.ndarray, *, symmetric: bool = False) -> list[float]:
    """Contrast limits of ``values``: 1st/99th percentiles (``±`` the larger when
    ``symmetric``), widened when they coincide (napari needs ``lo < hi``)."""
    v = values[np.isfinite(values)]
    if v.size == 0:
        return [-1.0, 1.0] if symmetric else [0.0, 1.0]
    lo, hi = (float(q) for q in np.percentile(v, [1, 99]))
    if symmetric:
        hi = max(abs(lo), abs(hi), float(np.abs(v).max()) * 1e-3)
        lo = -hi
    if not hi > lo:
        pad = max(abs(hi), 1.0) * 1e-6
        lo, hi = lo - pad, hi + pad
    return [lo, hi]



@dataclass(frozen=True)
class Frame:
    """Level-0 placement of the reference scan: world = ``shift + scale * level-0 voxel``.

    Attributes
    ----------
    scale, shift : tuple of 3 float
        ``(z, y, x)``, in ``unit`` (voxels when ``unit`` is None).
    unit : str or None
        OME-NGFF length unit.
    """

    scale: tuple[float, float, float]
    shift: tuple[float, float, float]
    unit: str | None

    def kwargs(self, *, scale=(1.0, 1.0, 1.0), offset=(0.0, 0.0, 0.0), time: bool = False) -> dict:
        """napari placement of data whose index ``j`` is at level-0 coordinate ``offset + scale j``."""
        s = [float(a * b) for a, b in zip(self.scale, scale)]
        t = [float(o + a * b) for o, a, b in zip(self.shift, self.scale, offset)]
        kw = {"scale": ([1.0] if time else []) + s, "translate": ([0.0] if time else []) + t,
              "axis_labels": (("t",) if time else ()) + ("z", "y", "x")}
        if self.unit:
            kw["units"] = (("dimensionless",) if time else ()) + (self.unit,) * 3
        return kw


def _grid(res, *, elements: bool) -> tuple[tuple, tuple]:
    """``(scale, offset)`` in level-0 voxels of a result's node grid (``elements=False``)
    or element-centre grid: index ``k`` at level-``s`` coordinate ``o + k ell - 0.5``
    (nodes) or ``o + k ell + (ell - 1)/2`` (centres)."""
    mesh, f = res.mesh, 2.0**res.level
    first = [o + ((mesh.element_size - 1) / 2 if elements else -0.5) for o in mesh.origin]
    return (mesh.element_size * f,) * 3, tuple(float(v) for v in level0_position(first, f))


def _displacement(res, frame: Frame) -> np.ndarray:
    """Nodal displacement ``(3, nz, ny, nx)`` in the frame's unit (level-0 voxels × scale)."""
    return res.displacement * 2.0**res.level * np.reshape(frame.scale, (3, 1, 1, 1))


def _stack(values: list[np.ndarray], time: bool) -> np.ndarray:
    """One array, or the time stack with ``t = 0`` (the reference: zero field) first."""
    if not time:
        return values[0]
    return np.stack([np.zeros_like(values[0])] + values)


def nodes_norm_layer(results, frame: Frame) -> Layer:
    """``|U|`` on the node grid (mesh-sized), in the frame's unit."""
    time = len(results) > 1
    values = [np.sqrt((_displacement(r, frame) ** 2).sum(axis=0)).astype(np.float32) for r in results]
    data = _stack(values, time)
    scale, offset = _grid(results[0], elements=False)
    return data, {"name": "|U| (nodes)", "colormap": "viridis", "contrast_limits": contrast_window(data), "opacity": 0.6,
                  "visible": False, "metadata": {"unit": frame.unit or "level-0 voxels"},
                  **frame.kwargs(scale=scale, offset=offset, time=time)}, "image"


def element_strain_layer(results, frame: Frame) -> Layer:
    """``eps_zz`` per element (the result's element strain), NaN outside the mask."""
    time = len(results) > 1
    values = []
    for r in results:
        e = np.array(r.element_strain()[0, 0], dtype=np.float32)
        if r.active is not None:
            e[~(r.active > 0)] = np.nan
        values.append(e)
    data = _stack(values, time)
    scale, offset = _grid(results[0], elements=True)
    return data, {"name": "eps_zz (elements)", "colormap": "bwr", "contrast_limits": contrast_window(data, symmetric=True),
                  "opacity": 0.6, "visible": False, **frame.kwargs(scale=scale, offset=offset, time=time)}, "image"


def mask_layer(res, frame: Frame) -> Layer | None:
    """The specimen mask as Labels (1 = material): the recorded mask file at level 0 when
    it opens, else the result's active elements on the element grid; None without a mask."""
    src = (res.info.get("inputs") or {}).get("mask")
    kw = {"name": "mask", "opacity": 0.3, "visible": False, "metadata": {"source": src}}
    if isinstance(src, str) and Path(src).exists():
        try:
            level0 = open_any(src).level(0)  # a TIFF or HDF5 mask too, read in place
        except InputError:
            level0 = None
        if level0 is not None:
            return (level0 != 0).astype(np.uint8), {**kw, **frame.kwargs()}, "labels"
    if res.active is None:
        return None
    scale, offset = _grid(res, elements=True)
    kw["metadata"] = {"source": "active elements"}
    return (np.asarray(res.active) > 0).astype(np.uint8), {**kw, **frame.kwargs(scale=scale, offset=offset)}, "labels"


def stride(shape, limit: int) -> int:
    """The smallest stride ``k`` with ``prod(ceil(n / k)) <= limit`` (one per axis).

    Examples
    --------
    >>> stride((10, 10, 10), 1000), stride((10, 10, 10), 999), stride((10, 10, 10), 1)
    (1, 2, 10)
    """
    if limit < 1:
        raise InputError(f"the number of vectors must be at least 1, got {limit}")
    k = 1
    while math.prod(-(-n // k) for n in shape) > limit:
        k += 1
    return k


def vector_layer(results, frame: Frame, max_vectors: int = MAX_VECTORS) -> Layer:
    """The nodal displacement of one result (3-D) or of the steps of a series (4-D, ``t``
    = step ``1..n``) as napari Vectors, sub-sampled and coloured by ``|U|``.

    Positions and directions are level-0 voxels (napari's ``scale``/``translate`` place them
    in the frame, directions scaled per axis as positions); NaN nodes are left out.
    """
    time = len(results) > 1
    k = stride(results[0].displacement.shape[1:], max_vectors)
    rows, norms = [], []
    for t, r in enumerate(results, start=1):
        sel = (slice(None),) + (slice(None, None, k),) * 3
        X = level0_position(r.node_coords[sel], 2.0**r.level).reshape(3, -1).T
        d = (r.displacement[sel] * 2.0**r.level).reshape(3, -1).T
        ok = np.isfinite(d).all(axis=1) & np.isfinite(X).all(axis=1)
        X, d = X[ok], d[ok]
        norms.append(np.sqrt(((d * np.asarray(frame.scale)) ** 2).sum(axis=1)))
        if time:
            X = np.column_stack([np.full(len(X), float(t)), X])
            d = np.column_stack([np.zeros(len(d)), d])
        rows.append(np.stack([X, d], axis=1))
    data = np.concatenate(rows).astype(np.float32) if rows else np.zeros((0, 2, 4 if time else 3), np.float32)
    norm = np.concatenate(norms)
    spacing = k * results[0].mesh.element_size * 2.0**results[0].level * min(frame.scale)
    top = float(norm.max()) if norm.size else 0.0
    length = VECTOR_FILL * spacing / top if top > 0 else 1.0
    kw = {"name": "displacement", "features": {"|U|": norm.astype(np.float32)}, "edge_color": "|U|",
          "edge_colormap": "viridis", "length": float(length), "vector_style": "arrow",
          "edge_width": float(max(1.0, 0.1 * k * results[0].mesh.element_size * 2.0**results[0].level)),
          "metadata": {"length": float(length), "stride": k, "unit": frame.unit or "level-0 voxels",
                       "vectors_per_step": [len(r) for r in rows]},
          **frame.kwargs(time=time)}
    return data, kw, "vectors"


def weak_layer(results, frame: Frame) -> Layer | None:
    """The nodes flagged weak (:data:`chunkdic.results.result.FLAG_WEAK`) of one result (3-D)
    or of the steps of a series (4-D, ``t`` = step ``1..n``) as napari Points; None when no
    node is flagged (or the results carry no flags).

    A weak node's value is regularised or not settled at the noise level: the points say
    where the field is the regulariser's rather than the scans' (what the VTU and CSV
    exports' ``flags`` say, shown on the scan). Positions are level-0 voxels, placed in the
    frame like every layer; the name carries the count (``weak nodes (12)``; a series: the
    most on any step), the features the node index and its flag bits (napari's status bar
    and tooltip show them for the point under the cursor).

    Parameters
    ----------
    results : list of Result
        One result, or the cumulative steps of a series (one mesh).
    frame : Frame

    Returns
    -------
    (data, kwargs, "points") or None
        ``data`` shape ``(k, 3)`` (``(k, 4)`` with ``t`` first for a series), float32,
        level-0 voxels.
    """
    time = len(results) > 1
    rows, index, bits, counts = [], [], [], []
    for t, r in enumerate(results, start=1):
        flags = np.zeros(r.displacement.shape[1:], np.uint8) if r.flags is None else np.asarray(r.flags)
        nodes = np.nonzero(flags & FLAG_WEAK)
        X = level0_position(r.node_coords[(slice(None), *nodes)], 2.0**r.level).T  # (k, 3)
        if time:
            X = np.column_stack([np.full(len(X), float(t)), X])
        rows.append(X)
        index.append(np.column_stack(nodes))
        bits.append(flags[nodes])
        counts.append(len(X))
    if not any(counts):
        return None
    index = np.concatenate(index).astype(np.int32)
    res = results[0]
    size = WEAK_MARKER * res.mesh.element_size * 2.0**res.level
    name = f"weak nodes ({counts[0]})" if not time else f"weak nodes (up to {max(counts)} per step)"
    kw = {"name": name, "symbol": "x", "size": float(size), "face_color": "orangered", "opacity": 0.9,
          "out_of_slice_display": True,  # nodes sit half a voxel off the voxel planes a slice shows
          "features": {"iz": index[:, 0], "iy": index[:, 1], "ix": index[:, 2],
                       "flags": np.concatenate(bits).astype(np.int32)},
          "metadata": {"count": counts[0] if not time else counts, "flag": FLAG_WEAK,
                       "meaning": "weak node: poorly textured, regularised, or not settled at the noise level"},
          **frame.kwargs(time=time)}
    return np.concatenate(rows).astype(np.float32), kw, "points"
