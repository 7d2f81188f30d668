"""Exports of a correlation result for other tools: VTK mesh (ParaView) and node CSV.

- :func:`write_vtk` writes the C8 mesh as VTK hexahedra (ParaView) with the nodal
  displacement and the element strains, via meshio; a ``.vtu`` file also carries the facts
  of the run as VTK field data (:func:`vtk_field_data`, read back by :func:`read_vtk_metadata`).
- :func:`write_nodes_csv` writes one line per node under a single header line (so that a
  plain ``pandas.read_csv`` reads it), and its metadata to a JSON sidecar ``NAME.csv.json``.

The corrected image and residual volumes are written by :mod:`chunkdic.export.corrected_image`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import InputError
from ..io.kinds import VTK_TITLE, VTU_MARK
from ..io.outputs import Outputs
from ..mesh import level0_position
from ..results.result import Result, jsonable
from ..results.scans import as_result
from ..results.strain import DEFAULT_MEASURE, check_measure, principal_strains

__all__ = ["write_vtk", "write_vtk_file", "write_nodes_csv", "write_nodes_csv_files", "read_vtk_metadata", "csv_sidecar",
           "CSV_COLUMNS", "CSV_PHYSICAL_COLUMNS", "VTK_HEX_ORDER"]

#: local nodes ``(dz, dy, dx)`` in VTK_HEXAHEDRON order: bottom face (z0) counter-clockwise
#: seen from +z starting at the origin, then the top face (z1) in the same order
VTK_HEX_ORDER = ((0, 0, 0), (0, 0, 1), (0, 1, 1), (0, 1, 0), (1, 0, 0), (1, 0, 1), (1, 1, 1), (1, 1, 0))


def _nodal_uncertainty(result: Result, units: str) -> np.ndarray | None:
    """``Result.uncertainty`` (3, nz, ny, nx) in the units of :func:`_positions` (None if absent)."""
    if result.uncertainty is None:
        return None
    if units != "physical":
        return result.uncertainty
    scale = result.scale
    return result.uncertainty * scale * np.asarray(result.info["voxel_size"], float)[:, None, None, None]


def _positions(result: Result, units: str):
    """Node positions and displacement, shape (3, nz, ny, nx), in level voxels or physical units."""
    X, u = result.node_coords, result.displacement
    if units == "voxels":
        return X, u, "voxel, level %d" % result.level
    if units != "physical":
        raise InputError(f"units must be 'voxels' or 'physical', got {units!r}")
    vs = result.info.get("voxel_size")
    if not vs:
        raise InputError("this result has no voxel size: export in voxels, or give the scans a voxel size")
    scale = result.scale
    v = np.asarray(vs, float)[:, None, None, None]
    level0 = level0_position(X, scale)
    return level0 * v, u * scale * v, result.info.get("unit") or "unit"


def hexahedra(nodes_shape) -> np.ndarray:
    """VTK_HEXAHEDRON connectivity of a regular node grid.

    Parameters
    ----------
    nodes_shape : tuple of 3 int
        ``(nz, ny, nx)`` nodes; points are numbered in C order over ``(z, y, x)``.

    Returns
    -------
    ndarray, shape ((nz-1)(ny-1)(nx-1), 8), int64
        Element rows in C order over ``(ez, ey, ex)``, columns in :data:`VTK_HEX_ORDER`.
    """
    nz, ny, nx = nodes_shape
    ez, ey, ex = np.meshgrid(np.arange(nz - 1), np.arange(ny - 1), np.arange(nx - 1), indexing="ij")
    cols = [((ez + dz) * ny + (ey + dy)) * nx + (ex + dx) for dz, dy, dx in VTK_HEX_ORDER]
    return np.stack([c.ravel() for c in cols], axis=1).astype(np.int64)


def write_vtk(result, path, *, units: str = "voxels", overwrite: bool = False, strain: str = DEFAULT_MEASURE) -> dict:
    """Write the C8 mesh, nodal displacement and element strains as a VTK file (meshio).

    Parameters
    ----------
    result : Result or path
    path : path
        Output file; the format follows the suffix (``.vtu`` XML unstructured grid
        recommended, ``.vtk`` legacy).
    units : {"voxels", "physical"}, keyword-only
        Coordinates and displacements in voxels of the result's level (default), or in
        the scan's physical unit (level-0 voxel centres scaled by ``voxel_size``).
    overwrite : bool, keyword-only
        Replace an existing VTK file that chunkdic wrote (nothing else).
    strain : {"green-lagrange", "small"}, keyword-only
        Measure of the cell strains (:mod:`chunkdic.results.strain`): Green–Lagrange by
        default (zero for a rigid rotation), ``"small"`` the paper's; a ``.vtu`` names it in
        its field data (``strain_measure=…``).

    Returns
    -------
    dict
        ``points``, ``cells`` counts, ``unit`` and ``strain`` (the measure).

    Notes
    -----
    VTK orders vector components ``(x, y, z)``: points are ``(x, y, z)``; point data
    ``displacement`` is ``(Ux, Uy, Uz)`` plus scalars ``Ux, Uy, Uz`` (in voxels, when the
    scan has a voxel size also ``displacement_physical`` in its unit); cell data ``strain``
    is the 9-component tensor in ``(x, y, z)`` order, plus scalars ``eps_xx`` … ``eps_xy``,
    ``volume_change`` = tr(eps) and ``max_abs_principal``.
    """
    result = as_result(result)
    check_measure(strain)
    plan = Outputs(inputs=[result.path] if result.path else [], overwrite=overwrite)
    entry = plan.add(path, "vtk")
    _positions(result, units)  # a bad unit refused before anything is written
    with plan:
        return write_vtk_file(result, entry.work, units=units, strain=strain)


def write_vtk_file(result: Result, work: Path, *, units: str, strain: str) -> dict:
    """:func:`write_vtk` into ``work`` (outputs checked by the caller, e.g. a ParaView series
    that stages its folder in one :class:`~chunkdic.io.outputs.Outputs`)."""
    import meshio

    X, u, unit = _positions(result, units)
    n = X.shape[1:]
    points = np.stack([X[2].ravel(), X[1].ravel(), X[0].ravel()], axis=1)
    disp = np.stack([u[2].ravel(), u[1].ravel(), u[0].ravel()], axis=1)
    cells = hexahedra(n)
    eps = result.element_strain(strain)  # (3, 3, ez, ey, ex), axes z, y, x
    if result.active is not None:  # a specimen mask: no strain where there is no material
        eps = np.where(result.active[None, None] > 0, eps, np.nan)
    eps_xyz = eps[::-1, ::-1].reshape(3, 3, -1).transpose(2, 0, 1).reshape(-1, 9)
    cell_data = {"strain": [eps_xyz]}
    names = "zyx"
    for i, j in ((2, 2), (1, 1), (0, 0), (1, 2), (0, 2), (0, 1)):
        cell_data[f"eps_{names[j]}{names[i]}" if i < j else f"eps_{names[i]}{names[j]}"] = [eps[i, j].ravel()]
    cell_data["volume_change"] = [np.trace(eps).ravel()]
    cell_data["max_abs_principal"] = [np.abs(principal_strains(eps)).max(axis=0).ravel()]
    if result.active is not None:
        cell_data["active"] = [result.active.ravel().astype(np.int32)]
    point_data = {"displacement": disp, "Ux": disp[:, 0], "Uy": disp[:, 1], "Uz": disp[:, 2]}
    if units == "voxels" and result.voxel_length() is not None:  # the scan's unit too
        point_data["displacement_physical"] = disp * result.voxel_length()[::-1]
    sigma = _nodal_uncertainty(result, units)
    if sigma is not None:  # per-node standard uncertainty, same units and component order
        point_data["uncertainty"] = np.stack([sigma[2].ravel(), sigma[1].ravel(), sigma[0].ravel()], axis=1)
    if result.flags is not None:  # chunkdic.results.result.FLAG_*: no data, weak texture, masked
        point_data["flags"] = result.flags.ravel().astype(np.int32)
    mesh = meshio.Mesh(points, [("hexahedron", cells)], point_data=point_data, cell_data=cell_data)
    work = Path(work)
    mesh.write(str(work))
    if work.suffix.lower() == ".vtu":
        _insert_field_data(work, {**vtk_field_data(result, unit), f"strain_measure={strain}": np.array([1], np.int32)})
    _mark_vtk(work)
    return {"points": len(points), "cells": len(cells), "unit": unit, "strain": strain}


def _version_of(result: Result) -> str:

    return str(result.info.get("chunkdic_version") or __version__)


def vtk_field_data(result: Result, coordinates: str) -> dict[str, np.ndarray]:
    """The facts of a run as VTK field data (arrays for the whole dataset).

    VTK field data are numeric arrays; meshio reads back numbers only, so a text fact is
    the name of a one-value array, ``"KEY=VALUE"`` (``"unit=micrometer"``,
    ``"status=converged"``), which ParaView lists by name (Information panel, spreadsheet
    view's Field Data). :func:`read_vtk_metadata` turns both back into a dict.

    Parameters
    ----------
    result : Result
    coordinates : str
        Unit of the points and displacements (``"voxel, level 0"``, ``"micrometer"``).

    Returns
    -------
    dict of str to ndarray
        ``element_size`` (voxels of ``level``), ``level``, ``scale`` (a level voxel in
        level-0 voxels), ``voxel_size`` (physical size of a level-0 voxel, ``(x, y, z)``
        order as every VTK vector; only when known), ``final_gap``, ``initial_gap``,
        ``converged`` (0/1), and the text facts ``unit=…`` (of ``voxel_size``),
        ``coordinates=…``, ``status=…``, ``chunkdic_version=…``.
    """
    info = result.info
    data = {"element_size": np.array([float(info["element_size"])]),
            "level": np.array([int(info.get("level", 0))], np.int32),
            "scale": np.array([float(info.get("scale", 1))])}
    if info.get("voxel_size"):
        data["voxel_size"] = np.asarray(info["voxel_size"], float)[::-1].copy()  # VTK order (x, y, z)
    for key in ("final_gap", "initial_gap"):
        if info.get(key) is not None:
            data[key] = np.array([float(info[key])])
    if (info.get("regularization") or {}).get("nominal_l10"):  # level-0 voxels, a lower bound
        data["nominal_l10"] = np.array([float(info["regularization"]["nominal_l10"])])
    data["converged"] = np.array([int(bool(info.get("converged", False)))], np.int32)
    texts = {"unit": info.get("unit") if info.get("voxel_size") else None, "coordinates": coordinates,
             "status": info.get("status"), "chunkdic_version": _version_of(result)}
    for key, value in texts.items():
        if value:
            data[f"{key}={value}"] = np.array([1], np.int32)  # Int32: VTK shows Int8 as a character
    return data


_VTK_TYPES = {"f": "Float64", "i": "Int32"}


def _mark_vtk(path: Path) -> None:
    """Put chunkdic's own mark in the header of the VTK file meshio wrote at ``path``
    (:data:`chunkdic.io.kinds.VTU_MARK` / ``VTK_TITLE``): ``--overwrite`` replaces only a
    file that carries it, never another meshio user's file."""

    text = path.read_bytes()
    if text.startswith(b"<?xml"):
        first = text.index(b"\n") + 1
        second = text.index(b"\n", first) + 1  # after <VTKFile ...>
        text = text[:second] + VTU_MARK + b"\n" + text[second:]
    else:  # legacy VTK: line 2 is a free title of at most 256 characters
        first = text.index(b"\n") + 1
        end = text.index(b"\n", first)
        text = text[:first] + VTK_TITLE + b" (" + text[first:end][:200] + b")" + text[end:]
    path.write_bytes(text)


def _insert_field_data(path: Path, data: dict[str, np.ndarray]) -> None:
    """Add ``<FieldData>`` to a VTU file written by meshio (its writer leaves field data out).

    The element goes first inside ``<UnstructuredGrid>``, where VTK puts a dataset's field
    data; arrays are ASCII with ``NumberOfTuples`` (VTK's XML reader needs it there).
    """
    from xml.sax.saxutils import quoteattr

    rows = []
    for name, arr in data.items():
        arr = np.asarray(arr).ravel()
        kind = arr.dtype.kind
        values = " ".join(repr(float(v)) if kind == "f" else str(int(v)) for v in arr)
        rows.append(f'<DataArray type="{_VTK_TYPES[kind]}" Name={quoteattr(name)} NumberOfTuples="{arr.size}" '
                    f'format="ascii">{values}</DataArray>')
    block = "<FieldData>\n" + "\n".join(rows) + "\n</FieldData>\n"
    text = path.read_bytes()  # mesh-sized: a few MB per 10^5 nodes
    tag = b"<UnstructuredGrid>\n"
    at = text.find(tag)
    if at < 0:
        raise RuntimeError(f"{path}: no <UnstructuredGrid> element in meshio's output")
    at += len(tag)
    path.write_bytes(text[:at] + block.encode() + text[at:])


def read_vtk_metadata(path) -> dict:
    """The facts of a run stored in a ``.vtu`` file by :func:`write_vtk` (via meshio).

    Returns
    -------
    dict
        Numbers as floats / ints (``voxel_size`` a tuple ``(x, y, z)``), text facts
        (``"KEY=VALUE"`` arrays) as strings.
    """
    import meshio

    out = {}
    for name, arr in meshio.read(str(path)).field_data.items():
        if "=" in name:
            key, value = name.split("=", 1)
            out[key] = value
            continue
        arr = np.asarray(arr).ravel()
        vals = [v.item() for v in arr]
        out[name] = vals[0] if len(vals) == 1 else tuple(vals)
    return out


#: columns of the node table (after ``iz, iy, ix``: positions, displacements, their standard
#: uncertainties, flags); its first line, by which :mod:`chunkdic.io.kinds` recognises it
CSV_COLUMNS = ("iz", "iy", "ix", "z", "y", "x", "Uz", "Uy", "Ux", "sigma_Uz", "sigma_Uy", "sigma_Ux", "flags")
#: columns added when the table is in voxels and the scan has a voxel size: positions
#: (level-0 voxel centres) and displacements in the scan's unit
CSV_PHYSICAL_COLUMNS = ("z_physical", "y_physical", "x_physical", "Uz_physical", "Uy_physical", "Ux_physical")


def csv_sidecar(path) -> Path:
    """The JSON sidecar of a node table: ``NAME.csv`` -> ``NAME.csv.json``."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def write_nodes_csv(result, path, *, units: str = "voxels", overwrite: bool = False) -> int:
    """One CSV line per node, and the table's metadata in a JSON sidecar (returns the row count).

    Parameters
    ----------
    result : Result or path
    path : path
        The table: a single header line (:data:`CSV_COLUMNS`, then
        :data:`CSV_PHYSICAL_COLUMNS` when ``units="voxels"`` and the scan has a voxel
        size) and one line per node, in C order over ``(iz, iy, ix)``;
        ``pandas.read_csv(path)`` reads it as is. NaN for a node that was not measured.
    units : {"voxels", "physical"}, keyword-only
        Positions, displacements and uncertainties in voxels of the result's level
        (default) or in the scan's physical unit.
    overwrite : bool, keyword-only
        Replace a node table (and its sidecar) that chunkdic wrote, nothing else.

    Notes
    -----
    The sidecar :func:`csv_sidecar` (``NAME.csv.json``) holds ``kind``, the unit of every
    column, the flag bits, element size, level, voxel size, status, gap and version. Both
    files are written staged and renamed into place together (:mod:`chunkdic.io.outputs`).
    """
    result = as_result(result)
    plan = Outputs(inputs=[result.path] if result.path else [], overwrite=overwrite)
    entry = plan.add(path, "csv")
    meta = plan.add(csv_sidecar(path), "csv-meta")
    with plan:
        return write_nodes_csv_files(result, entry.work, meta.work, units=units, name=Path(path).name)


def write_nodes_csv_files(result: Result, csv_path: Path, json_path: Path, *, units: str, name: str) -> int:
    """:func:`write_nodes_csv` into ``csv_path`` / ``json_path`` (outputs checked by the caller, e.g.
    ``chunkdic export``, which stages several outputs in one :class:`~chunkdic.io.outputs.Outputs`)."""
    X, u, unit = _positions(result, units)
    idx = np.indices(X.shape[1:]).reshape(3, -1).T
    sigma = _nodal_uncertainty(result, units)
    if sigma is None:
        sigma = np.full_like(u, np.nan)
    flags = np.zeros(X.shape[1:], np.uint8) if result.flags is None else result.flags
    data = np.column_stack([idx, X.reshape(3, -1).T, u.reshape(3, -1).T, sigma.reshape(3, -1).T, flags.reshape(-1)])
    fmt = ["%d"] * 3 + ["%.6f"] * 3 + ["%.8g"] * 6 + ["%d"]
    columns = CSV_COLUMNS
    if units == "voxels" and result.voxel_length() is not None:  # the scan's unit too
        Xp, up, _ = _positions(result, "physical")
        data = np.column_stack([data, Xp.reshape(3, -1).T, up.reshape(3, -1).T])
        fmt += ["%.8g"] * 6
        columns = CSV_COLUMNS + CSV_PHYSICAL_COLUMNS
    np.savetxt(csv_path, data, delimiter=",", header=",".join(columns), comments="", fmt=fmt)
    meta = _csv_metadata(result, unit, name)
    meta["columns"].update({c: result.info.get("unit") or "unit" for c in columns[len(CSV_COLUMNS):]})
    json_path.write_text(json.dumps(jsonable(meta), indent=2) + "\n")
    return len(data)


def _csv_metadata(result: Result, unit: str, name: str) -> dict:
    """The sidecar of a node table (``kind`` first: :mod:`chunkdic.io.kinds` reads it)."""
    info = result.info
    length = {"iz": "1", "iy": "1", "ix": "1", "flags": "1"}
    return {
        "kind": "csv-meta",
        "table": name,
        "description": "chunkdic node table: one line per node of the C8 mesh, C order over (iz, iy, ix); "
                       "positions z, y, x, displacements Uz, Uy, Ux and their standard uncertainties "
                       "sigma_U*; NaN where not measured",
        "columns": {c: length.get(c, unit) for c in CSV_COLUMNS},
        "unit": unit,
        "flags": {"1": "no data (displacement NaN)", "2": "weak texture (regularised, unreliable)",
                  "4": "outside the specimen mask (NaN)"},
        "element_size": info.get("element_size"),
        "regularization": info.get("regularization"),
        "level": info.get("level", 0),
        "scale": info.get("scale", 1),
        "voxel_size": info.get("voxel_size"),
        "voxel_unit": info.get("unit"),
        "status": info.get("status"),
        "final_gap": info.get("final_gap"),
        "result": result.path,
        "chunkdic_version": _version_of(result),
    }
