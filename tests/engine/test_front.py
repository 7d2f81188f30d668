"""One front door (chunkdic.engine.front.prepare_run) for correlate, plan, series and the studies.

Truths: a physical element size is the same run as its whole number of voxels (2 µm voxels:
24 µm = 12 voxels), for ``plan`` as for ``correlate``; every front door refuses an unknown
keyword in the same words, naming the function, before anything is written; with a start
field the run starts on the correlated level.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import chunkdic
from chunkdic.engine.front import prepare_run
from chunkdic.results.layout import HISTORY_FIELDS
from textures import smooth_noise


@pytest.fixture(scope="module")
def micron_pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("front")
    f = (smooth_noise((48, 48, 48), seed=3) * 1000 + 30000).astype(np.uint16)
    for name in ("ref.zarr", "def.zarr"):
        chunkdic.write_scan(d / name, f, voxel_size=(2.0, 2.0, 2.0), unit="micrometer")
    return str(d / "ref.zarr"), str(d / "def.zarr")


def _comparable(p):
    """A plan without what the disk's free space and the clock say (they move between calls)."""
    return dataclasses.replace(p, scratch_free=0, output_free=0)


def test_plan_takes_a_physical_element_size_as_correlate(micron_pair):
    ref, dfm = micron_pair
    physical = chunkdic.plan(ref, dfm, element_size="24um", calibrate=False)
    voxels = chunkdic.plan(ref, dfm, element_size=12, calibrate=False)
    assert _comparable(physical) == _comparable(voxels)
    assert voxels.levels[-1].level == 0 and voxels.levels[-1].nodes == (4, 4, 4)  # 3 elements across 48
    # a physical ROI too, and the settings the run would have
    spec = prepare_run(ref, dfm, element_size="24um", roi="4:92,4:92,4:92um")
    assert spec.settings.element_size == 12 and spec.roi == "2:46,2:46,2:46"


@pytest.mark.parametrize("call", ["correlate", "plan", "series", "uncertainty", "sweep", "resolution"])
def test_every_front_door_refuses_an_unknown_keyword_alike(micron_pair, tmp_path, call):
    ref, dfm = micron_pair
    out = tmp_path / "out"
    calls = {
        "correlate": lambda: chunkdic.correlate(ref, dfm, element_size=12, output=out, bogus=1),
        "plan": lambda: chunkdic.plan(ref, dfm, element_size=12, bogus=1),
        "series": lambda: chunkdic.series([ref, dfm], out, element_size=12, bogus=1),
        "uncertainty": lambda: chunkdic.uncertainty(ref, [12], out, bogus=1),
        "sweep": lambda: chunkdic.sweep(ref, dfm, [12], out, bogus=1),
        "resolution": lambda: chunkdic.resolution(ref, [12], out, bogus=1),
    }
    with pytest.raises(TypeError, match=rf"^{call}\(\) got unexpected keyword arguments \['bogus'\]$"):
        calls[call]()
    assert not out.exists()


def test_a_start_field_starts_on_the_correlated_level():
    """With ``init``, no coarse level: the earlier field already holds the large displacements
    (the scans are only planned: an array of zeros, never read)."""
    f = np.zeros((128,) * 3, np.uint16)
    alone = prepare_run(f, f, element_size=8)
    assert alone.levels == [2, 1, 0]
    mesh = alone.meshes[0]
    earlier = chunkdic.Result(np.full((3,) + mesh.nodes_shape, 0.25), mesh.node_coords(),
                              {k: np.zeros(0) for k in HISTORY_FIELDS},
                              {"element_size": 8, "roi": [[r.start, r.stop] for r in mesh.roi], "final_gap": 0.0,
                               "level": 0, "input_shapes": {"reference": [128] * 3}})
    spec = prepare_run(f, f, element_size=8, init=earlier)
    assert spec.levels == [0] and spec.init is earlier
    assert prepare_run(f, f, element_size=8, coarsest=1, init=earlier).levels == [1, 0]
