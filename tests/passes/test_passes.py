"""What the finest level's passes cost and report (issue 21 item 3): the start gaps measured
inside the first pass, and the passes the stopping rule spends.

Truths: the matching gap of the paper (section 5.1) computed here by hand with NumPy/SciPy
for the zero field and the reported rigid translation (trilinear interpolation, no low-pass,
no brightness model: ``rms(f - g(X + t)) / (max f - min f)`` over the ROI, each voxel
weighted as the engine weights it near the faces of ``g``); and the analytic translation of
a Fourier-shifted pair.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from textures import fourier_shift, smooth_noise

import chunkdic
from chunkdic.method.stopping import still_to_come


def _gap_by_hand(f, g, roi, t, ell, every_other: bool) -> float:
    """The gap of the uniform field ``t`` (3,) over the box ``roi`` ((z0, z1), ...): linear
    interpolation of ``g`` at ``X + t``, weights ``min(1, distance inside g)`` (the engine's
    taper, :func:`chunkdic.kernels.rows.taper`); ``every_other``: only the elements of even
    index along every axis (the diagnostic sample of large meshes)."""
    axes = [np.arange(a, b, dtype=float) for a, b in roi]
    X = np.meshgrid(*axes, indexing="ij")
    keep = np.ones(X[0].shape, bool)
    if every_other:
        for a, (lo, _) in enumerate(roi):
            keep &= ((X[a] - lo) // ell) % 2 == 0
    pos = [X[a] + t[a] for a in range(3)]
    w = np.clip(np.min([np.minimum(p, n - 1 - p) for p, n in zip(pos, g.shape)], axis=0), 0.0, 1.0)
    gx = ndimage.map_coordinates(g.astype(np.float64), pos, order=1, mode="nearest")
    fx = f[tuple(slice(a, b) for a, b in roi)].astype(np.float64)
    r2, w = ((fx - gx) ** 2)[keep], w[keep]
    return float(np.sqrt((w * r2).sum() / w.sum()) / (fx.max() - fx.min()))


@pytest.mark.parametrize("size, ell, sampled", [(40, 8, False), (72, 4, True)])
def test_the_reported_gaps_are_those_of_no_motion_and_of_the_rigid_translation(size, ell, sampled):
    """``initial_gap`` and ``rigid_gap``, now summed inside the finest level's first pass
    (``probes`` of ``LevelPasses.assemble_b``), equal the gaps of the zero field and of the rigid
    translation computed by hand: on every element (5³ elements) and on the one-in-8 sample
    of a mesh of 4096 elements or more (18³). The first pass is not summed twice: the level
    spends as many passes as it reports iterations with a new gap."""
    f = smooth_noise((size,) * 3, sigma=1.5, seed=3).astype(np.float32)
    g = fourier_shift(f, (0.6, -0.3, 0.4)).astype(np.float32)  # g(x) = f(x - t)
    roi = [(4, size - 4)] * 3
    events = []
    res = chunkdic.correlate(f, g, element_size=ell, roi=",".join(f"{a}:{b}" for a, b in roi), smoothing=0,
                             interpolation="linear", grey="none", regularization="none", coarsest=0,
                             progress=events.append)
    assert res.converged
    t = np.asarray(res.info["rigid_translation"])
    assert np.abs(t - (0.6, -0.3, 0.4)).max() < 0.05
    assert res.info["initial_gap"] == pytest.approx(_gap_by_hand(f, g, roi, (0, 0, 0), ell, sampled), rel=1e-5)
    assert res.info["rigid_gap"] == pytest.approx(_gap_by_hand(f, g, roi, t, ell, sampled), rel=1e-5)
    assert res.info["rigid_gap"] < res.info["initial_gap"] / 3


@pytest.mark.parametrize("grey_cell", [0, 32])
def test_the_finest_level_spends_three_passes_on_a_band_where_it_spent_six(tmp_path, monkeypatch, grey_cell):
    """The 64³ band pair (grains, independent 2 % noise, ℓ = 8, the defaults: automatic
    length, one robust reweighting). Before: 6 sums over level 0's voxels (the gaps of no
    motion and of the rigid translation, two passes to the coarse tolerance, one after the
    length choice whose increment 0.033 voxel left 0.00086 to apply after one more pass).
    Now 3: the gaps inside the first pass, the length chosen after the second (its increment
    0.030 after 0.295: the passes to come add up to ~0.003 < 0.01), and the level converged
    after the third (0.0031 after the choice's 0.050: ~2e-4 still to come < 1e-3). The field
    is as far from the analytic band as before (RMS between the nodes 0.03292 then, 0.03292 now),
    and a level converged so flags no node as unsettled (its last increment, 0.003 voxel, is
    above the tolerance at a few nodes, but what is still to come is not)."""
    from chunkdic.analysis.scoring import score_between_nodes
    from chunkdic.passes import level
    from chunkdic.synth import synthetic
    from chunkdic.synth.ctpair import standard_field

    size, ell = 64, 8
    field = standard_field("band", (size,) * 3)[0]
    pair = synthetic.synthesize(tmp_path / "band", (size,) * 3, field=field, specimen="grains", noise=0.02, seed=1,
                                dtype="uint16")
    passes: dict[int, int] = {}
    summed = level.LevelPasses.assemble_b

    def counted(self, u, op, **kwargs):
        passes[self.level] = passes.get(self.level, 0) + 1
        return summed(self, u, op, **kwargs)

    monkeypatch.setattr(level.LevelPasses, "assemble_b", counted)
    events = []
    # one brightness offset per element (grey_cell 0), the form both counts were measured
    # with, and the default cells of 32 voxels (4³ elements here), whose offsets the step
    # models since session 30 (left out of M, they took 4 passes)
    res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=ell, progress=events.append,
                             grey_cell=grey_cell)
    assert res.converged and res.info["levels"][-1] == 0
    assert passes[0] == 3
    # converged by the tolerance, not at the noise level: no node is flagged for still moving
    assert not [e for e in events if e["stage"] == "unsettled"]
    axes = [np.unique(a) for a in res.node_coords.reshape(3, -1)]
    assert score_between_nodes(axes, res.displacement, field, (size,) * 3, ell).rms < 0.034


def test_the_increments_still_to_come_of_a_geometric_contraction():
    """The prediction that ends a level: ``r / (1 - r)`` times the last increment when it
    shrank by ``r ≤ CONTRACTION`` (0.25), else nothing is predicted (``inf``)."""
    assert still_to_come(0.1, 0.01) == pytest.approx(0.01 * 0.1 / 0.9)
    assert still_to_come(0.04, 0.01) == pytest.approx(0.01 / 3)  # r = 0.25: the bound
    assert still_to_come(0.039, 0.01) == float("inf")  # slower than ×0.25 per pass
    assert still_to_come(float("inf"), 1e-6) == float("inf")  # no increment before
    assert still_to_come(0.0, 0.0) == float("inf")
