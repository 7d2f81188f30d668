"""The files of ``chunkdic crack -o DIR``: the cracks' surfaces for ParaView and napari, their table.

- ``cracks.vtu``: each crack element's piece of surface, the polygon where the plane through
  the element's centre with the element's normal cuts the element's cube (3 to 6 vertices),
  with cell data ``crack`` (its number), ``opening``, ``sliding`` and their ``sigma_*``,
  ``jump``, ``residual_ratio`` and ``normal``; points ``(x, y, z)`` in voxels of the result's
  level (or the scan's unit). A ParaView user colours the surface by the opening.
- ``cracks-labels.zarr``: an OME-NGFF 0.5 labels image (``image-label``) on the element grid,
  one voxel per element holding its crack's number, placed on the scan's frame (scale the
  element's size, translation the first element's centre): napari-ome-zarr opens it as a
  labels layer over the reference scan. Mesh-sized.
- ``cracks.csv``: one line per crack element; ``cracks.json``: the cracks (:meth:`CrackMap.as_dict`).

Takes the per-element arrays of :class:`chunkdic.analysis.cracks.CrackMap` (this layer does
not import the analyses).
"""

from __future__ import annotations

import itertools
import json

import numpy as np

from ..io.ngff import multiscales
from ..mesh import level0_position

__all__ = ["write_crack_files", "cube_section"]

#: the 12 edges of the unit cube, as pairs of corner indices of ``itertools.product((0, 1), repeat=3)``
_CORNERS = np.array(list(itertools.product((0.0, 1.0), repeat=3)))
_EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8) if np.abs(_CORNERS[a] - _CORNERS[b]).sum() == 1]


def cube_section(centre, half: float, normal) -> np.ndarray:
    """The polygon where the plane through ``centre`` with ``normal`` cuts the cube of half-edge
    ``half`` around it: vertices (k, 3), k in 3..6, in order around the polygon."""
    c = np.asarray(centre, np.float64)
    n = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    corners = c + (2 * _CORNERS - 1) * half
    side = (corners - c) @ n
    points = []
    for a, b in _EDGES:
        if (side[a] > 0) != (side[b] > 0):
            t = side[a] / (side[a] - side[b])
            points.append(corners[a] + t * (corners[b] - corners[a]))
    pts = np.unique(np.round(np.array(points), 12), axis=0)
    e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    angle = np.arctan2((pts - c) @ e2, (pts - c) @ e1)
    return pts[np.argsort(angle)]


def _frame(result, units: str):
    """Positions of level voxels in the output unit: ``p -> p * factor + offset`` per axis."""
    if units == "physical" and result.voxel_size is not None:
        vs = np.asarray(result.voxel_size, np.float64)
        return result.scale * vs, (result.scale - 1) / 2 * vs, result.unit
    return np.ones(3), np.zeros(3), f"voxel, level {result.level}"


