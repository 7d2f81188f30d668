"""A loading series as a ParaView time series: one VTK file per step and a ``.pvd`` collection.

``chunkdic export SERIES.zarr --pvd DIR`` writes ``DIR/step-000.vtu`` (the reference: the mesh
with zero displacement), ``DIR/step-001.vtu`` … (each step's field from the reference: the
cumulative correlation, or the composed field; :func:`chunkdic.open_series`) with
:func:`chunkdic.export.meshfiles.write_vtk_file`, and ``DIR/series.pvd``, the VTK collection that
ParaView opens as one dataset with a time slider (``timestep`` = the step number). Every step
lives on the reference mesh, so ParaView's *Warp By Vector* and *Plot Over Time* work across
steps.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from ..io.outputs import Outputs
from ..results.strain import DEFAULT_MEASURE, check_measure
from .meshfiles import write_vtk_file

__all__ = ["write_pvd", "PVD_NAME"]

#: the collection's file name in the folder
PVD_NAME = "series.pvd"


def write_pvd(series, out_dir, *, units: str = "voxels", strain: str = DEFAULT_MEASURE, overwrite: bool = False,
              transform=None) -> dict:
    """Write a loading series as a ParaView time series (module docstring).

    Parameters
    ----------
    series : SeriesResult
        :func:`chunkdic.open_series` of the series store.
    out_dir : path
        The folder to create (``pvd`` kind: ``series.pvd``, ``step-*.vtu``).
    units, strain
        As in :func:`chunkdic.write_vtk`.
    overwrite : bool
        Replace a folder an earlier export wrote.
    transform : callable(Result) -> Result, optional
        Applied to each step before it is written (``--remove-rigid``).

    Returns
    -------
    dict
        ``path`` (the ``.pvd``), ``steps`` (written, the reference included).
    """
    check_measure(strain)
    steps = sorted(series.cumulative.items())
    plan = Outputs(inputs=[series.path], overwrite=overwrite)
    out = plan.add(out_dir, "pvd")
    first = steps[0][1]
    reference = dataclasses.replace(first, displacement=np.where(np.isfinite(first.displacement), 0.0, np.nan),
                                    strain=None, info={**first.info, "status": "reference"})
    entries = []
    with plan:
        out.work.mkdir(parents=True, exist_ok=True)
        for k, res in [(0, reference)] + steps:
            name = f"step-{k:03d}.vtu"
            write_vtk_file(res if transform is None or k == 0 else transform(res), out.work / name, units=units,
                           strain=strain)
            entries.append(f'    <DataSet timestep="{k}" group="" part="0" file={quoteattr(name)}/>')
        (out.work / PVD_NAME).write_text(
            '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
            "  <Collection>\n" + "\n".join(entries) + "\n  </Collection>\n</VTKFile>\n")
    return {"path": str(Path(out_dir) / PVD_NAME), "steps": len(entries)}
