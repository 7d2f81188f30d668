"""Voxel-wise fields for viewers: ``export --fields`` (issue 13, item 2)."""

from __future__ import annotations

import json
import time

import dask.config
import numpy as np
import pytest

import chunkdic
from chunkdic.cli.app import main
from chunkdic.mesh import Mesh
from chunkdic.synth import synthetic
from chunkdic.export.corrected_image import open_corrected, write_corrected
from chunkdic.export.voxel_values import CHANNELS, equivalent_strain
from chunkdic.export.fields_reader import open_levels
from chunkdic.export.fields_image import write_fields

A = ((-0.02, 0.0, 0.0), (0.0, 0.01, 0.0), (0.005, 0.0, 0.01))  # dU_i / dX_j, axes (z, y, x)
CENTER, T = (24.0, 24.0, 24.0), (1.3, -0.7, 0.4)
VOXEL = 2.5  # micrometer


def _affine(points):
    """The analytic field at level-0 points ``(3, ...)`` (level-0 voxels)."""
    a = np.asarray(A)
    return np.einsum("ij,j...->i...", a, points - np.reshape(CENTER, (3,) + (1,) * (points.ndim - 1))) \
        + np.reshape(T, (3,) + (1,) * (points.ndim - 1))


@pytest.fixture(scope="module")
def affine(tmp_path_factory):
    """A 48³ affine pair with a voxel size and a 2-level pyramid, correlated at ell = 12."""
    d = tmp_path_factory.mktemp("affine")
    field = synthetic.Affine(matrix=A, center=CENTER, translation=T)
    pair = synthetic.synthesize(d, (48, 48, 48), field=field, seed=3, dtype="float32", voxel_size=VOXEL,
                                unit="um", levels=2)
    res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=12, output=d / "result.zarr")
    assert res.converged and res.info["roi"] == [[6, 42]] * 3
    with dask.config.set({"chunkdic.chunk-size": 16}):  # 27 tasks; the ROI cuts chunks
        out = write_fields(res, d / "fields.zarr")
    return pair, res, d, out


def _read(path):
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    nodes = list(Reader(parse_url(str(path)))())
    assert nodes
    return nodes[0]


def _node_values(vol: np.ndarray, mesh: Mesh) -> np.ndarray:
    """Nodal values recovered from a voxel volume ``(c, nz, ny, nx)`` (level 0, mesh at level 0).

    Nodes sit between voxels (``origin + k ell - 0.5``); the C8 field is linear along each
    axis inside an element, so the node value is ``1.5 v(node + 0.5) - 0.5 v(node + 1.5)``
    from the two voxels of the element on its inner side (the last node: the element
    before it), exact for a trilinear field.
    """
    picks = []
    for axis in range(3):
        nodes = mesh.node_axes()[axis]
        rows = []
        for k, x in enumerate(nodes):
            step = 1 if k < len(nodes) - 1 else -1
            rows.append(((int(x + 0.5 * step), 1.5), (int(x + 1.5 * step), -0.5)))
        picks.append(rows)
    out = np.zeros((vol.shape[0],) + mesh.nodes_shape)
    for i, rz in enumerate(picks[0]):
        for j, ry in enumerate(picks[1]):
            for k, rx in enumerate(picks[2]):
                out[:, i, j, k] = sum(wz * wy * wx * vol[:, z, y, x]
                                      for z, wz in rz for y, wy in ry for x, wx in rx)
    return out


