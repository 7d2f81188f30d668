"""The prepared deformed image (low-pass, B-spline coefficients) equals a whole-volume filter."""

from __future__ import annotations

import dask.config
import numpy as np
import pytest
import scipy.ndimage as ndi

from chunkdic.passes.prefilter import build_prepared, prepared_halo, write_npy_region
from chunkdic.io.handles import ArrayRef
from chunkdic.scheduler import open_runner


@pytest.mark.parametrize("sigma", [0.0, 1.0], ids=["no-low-pass", "low-pass"])
@pytest.mark.parametrize("local", [True, False], ids=["memory-mapped", "zarr"])
@pytest.mark.parametrize("task_voxels", [None, 24], ids=["one-task", "many-tasks"])
def test_prepared_box_equals_whole_volume_filters(tmp_path, noise64, local, sigma, task_voxels):
    np.save(tmp_path / "g.npy", noise64)
    g = ArrayRef("npy", str(tmp_path / "g.npy"), "", noise64.shape, "float32")
    box = ((5, 64), (0, 64), (10, 50))  # touches the volume's faces on some sides only
    halo = prepared_halo(sigma, "cubic", 12)
    # 24-voxel tasks: 3 x 3 x 2 regions written concurrently, none spanning whole rows of the store
    with open_runner(None) as runner, dask.config.set({"chunkdic.prepare-voxels": task_voxels}):
        prep = build_prepared(g, box, tmp_path / "c", runner.map_unordered, halo=halo, local=local,
                              sigma=sigma, interpolation="cubic")
    assert prep.ref.kind == ("npy" if local else "zarr")
    whole = noise64.astype(np.float64)
    if sigma:
        whole = ndi.gaussian_filter(whole, sigma, mode="mirror", truncate=4.0)
    whole = ndi.spline_filter(whole, order=3, mode="mirror")
    window = (slice(5, 64), slice(0, 64), slice(10, 50))
    assert prep.covers(window) and not prep.covers((slice(4, 10),) + window[1:])
    span = float(noise64.max() - noise64.min())
    np.testing.assert_allclose(prep.read(window), whole[window], rtol=0, atol=1e-6 * span)


@pytest.mark.skipif(not __import__("os").path.exists("/proc/self/maps"), reason="needs Linux /proc")
def test_reading_a_memory_mapped_store_leaves_no_mapping_behind(tmp_path, noise64):
    # A mapping kept across tasks counts every page ever read in the worker's RSS (the
    # figure Dask's nanny acts on): 4.3 GiB at level 0 of 1024^3. Each read must unmap.
    path = tmp_path / "coefficients.npy"
    np.save(path, noise64)
    ref = ArrayRef("npy", str(path), "", noise64.shape, "float32")
    window = (slice(3, 40), slice(0, 64), slice(7, 9))
    got = ref.read(window)
    np.testing.assert_array_equal(got, noise64[window])
    with open("/proc/self/maps") as fh:
        assert str(path) not in fh.read()


@pytest.mark.parametrize("dtype", ["uint16", "float32"])
def test_npy_region_writes_equal_numpy_slice_assignment(tmp_path, dtype):
    # the prepared store's writes (pwrite of each contiguous run, not a memory map): parts
    # of rows, whole rows (one run per plane) and whole planes (one run), at any offset
    shape = (7, 9, 11)
    path = tmp_path / "store.npy"
    np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape).flush()
    want = np.zeros(shape, dtype)
    rng = np.random.default_rng(1)
    regions = [(slice(1, 4), slice(2, 5), slice(3, 10)),  # parts of rows
               (slice(4, 6), slice(1, 8), slice(0, 11)),  # whole rows
               (slice(0, 1), slice(0, 9), slice(0, 11)),  # a whole plane
               (slice(6, 7), slice(8, 9), slice(10, 11))]  # the last voxel
    for region in regions:
        data = (rng.random(tuple(r.stop - r.start for r in region)) * 60000).astype(dtype)
        write_npy_region(path, region, data)
        want[region] = data
    # a view whose rows only are contiguous (a task's crop of its float32 result)
    big = (rng.random((5, 9, 13)) * 60000).astype(dtype)
    write_npy_region(path, (slice(2, 5), slice(0, 9), slice(0, 11)), big[1:4, :, 2:])
    want[2:5] = big[1:4, :, 2:]
    np.testing.assert_array_equal(np.load(path), want)
    with pytest.raises(ValueError):
        write_npy_region(path, regions[0], np.zeros((2, 2, 2), dtype))


@pytest.mark.parametrize("shape", [(1, 6, 10), (5, 7, 9), (23, 17, 30)])
@pytest.mark.parametrize("sigma, cubic", [(1.0, True), (1.0, False), (0.0, True), (0.7, True)])
def test_fused_filter_equals_scipy(shape, sigma, cubic):
    """One sweep per axis (Gaussian then B-spline) against scipy's two whole-volume filters:
    equal to float32 round-off of the coefficients' range, short and odd axes included."""
    from chunkdic.kernels.lowpass import lowpass_bspline

    g = (np.random.default_rng(7).random(shape) * 4000).astype(np.uint16)
    want = g.astype(np.float32)
    if sigma > 0:
        want = ndi.gaussian_filter(want, sigma, mode="mirror", truncate=4.0, output=np.float32)
    if cubic:
        want = ndi.spline_filter(want, order=3, mode="mirror", output=np.float32)
    got = lowpass_bspline(g, sigma, cubic)
    assert got.dtype == np.float32 and got.shape == shape
    assert np.max(np.abs(got - want)) <= 5e-6 * np.ptp(want)
