"""The robust reweighting of the penalty on whole correlations (issue 20: the band at ℓ = 8).

Truths: the analytic band and translation of CT-like pairs with independent noise in each
scan (:mod:`chunkdic.synth`), scored between the nodes as issue 20 scores (trilinear on the
node grid, every voxel at least ℓ from the faces); the plain penalty
(``regularization_reweights=0``) on the same pairs as the reference.
"""

from __future__ import annotations

import numpy as np
import pytest

import chunkdic
from chunkdic.analysis.scoring import score_between_nodes
from chunkdic.errors import InputError
from chunkdic.synth import synthetic
from chunkdic.synth.ctpair import standard_field

SIZE, ELL = 64, 8
#: the band pairs: issue 20's size (at 64³, 8³ nodes, the reweighting gained nothing:
#: 0.0329 → 0.0329 and 0.0518 → 0.0524 at the offsets below; docs/engine.md)
BAND_SIZE = 100
#: where the band's plane falls, voxels from the volume's centre: at 100³ the default ROI puts
#: nodes at 1.5 + 8k, so 0 is on a node (issue 20's table) and 4 half an element from one
OFFSETS = (0.0, 4.0)


def _between(res, field, size=SIZE) -> float:
    axes = [np.unique(a) for a in res.node_coords.reshape(3, -1)]
    return score_between_nodes(axes, res.displacement, field, (size,) * 3, ELL).rms


@pytest.fixture(scope="module")
def band_runs(tmp_path_factory):
    """Band pairs (grains, seed 1, independent 2 % noise, the issue-20 pairs of
    ``bench_vs_aldvc.py``) at each offset, correlated at ℓ = 8 with the plain penalty and with
    the defaults."""
    from dataclasses import replace

    root = tmp_path_factory.mktemp("irls")
    out = []
    for offset in OFFSETS:
        field = standard_field("band", (BAND_SIZE,) * 3)[0]
        field = replace(field, center_z=field.center_z + offset)
        p = synthetic.synthesize(root / f"band{offset:g}", (BAND_SIZE,) * 3, field=field, specimen="grains",
                                 noise=0.02, seed=1, dtype="uint16")
        runs = {name: chunkdic.correlate(p["reference"], p["deformed"], element_size=ELL, **opts)
                for name, opts in (("plain", {"regularization_reweights": 0}), ("default", {}))}
        out.append((field, runs))
    return out


@pytest.mark.slow
def test_reweighting_measures_the_band_better_than_the_plain_penalty(band_runs):
    """Averaged over where the band falls, the reweighted field's error between the nodes is
    below the plain penalty's by more than 8 %. Measured by ``validation/scripts/bench_irls.py`` on
    the same pairs, on the voxels common with al-dvc (13 … 85): 0.0433 → 0.0409 (offset 0,
    the band's plane on a node) and 0.0352 → 0.0268 (offset 4, between two nodes), −14 % on
    the mean; this test scores every voxel ≥ ℓ from the faces."""
    errors = {"plain": [], "default": []}
    for field, runs in band_runs:
        assert runs["default"].info["regularization"]["freed_terms"] > 0
        assert runs["plain"].info["regularization"]["freed_terms"] == 0
        for name, res in runs.items():
            assert res.info["status"] == "converged"
            errors[name].append(_between(res, field, BAND_SIZE))
    assert np.mean(errors["default"]) < 0.92 * np.mean(errors["plain"]), errors


@pytest.fixture(scope="module")
def translation_pair(tmp_path_factory):
    return synthetic.standard_case(tmp_path_factory.mktemp("irls-shift") / "shift", "shift", SIZE,
                                   specimen="grains", noise=0.02, seed=1)


def test_reweighting_leaves_a_translation_s_noise_alone(translation_pair):
    """On a (0.5, 0.5, 0.5) translation with independent noise, the noise (σ pooled between the
    nodes) stays within 3 % of the plain penalty's."""
    field = standard_field("shift", (SIZE,) * 3)[0]
    sigma = {}
    for name, opts in (("plain", {"regularization_reweights": 0}), ("default", {})):
        res = chunkdic.correlate(translation_pair["reference"], translation_pair["deformed"], element_size=ELL,
                                 **opts)
        axes = [np.unique(a) for a in res.node_coords.reshape(3, -1)]
        sigma[name] = score_between_nodes(axes, res.displacement, field, (SIZE,) * 3, ELL).sigma
    assert sigma["default"] <= 1.03 * sigma["plain"], sigma


@pytest.mark.parametrize("options, message", [
    ({"regularization": "equilibrium-gap", "regularization_reweights": 1}, "tikhonov penalty only"),
    ({"regularization_length": 40.0, "regularization_reweights": 2}, "automatic length"),
    ({"regularization_reweights": -1}, "integer >= 0"),
])
def test_reweights_that_cannot_apply_are_refused(options, message):
    with pytest.raises(InputError, match=message):
        chunkdic.Settings(element_size=8, **options)


def test_reweights_default_to_one_only_where_they_apply():
    assert chunkdic.Settings(element_size=8).reweights == 1
    assert chunkdic.Settings(element_size=8, regularization="equilibrium-gap").reweights == 0
    assert chunkdic.Settings(element_size=8, regularization_length=40.0).reweights == 0
    assert chunkdic.Settings(element_size=8, regularization="none").reweights == 0
