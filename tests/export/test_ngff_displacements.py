"""Exports for other tools: the OME-NGFF 0.6 displacement field (read back by ngff-zarr, an
independent reader and ITK bridge) and a loading series as a ParaView time series; gauges over it."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest
import zarr

import chunkdic
from chunkdic.analysis.gauge import gauge
from chunkdic.cli.app import main
from chunkdic.mesh import level0_position
from chunkdic.synth import synthetic

ngff_zarr = pytest.importorskip("ngff_zarr")

N, ELL = 40, 8
C = (N - 1) / 2


def _field(k: int):
    return synthetic.Affine(matrix=((-0.01 * k, 0, 0), (0, 0, 0), (0, 0, 0)), center=(C, C, C),
                            translation=(0.3 * k, -0.2 * k, 0.1 * k))


@pytest.fixture(scope="module")
def series_dir(tmp_path_factory):
    """Three scans of one foam (2.5 µm voxels), scan k under −k % along z; a cumulative series."""
    d = tmp_path_factory.mktemp("ngff")
    scans = []
    for k in range(3):
        lazy = synthetic.as_dask((N,) * 3, chunks=N, field=None if k == 0 else _field(k), seed=6,
                                 which="reference" if k == 0 else "deformed", dtype="float32")
        scans.append(d / f"scan{k}.zarr")
        chunkdic.write_scan(scans[-1], lazy, voxel_size=2.5, unit="micrometer")
    chunkdic.series(scans, d / "series.zarr", element_size=ELL, regularization="none", mode="cumulative")
    return d


def test_displacements_are_an_ngff_06_transformation_read_back_by_ngff_zarr(series_dir, tmp_path):
    """The scene and the field, validated by ngff-zarr against the 0.6 schemas: axis types, unit,
    per-level scale and translation, the values in micrometer at every node, and ITK's field (through
    ngff-zarr's bridge) the same vectors in (x, y, z) order."""
    res = chunkdic.open_result(series_dir / "series.zarr" / "steps" / "002-cumulative")
    out = tmp_path / "displacement.zarr"
    assert main(["export", str(res.path), "--displacements", str(out), "-q"]) == 0
    scene = ngff_zarr.from_ome_zarr(str(out), kind="scene", validate=True)
    (t,) = scene.coordinateTransformations
    assert (t.type, t.input.name, t.output.name, t.interpolation) == ("displacements", "reference", "deformed",
                                                                       "linear")
    assert [a.unit for s in scene.coordinateSystems for a in s.axes] == ["micrometer"] * 6
    field = ngff_zarr.from_ome_zarr(str(out / t.path), validate=True)
    axes = field.metadata.coordinateSystems[0].axes
    assert [(a.name, a.type) for a in axes] == [("c", "displacement"), ("z", "space"), ("y", "space"), ("x", "space")]
    assert axes[0].discrete is True
    node0 = level0_position(res.node_coords[:, 0, 0, 0], 1) * 2.5
    img0, img1 = field.images[0], field.images[1]
    assert [img0.scale[a] for a in "zyx"] == [ELL * 2.5] * 3 and [img1.scale[a] for a in "zyx"] == [2 * ELL * 2.5] * 3
    assert np.allclose([img0.translation[a] for a in "zyx"], node0)
    assert np.allclose([img1.translation[a] for a in "zyx"], node0 + ELL * 2.5 / 2)
    values = np.asarray(img0.data)
    assert np.allclose(values, res.displacement * 2.5, atol=1e-12)
    assert np.allclose(np.asarray(img1.data)[:, 0, 0, 0], (res.displacement[:, :2, :2, :2] * 2.5).mean(axis=(1, 2, 3)))
    from ngff_zarr.displacement_field_transform import ngff_displacement_field_to_itk_transform

    (itk,) = ngff_displacement_field_to_itk_transform(t, field, ("z", "y", "x"))
    vectors = np.asarray(itk.parameters).reshape(values.shape[1:] + (3,))
    assert np.allclose(vectors[..., ::-1], np.moveaxis(values, 0, -1))  # ITK: (x, y, z) components
    assert zarr.open_group(str(out), mode="r").attrs["chunkdic"]["kind"] == "displacements"


def test_series_as_a_paraview_time_series(series_dir, tmp_path):
    """``export SERIES --pvd DIR``: a collection of 3 steps (the reference at zero), each .vtu holding
    that step's field; refusals for a result given --pvd and a series given --vtk."""
    out = tmp_path / "pvd"
    assert main(["export", str(series_dir / "series.zarr"), "--pvd", str(out), "-q"]) == 0
    sets = ET.parse(out / "series.pvd").getroot().find("Collection").findall("DataSet")
    assert [(d.get("timestep"), d.get("file")) for d in sets] == [("0", "step-000.vtu"), ("1", "step-001.vtu"),
                                                                   ("2", "step-002.vtu")]
    step2 = chunkdic.open_result(series_dir / "series.zarr" / "steps" / "002-cumulative")
    mesh = meshio.read(out / "step-002.vtu")
    assert np.allclose(mesh.point_data["Uz"], step2.displacement[0].ravel())
    assert np.abs(meshio.read(out / "step-000.vtu").point_data["displacement"]).max() == 0
    assert main(["export", str(step2.path), "--pvd", str(tmp_path / "x")]) == 2
    assert main(["export", str(series_dir / "series.zarr"), "--vtk", str(tmp_path / "x.vtu")]) == 2


def test_gauge_over_a_series_reads_each_steps_strain(series_dir, tmp_path):
    """A plane gauge over the series: 0, −1 %, −2 % (within 3e-4), a curve per step in CSV and PNG."""
    curve = gauge(series_dir / "series.zarr", planes=["z=8", "z=32"])
    assert [r.step for r in curve.readings] == [0, 1, 2]
    assert np.allclose([r.strain for r in curve.readings], [0.0, -0.01, -0.02], atol=3e-4)
    assert all(np.isfinite(r.sigma_strain) for r in curve.readings[1:])
    assert main(["gauge", str(series_dir / "series.zarr"), "--planes", "z=8", "z=32", "-o", str(tmp_path / "g"),
                 "-q"]) == 0
    lines = (tmp_path / "g" / "gauge.csv").read_text().splitlines()
    assert lines[0].startswith("step,length,elongation") and len(lines) == 4
