"""The plan of a run (issue 21 item 4): `--plan` writes nothing, its memory estimate holds,
a memory target changes the blocks and is honoured, a run the disk cannot hold is refused
before anything is written."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import dask.config
import numpy as np
import pytest
from textures import smooth_noise

import chunkdic
from chunkdic.cli.app import main
from chunkdic import inputs
from chunkdic.engine import costs, runplan
from chunkdic.errors import InputError

N = 128
MiB = 2**20

# runs the correlation in a fresh process and prints its peak resident memory (VmHWM) and blocks
RUN = textwrap.dedent("""
    import json, sys, chunkdic
    blocks = {}
    def progress(e):
        if e["stage"] == "matrix":
            blocks[e["level"]] = e["blocks"]
    res = chunkdic.correlate(sys.argv[1], sys.argv[2], element_size=int(sys.argv[4]),
                             memory_target=sys.argv[3] or None, progress=progress)
    peak = [int(l.split()[1]) * 1024 for l in open("/proc/self/status") if l.startswith("VmHWM")][0]
    # did the run compile a kernel (numba cache miss)? its base memory is then the cold one
    import importlib
    from numba.core.dispatcher import Dispatcher
    from chunkdic.kernels.jit import KERNEL_MODULES
    compiled = sum(sum(o.stats.cache_misses.values()) for m in KERNEL_MODULES
                   for o in vars(importlib.import_module(m)).values() if isinstance(o, Dispatcher))
    print(json.dumps({"peak": peak, "blocks": blocks, "status": res.info["status"], "compiled": compiled}))
