"""Fields and corrected images of whole specimens: a coarser grid (``--fields-level S``) and
the disk they need, checked before anything is written (issue 21, the export stage)."""

from __future__ import annotations

import dask.config
import numpy as np
import pytest
import zarr

import chunkdic
from chunkdic.cli.app import main
from chunkdic.io import diskspace
from chunkdic.mesh import Block, Mesh
from chunkdic.synth import synthetic
from chunkdic.export import voxel_values as fields_module
from chunkdic.export.voxel_values import CHANNELS
from chunkdic.export.fields_reader import open_levels
from chunkdic.export.fields_image import write_fields

A = ((-0.02, 0.0, 0.0), (0.0, 0.01, 0.0), (0.005, 0.0, 0.01))  # dU_i / dX_j, axes (z, y, x)
CENTER, T = (24.0, 24.0, 24.0), (1.3, -0.7, 0.4)
VOXEL = 2.5  # micrometer
N = 48


def _affine(points):
    """The analytic field at level-0 points ``(3, ...)`` (level-0 voxels)."""
    a = np.asarray(A)
    c = np.reshape(CENTER, (3,) + (1,) * (points.ndim - 1))
    return np.einsum("ij,j...->i...", a, points - c) + np.reshape(T, (3,) + (1,) * (points.ndim - 1))


@pytest.fixture(scope="module")
def affine(tmp_path_factory):
    """A 48³ affine pair (voxel size 2.5 um, scan pyramid to level 2), correlated at ell = 12
    on level 0: ROI [6, 42)³."""
    d = tmp_path_factory.mktemp("affine-level")
    field = synthetic.Affine(matrix=A, center=CENTER, translation=T)
    pair = synthetic.synthesize(d, (N,) * 3, field=field, seed=3, dtype="float32", voxel_size=VOXEL,
                                unit="um", levels=2)
    res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=12, output=d / "result.zarr")
    assert res.converged and res.info["roi"] == [[6, 42]] * 3
    return pair, res, d


