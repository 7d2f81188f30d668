"""The common scoring rule (chunkdic.analysis.scoring): border exclusion, pooled sigma, RMS, failures.

Every expected number below is computed by hand in the comments, not by the code.
"""

import math

import numpy as np
import pytest

import chunkdic
from chunkdic.analysis.scoring import score_displacement, scored_region
from chunkdic.errors import InputError


def test_border_exclusion_uses_the_outer_voxel_faces():
    # 40 voxels per axis: faces at -0.5 and 39.5; ell = 8 keeps 7.5 <= p <= 31.5
    shape, ell = (40, 40, 40), 8
    z = np.array([7.5, 7.49, 31.5, 31.51, 20.0, 20.0, 20.0, 20.0])
    y = np.array([20.0, 20.0, 20.0, 20.0, 7.4, 32.0, 20.0, 20.0])
    x = np.array([20.0, 20.0, 20.0, 20.0, 20.0, 20.0, 7.5, 31.6])
    inside = scored_region(np.stack([z, y, x]), shape, ell)
    assert inside.tolist() == [True, False, True, False, False, False, True, False]


def test_pooled_sigma_bias_rms_and_max_by_hand():
    shape, ell = (64, 64, 64), 16
    # four points inside (16 <= p <= 47), one outside (p = 5 along z) with a huge error
    pts = np.array([
        [20.0, 30.0, 40.0, 25.0, 5.0],
        [20.0, 20.0, 20.0, 20.0, 20.0],
        [20.0, 20.0, 20.0, 20.0, 20.0],
    ])
    truth = np.array([0.5, -0.25, 1.0])
    # errors e (z, y, x) at the four inside points:
    #   z: +0.1, -0.1, +0.1, -0.1  -> bias 0,   var 0.01
    #   y: +0.2, +0.2, +0.2, +0.2  -> bias 0.2, var 0
    #   x: +0.0, +0.3, +0.0, -0.3  -> bias 0,   var (0 + 0.09 + 0 + 0.09) / 4 = 0.045
    e = np.array([
        [0.1, -0.1, 0.1, -0.1, 50.0],
        [0.2, 0.2, 0.2, 0.2, 0.0],
        [0.0, 0.3, 0.0, -0.3, 0.0],
    ])
    s = score_displacement(pts, truth[:, None] + e, truth, shape, ell)
    assert (s.n_points, s.n_failed, s.n_outside) == (4, 0, 1)
    np.testing.assert_allclose(s.bias, (0.0, 0.2, 0.0), atol=1e-12)
    np.testing.assert_allclose(s.std, (0.1, 0.0, math.sqrt(0.045)), atol=1e-12)
    # pooled sigma = sqrt((0.01 + 0 + 0.045) / 3) = sqrt(0.055 / 3)
    assert s.sigma == pytest.approx(math.sqrt(0.055 / 3), rel=1e-12)
    # |e|^2 per point: 0.01 + 0.04 + 0 = 0.05; 0.01 + 0.04 + 0.09 = 0.14; 0.05; 0.14
    # rms = sqrt(0.38 / 4) = sqrt(0.095); max = sqrt(0.14)
    assert s.rms == pytest.approx(math.sqrt(0.095), rel=1e-12)
    assert s.max_error == pytest.approx(math.sqrt(0.14), rel=1e-12)


def test_failed_points_are_counted_not_scored():
    shape, ell = (50, 50, 50), 10
    pts = np.full((3, 5), 25.0)
    pts[0, 4] = 2.0  # outside: neither scored nor counted as failed
    u = np.zeros((3, 5))
    u[:, 1] = np.nan  # tool returned NaN
    u[0, 2] = 1000.0  # tool flagged it (valid=False): its wild value must not count
    u[0, 3] = 0.4
    u[:, 4] = np.nan
    valid = np.array([True, True, False, True, True])
    s = score_displacement(pts, u, (0.0, 0.0, 0.0), shape, ell, valid=valid)
    assert (s.n_points, s.n_failed, s.n_outside) == (2, 2, 1)
    # errors on z at the two scored points: 0 and 0.4 -> bias 0.2, std 0.2, rms sqrt(0.16 / 2)
    assert s.bias[0] == pytest.approx(0.2) and s.std[0] == pytest.approx(0.2)
    assert s.sigma == pytest.approx(0.2 / math.sqrt(3))
    assert s.rms == pytest.approx(math.sqrt(0.08))
    assert s.max_error == pytest.approx(0.4)


def test_grid_shaped_input_and_no_scored_point():
    # (3, nz, ny, nx) input, as chunkdic.Result stores it; nodes all nearer than ell
    zz, yy, xx = np.meshgrid([1.5, 3.5], [1.5, 3.5], [1.5, 3.5], indexing="ij")
    pts = np.stack([zz, yy, xx])
    s = score_displacement(pts, np.zeros_like(pts), np.zeros_like(pts), (6, 6, 6), 4)
    assert (s.n_points, s.n_failed, s.n_outside) == (0, 0, 8)
    assert math.isnan(s.sigma) and math.isnan(s.rms)
    assert s.as_dict()["n_outside"] == 8


def test_public_export_and_bad_shapes():
    assert chunkdic.score_displacement is score_displacement
    assert "score_displacement" in chunkdic.__all__
    with pytest.raises(InputError):
        score_displacement(np.zeros((3, 4)), np.zeros((3, 5)), (0, 0, 0), (9, 9, 9), 1)
    with pytest.raises(InputError):
        score_displacement(np.zeros((2, 4)), np.zeros((2, 4)), (0, 0), (9, 9, 9), 1)
    with pytest.raises(InputError):
        scored_region(np.zeros((3, 4)), (9, 9), 1)


