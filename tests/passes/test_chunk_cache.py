"""The cache of decoded scan chunks (chunkdic.io.chunkread) changes no number of a level:
``M`` and the prepared ``g`` of a Zarr pair with several chunks per axis are the same bits
with and without it, and the prepared ``g`` whatever the block size and the threads."""

from __future__ import annotations

import dask
import numpy as np

import chunkdic
from chunkdic.passes import level as level_module
from chunkdic.io import chunkread
from chunkdic.io.handles import forget_open_arrays


def _run(pair, *, cache: int, threads: int, block_elements: int):
    """One correlation of level 0 alone, capturing its ``M`` stencil, the prepared ``g``
    and how many chunks were decoded and found in the cache."""
    got = {"decoded": 0, "hits": 0, "parts": {}}
    m_pass, build, m_task = level_module.LevelPasses._m_pass, level_module.build_prepared, level_module.m_task

    def keep_part(inputs, job, u_block):
        out = m_task(inputs, job, u_block)
        got["parts"][job.block.elements] = (out[1], out[2], out[3])  # the block's stencil, min and max of f
        return out

    def counted(start: bool):
        # the decodes of these passes only, from an empty cache (the plan's calibration and
        # the rigid start read the scans too)
        if start:
            chunkread.forget_chunks()
        c = chunkread.chunk_cache()
        if c is not None and not start:
            got["decoded"] += c.decoded
            got["hits"] += c.hits
        if c is not None:
            c.decoded = c.hits = 0

    def keep_m(self, u):
        counted(True)
        m = m_pass(self, u)
        counted(False)
        got["M"] = m.stencil.copy()
        return m

    def keep_g(*args, **kwargs):
        counted(True)
        prepared = build(*args, **kwargs)
        counted(False)
        got["g"] = prepared.read(tuple(slice(a, b) for a, b in prepared.box))
        return prepared

    with dask.config.set({"chunkdic.chunk-cache": cache, "chunkdic.num-threads": threads}):
        forget_open_arrays()
        level_module.LevelPasses._m_pass, level_module.build_prepared, level_module.m_task = keep_m, keep_g, keep_part
        try:
            res = chunkdic.correlate(pair / "ref.zarr", pair / "def.zarr", element_size=8, coarsest=0,
                                     block_elements=block_elements, max_iterations=2,
                                     grey_cell=0)  # one offset per element: blocks of any size (cells round them)
        finally:
            level_module.LevelPasses._m_pass, level_module.build_prepared, level_module.m_task = m_pass, build, m_task
            forget_open_arrays()
    got["u"] = res.displacement
    return got


def test_m_and_the_prepared_g_are_the_same_bits_with_and_without_the_chunk_cache(tmp_path):
    from chunkdic.synth import synthetic
    from chunkdic.synth.fields import Translation

    # chunks of 24 over 80³: 4 per axis, every block's low-pass halo crosses chunk faces
    pair = tmp_path / "pair"
    synthetic.synthesize(pair, (80,) * 3, field=Translation((0.3, -0.2, 0.4)), specimen="grains", noise=0.02, seed=2,
                         dtype="uint16", chunks=24)
    plain = _run(pair, cache=0, threads=1, block_elements=2)
    cached = _run(pair, cache=64 << 20, threads=1, block_elements=2)
    assert plain["decoded"] == 0 and cached["decoded"] > 0
    # each of the 4³ chunks of each scan decoded once per pass (M: f; prefilter: g), the rest hits
    assert cached["decoded"] == 2 * 64 and cached["hits"] > cached["decoded"]
    # every block's share of M, the same bits (the client adds them up in the order they
    # arrive: M itself to float32 round-off)
    assert cached["parts"].keys() == plain["parts"].keys() and len(plain["parts"]) == 125
    for key, (stencil, lo, hi) in plain["parts"].items():
        np.testing.assert_array_equal(cached["parts"][key][0], stencil)
        assert cached["parts"][key][1:] == (lo, hi)
    np.testing.assert_allclose(cached["M"], plain["M"], rtol=2e-6, atol=1e-7 * np.abs(plain["M"]).max())
    np.testing.assert_array_equal(cached["g"], plain["g"])
    # the field from the same M and g (the client's solve rounds alike to 1e-15 between runs)
    np.testing.assert_allclose(cached["u"], plain["u"], rtol=0, atol=1e-12)
    # two threads sharing the cache, other blocks: the prefilter's tasks are the same, M
    # sums the same voxels in another order (float32 round-off)
    other = _run(pair, cache=4 << 20, threads=2, block_elements=3)
    np.testing.assert_array_equal(other["g"], plain["g"])
    np.testing.assert_allclose(other["M"], plain["M"], rtol=2e-5, atol=1e-6 * np.abs(plain["M"]).max())
    assert len(other["parts"]) == 27
