"""A residual that is not noise: mismatched elements, flagged nodes, and no wrong "converged"
(chunkdic.method.mismatch; 2-D: chunkdic.analysis.q4)."""

from __future__ import annotations

import numpy as np
import pytest

import chunkdic
from chunkdic.analysis.q4 import correlate2d
from chunkdic.method.mismatch import local_residual, mismatched, node_share, residual_status
from chunkdic.results.result import FLAG_MISMATCH, FLAG_NO_DATA
from chunkdic.synth import foam
from chunkdic.synth.fields import Affine, true_displacement

BLOCK = 16


def test_local_residual_is_the_least_squares_misfit_of_a_gain_and_offset():
    """Against a direct least-squares fit of f ≈ λ g + μ over one element's voxels."""
    rng = np.random.default_rng(0)
    g = rng.random(700) * 50
    f = 1.7 * g - 3.0 + rng.standard_normal(700)
    d = f - g
    got = local_residual(np.array(700.0), d.sum(), g.sum(), d @ d, d @ g, g @ g)
    A = np.c_[g, np.ones_like(g)]
    fit = np.linalg.lstsq(A, f, rcond=None)[0]
    assert got[0] == pytest.approx(np.sum((f - A @ fit) ** 2), rel=1e-9)
    assert got[1] == pytest.approx(np.sum((f - f.mean()) ** 2), rel=1e-12)


def test_mismatched_elements_and_their_nodes_by_hand():
    """4 x 4 elements: one textured element unexplained is mismatched, an untextured one (its
    own variation at the noise level, air) is not judged, and a node is flagged when half or
    more of its elements are."""
    n = np.full((4, 4), 100.0)
    own = np.full((4, 4), 100.0 * 50.0)  # variance 50 per voxel
    ssr = np.full((4, 4), 100.0 * 1.0)  # noise 1 per voxel: explained
    ssr[1, 1] = 0.9 * own[1, 1]  # textured, unexplained
    own[3, 3], ssr[3, 3] = 100.0 * 1.5, 100.0 * 1.4  # variation at the noise level: not judged
    bad = mismatched(np.stack([ssr, own]), n)
    assert bad.sum() == 1 and bad[1, 1]
    nodes = node_share(bad, n)
    # node (i, j) touches elements (i-1..i, j-1..j): those around element (1, 1) have 1 of 4 (not
    # half), except none; with elements (1, 1) and (1, 2) both bad, nodes (1..2, 2) have 2 of 4
    assert not nodes.any()
    bad2 = bad.copy()
    bad2[1, 2] = True
    flagged = np.argwhere(node_share(bad2, n))
    assert sorted(map(tuple, flagged)) == [(1, 2), (2, 2)]


def test_everything_unexplained_is_mismatched():
    """Two unrelated images: every element leaves its whole variation, none stands out of the
    residual of the others; every element is mismatched."""
    rng = np.random.default_rng(1)
    n = np.full((5, 5), 64.0)
    own = rng.uniform(10, 200, (5, 5)) * 64
    ssr = own * rng.uniform(0.85, 1.0, (5, 5))
    assert mismatched(np.stack([ssr, own]), n).all()


def test_an_older_checkpoint_without_residual_rows_keeps_its_status():
    flags = np.zeros((3, 3, 3), np.uint8)
    assert residual_status("converged", flags, np.ones((6, 2, 2, 2))) == "converged" and not flags.any()


def _checker(g: np.ndarray, origin: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``g`` with every other 16³ block from voxel ``origin`` (checkerboard) replaced by Gaussian
    noise of its mean and standard deviation; and the mask of those blocks."""
    rng = np.random.default_rng(seed)
    out = g.copy()
    idx = (np.indices(g.shape) - origin) // BLOCK
    noisy = (idx.sum(axis=0) % 2) == 0
    out[noisy] = rng.normal(g.mean(), g.std(), int(noisy.sum()))
    return out, noisy


@pytest.mark.parametrize("noisy", [False, True])
def test_half_of_the_blocks_replaced_by_noise_is_not_converged(noisy):
    """48³ affine pair, ℓ = 8: with half of the deformed scan's 16³ blocks noise, the iterations
    end at the noise level with errors of voxels there; the run is ``mismatch``, not converged,
    and the flags follow the noise blocks: every node whose elements lie wholly in noise blocks is
    flagged, no node whose elements lie wholly in clean ones is. The same pair without the noise:
    converged, nothing flagged, the field within 0.01 voxel of the truth."""
    n, ell = 48, 8
    field = Affine(matrix=((0.01, 0, 0), (0, -0.005, 0), (0, 0, 0.004)), center=(n / 2,) * 3,
                   translation=(1.3, -0.7, 0.4))
    f = foam.render((n,) * 3, seed=3).astype(np.float32)
    g = foam.render((n,) * 3, seed=3, field=field, which="deformed").astype(np.float32)
    if noisy:
        g, blocks = _checker(g, 4)  # blocks of whole elements of the ROI below
    res = chunkdic.correlate(f, g, element_size=ell, roi="4:44,4:44,4:44")
    flagged = (res.flags & FLAG_MISMATCH) > 0
    if not noisy:
        err = np.abs(res.displacement - true_displacement(field, *res.node_coords)).max()
        assert res.info["status"] == "converged" and not flagged.any() and err < 0.01
        return
    assert res.info["status"] == "mismatch" and not res.info["converged"]
    # the share of each element's voxels in noise blocks, from the mesh's ROI
    (z0, _), (y0, _), (x0, _) = res.info["roi"]
    ez, ey, ex = (k - 1 for k in res.flags.shape)
    share = blocks[z0:z0 + ez * ell, y0:y0 + ey * ell, x0:x0 + ex * ell].reshape(ez, ell, ey, ell, ex, ell).mean(
        axis=(1, 3, 5))
    pad = np.pad(share, 1, constant_values=np.nan)
    around = np.stack([pad[dz:dz + ez + 1, dy:dy + ey + 1, dx:dx + ex + 1]
                       for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)])
    measured = (res.flags & FLAG_NO_DATA) == 0
    all_noise = np.nanmin(around, axis=0) == 1.0
    all_clean = np.nanmax(around, axis=0) == 0.0
    assert all_noise.any() and all_clean.any()
    assert flagged[all_noise & measured].all()
    assert not flagged[all_clean].any()


def _texture(n: int, seed: int) -> np.ndarray:
    r = np.random.default_rng(seed).random((n, n))
    return np.fft.ifft2(np.fft.fft2(r) * np.exp(-20 * np.add.outer(np.fft.fftfreq(n) ** 2,
                                                                     np.fft.fftfreq(n) ** 2))).real


def test_2d_unrelated_images_and_a_wrap_around_roll_are_not_converged():
    """correlate2d: two unrelated noise images (``mismatch``), and a 20-pixel wrap-around roll of
    a 48-pixel image, which converges to +20 on the part that did not wrap while 640 of the
    ROI's 1 600 pixels map outside (``excluded``); a 2-pixel roll still converges to 2."""
    rng = np.random.default_rng(0)
    noise = correlate2d(rng.random((40, 40)), rng.random((40, 40)), element_size=8)
    assert noise.status == "mismatch"
    f = _texture(48, 1)
    roll = correlate2d(f, np.roll(f, 20, axis=1), element_size=8)
    assert roll.status == "excluded" and roll.excluded == 640
    assert np.mean(roll.displacement[1]) == pytest.approx(20.0, abs=1e-3)
    small = correlate2d(f, np.roll(f, 2, axis=1), element_size=8)
    assert small.status == "converged" and np.mean(small.displacement[1]) == pytest.approx(2.0, abs=1e-3)