def test_fields_read_back_on_the_scan_grid(affine):
    pair, res, d, out = affine
    scan = _read(pair["reference"])
    node = _read(d / "fields.zarr")
    # OME-NGFF frame: level t has the scan's own level-t scale and translation (2x per level)
    ours, theirs = node.metadata["coordinateTransformations"], scan.metadata["coordinateTransformations"]
    assert len(ours) == 3 == len(out["levels"])
    for t, (mine, scan_t) in enumerate(zip(ours, theirs)):
        m = {x["type"]: x for x in mine}
        s = {x["type"]: x for x in scan_t}
        assert m["scale"]["scale"] == [1.0] + s["scale"]["scale"] == [1.0] + [VOXEL * 2**t] * 3
        assert m["translation"]["translation"] == [0.0] + s["translation"]["translation"]
        assert m["translation"]["translation"][1:] == pytest.approx([VOXEL * (2**t - 1) / 2] * 3)
    assert [a.get("unit") for a in node.metadata["axes"][1:]] == ["micrometer"] * 3
    assert node.metadata["channel_names"] == list(CHANNELS)  # omero channel labels
    assert node.metadata["visible"] == [True] + [False] * 6
    lo, hi = node.metadata["contrast_limits"][0]
    assert lo < hi
    vol = np.asarray(node.data[0])
    assert vol.shape == (7, 48, 48, 48) and vol.dtype == np.float32
    assert [tuple(x.shape[1:]) for x in node.data] == [(48,) * 3, (24,) * 3, (12,) * 3]
    # NaN outside the ROI [6, 42)^3, finite inside
    inside = np.zeros((48,) * 3, bool)
    inside[6:42, 6:42, 6:42] = True
    assert np.isfinite(vol[:, inside]).all() and np.isnan(vol[:, ~inside]).all()
    # sampled at the nodes, the voxel field is the nodal displacement (level 0: factor 1)
    nodal = _node_values(vol[:3].astype(np.float64), res.mesh)
    assert np.abs(nodal - res.displacement).max() < 1e-4
    # strain: per element, the result's own element strain; near the analytic one
    ell = 12
    centres = [np.arange(6 + ell // 2, 42, ell)] * 3
    per_element = vol[4][np.ix_(*centres)]
    assert np.allclose(per_element, res.element_strain("green-lagrange")[0, 0], atol=1e-6)  # the default measure
    assert abs(per_element[1:-1, 1:-1, 1:-1].mean() - A[0][0]) < 1e-3
    assert np.abs(per_element - A[0][0]).max() < 5e-3
    sym = 0.5 * (np.asarray(A) + np.asarray(A).T)
    assert np.median(vol[5][inside]) == pytest.approx(float(equivalent_strain(sym[:, :, None])[0]), abs=2e-3)
    assert np.sqrt(np.mean((vol[0][inside] - _affine(np.indices((48,) * 3, float))[0][inside]) ** 2)) < 0.02
    # pyramid: NaN-aware 2x2x2 means of the level below
    lvl1 = np.asarray(node.data[1])
    blocks = vol.reshape(7, 24, 2, 24, 2, 24, 2)
    with np.errstate(invalid="ignore"):
        expect = np.nansum(blocks, axis=(2, 4, 6)) / np.isfinite(blocks).sum(axis=(2, 4, 6))
    assert np.allclose(lvl1, expect, equal_nan=True, atol=1e-6)


def test_residual_is_the_corrected_residual(affine, tmp_path):
    _, res, d, _ = affine
    write_corrected(res, tmp_path / "c.zarr")
    _, residual, _ = open_corrected(tmp_path / "c.zarr")
    levels, attrs = open_levels(d / "fields.zarr")
    ours = levels[0][6][6:42, 6:42, 6:42]
    r = residual[...]
    assert np.abs(ours - r).max() < 1e-3 * np.abs(r).max()
    assert attrs["chunkdic"]["kind"] == "fields" and attrs["ome"]["version"] == "0.5"


def test_chunking_does_not_change_the_fields(affine, tmp_path):
    _, res, d, _ = affine
    write_fields(res, tmp_path / "f.zarr", residual=False, levels=0)  # one 48^3 chunk
    one, _ = open_levels(tmp_path / "f.zarr")
    many, _ = open_levels(d / "fields.zarr")
    assert len(one) == 1
    assert np.allclose(one[0][:6], many[0][:6], atol=1e-6, equal_nan=True)
    assert np.isnan(one[0][6]).all()


def test_level_1_result_maps_onto_level_0_voxels(affine, tmp_path):
    """A result on pyramid level 1 whose nodal field is exactly affine: its trilinear
    field at every level-0 voxel centre is the analytic field (half-voxel offset, x2)."""
    pair, res, _, _ = affine
    mesh = Mesh((3, 3, 3), 6, (3, 3, 3))  # level-1 ROI [3, 21) = level-0 [6, 42)
    nodes1 = mesh.node_coords()
    u1 = _affine(2.0 * nodes1 + 0.5) / 2.0  # level-1 voxels
    info = {**res.info, "level": 1, "scale": 2, "element_size": 6, "roi": [[3, 21]] * 3}
    fake = chunkdic.Result(u1, nodes1, res.history, info)
    for units, factor in (("voxels", 1.0), ("physical", VOXEL)):
        out = tmp_path / f"{units}.zarr"
        write_fields(fake, out, residual=False, units=units, strain="small")  # analytic truth below: small strain
        vol = open_levels(out)[0][0][...]
        truth = _affine(np.indices((48,) * 3, float))[:, 6:42, 6:42, 6:42] * factor
        assert np.abs(vol[:3, 6:42, 6:42, 6:42] - truth).max() < 1e-4 * factor
        assert np.isnan(vol[:, :6]).all() and np.isnan(vol[:, 42:]).all()
    assert np.allclose(vol[4, 6:42, 6:42, 6:42], A[0][0], atol=1e-6)
    sym = 0.5 * (np.asarray(A) + np.asarray(A).T)
    assert np.allclose(vol[5, 6:42, 6:42, 6:42], equivalent_strain(sym[:, :, None])[0], atol=1e-6)


def test_cli_export_fields_and_refusals(affine, tmp_path, capsys):
    pair, res, d, _ = affine
    result = str(d / "result.zarr")
    out = tmp_path / "f.zarr"
    t0 = time.monotonic()
    assert main(["export", result, "--fields", str(out)]) == 0
    seconds = time.monotonic() - t0
    cap = capsys.readouterr()
    assert cap.out.strip() == str(out) and "fields: 100%" in cap.err and "on 3 levels" in cap.err
    # progress at most one line per 5 s (issue 23: 22 lines for 100³), its 100 % line included
    assert len([line for line in cap.err.splitlines() if "%" in line]) <= 1 + seconds // 5
    assert json.loads((out / "zarr.json").read_text())["attributes"]["ome"]["multiscales"][0]["name"] == "f.zarr"
    # an existing fields image: refused without --overwrite, replaced with it
    assert main(["export", result, "--fields", str(out)]) == 2
    assert "complete fields image" in capsys.readouterr().err
    assert main(["export", result, "--fields", str(out), "--overwrite"]) == 0
    capsys.readouterr()
    # the scan itself, a user's folder, a path inside the result: refused, nothing written
    ref = pair["reference"]
    before = {p.relative_to(ref): p.stat().st_mtime_ns for p in sorted(__import__("pathlib").Path(ref).rglob("*"))}
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    for target in (str(ref), str(mine), str(d / "result.zarr" / "f.zarr")):
        for extra in ([], ["--overwrite"]):
            assert main(["export", result, "--fields", target, *extra]) == 2, (target, extra)
            assert capsys.readouterr().err.startswith("chunkdic: error:")
    after = {p.relative_to(ref): p.stat().st_mtime_ns for p in sorted(__import__("pathlib").Path(ref).rglob("*"))}
    assert before == after
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"] and (mine / "notes.txt").read_text() == "mine"
    assert not (d / "result.zarr" / "f.zarr").exists()
    assert not [p for p in tmp_path.iterdir() if "partial" in p.name]


def _frames(node):
    return [{x["type"]: x[x["type"]] for x in t} for t in node.metadata["coordinateTransformations"]]


def test_corrected_is_an_image_on_the_scan_grid(affine, tmp_path):
    """``export --corrected``: an OME-NGFF image on the scan's grid whose channels are the
    corrected image and residual of one whole-ROI block (independent of the chunking)
    and whose residual is the fields image's."""
    from chunkdic.mesh import Block
    from chunkdic.results.scans import level_refs
    from chunkdic.export.correction import Correction, correct_block

    pair, res, d, _ = affine
    with dask.config.set({"chunkdic.chunk-size": 16}):  # 27 tasks; the ROI [6, 42) cuts chunks
        out = write_corrected(res, tmp_path / "c.zarr")
    assert out["gap"] == pytest.approx(res.final_gap, rel=1e-3) and out["excluded"] == 0
    node, scan = _read(tmp_path / "c.zarr"), _read(pair["reference"])
    assert _frames(node) == [{"scale": [1.0] + f["scale"], "translation": [0.0] + f["translation"]}
                             for f in _frames(scan)]
    assert [a.get("unit") for a in node.metadata["axes"][1:]] == ["micrometer"] * 3
    assert node.metadata["channel_names"] == ["corrected", "residual"]
    vol = np.asarray(node.data[0])
    inside = np.zeros((48,) * 3, bool)
    inside[6:42, 6:42, 6:42] = True
    assert vol.shape == (2, 48, 48, 48) and np.isfinite(vol[:, inside]).all() and np.isnan(vol[:, ~inside]).all()
    # oracle: the whole ROI corrected as one block
    with level_refs(res) as (f_ref, g_ref):
        corr = Correction.of_result(res, f_ref, g_ref)
        f, c, valid = correct_block(corr, Block(((0, 3),) * 3), res.displacement, res.brightness)
    assert valid.all()
    roi = (slice(6, 42),) * 3
    assert np.abs(vol[0][roi] - c).max() < 1e-5 * np.abs(c).max()
    assert np.abs(vol[1][roi] - (f - c)).max() < 1e-5 * np.abs(c).max()
    fields = np.asarray(open_levels(d / "fields.zarr")[0][0][6])
    assert np.abs(vol[1] - fields)[inside].max() < 1e-5 * np.abs(c).max()
    # open_corrected: the ROI of level 0; level 1 the NaN-aware mean
    corrected, residual, meta = open_corrected(tmp_path / "c.zarr")
    assert np.array_equal(np.asarray(corrected), vol[0][roi]) and np.array_equal(np.asarray(residual), vol[1][roi])
    assert meta["kind"] == "corrected" and meta["complete"] is True
    blocks = vol.reshape(2, 24, 2, 24, 2, 24, 2)
    with np.errstate(invalid="ignore"):
        expect = np.nansum(blocks, axis=(2, 4, 6)) / np.isfinite(blocks).sum(axis=(2, 4, 6))
    assert np.allclose(np.asarray(node.data[1]), expect, equal_nan=True, atol=1e-4)


def test_corrected_of_a_level_1_result_lies_on_scan_level_1(affine, tmp_path):
    pair, res, _, _ = affine
    mesh = Mesh((3, 3, 3), 6, (3, 3, 3))  # level-1 ROI [3, 21)
    nodes1 = mesh.node_coords()
    info = {**res.info, "level": 1, "scale": 2, "element_size": 6, "roi": [[3, 21]] * 3}
    fake = chunkdic.Result(_affine(2.0 * nodes1 + 0.5) / 2.0, nodes1, res.history, info)
    write_corrected(fake, tmp_path / "c1.zarr")
    node, scan = _read(tmp_path / "c1.zarr"), _read(pair["reference"])
    frames = _frames(scan)[1:]  # the scan's levels 1 and 2
    assert _frames(node)[:2] == [{"scale": [1.0] + f["scale"], "translation": [0.0] + f["translation"]}
                                 for f in frames]
    assert _frames(node)[0]["translation"][1:] == pytest.approx([VOXEL / 2] * 3)
    vol = np.asarray(node.data[0])
    assert vol.shape == (2, 24, 24, 24)
    assert np.isfinite(vol[:, 3:21, 3:21, 3:21]).all() and np.isnan(vol[:, :3]).all() and np.isnan(vol[:, 21:]).all()


def test_napari_layers_place_the_fields_on_the_scan(affine):
    """napari-ome-zarr's own reader (no window): every field layer has the scan's level-0
    scale and translation, so napari overlays it voxel on voxel."""
    pytest.importorskip("napari_ome_zarr")
    from napari_ome_zarr._reader import napari_get_reader

    pair, res, d, out = affine

    def layers(path):
        return napari_get_reader(str(path))(str(path))

    (scan_data, scan_kw, _), = layers(pair["reference"])
    scale = np.asarray(scan_kw["scale"], float)
    shift = np.asarray(scan_kw.get("translate", (0.0,) * 3), float)
    np.testing.assert_allclose(scale, (VOXEL,) * 3)
    fields = layers(d / "fields.zarr")
    assert fields
    for data, kw, kind in fields:
        assert kind == "image"
        np.testing.assert_allclose(np.asarray(kw["scale"], float)[-3:], scale)
        np.testing.assert_allclose(np.asarray(kw.get("translate", (0.0,) * 3), float)[-3:], shift)
        assert tuple(data[0].shape[-3:]) == tuple(scan_data[0].shape)
    names = fields[0][1].get("name")  # one layer per channel, "fields.zarr: Uz", ...
    assert [str(n).split(": ")[-1] for n in names] == list(CHANNELS)


def test_open_fields_gives_one_level_as_xarray_with_physical_coordinates(affine):
    """Issue 23 item 6: chunkdic.open_fields -> xarray.Dataset, named channels, the scan's frame."""
    _, res, d, _ = affine
    levels, _ = open_levels(d / "fields.zarr")
    ds = chunkdic.open_fields(d / "fields.zarr")
    assert list(ds.data_vars) == list(CHANNELS)
    assert ds["Uz"].dims == ("z", "y", "x") and ds["Uz"].shape == (48, 48, 48)
    assert np.allclose(ds["z"].values, VOXEL * np.arange(48)) and ds["z"].attrs["units"] == "micrometer"
    for k, name in enumerate(CHANNELS):
        np.testing.assert_array_equal(ds[name].values, np.asarray(levels[0][k]))
    one = chunkdic.open_fields(d / "fields.zarr", level=1)
    # a level-1 voxel j is the mean of level-0 voxels 2j, 2j + 1: centre 2 j + 1/2 (DESIGN.md)
    assert np.allclose(one["x"].values, VOXEL * (2 * np.arange(24) + 0.5))
    np.testing.assert_array_equal(one["eps_zz"].values, np.asarray(levels[1][4]))
    assert ds.attrs["strain_measure"] == "green-lagrange" and ds.attrs["kind"] == "fields"
    with pytest.raises(chunkdic.InputError, match="levels 0 to"):
        chunkdic.open_fields(d / "fields.zarr", level=len(levels))
