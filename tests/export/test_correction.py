"""The corrected image rebuilds the engine's brightness model exactly (chunkdic.export.correction).

With affine offsets per cell (``grey_cell``) the result stores each element's gain and the
offset at its centre; the slopes inside the elements are read back from those offsets
(:func:`cell_slopes`). Known answers: a hand-built affine offset per cell, and a pair whose
brightness drift bends between two cells, where the corrected image's gap must be the
engine's own final gap (the engine's sums are independent of this module's rebuilding).
"""

from __future__ import annotations

import numpy as np
import pytest
from textures import fourier_shift, smooth_noise

import chunkdic
from chunkdic.mesh import Block
from chunkdic.results.scans import level_refs
from chunkdic.export.correction import (
    Correction,
    brightness_fields,
    cell_slopes,
    correct_block,
)


def test_cell_slopes_read_back_from_element_offsets():
    """Offsets ``a_c + b_c · (X_e - X_c)`` at the element centres of cells of 3³ elements on a
    7 × 5 × 4 element mesh (cells 3 + 3 + 1 along z, 3 + 2 along y, 3 + 1 along x): every
    cell at least two elements thick along an axis gives back its own slope there; the
    one-element-thick ones (z's last, x's last) the drift passed in; a NaN offset is skipped."""
    ell, k, shape = 6, 3, (7, 5, 4)
    rng = np.random.default_rng(0)
    n_cells = (3, 2, 2)
    a = rng.normal(size=n_cells) * 10
    b = rng.normal(size=(3,) + n_cells)  # grey levels per voxel
    centre = [np.arange(n) * ell + (ell - 1) / 2 for n in shape]  # element centres, voxels
    cell_centre = [np.array([np.mean(c[i * k:(i + 1) * k]) for i in range(m)]) for c, m in zip(centre, n_cells)]
    idx = np.ix_(*(np.arange(n) // k for n in shape))
    offset = a[idx].copy()
    for axis in range(3):
        rel = (centre[axis] - cell_centre[axis][np.arange(shape[axis]) // k])
        offset += b[axis][idx] * rel.reshape([-1 if i == axis else 1 for i in range(3)])
    offset[1, 1, 1] = np.nan  # an element with no valid voxel
    drift = (0.125, -0.25, 0.5)
    got = cell_slopes(offset, k, ell, drift)
    assert got.shape == (3,) + shape
    want = np.stack([b[axis][idx] for axis in range(3)])
    want[0, 6:] = drift[0]  # the last z cell is one element thick
    want[2, :, :, 3:] = drift[2]  # the last x cell too
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    # one offset per element (cell 1): the drift everywhere
    np.testing.assert_array_equal(cell_slopes(offset, 1, ell, drift), np.broadcast_to(
        np.asarray(drift)[:, None, None, None], (3,) + shape))


@pytest.fixture(scope="module")
def bent(tmp_path_factory):
    """The pair of ``test_cell_offsets_follow_a_drift_that_bends_…`` (tests/method/test_brightness.py):
    a smooth texture Fourier-shifted by a sub-voxel translation, the deformed scan ×1.25, +40
    and a drift along z of 0.2 grey level per voxel below the two cells' boundary and 0.8
    above, correlated with cells of 32 voxels (4 elements at ℓ = 8; the mesh's 7 elements
    make cells of 4 and 3)."""
    d = tmp_path_factory.mktemp("bent")
    n, ell, t, gain, base = 64, 8, (0.4, -0.3, 0.25), 1.25, 40.0
    f = smooth_noise((n, n, n), sigma=1.5, seed=5)
    bend = 4 + 4 * ell - 0.5 + t[0]
    z = np.arange(n, dtype=np.float64)[:, None, None]
    g = gain * fourier_shift(f, t) + base + np.where(z < bend, 0.2 * (z - bend), 0.8 * (z - bend))
    np.save(d / "f.npy", f.astype(np.float32))
    np.save(d / "g.npy", g.astype(np.float32))
    res = chunkdic.correlate(str(d / "f.npy"), str(d / "g.npy"), element_size=ell, coarsest=0,
                             regularization="none", tolerance=1e-4, smoothing=0, grey_cell=32)
    assert res.converged and res.mesh.shape == (7, 7, 7)
    return res, gain


def test_corrected_image_is_the_engines_model_with_brightness_cells(bent):
    """The corrected image over the whole ROI gives the engine's final gap (its sums were
    made in the engine's tasks: measured equal to 2e-6 relative), because each element
    ramps with its own cell's slope (-0.2 / 1.25 and -0.8 / 1.25 grey level per voxel along
    z, read back to 2e-3). Rebuilt with the cells' mean slope instead (the result's one
    ``drift``, what the views did before) the gap is 16 times the engine's."""
    res, gain = bent
    fields = brightness_fields(res)
    assert fields.shape == (5, 7, 7, 7)
    np.testing.assert_allclose(fields[2, :4], -0.2 / gain, atol=2e-3)
    np.testing.assert_allclose(fields[2, 4:], -0.8 / gain, atol=2e-3)
    np.testing.assert_allclose(fields[3:], 0.0, atol=2e-3)
    with level_refs(res) as (f_ref, g_ref):
        corr = Correction.of_result(res, f_ref, g_ref)
        whole = Block(tuple((0, m) for m in res.mesh.shape))
        gaps = {}
        for name, brightness in (("cells", fields), ("mean slope", res.brightness)):
            f, c, valid = correct_block(corr, whole, res.displacement, brightness)
            assert valid.all()
            gaps[name] = float(np.sqrt(np.mean((f - c) ** 2.0)) / (f.max() - f.min()))
    assert gaps["cells"] == pytest.approx(res.final_gap, rel=1e-4)
    assert gaps["mean slope"] > 10 * res.final_gap