""")


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("budget")
    f = smooth_noise((N, N, N), sigma=1.5, seed=3)
    f = ((f - f.min()) / (f.max() - f.min()) * 50000 + 5000).astype(np.uint16)
    np.save(d / "ref.npy", f)
    np.save(d / "def.npy", np.roll(f, (1, -1, 0), axis=(0, 1, 2)))
    return d


def _measure(pair, scratch, target="", element_size=16, **env):
    env = dict(os.environ, DASK_CHUNKDIC__SCRATCH_DIRECTORY=str(scratch), **env,
               PYTHONPATH=os.pathsep.join([str(Path(chunkdic.__file__).parents[1]), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", RUN, str(pair / "ref.npy"), str(pair / "def.npy"), target,
                          str(element_size)], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _plan(pair, scratch, **kw):
    with dask.config.set({"chunkdic.scratch-directory": str(scratch)}):
        return chunkdic.plan(pair / "ref.npy", pair / "def.npy", calibrate=False, **{"element_size": 16, **kw})


def test_plan_writes_nothing_and_its_memory_estimate_holds(pair, tmp_path, capsys):
    scratch, out = tmp_path / "scratch", tmp_path / "res.zarr"
    scratch.mkdir()
    with dask.config.set({"chunkdic.scratch-directory": str(scratch)}):
        code = main(["correlate", str(pair / "ref.npy"), str(pair / "def.npy"), "-o", str(out), "--element-size",
                     "16", "--plan"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "level 0: 8x8x8 nodes" in printed and "peak per process" in printed and "scratch" in printed
    assert "time: ~" in printed and "calibrated now" in printed
    assert not out.exists() and os.listdir(scratch) == [] and sorted(os.listdir(tmp_path)) == ["scratch"]
    plan, plan_base = _plan(pair, scratch), costs.base_bytes()
    measured = _measure(pair, scratch)
    assert measured["status"] == "converged"
    # the plan assumes a compiling run unless every kernel of KERNEL_MODULES is cached (a
    # safe side: kernels some runs never call keep it cold, e.g. part-way through the test
    # suite); its model is checked for the state the measured run was in: the measured base
    # constants (costs.BASE_BYTES, compiling; WARM_BASE_BYTES, loading) plus tasks and mesh
    base = costs.BASE_BYTES if measured["compiled"] else costs.WARM_BASE_BYTES
    estimate = plan.process_bytes - plan_base + base
    assert plan_base >= base  # the plan never assumed the warm base for a run that compiled
    assert abs(estimate - measured["peak"]) <= 0.25 * measured["peak"], (estimate / MiB, measured["peak"] / MiB,
                                                                         measured["compiled"])


def test_plan_without_calibration_reads_no_voxel(pair, tmp_path, capsys, monkeypatch):
    """``--plan --no-calibration`` (a cluster other than the planning machine): the time from
    the assumed prefilter rate, and not one region of ``g`` timed; nothing written."""
    from chunkdic.engine import runplan

    def timed_here(*args, **kwargs):
        raise AssertionError("calibrated on the planning machine")

    monkeypatch.setattr(runplan, "calibrate", timed_here)
    out = tmp_path / "out.zarr"
    code = main(["correlate", str(pair / "ref.npy"), str(pair / "def.npy"), "-o", str(out), "--element-size",
                 "16", "--plan", "--no-calibration"])
    printed = capsys.readouterr().out
    assert code == 0 and "not calibrated: prefilter of g at 6 Mvoxel/s per task assumed" in printed
    assert not out.exists()


def test_memory_estimate_holds_with_the_mesh_data_in_blocks(pair, tmp_path):
    """The embedded scheduler with the mesh data in node blocks (the stencil in files under the
    scratch, CG's vectors in the process, the only process of the run): the plan's peak within
    25 % of the measured one."""
    blocks = {"DASK_CHUNKDIC__MESH_DATA": "blocks", "DASK_CHUNKDIC__BLOCK_VOXELS": "64"}
    with dask.config.set({"chunkdic.mesh-data": "blocks", "chunkdic.block-voxels": 64}):
        plan, plan_base = _plan(pair, tmp_path), costs.base_bytes()
    assert plan.mesh_data == "disk" and plan.levels[-1].blocks == 8
    measured = _measure(pair, tmp_path, **blocks)
    assert measured["status"] == "converged" and measured["blocks"]["0"] == 8
    base = costs.BASE_BYTES if measured["compiled"] else costs.WARM_BASE_BYTES
    estimate = plan.process_bytes - plan_base + base
    assert abs(estimate - measured["peak"]) <= 0.25 * measured["peak"], (estimate / MiB, measured["peak"] / MiB,
                                                                         measured["compiled"])


def test_memory_target_changes_blocks_and_is_honoured(pair, tmp_path):
    default = _plan(pair, tmp_path)
    target = default.process_bytes - 30 * MiB
    planned = _plan(pair, tmp_path, memory_target=target)
    assert planned.block_voxels < default.block_voxels
    assert planned.levels[-1].blocks > default.levels[-1].blocks
    assert planned.process_bytes <= target
    measured = _measure(pair, tmp_path, str(target))
    assert measured["blocks"]["0"] == planned.levels[-1].blocks > 1
    # issue 21's +10 % is the benchmark's median (validation/scale/bench_plan.py); one run in a test
    # gets a margin for the shared machine: 303 MiB for a 299 MiB target alone, 331 (+10.9 %)
    # once in a whole CI run at load ~5 (the embedded pool's two tasks overlapping differently)
    assert measured["peak"] <= 1.15 * target, (measured["peak"] / MiB, target / MiB)


# Two prefilter tasks at once in a fresh process, as a level-0 run's embedded pool runs them,
# on a zarr scan whose chunks their reads cross (the run's largest tasks): the peak resident
# memory above the process's before (the kernel's high-water mark, reset first), and the
# plan's model of it (costs.prepare_bytes with the read's buffers, times 2).
PREFILTER = textwrap.dedent("""
    import concurrent.futures, json, sys
    import numpy as np
    from chunkdic import config, scheduler
    from chunkdic.engine import costs
    from chunkdic.passes import prefilter as P
    from chunkdic.io.handles import ArrayRef
    from chunkdic.io.scan import open_scan

    scan, store, edge = open_scan(sys.argv[1]), sys.argv[2], int(sys.argv[3])
    g = scan.stored_refs()[0]
    sigma, interp = 1.0, "cubic"
    halo = P.prepared_halo(sigma, interp, int(config.get("bspline-halo")))
    grid = P.prepared_grid(g.dtype, sigma, interp)
    np.lib.format.open_memmap(store, mode="w+", dtype="uint16", shape=g.shape).flush()
    out = ArrayRef("npy", store, "", g.shape, "uint16")
    box = tuple((0, n) for n in g.shape)
    # 8 tasks, each read crossing a chunk boundary of y and x (chunks of 128)
    regions = [(slice(halo + 8, halo + 8 + edge), slice(104 + 128 * (k // 4), 104 + 128 * (k // 4) + edge),
                slice(104 + 128 * (k % 4), 104 + 128 * (k % 4) + edge)) for k in range(8)]
    # as in a run, whose earlier levels loaded the kernels and started zarr's reading threads
    P.prepare_deformed(np.zeros((8, 8, 8), np.float32), sigma, interp)
    P.write_region(out, (slice(0, 1), slice(0, 1), slice(0, 2)), np.zeros((1, 1, 2), np.uint16))
    g.read((slice(0, 1),) * 3)
    scheduler.release_freed_memory()
    open("/proc/self/clear_refs", "w").write("5")  # the high-water mark starts from here
    before = [int(l.split()[1]) * 1024 for l in open("/proc/self/status") if l.startswith("VmRSS")][0]
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        for _ in pool.map(lambda r: P.prepare_task(g, out, box, r, halo, sigma, interp, grid), regions):
            scheduler.release_freed_memory()  # as the passes do between results
    peak = [int(l.split()[1]) * 1024 for l in open("/proc/self/status") if l.startswith("VmHWM")][0] - before
    grown = [min(edge + 2 * halo, n) for n in g.shape]
    model = 2 * costs.prepare_bytes(edge, sigma, interp, shape=g.shape, raw_itemsize=2, quantized=grid[1] > 0,
                                     read_bytes=costs.read_buffer_bytes(scan, 0, grown))
    model += costs.chunk_cache_bytes((scan,), 0)  # the decoded chunks the process keeps, once
    print(json.dumps({"peak": peak, "model": model}))
""")


@pytest.mark.skipif(not os.path.exists("/proc/self/clear_refs"), reason="needs Linux /proc")
def test_two_prefilter_tasks_at_once_stay_within_their_memory_model(tmp_path):
    # uint16 noise (zarr cannot compress it, as real CT noise) in chunks of 128: the reads'
    # buffers are most of these small tasks' memory (measured 42-52 MiB, model 59 MiB; the
    # model before issue 21's fix, 5 float32 copies of the region, said 20 MiB)
    from chunkdic.io.scanwrite import write_scan

    data = np.random.default_rng(5).integers(1000, 60000, (80, 384, 640), dtype=np.uint16)
    write_scan(tmp_path / "g.zarr", data, chunks=128)
    del data
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(chunkdic.__file__).parents[1]),
                                                       os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", PREFILTER, str(tmp_path / "g.zarr"), str(tmp_path / "g.npy"), "48"],
                         env=env, capture_output=True, text=True, check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    # 42-52 MiB measured for 59 planned, once 65 and once 27 inside the whole suite (loaded CI
    # runs); the model before the prefilter's memory was measured said 20 MiB
    assert 0.4 * got["model"] <= got["peak"] <= 1.25 * got["model"], (got["peak"] / MiB, got["model"] / MiB)


def test_memory_target_too_small_is_refused_before_writing(pair, tmp_path, capsys):
    out = tmp_path / "res.zarr"
    code = main(["correlate", str(pair / "ref.npy"), str(pair / "def.npy"), "-o", str(out), "--element-size", "16",
                 "--memory-target", "200MiB"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "memory target 200 MiB" in err[0]
    assert not out.exists()
    with dask.config.set({"chunkdic.memory-target": "200MiB"}), pytest.raises(InputError, match="memory target"):
        chunkdic.correlate(pair / "ref.npy", pair / "def.npy", element_size=16)


@pytest.fixture
def small_disk(tmp_path, monkeypatch):
    """A 2 MiB file system: a real tmpfs when this process may mount one, else a free-space probe that says so."""
    d = tmp_path / "small"
    d.mkdir()
    mounted = os.geteuid() == 0 and subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(d)],
                                                   capture_output=True).returncode == 0
    if not mounted:
        real = runplan._free
        monkeypatch.setattr(runplan, "_free", lambda p: 2 * MiB if str(Path(p).absolute()).startswith(str(d))
                            else real(p))
    yield d
    if mounted:
        subprocess.run(["umount", str(d)], check=True)


def test_run_refused_for_lack_of_disk_leaves_nothing(pair, small_disk, capsys):
    out = small_disk / "res.zarr"
    with dask.config.set({"chunkdic.scratch-directory": str(small_disk / "scratch")}):
        code = main(["correlate", str(pair / "ref.npy"), str(pair / "def.npy"), "-o", str(out), "--element-size",
                     "16"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not enough disk" in err[0]
    assert os.listdir(small_disk) == []


def test_parse_memory():
    assert inputs.parse_memory("2GiB") == 2**31 and inputs.parse_memory(None) is None
    assert inputs.parse_memory(1000) == 1000
    for bad in ("lots", "-1GB", 0):
        with pytest.raises(InputError):
            inputs.parse_memory(bad)


def test_quantised_reference_copy_is_block_independent_and_close_to_float32():
    """The uint16 haloed copy of a low-passed 16-bit scan (chunkdic.scratch-precision): a grid of the
    level, not of the block, so the field does not depend on the blocks; half the disk of float32."""
    f = smooth_noise((48, 48, 48), sigma=1.2, seed=5)
    f = ((f - f.min()) / (f.max() - f.min()) * 60000 + 2000).astype(np.uint16)
    g = np.roll(f, (1, 2, -1), axis=(0, 1, 2))
    runs = {}
    for prec, m in (("uint16", 1), ("uint16", 4), ("float32", 4)):
        with dask.config.set({"chunkdic.scratch-precision": prec}):
            # one offset per element: cells of 32 voxels (4³ elements) would make both blocks 4
            runs[prec, m] = chunkdic.correlate(f, g, element_size=8, block_elements=m, coarsest=0,
                                               grey_cell=0.0).displacement
    np.testing.assert_allclose(runs["uint16", 1], runs["uint16", 4], rtol=0, atol=1e-6)
    np.testing.assert_allclose(runs["uint16", 4], runs["float32", 4], rtol=0, atol=1e-4)
    from chunkdic.passes.haloed import quantization
    assert quantization("uint16") == (0.0, 1.0) and quantization("uint8") == (0.0, 2.0**-8)
    assert quantization("float32") == (0.0, 0.0) and quantization("uint32") == (0.0, 0.0)


def test_prepared_grid_holds_the_coefficients_without_clipping():
    """The 16-bit grid of the prepared g covers the coefficients' overshoot (σ = 1: 1.9 % of the range)."""
    from chunkdic.passes.prefilter import (
        dequantize,
        prepare_deformed,
        prepared_grid,
        quantize,
    )

    rng = np.random.default_rng(0)
    raw = np.where(rng.random((40, 40, 40)) > 0.5, 65535, 0).astype(np.uint16)  # the worst texture: sharp, full range
    with dask.config.set({"chunkdic.scratch-precision": "uint16"}):
        grid = prepared_grid("uint16", 1.0, "cubic")
        assert prepared_grid("uint16", 0.0, "cubic") == (0.0, 0.0) and prepared_grid("float32", 1.0, "cubic") == (0, 0)
    coeffs = prepare_deformed(raw, 1.0, "cubic")
    q = quantize(coeffs, grid)
    assert q.dtype == np.uint16 and 0 < q.min() and q.max() < 65535
    assert np.abs(dequantize(q, grid) - coeffs).max() <= 0.5 * grid[1] + 0.01  # + float32 round-off at 4e4


def test_plan_chooses_the_compact_layout_only_when_the_fast_one_does_not_fit(pair, tmp_path, monkeypatch):
    """Issue 21: the fast (uncompressed) scratch layout while the disk holds it; the compact one,
    said in the plan's line and summary and used by the run, when it does not; refused when
    neither fits."""
    from chunkdic.passes.scratchstore import COMPACT_RATIO

    fast = _plan(pair, tmp_path)
    assert fast.layout == "fast" and fast.scratch_bytes == fast.fast_scratch_bytes
    assert "fast layout" in fast.summary() and "scratch" in fast.line()
    free = int(fast.scratch_bytes * 0.8)
    monkeypatch.setattr(runplan, "_free", lambda path: free)
    compact = _plan(pair, tmp_path)
    assert compact.layout == "compact" and compact.fast_scratch_bytes == fast.scratch_bytes
    assert " compact;" in compact.line() and "compact layout" in compact.summary() and "do not fit" in compact.summary()
    f0, c0 = fast.levels[-1], compact.levels[-1]  # the 16-bit level-0 stores, planned at the measured ratios
    assert c0.f_copy_bytes == int(f0.f_copy_bytes * COMPACT_RATIO["f"])
    assert c0.prepared_bytes == int(f0.prepared_bytes * COMPACT_RATIO["g"])
    assert compact.scratch_bytes < free
    codecs = {}

    def progress(event):  # what the run's level-0 stores are, while they exist
        if event["stage"] == "matrix" and event["level"] == 0:
            for path in tmp_path.rglob("f-level0.zarr/zarr.json"):
                codecs["f"] = json.loads(path.read_text())["codecs"]

    with dask.config.set({"chunkdic.scratch-directory": str(tmp_path)}):
        res = chunkdic.correlate(pair / "ref.npy", pair / "def.npy", element_size=16, progress=progress)
    assert res.info["status"] == "converged"
    assert any(c.get("name") == "blosc" for c in codecs["f"]), codecs
    monkeypatch.setattr(runplan, "_free", lambda path: int(compact.scratch_bytes * 0.5))
    with pytest.raises(InputError, match="not enough disk: .* in the compact layout"):
        _plan(pair, tmp_path).check()


def test_a_dead_runs_scratch_counts_as_free_disk(pair, tmp_path, monkeypatch):
    """Issue 21, item 5: a run killed at 2048³ leaves ~33 GB of scratch on a disk with 37 GB
    free; its resume found that disk full of its own interrupted run's stores and chose the
    compact layout (another scratch identity: nothing adopted) or refused to run. The plan
    counts the scratch of dead runs, which this run reclaims or adopts, as free; not what is
    kept for the resume of another output."""
    from chunkdic.io.owners import Owner
    from chunkdic.io.scratch import SCRATCH_MARKER

    scratch = tmp_path / "scratch"
    scratch.mkdir()
    fast = _plan(pair, scratch)
    free = int(fast.scratch_bytes * 0.8)
    monkeypatch.setattr(runplan, "_free", lambda path: free)
    assert _plan(pair, scratch).layout == "compact"

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()  # a dead pid
    left = scratch / "chunkdic-killed"
    left.mkdir()
    with open(left / "g-level0-1.npy", "wb") as fh:
        fh.truncate(int(fast.scratch_bytes * 0.5))  # its size without the disk (sparse)
    record = {**Owner.me().__dict__, "pid": proc.pid, "start": None, "run": "x"}
    (left / SCRATCH_MARKER).write_text(json.dumps(record))
    size = sum(p.stat().st_size for p in left.iterdir())
    plan = _plan(pair, scratch)
    assert plan.layout == "fast" and plan.scratch_free == free + size
    plan.check()  # not refused

    out = tmp_path / "other.zarr"  # now kept for the resume of another output: not this run's to use
    out.mkdir()
    (out / "zarr.json").write_text(json.dumps({"zarr_format": 3, "node_type": "group", "attributes": {
        "chunkdic": {"kind": "result", "complete": False, "fingerprint": "fp"}}}))
    record["resume"] = {"output": str(out.resolve()), "fingerprint": "fp"}
    (left / SCRATCH_MARKER).write_text(json.dumps(record))
    plan = _plan(pair, scratch)
    assert plan.layout == "compact" and plan.scratch_free == free
    monkeypatch.setattr(runplan, "_free", lambda path: 0)  # refused: the line says what holds the disk
    with pytest.raises(InputError, match=rf"not enough disk: .* \(\d+ MiB there is kept for the resume of "
                                         rf"{out.resolve()}: resume, or remove the output to free it\)$"):
        _plan(pair, scratch).check()
