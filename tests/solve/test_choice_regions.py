"""Where the automatic length choice looks: sub-meshes that hold the field's feature wherever it
lies (docs/engine.md, "Where the choice looks").

Truths: a score whose hot plane is placed by hand, and a slip whose analytic field scores the
whole engine's result between the nodes against the engine run at fixed lengths.
"""

from __future__ import annotations

import numpy as np
import pytest

import chunkdic
from chunkdic.analysis.scoring import score_between_nodes
from chunkdic.solve.regchoice import feature_regions, regions, regions_cover
from chunkdic.synth import synthetic
from chunkdic.synth.shear import Slip


@pytest.mark.parametrize("n, covered", [(24, True), (30, True), (47, True), (48, False), (50, False), (256, False)])
def test_fixed_boxes_leave_the_middle_out_from_48_nodes(n, covered):
    """Two 24-node boxes hold 47 nodes' elements; at 48 the element between them is in neither."""
    assert regions_cover((n, 10, 10), 24) is covered
    inner = set()
    for box in regions((n, 10, 10), 24):
        inner |= set(range(box[0].start, box[0].stop - 1))  # elements k: nodes k and k + 1
    first, last = min(inner), max(inner)
    assert (set(range(first, last + 1)) <= inner) is covered


def test_the_first_box_is_centred_on_a_hot_plane_anywhere():
    """A noise-like score with one plane 20× hotter: the first box holds the plane at least a
    quarter of its edge from either face, wherever the plane lies; later boxes differ from it
    by at least half an edge along some axis."""
    rng = np.random.default_rng(0)
    for plane in (2, 25, 37, 58):
        score = rng.random((60, 30, 40))
        score[plane] += 20.0
        boxes = feature_regions(score, 24)
        z = boxes[0][0]
        assert z.stop - z.start == 24 and z.start <= plane < z.stop
        assert min(plane - z.start, z.stop - 1 - plane) >= 6 or z.start == 0 or z.stop == 60
        corners = [tuple(s.start for s in b) for b in boxes]
        assert 2 <= len(set(corners)) == len(corners) <= 8
        for i, a in enumerate(corners):
            for b in corners[:i]:
                assert any(2 * abs(p - q) >= 24 for p, q in zip(a, b))


SHAPE = (300, 48, 48)


@pytest.mark.slow
def test_a_slip_between_the_fixed_boxes_is_kept(tmp_path):
    """A 1-voxel shear slip across the middle of a 300-voxel bar of grains at texture scale 4
    (ℓ = 6: 50 nodes along z, the slip between the fixed boxes' [0, 24) and [25, 49)), noise 0.02
    in each scan. Where the choice looked only in the fixed boxes it saw no feature and took the
    longest length, 192 voxels: 0.21 voxel against 0.095 at a fixed 17. The defaults must be
    within 1.15 of the best of the whole engine at fixed 17 and 24 voxels."""
    field = Slip(center=(SHAPE[0] - 1) / 2, jump=1.0, edge=3.0)
    pair = synthetic.synthesize(tmp_path / "bar", SHAPE, field=field, specimen="grains", seed=1, noise=0.02,
                                texture_scale=4.0)

    def error(**settings) -> float:
        res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=6, **settings)
        assert res.info["status"] == "converged"
        axes = [np.unique(a) for a in res.node_coords.reshape(3, -1)]
        return score_between_nodes(axes, res.displacement, field, SHAPE, 6).rms

    with pytest.warns(UserWarning):  # 6 voxels is below what this texture supports
        auto = error()
    best = min(error(regularization_length=L) for L in (17.0, 24.0))
    assert auto <= 1.15 * best
