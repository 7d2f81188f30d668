"""An empty ``M`` blamed on its real cause (issue 24): "the reference image has no
gradient" misled when the mask kept only untextured voxels or when the ``--init`` field
moved the ROI out of the deformed scan.

Each refusal: exit status 2, one ``chunkdic: error:`` line naming the cause, no
traceback, nothing written, inputs byte-identical. 32³ scans, elements of 8 voxels.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import zarr
from test_data_safety import N, T, nothing_left, refused, tree

import chunkdic
from chunkdic.cli.app import main
from chunkdic.synth import foam, synthetic

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A pair whose upper part (z < 20) is constant in both scans, a mask keeping z < 12 only
    (the ROI's first layer of elements, 4 to 12: constant), and a result of the textured pair."""
    d = tmp_path_factory.mktemp("causes")
    f = foam.render((N,) * 3, seed=4).astype(np.float32)
    g = foam.render((N,) * 3, seed=4, field=synthetic.Translation(T), which="deformed").astype(np.float32)
    np.save(d / "f.npy", f)
    np.save(d / "g.npy", g)
    f[:20], g[:20] = 100.0, 100.0
    np.save(d / "hf.npy", f)
    np.save(d / "hg.npy", g)
    mask = np.zeros((N,) * 3, np.uint8)
    mask[:12] = 1  # keeps only constant voxels: an inverted mask of the specimen
    np.save(d / "m.npy", mask)
    chunkdic.correlate(str(d / "f.npy"), str(d / "g.npy"), element_size=8, output=str(d / "r.zarr"))
    return d


def test_a_mask_that_keeps_no_texture_is_named(data, tmp_path, capsys):
    before = tree(data / "hf.npy", data / "hg.npy", data / "m.npy")
    out = tmp_path / "o.zarr"
    line = refused(["correlate", data / "hf.npy", data / "hg.npy", "-l", "8", "--mask", data / "m.npy", "-o", out],
                   capsys, r"the mask keeps no textured voxel of the ROI .*check the mask", only_line=False)
    assert "reference image has no gradient" not in line
    nothing_left(out)
    assert tree(data / "hf.npy", data / "hg.npy", data / "m.npy") == before
    # the same pair with the mask inverted (the textured half) correlates: the mask was the cause
    np.save(tmp_path / "inv.npy", 1 - np.load(data / "m.npy"))
    assert main(["correlate", str(data / "hf.npy"), str(data / "hg.npy"), "-l", "8", "--mask",
                 str(tmp_path / "inv.npy"), "-o", str(out)]) in (0, 1)
    capsys.readouterr()
    assert chunkdic.open_result(out).displacement.shape[0] == 3


def test_an_init_field_that_moves_the_roi_out_of_the_deformed_scan_is_named(data, tmp_path, capsys):
    far = tmp_path / "far.zarr"
    shutil.copytree(data / "r.zarr", far)
    disp = zarr.open_array(str(far / "displacement"), mode="r+")
    disp[...] = disp[...] + 200.0  # 200 voxels: the whole ROI lands outside the 32³ deformed scan
    before = tree(data / "f.npy", data / "g.npy", far)
    out = tmp_path / "o.zarr"
    line = refused(["correlate", data / "f.npy", data / "g.npy", "-l", "8", "--init", far, "-o", out], capsys,
                   r"the start field of level 0 maps 100% of the ROI's elements outside the deformed scan "
                   r"\(mean displacement \+200\.\d, \+199\.\d, \+200\.\d .*check --init", only_line=False)
    assert "reference image has no gradient" not in line
    nothing_left(out)
    assert tree(data / "f.npy", data / "g.npy", far) == before


def test_a_constant_reference_is_still_blamed_on_the_reference(data, tmp_path, capsys):
    """Without a mask or a far start, an untextured ROI is the reference's, and no numpy warning
    line precedes the error (the rigid step's phase correlation divided 0 by 0): the one
    warning is the texture check's, that the reference holds no texture."""
    out = tmp_path / "o.zarr"
    refused(["correlate", data / "hf.npy", data / "hg.npy", "-l", "8", "--roi", "0:12,0:32,0:32", "-o", out],
            capsys, "the reference is constant over the ROI|the reference image has no gradient", only_line=False)
    capsys.readouterr()
    assert main(["correlate", str(data / "hf.npy"), str(data / "hg.npy"), "-l", "8", "--roi", "0:12,0:32,0:32",
                 "-o", str(out)]) == 2
    warned = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(warned) == 1 and "supports no element size of 8 voxels (no texture above the noise" in warned[0]
    nothing_left(out)