def _centres(grid_level: int) -> np.ndarray:
    """Level-0 coordinates of the level-S voxel centres along one axis: ``2^S j + (2^S - 1) / 2``."""
    f = 2**grid_level
    return f * np.arange(N // f) + (f - 1) / 2


def _read(path):
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    return list(Reader(parse_url(str(path)))())[0]


@pytest.mark.parametrize("result_level", [0, 1])
@pytest.mark.parametrize("grid_level", [1, 2])
def test_level_s_fields_are_the_affine_field_at_the_level_s_centres(affine, tmp_path, result_level, grid_level):
    """A result whose nodal field is exactly affine (on level 0 or 1): the image on the
    scan's level-S grid holds the analytic field at the level-S voxel centres (level-0
    voxels and micrometres), NaN exactly where the centre leaves the mesh's box, and lies on
    the scan's own level-S frame."""
    pair, res, _ = affine
    f = 2**result_level
    mesh = Mesh((6 // f,) * 3, 12 // f, (3, 3, 3))  # level-0 ROI [6, 42) on either level
    nodes = mesh.node_coords()
    u = _affine(f * nodes + (f - 1) / 2) / f  # nodes are level-s positions; u in level-s voxels
    info = {**res.info, "level": result_level, "scale": f, "element_size": 12 // f,
            "roi": [[6 // f, 42 // f]] * 3}
    fake = chunkdic.Result(u, nodes, res.history, info)
    centres = _centres(grid_level)
    # the box of the mesh in level-0 coordinates: first node 5.5 to last node 41.5
    inside1 = (centres >= 5.5) & (centres <= 41.5)
    inside = inside1[:, None, None] & inside1[None, :, None] & inside1[None, None, :]
    truth = _affine(np.stack(np.meshgrid(centres, centres, centres, indexing="ij")))
    for units, factor in (("voxels", 1.0), ("physical", VOXEL)):
        out = tmp_path / f"{units}.zarr"
        with dask.config.set({"chunkdic.chunk-size": 8}):  # several chunks cut by the ROI
            write_fields(fake, out, residual=False, units=units, strain="small", grid_level=grid_level)
        vol = np.asarray(open_levels(out)[0][0])
        assert vol.shape == (7,) + (N >> grid_level,) * 3
        assert np.isfinite(vol[:6, inside]).all() and np.isnan(vol[:6, ~inside]).all()
        assert np.abs(vol[:3, inside] - factor * truth[:, inside]).max() < 2e-5 * factor
        assert np.allclose(vol[3, inside], factor * np.sqrt((truth[:, inside] ** 2).sum(axis=0)), rtol=1e-5)
        assert np.allclose(vol[4, inside], A[0][0], atol=1e-6)
        assert np.isnan(vol[6]).all()  # no residual asked
    # the frame: the scan's level-S scale and translation, i.e. voxel j at VOXEL * (2^S j + (2^S - 1) / 2)
    ours, scan = _read(out), _read(pair["reference"])
    frame = {t["type"]: t[t["type"]] for t in ours.metadata["coordinateTransformations"][0]}
    theirs = {t["type"]: t[t["type"]] for t in scan.metadata["coordinateTransformations"][grid_level]}
    assert frame["scale"] == [1.0] + theirs["scale"] and frame["translation"] == [0.0] + theirs["translation"]
    physical = frame["translation"][1] + frame["scale"][1] * np.arange(N >> grid_level)
    np.testing.assert_allclose(physical, VOXEL * centres)
    ds = chunkdic.open_fields(out)
    np.testing.assert_allclose(ds["x"].values, VOXEL * centres)


def test_napari_and_chunkdic_view_place_a_level_2_image_on_the_scan(affine, tmp_path):
    """``chunkdic view``'s layers put a level-2 fields image on the scan: voxel j of its level
    0 at VOXEL * (4 j + 1.5), the scan's level-2 voxel; napari-ome-zarr's reader gives its
    scale and the scan's level-2 shape."""
    pytest.importorskip("napari_ome_zarr")
    from napari_ome_zarr._reader import napari_get_reader

    from chunkdic.viewer.layers import fields_layers

    pair, res, _ = affine
    write_fields(res, tmp_path / "f2.zarr", grid_level=2, residual=False)
    scale, shift = (4 * VOXEL,) * 3, (1.5 * VOXEL,) * 3
    (scan, scan_kw, _), = napari_get_reader(str(pair["reference"]))(str(pair["reference"]))
    assert tuple(scan[2].shape) == (12, 12, 12)  # the scan's own level 2
    for data, kw, _ in napari_get_reader(str(tmp_path / "f2.zarr"))(str(tmp_path / "f2.zarr")):
        # the scale only: napari-ome-zarr 0.10 reads the first transform of datasets[0] and drops
        # the translation (ome/napari-ome-zarr#73; docs/analysis.md says so), chunkdic view does not
        np.testing.assert_allclose(np.asarray(kw["scale"], float)[-3:], scale)
        assert tuple(data[0].shape[-3:]) == (12, 12, 12)
    layers = fields_layers(tmp_path / "f2.zarr")
    assert [kw["name"] for _, kw, _ in layers] and all(
        np.allclose(kw["scale"], scale) and np.allclose(kw["translate"], shift) for _, kw, _ in layers)


def _roi_residual(res):
    """Oracle of the residual: the whole ROI corrected as one block, on the level-0 grid (NaN
    outside the ROI), with no fields code involved."""
    from chunkdic.results.scans import level_refs
    from chunkdic.export.correction import Correction, correct_block

    with level_refs(res) as (f_ref, g_ref):
        corr = Correction.of_result(res, f_ref, g_ref)
        f, c, valid = correct_block(corr, Block(((0, 3),) * 3), res.displacement, res.brightness)
    assert valid.all()
    r = np.full((N,) * 3, np.nan)
    r[6:42, 6:42, 6:42] = f.astype(np.float64) - c
    return r


@pytest.mark.parametrize("grid_level", [1, 2])
def test_level_s_residual_is_the_mean_abs_residual_over_each_voxel(affine, tmp_path, monkeypatch, grid_level):
    """On a grid coarser than the result's, the residual channel is the mean |r| over the
    level-0 voxels of each level-S voxel that lie in the ROI (level 2: border voxels hold
    2 of their 4 voxels per axis), whatever the chunks and the pieces a task corrects."""
    _, res, _ = affine
    monkeypatch.setattr(fields_module, "RESIDUAL_PIECE", 12)  # one element per piece: 27 pieces binned
    with dask.config.set({"chunkdic.chunk-size": 4}):
        write_fields(res, tmp_path / "f.zarr", grid_level=grid_level)
    got = np.asarray(open_levels(tmp_path / "f.zarr")[0][0][6])
    f = 2**grid_level
    blocks = np.abs(_roi_residual(res)).reshape(N // f, f, N // f, f, N // f, f)
    with np.errstate(invalid="ignore"):
        expect = np.nansum(blocks, axis=(1, 3, 5)) / np.isfinite(blocks).sum(axis=(1, 3, 5))
    assert np.array_equal(np.isfinite(got), np.isfinite(expect))
    scale = np.nanmax(expect)
    assert scale > 0 and np.nanmax(np.abs(got - expect)) < 1e-5 * scale


def test_level_s_residual_on_the_results_own_grid_is_the_corrected_images(affine, tmp_path):
    """A level-1 result exported on the level-1 grid (S = s): the residual channel is the
    corrected image's residual, voxel for voxel (both on the scan's level-1 grid); on the
    level-0 grid (S < s) each level-1 value is repeated over its 2³ level-0 voxels."""
    from chunkdic.export.corrected_image import write_corrected

    _, res, _ = affine
    mesh = Mesh((3, 3, 3), 6, (3, 3, 3))  # level-1 ROI [3, 21)
    nodes = mesh.node_coords()
    info = {**res.info, "level": 1, "scale": 2, "element_size": 6, "roi": [[3, 21]] * 3}
    fake = chunkdic.Result(_affine(2.0 * nodes + 0.5) / 2.0, nodes, res.history, info)
    write_corrected(fake, tmp_path / "c.zarr")
    with dask.config.set({"chunkdic.chunk-size": 8}):
        write_fields(fake, tmp_path / "f1.zarr", grid_level=1)
        write_fields(fake, tmp_path / "f0.zarr", grid_level=0)
    truth = np.asarray(zarr.open_array(str(tmp_path / "c.zarr"), path="0")[1])
    one = np.asarray(open_levels(tmp_path / "f1.zarr")[0][0][6])
    zero = np.asarray(open_levels(tmp_path / "f0.zarr")[0][0][6])
    assert one.shape == truth.shape == (24, 24, 24) and np.isfinite(truth[3:21, 3:21, 3:21]).all()
    scale = np.nanmax(np.abs(truth))
    np.testing.assert_array_equal(np.isfinite(one), np.isfinite(truth))
    assert np.nanmax(np.abs(one - truth)) < 1e-5 * scale
    repeated = truth.repeat(2, 0).repeat(2, 1).repeat(2, 2)
    assert np.nanmax(np.abs(zero - repeated)) < 1e-5 * scale


# hand-computed sizes (float32, chunks of 128 voxels hold each level whole; pyramid down to an edge of 8):
LEVEL0 = 7 * 4 * (48**3 + 24**3 + 12**3)  # 3 532 032 B: levels 48³, 24³, 12³
LEVEL1 = 7 * 4 * (24**3 + 12**3)  # 435 456 B
CORRECTED = 2 * 4 * (48**3 + 24**3 + 12**3)  # 1 009 152 B: the result's level 0


def _listing(path):
    return sorted(p.name for p in path.iterdir())


def test_export_refused_for_lack_of_disk_writes_nothing(affine, tmp_path, monkeypatch, capsys):
    """With the free disk set small, the level-0 fields (3.5 MB), the corrected image
    (1.0 MB), and both together where each fits alone, are refused in one line naming the
    need, the free space and the finest --fields-level that fits; nothing is left behind;
    the level named then fits and its estimate is said first."""
    _, res, d = affine
    result = str(d / "result.zarr")
    free = {"bytes": 0}
    monkeypatch.setattr(diskspace, "free_bytes", lambda path: free["bytes"])
    out, corrected = tmp_path / "f.zarr", tmp_path / "c.zarr"
    for argv, room, need, hint in (
            (["--fields", str(out)], 1_000_000, LEVEL0, "--fields-level 1 (grid_level=1, 24x24x24 voxels)"),
            (["--corrected", str(corrected)], 1_000_000, CORRECTED, "--fields-level S"),
            # 1.2 MB: each fits alone, not both on one file system; level 2 fits beside the corrected image
            (["--fields", str(out), "--fields-level", "1", "--corrected", str(corrected)], 1_200_000,
             LEVEL1 + CORRECTED, "--fields-level 2 (grid_level=2, 12x12x12 voxels)")):
        free["bytes"] = room
        assert main(["export", result, *argv]) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and err.startswith("chunkdic: error: not enough disk"), err
        assert f"up to {diskspace.format_bytes(need)} in" in err and hint in err
        assert f"{diskspace.format_bytes(room)} free" in err
        assert _listing(tmp_path) == [], argv  # no image, no staged copy, no lock
    free["bytes"] = 1_000_000
    assert main(["export", result, "--fields", str(out), "--fields-level", "1"]) == 0
    err = capsys.readouterr().err
    assert "7 channels on the scan's level-1 grid (24x24x24 voxels, 2 levels): up to 425 KiB" in err
    assert "level 0 = the scan's level 1" in err
    assert np.asarray(open_levels(out)[0][0]).shape == (7, 24, 24, 24)
    assert _listing(tmp_path) == ["f.zarr"]
    # the API refuses the same way, before writing
    with pytest.raises(chunkdic.InputError, match="not enough disk"):
        write_fields(res, tmp_path / "g.zarr")
    assert _listing(tmp_path) == ["f.zarr"]
    # --fields-level without --fields, or a level coarser than the scan: refused
    assert main(["export", result, "--csv", str(tmp_path / "n.csv"), "--fields-level", "1"]) == 2
    assert main(["export", result, "--fields", str(tmp_path / "h.zarr"), "--fields-level", "9"]) == 2
    assert "coarser than the scan" in capsys.readouterr().err
    assert _listing(tmp_path) == ["f.zarr"]


def test_image_bytes_is_the_hand_count():
    from chunkdic.export.images import field_levels, image_bytes

    assert image_bytes(field_levels((48, 48, 48)), len(CHANNELS), 128) == LEVEL0
    # 2048³ on the level-2 grid: 512³ x 7 x 4 B, pyramid to 8³ (7 levels: 8/7 of level 0 at most)
    size = image_bytes(field_levels((512,) * 3), 7, 128)
    assert 7 * 4 * 512**3 < size <= 7 * 4 * 512**3 * 8 / 7
