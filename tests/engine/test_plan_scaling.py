"""The plan of a scan too large for this machine, from its metadata alone: what it says per
worker follows the number of workers, and nothing else does (docs/distributed.md, "Scaling")."""

from __future__ import annotations

import math
import warnings

import dask.config
import pytest
import zarr

import chunkdic
from chunkdic.engine import runplan
from chunkdic.io.integrity import MissingChunksWarning

N = 1024  # 2 GiB a scan: never written, the plan reads the metadata only


@pytest.fixture(scope="module")
def empty_pair(tmp_path_factory):
    """A uint16 pair of ``N``³ scans with metadata only (no chunk written)."""
    d = tmp_path_factory.mktemp("empty")
    for name in ("ref.zarr", "def.zarr"):
        g = zarr.open_group(str(d / name), mode="w", zarr_format=3)
        g.create_array("0", shape=(N,) * 3, chunks=(128,) * 3, dtype="uint16", fill_value=0)
    return d


def _plan(d, scheduler, monkeypatch):
    monkeypatch.setattr(runplan, "_free", lambda path: 2**50)  # the fast layout whatever this disk holds
    with warnings.catch_warnings(), dask.config.set({"chunkdic.mesh-data": "blocks"}):
        warnings.simplefilter("ignore", MissingChunksWarning)
        return chunkdic.plan(d / "ref.zarr", d / "def.zarr", element_size=8, scheduler=scheduler, calibrate=False)


def test_plan_of_n_workers_divides_the_voxel_passes_and_the_node_blocks_by_n(empty_pair, monkeypatch):
    """A 1024³ pair at ℓ = 8 (2.1 M nodes), on 4 and on 64 single-threaded workers: the same
    levels, blocks, scratch and client; the voxel passes' time and each worker's share of the
    node blocks 16 times smaller on 64 workers (the work and the blocks are the same, spread
    over 16 times as many workers); and no chunk is written (the stores hold metadata only)."""
    p4, p64 = (_plan(empty_pair, f"local:{n}", monkeypatch) for n in (4, 64))
    assert (p4.workers, p64.workers) == (4, 64) and p4.mesh_data == p64.mesh_data == "workers"
    assert math.prod(p4.levels[-1].nodes) == 128**3
    same = ("client_bytes", "scratch_bytes", "pyramid_bytes", "blocks_bytes", "output_bytes", "solve_seconds")
    assert [getattr(p4, k) for k in same] == [getattr(p64, k) for k in same]
    assert [(lv.nodes, lv.blocks, lv.work) for lv in p4.levels] == [(lv.nodes, lv.blocks, lv.work) for lv in p64.levels]
    for a, b in zip(p4.levels, p64.levels):
        assert a.seconds == pytest.approx(16 * b.seconds, rel=1e-12)
    share = {p.workers: p.blocks_bytes / p.workers for p in (p4, p64)}
    assert share[4] == pytest.approx(16 * share[64], rel=1e-12)
    assert f"on the 64 workers ({runplan._b(share[64])} each)" in p64.summary()
    files = [f.name for f in empty_pair.rglob("*") if f.is_file()]
    assert set(files) == {"zarr.json"}, files


class _Cluster:
    """What the plan reads of a ``distributed.Client``: its workers' threads."""

    def __init__(self, threads: list[int]):
        self.threads = threads

    def scheduler_info(self) -> dict:
        return {"workers": {f"tcp://w{i}": {"nthreads": n} for i, n in enumerate(self.threads)}}


def test_node_blocks_are_shared_by_the_workers_not_by_their_threads(empty_pair, monkeypatch):
    """2 workers of 4 threads and 8 single-threaded workers run 8 tasks at once alike (the same
    voxel-pass time), but the node blocks are held by processes: 2 workers hold a half each,
    4 times the share of each of 8, and the plan names 2 workers."""
    p2, p8 = _plan(empty_pair, _Cluster([4, 4]), monkeypatch), _plan(empty_pair, "local:8", monkeypatch)
    assert (p2.threads, p8.threads) == (8, 8) and (p2.workers, p8.workers) == (2, 8)
    assert p2.blocks_bytes == p8.blocks_bytes > 0
    assert [lv.seconds for lv in p2.levels] == pytest.approx([lv.seconds for lv in p8.levels], rel=1e-12)
    assert f"on the 2 workers ({runplan._b(p2.blocks_bytes / 2)} each)" in p2.summary()
    assert p2.process_bytes >= p2.base_bytes + p2.blocks_bytes / 2 and p2.process_bytes > p8.process_bytes


