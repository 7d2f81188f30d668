"""A correlation whose mesh data go to node blocks gives the field of the in-memory one."""

from __future__ import annotations

import dask.config
import numpy as np
import pytest

import chunkdic
from chunkdic.synth import foam, synthetic


@pytest.fixture(scope="module")
def pair():
    n = 48
    field = synthetic.Affine(matrix=((0.01, 0.0, 0.0), (0.004, -0.005, 0.0), (0.0, 0.0, 0.0)),
                             center=(n / 2, n / 2, n / 2), translation=(1.2, -0.7, 0.4))
    f = foam.render((n, n, n), seed=11)
    g = foam.render((n, n, n), seed=11, field=field, which="deformed")
    # ℓ = 8: 6³ nodes (the low-pass margin leaves 5 elements per axis) in blocks of 4 elements
    # (the drift model's cells of 4³): 8 node blocks
    ref = chunkdic.correlate(f, g, element_size=8, block_elements=4, coarsest=0, regularization_length=16)
    return f, g, ref


def test_a_memory_target_below_the_client_mesh_data_puts_them_in_blocks(pair):
    f, g, ref = pair
    options = dict(element_size=8, block_elements=4, coarsest=0, regularization_length=16)
    fits = chunkdic.plan(f, g, calibrate=False, memory_target="64GiB", **options)
    assert fits.mesh_data == "client" and fits.levels[-1].nodes == (6, 6, 6) and fits.levels[-1].blocks == 8
    # just below what the in-memory run needs with its smallest blocks
    target = fits.smallest_bytes - 1
    plan = chunkdic.plan(f, g, calibrate=False, memory_target=target, **options)
    assert plan.mesh_data == "disk" and plan.mesh_blocks_from == 6**3
    assert "in node blocks in files under the scratch" in plan.summary()
    with dask.config.set({"chunkdic.memory-target": target}):
        res = chunkdic.correlate(f, g, **options)
    assert res.info["status"] == ref.info["status"] == "converged"
    assert len(res.history["iteration"]) == len(ref.history["iteration"])
    scale = np.abs(ref.displacement).max()
    np.testing.assert_allclose(res.displacement, ref.displacement, rtol=0, atol=1e-8 * scale)