def write_crack_files(result, cmap, out, *, units: str = "voxels") -> dict:
    """Write ``cracks.vtu``, ``cracks-labels.zarr``, ``cracks.csv`` and ``cracks.json`` into ``out``.

    Parameters
    ----------
    result : Result
    cmap : CrackMap
        :func:`chunkdic.analysis.cracks.find_cracks` of ``result``.
    out : path
        The folder (created and owned by the caller, :mod:`chunkdic.io.outputs`).
    units : {"voxels", "physical"}
        Coordinates of the surface (the openings stay in voxels of the result's level).

    Returns
    -------
    dict
        ``files`` written and ``polygons`` count.
    """
    import meshio

    from pathlib import Path

    out = Path(out)
    centres = np.stack(np.meshgrid(*result.mesh.element_axes(), indexing="ij"))
    factor, offset, unit = _frame(result, units)
    half = result.mesh.element_size / 2.0
    elements = [tuple(int(v) for v in e) for e in np.argwhere(cmap.labels > 0)]
    points, blocks, data = [], {}, {}
    names = ("crack", "opening", "sigma_opening", "sliding", "sigma_sliding", "jump", "residual_ratio")
    arrays = {"crack": cmap.labels, "opening": cmap.opening, "sigma_opening": cmap.sigma_opening,
              "sliding": cmap.sliding, "sigma_sliding": cmap.sigma_sliding, "jump": cmap.jump,
              "residual_ratio": cmap.residual_ratio}
    for e in elements:
        poly = cube_section(centres[(slice(None),) + e], half, cmap.normal[(slice(None),) + e])
        ids = list(range(len(points), len(points) + len(poly)))
        points.extend((poly * factor + offset)[:, ::-1])  # VTK: (x, y, z)
        kind = {3: "triangle", 4: "quad"}.get(len(poly), "polygon")
        key = (kind, len(poly))
        blocks.setdefault(key, []).append(ids)
        row = data.setdefault(key, {n: [] for n in names + ("normal",)})
        for n in names:
            row[n].append(float(arrays[n][e]))
        row["normal"].append(cmap.normal[(slice(None),) + e][::-1])
    keys = list(blocks)
    cells = [(k[0], np.asarray(blocks[k], np.int64)) for k in keys]
    cell_data = {n: [np.asarray(data[k][n]) for k in keys] for n in names + ("normal",)}
    files = {"vtu": out / "cracks.vtu", "labels": out / "cracks-labels.zarr", "csv": out / "cracks.csv",
             "json": out / "cracks.json"}
    mesh = meshio.Mesh(np.asarray(points, np.float64).reshape(-1, 3), cells, cell_data=cell_data if keys else {})
    mesh.write(str(files["vtu"]))
    _write_labels(result, cmap.labels, files["labels"])
    with open(files["csv"], "w") as fh:
        fh.write("ez,ey,ex,z,y,x," + ",".join(names) + ",nz,ny,nx\n")
        for e in elements:
            c = centres[(slice(None),) + e]
            fh.write(",".join(map(str, e)) + "," + ",".join(f"{v:.6g}" for v in c) + ","
                     + ",".join(f"{float(arrays[n][e]):.8g}" for n in names) + ","
                     + ",".join(f"{v:.6f}" for v in cmap.normal[(slice(None),) + e]) + "\n")
    files["json"].write_text(json.dumps({"result": result.path, "coordinates": unit, **cmap.as_dict()}, indent=2)
                             + "\n")
    return {"files": {k: str(v) for k, v in files.items()}, "polygons": len(elements)}


def _write_labels(result, labels: np.ndarray, path) -> None:
    """The crack numbers per element as an OME-NGFF 0.5 labels image on the scan's frame."""
    import zarr

    vs = np.asarray(result.voxel_size, np.float64) if result.voxel_size is not None else np.ones(3)
    ell0 = result.mesh.element_size * result.scale
    first = np.array([level0_position(a[0], result.scale) for a in result.mesh.element_axes()])
    root = zarr.open_group(str(path), mode="w", zarr_format=3)
    root.create_array("0", data=np.ascontiguousarray(labels, np.uint16), dimension_names=["z", "y", "x"])
    ome = multiscales("cracks", [0], (ell0 * vs).tolist(), (first * vs).tolist(),
                      result.unit if result.voxel_size is not None else None, kind="labels",
                      description="crack number per C8 element (0: none)", method="chunkdic crack")
    n = int(labels.max())
    rng = np.random.default_rng(0)
    ome["image-label"] = {"version": "0.5",
                          "colors": [{"label-value": k, "rgba": [int(v) for v in rng.integers(64, 256, 3)] + [255]}
                                     for k in range(1, n + 1)],
                          "properties": [{"label-value": k, "name": f"crack {k}"} for k in range(1, n + 1)]}
    root.attrs.update({"ome": ome, "chunkdic": {"kind": "cracks-labels", "complete": True, "result": result.path}})