def test_node_blocks_count_on_the_scratch_and_not_in_the_output(empty_pair, monkeypatch):
    """The same 1024³ pair at ℓ = 8 (128³ nodes) with the embedded scheduler, its mesh data in
    the client or in node blocks on the scratch disk. In blocks, ``M`` (a float32 half stencil,
    14 × 3 × 3 × 4 = 504 B per node) is on the scratch twice while it is made, as the voxel
    blocks' partials and as the node blocks' files; and it is not kept in the output for a
    resumed run, which the in-memory run's output is, by exactly that stencil."""
    def plan(mode):
        monkeypatch.setattr(runplan, "_free", lambda path: 2**50)
        with warnings.catch_warnings(), dask.config.set({"chunkdic.mesh-data": mode, "chunkdic.num-threads": 2}):
            warnings.simplefilter("ignore", MissingChunksWarning)
            return chunkdic.plan(empty_pair / "ref.zarr", empty_pair / "def.zarr", element_size=8, scheduler="threads",
                                 output=empty_pair / "out.zarr", calibrate=False, grey="global")
    client, disk = plan("client"), plan("blocks")
    assert (client.mesh_data, disk.mesh_data) == ("client", "disk")
    assert math.prod(client.levels[-1].nodes) == 128**3
    stencil = 504 * 128**3
    assert client.output_bytes - disk.output_bytes == stencil
    extra = disk.scratch_bytes - client.scratch_bytes
    assert 2 * stencil <= extra <= 2 * stencil * 1.5, extra / stencil


def test_node_blocks_go_to_the_scratch_when_the_workers_cannot_hold_their_share(empty_pair, monkeypatch):
    """The 1024³ pair at ℓ = 8 (128³ nodes) on 2 single-threaded workers, mesh data in blocks by
    the memory target. Under 2 GiB each worker holds half the node blocks (680 B per node:
    0.67 GiB) beside its tasks. Under 1 GiB that half and a worker's base and tasks do not
    fit, while the client's share of the mesh data does: the blocks go to files on the scratch
    disk (their products in the client, its threads' blocks in flight counted there), the
    workers hold tasks only, and no process is planned above the target."""
    from chunkdic.engine.costs import BLOCKED_CLIENT_BYTES_PER_NODE, BLOCKS_BYTES_PER_NODE
    from chunkdic.solve.nodeblocks import MAX_TASK_BYTES

    def plan(target):
        monkeypatch.setattr(runplan, "_free", lambda path: 2**50)
        with warnings.catch_warnings(), dask.config.set({"chunkdic.num-threads": 2}):
            warnings.simplefilter("ignore", MissingChunksWarning)
            return chunkdic.plan(empty_pair / "ref.zarr", empty_pair / "def.zarr", element_size=8,
                                 scheduler="local:2", calibrate=False, memory_target=target, grey="global")

    roomy, tight = plan("2GiB"), plan("1GiB")
    nodes = 128**3
    assert roomy.mesh_data == "workers" and tight.mesh_data == "disk"
    assert roomy.blocks_bytes == tight.blocks_bytes == BLOCKS_BYTES_PER_NODE * nodes
    assert "in files under the scratch" in tight.summary() and "each worker's share" in tight.summary()
    # the client: its share per node, plus two threads' blocks in flight with the blocks on disk
    assert tight.client_bytes - roomy.client_bytes == 2 * MAX_TASK_BYTES
    assert roomy.client_bytes == BLOCKED_CLIENT_BYTES_PER_NODE * nodes
    assert tight.process_bytes <= 2**30 < tight.base_bytes + tight.task_bytes + tight.blocks_bytes // 2
    assert tight.scratch_bytes - roomy.scratch_bytes >= tight.blocks_bytes  # the blocks' files
    tight.check()