def _parabola(z, y, x):
    """The truth u = (0, 0, (x - 9.5)² / 16) on broadcast axes."""
    z, y, x = np.broadcast_arrays(z, y, x)
    return np.stack([0 * x, 0 * x, (x - 9.5) ** 2 / 16])


def _parabola_at_nodes():
    """Nodes every 4 voxels from -0.5 to 19.5 per axis and :func:`_parabola` at them."""
    axes = [np.arange(6) * 4.0 - 0.5] * 3
    return axes, _parabola(*np.meshgrid(*axes, indexing="ij"))


def test_between_nodes_scores_every_voxel_of_the_trilinear_field():
    from chunkdic.analysis.scoring import score_between_nodes

    # 20 voxels per axis, ell 4: voxels 4..15 are scored (12 per axis, 1728 in all); nodes every
    # 4 voxels from -0.5 to 19.5. Along x the truth is u_x = (x - 9.5)^2 / 16 and the nodal field
    # takes it at the nodes: between nodes 4 apart the chord of x^2/16 exceeds it by
    # t (4 - t) / 16 at t voxels from a node; voxels sit at t = 0.5, 1.5, 2.5, 3.5, so the
    # error is 7/64 (t = 0.5, 3.5) or 15/64 (t = 1.5, 2.5), half the voxels each.
    axes, u = _parabola_at_nodes()
    truth = _parabola
    s = score_between_nodes(axes, u, truth, (20, 20, 20), 4)
    assert s.n_points == 12**3 and s.n_failed == 0 and s.n_outside == 0
    assert s.rms == pytest.approx(math.sqrt(((7 / 64) ** 2 + (15 / 64) ** 2) / 2), rel=1e-12)
    assert s.max_error == pytest.approx(15 / 64, rel=1e-12)
    # a NaN node fails the voxels of its 8 cells that are scored; a grid covering only
    # part of the region leaves the rest outside
    u[0, 2, 2, 2] = np.nan  # node at 7.5: cells 3.5..11.5 per axis hold scored voxels 4..11 (8)
    s = score_between_nodes(axes, u, truth, (20, 20, 20), 4)
    assert s.n_failed == 8**3 and s.n_points == 12**3 - 8**3
    short = [axes[0][:3], axes[1], axes[2]]  # z nodes up to 7.5: scored z voxels 4..7 only
    s = score_between_nodes(short, np.zeros((3, 3, 6, 6)), truth, (20, 20, 20), 4)
    assert s.n_points == 4 * 144 and s.n_outside == 8 * 144


def test_between_nodes_score_does_not_depend_on_the_slabs_it_is_evaluated_in():
    from chunkdic.analysis.scoring import score_between_nodes

    # a rough nodal field with a NaN node against a smooth truth: scored in one piece, one
    # z plane at a time, or in slabs of a few planes, the statistics are the same numbers
    rng = np.random.default_rng(3)
    axes = [np.arange(7) * 5.0 - 0.5, np.arange(6) * 5.0 - 0.5, np.arange(5) * 6.0 - 0.5]
    u = rng.normal(0.2, 0.3, (3, 7, 6, 5))
    u[1, 3, 2, 1] = np.nan

    def truth(z, y, x):
        z, y, x = np.broadcast_arrays(z, y, x)
        return np.stack([0.01 * z, np.sin(y / 7.0), 0.1 + 0 * x])

    whole = score_between_nodes(axes, u, truth, (31, 26, 25), 3, slab_voxels=10**9)
    assert whole.n_failed > 0 and whole.n_points > 1000
    for slab in (1, 3 * 20 * 19, 1000):
        s = score_between_nodes(axes, u, truth, (31, 26, 25), 3, slab_voxels=slab)
        assert (s.n_points, s.n_failed, s.n_outside) == (whole.n_points, whole.n_failed, whole.n_outside)
        for a, b in [(s.rms, whole.rms), (s.sigma, whole.sigma), (s.max_error, whole.max_error),
                     *zip(s.bias, whole.bias), *zip(s.std, whole.std)]:
            assert a == pytest.approx(b, rel=1e-10, abs=1e-14)


def test_between_nodes_sampled_score_is_the_score_of_those_voxels():
    from chunkdic.analysis.scoring import score_between_nodes

    # the trilinear chord of u_x = (x - 9.5)^2 / 16 between nodes 4 apart: at a voxel t from a
    # node the error is t (4 - t) / 16, 7/64 or 15/64 (test above); any sample of voxels
    # holds only those two values, so its RMS lies between them and its max is one of them
    axes, u = _parabola_at_nodes()
    truth = _parabola
    s = score_between_nodes(axes, u, truth, (20, 20, 20), 4, sample=1000, seed=1)
    assert s.n_points == 1000 and s.n_outside == 0
    assert 7 / 64 < s.rms < 15 / 64 and s.max_error == pytest.approx(15 / 64, rel=1e-12)
    full = score_between_nodes(axes, u, truth, (20, 20, 20), 4)
    assert s.rms == pytest.approx(full.rms, rel=0.05)  # half the voxels at each value
    # a rough field on a larger grid (56³ scored voxels): 100 000 voxels drawn with replacement
    # give the full statistics to sampling error (~0.3 %)
    rng = np.random.default_rng(5)
    axes = [np.arange(17) * 4.0 - 0.5] * 3
    u = rng.normal(0, 0.3, (3, 17, 17, 17))
    full = score_between_nodes(axes, u, truth, (64, 64, 64), 4)
    s = score_between_nodes(axes, u, truth, (64, 64, 64), 4, sample=100_000)
    assert full.n_points == 56**3 and s.n_points == 100_000
    assert s.rms == pytest.approx(full.rms, rel=0.01) and s.sigma == pytest.approx(full.sigma, rel=0.01)
    assert s.max_error <= full.max_error + 1e-12
