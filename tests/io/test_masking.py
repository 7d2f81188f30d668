"""`chunkdic mask`: a specimen mask chunk by chunk, against NumPy / scikit-image on the whole scan."""

from __future__ import annotations

import dask
import numpy as np
import pytest
from scipy import ndimage as ndi

import chunkdic
from chunkdic.cli.app import main

SHAPE = (40, 48, 60)


def _scan():
    """A bright textured cylinder (axis z) with closed pores, a bright box elsewhere that is larger
    than the cylinder's part in any one slab of 16 planes but smaller than the whole cylinder, noise."""
    rng = np.random.default_rng(7)
    z, y, x = np.indices(SHAPE)
    cyl = (y - 24) ** 2 + (x - 18) ** 2 <= 10**2
    pores = ((z - 12) ** 2 + (y - 24) ** 2 + (x - 18) ** 2 <= 3**2) | ((z - 30) ** 2 + (y - 20) ** 2 + (x - 15) ** 2 <= 2**2)
    box = (z >= 16) & (z < 32) & (y >= 10) & (y < 28) & (x >= 36) & (x < 54)
    vol = 1000 + rng.normal(0, 60, SHAPE)
    vol[cyl & ~pores] += 2000 + rng.normal(0, 150, int((cyl & ~pores).sum()))
    vol[box] += 1800
    return np.clip(vol, 0, 65535).astype(np.uint16), cyl, pores, box


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    d = tmp_path_factory.mktemp("mask")
    vol, *_ = _scan()
    chunkdic.write_scan(d / "scan.zarr", vol, voxel_size=(6.5, 6.5, 6.5), unit="micrometer", chunks=16)
    return d, vol


def test_mask_matches_numpy_and_scikit_image(scan, tmp_path):
    from skimage.filters import threshold_otsu
    from skimage.measure import label

    d, vol = scan
    with dask.config.set({"chunkdic.chunk-size": 16}):  # 3 slabs: the components meet across slab faces
        assert main(["mask", str(d / "scan.zarr"), "-o", str(tmp_path / "m.zarr"), "--largest"]) == 0
    t = threshold_otsu(vol)
    import zarr

    g = zarr.open_group(str(tmp_path / "m.zarr"), mode="r")
    got = np.asarray(g["0"]).astype(bool)
    assert g.attrs["chunkdic"]["threshold"] == t
    # the reference on the whole scan: threshold, holes of every z-slice, largest 6-connected component
    m = vol > t
    m = np.stack([ndi.binary_fill_holes(s) for s in m])
    lab = label(m, connectivity=1)
    biggest = np.argmax(np.bincount(lab.ravel())[1:]) + 1
    np.testing.assert_array_equal(got, lab == biggest)
    _, cyl, pores, box = _scan()
    assert got[pores].all() and not got[box].any() and abs(int(got.sum()) - int(cyl.sum())) < 0.02 * cyl.sum()
    # without --largest and --no-fill: the plain threshold
    assert main(["mask", str(d / "scan.zarr"), "-o", str(tmp_path / "t.zarr"), "--no-fill"]) == 0
    np.testing.assert_array_equal(np.asarray(zarr.open_array(str(tmp_path / "t.zarr"), path="0")).astype(bool),
                                  vol > t)
    # a cylinder and a box with a fixed threshold
    assert main(["mask", str(d / "scan.zarr"), "-o", str(tmp_path / "c.zarr"), "--threshold", "2000",
                 "--cylinder", "24,18,8", "--box", "0:30,0:48,0:60", "--no-fill"]) == 0
    z, y, x = np.indices(SHAPE)
    expect = (vol > 2000) & ((y - 24) ** 2 + (x - 18) ** 2 <= 64) & (z < 30)
    np.testing.assert_array_equal(np.asarray(zarr.open_array(str(tmp_path / "c.zarr"), path="0")).astype(bool), expect)


def test_mask_is_an_ngff_labels_image_that_correlate_reads(scan, tmp_path):
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Label, Reader

    from chunkdic.io.formats.anyscan import open_any

    d, vol = scan
    out = chunkdic.make_mask(d / "scan.zarr", tmp_path / "m.zarr", largest=True)
    assert 0.05 < out["fraction"] < 0.2
    nodes = list(Reader(parse_url(str(tmp_path / "m.zarr")))())
    assert any(isinstance(s, Label) for s in nodes[0].specs)  # napari-ome-zarr: a Labels layer
    scale = nodes[0].metadata["coordinateTransformations"][0][0]["scale"]
    assert scale == [6.5, 6.5, 6.5]
    m = open_any(tmp_path / "m.zarr")  # what correlate --mask opens
    assert m.shape(0) == SHAPE and m.voxel_size == (6.5, 6.5, 6.5)


@pytest.mark.parametrize("args, message", [
    (["--threshold", "abc"], "--threshold"),
    (["--cylinder", "1,2"], "--cylinder"),
    (["--box", "0:50,0:48,0:60"], "--box"),
    (["--threshold", "none"], "--cylinder or --box"),
    (["--threshold", "70000"], "empty"),
])
def test_bad_mask_input_is_one_line_exit_2_nothing_written(scan, tmp_path, capsys, args, message):
    d, _ = scan
    assert main(["mask", str(d / "scan.zarr"), "-o", str(tmp_path / "m.zarr"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert not (tmp_path / "m.zarr").exists()
