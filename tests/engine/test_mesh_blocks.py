"""A correlation whose mesh data go to node blocks gives the field of the in-memory one."""

from __future__ import annotations

import dask.config
import numpy as np
import pytest

import chunkdic
from chunkdic.synth import foam, synthetic
from chunkdic.synth.shear import Slip


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


@pytest.mark.parametrize("length, tolerance", [(16, 1e-12), (None, 1e-8)])
def test_the_state_parked_on_the_scratch_gives_the_field_and_brightness_of_the_state_kept_in_memory(
        pair, monkeypatch, length, tolerance):
    """A level in node blocks keeps its best field, element fields and a pass's ``b`` in files
    (``Passes.park``): a lossless round trip, so the run equals the same run with them in memory
    to the round-off by which two runs of either differ (the order in which the blocks' partials
    add up: 2e-16 of the largest displacement at a fixed length; the length's choice, where the
    iterations start again from a pass whose fields are parked, carries it to 4e-9); the files
    are made, and gone with the run."""
    from chunkdic.method.protocol import stack_rows
    from chunkdic.passes.level import LevelPasses
    from chunkdic.passes.parked import Parked

    f, g, _ = pair
    options = dict(element_size=8, block_elements=4, coarsest=0, regularization_length=length)
    made = []
    write = Parked.__init__

    def counted(self, *args, **kwargs):
        write(self, *args, **kwargs)
        made.append(self.path)

    monkeypatch.setattr(Parked, "__init__", counted)
    with dask.config.set({"chunkdic.mesh-data": "blocks"}):
        parked = chunkdic.correlate(f, g, **options)
        monkeypatch.setattr(LevelPasses, "park", lambda self, array: stack_rows(array))
        kept = chunkdic.correlate(f, g, **options)
    # each Gauss-Newton pass's element fields and best field, and its b while it is solved for
    passes = int((parked.history["iteration"] >= 0).sum())
    assert passes >= 2 and len(made) >= 2 * passes
    assert not any(path.exists() for path in made)
    assert parked.info["status"] == kept.info["status"] == "converged"
    scale = np.abs(kept.displacement).max()
    np.testing.assert_allclose(parked.displacement, kept.displacement, rtol=0, atol=tolerance * scale)
    np.testing.assert_allclose(parked.brightness, kept.brightness, rtol=tolerance)
    np.testing.assert_array_equal(parked.flags, kept.flags)


def test_node_blocks_on_the_scratch_with_the_tasks_on_a_local_cluster_give_the_in_memory_field(pair, monkeypatch):
    """Where the workers cannot hold their share of the node blocks, the plan puts them in
    files on the scratch with the products in the client while the voxel passes run on the
    workers (forced here on a 2-worker ``LocalCluster``): the in-memory run's field to 1e-8 of
    its largest value, as the blocks on the workers or with the embedded scheduler."""
    from chunkdic.engine import processmemory
    from chunkdic.passes import level

    f, g, ref = pair
    options = dict(element_size=8, block_elements=4, coarsest=0, regularization_length=16)
    monkeypatch.setattr(processmemory, "blocks_place", lambda model, target: ("disk", ""))
    held, holder_for = [], level.holder_for
    monkeypatch.setattr(level, "holder_for", lambda runner, d: held.append((runner, holder_for(runner, d))) or held[-1][1])
    with dask.config.set({"chunkdic.mesh-data": "blocks"}):
        plan = chunkdic.plan(f, g, calibrate=False, scheduler="local:2", **options)
        assert plan.mesh_data == "disk" and plan.separate_client
        res = chunkdic.correlate(f, g, scheduler="local:2", **options)
    assert held and all(r.client is not None and h.where == "disk" for r, h in held)
    assert res.info["status"] == ref.info["status"] == "converged"
    scale = np.abs(ref.displacement).max()
    np.testing.assert_allclose(res.displacement, ref.displacement, rtol=0, atol=1e-8 * scale)


@pytest.mark.slow
def test_a_run_in_node_blocks_killed_mid_level_resumes_to_the_uninterrupted_field(pair, tmp_path, capsys):
    """The checkpoints of a level in node blocks read the parked arrays back (the best field,
    the element fields): a CLI run killed (SIGKILL) once its third pass of level 0 is reported
    resumes from its checkpoint to the field of an uninterrupted run in node blocks."""
    import os
    import signal
    import subprocess
    import sys

    from chunkdic.cli.app import main

    f, g, _ = pair
    np.save(tmp_path / "f.npy", f)
    np.save(tmp_path / "g.npy", g)
    out = tmp_path / "res.zarr"
    cmd = ["correlate", str(tmp_path / "f.npy"), str(tmp_path / "g.npy"), "-o", str(out), "--element-size", "8",
           "--tolerance", "1e-6", "--coarsest", "0", "--regularization-length", "16"]
    # 8 node blocks (of 4 elements), four passes of level 0
    blocks = {"chunkdic.mesh-data": "blocks", "chunkdic.block-voxels": 32}
    env = dict(os.environ, DASK_CHUNKDIC__MESH_DATA="blocks", DASK_CHUNKDIC__BLOCK_VOXELS="32")
    proc = subprocess.Popen([sys.executable, "-m", "chunkdic", *cmd], stderr=subprocess.PIPE, text=True, env=env)
    for line in proc.stderr:
        if line.startswith("level 0 iter  2"):
            os.kill(proc.pid, signal.SIGKILL)
            break
    assert proc.wait() == -signal.SIGKILL
    with dask.config.set(blocks):
        assert main(cmd) in (0, 1)
        assert "resuming the interrupted run from its checkpoint: level 0, iteration" in capsys.readouterr().err
        reference = chunkdic.correlate(f, g, element_size=8, tolerance=1e-6, coarsest=0, regularization_length=16)
    resumed = chunkdic.open_result(out)
    scale = np.abs(reference.displacement).max()
    np.testing.assert_allclose(resumed.displacement, reference.displacement, rtol=0, atol=1e-8 * scale)


def test_the_automatic_length_and_its_field_do_not_change_with_the_block_size(tmp_path):
    # the noise correlation κ sets the length choice's budget; summed on one row in eight counted
    # within each block, each lag k over nx - k voxels, it read 15.1 or 16.5 on this bar as its
    # blocks had 4 or 10 elements a side, and the choice kept 33.9 or 48 voxels (fields 0.05
    # voxel apart)
    shape = (300, 48, 48)
    field = Slip(center=(shape[0] - 1) / 2, jump=1.0, edge=3.0)
    pair = synthetic.synthesize(tmp_path / "bar", shape, field=field, specimen="grains", seed=1, noise=0.02,
                                texture_scale=4.0)
    runs = {}
    for elements in (4, 10):
        with pytest.warns(UserWarning):  # 6 voxels is below what this texture supports
            runs[elements] = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=6,
                                                block_elements=elements)
    small, large = runs[4], runs[10]
    assert small.info["regularization"]["length"] == large.info["regularization"]["length"]
    assert small.info["noise"]["kappa"] == pytest.approx(large.info["noise"]["kappa"], rel=0.03)
    np.testing.assert_allclose(small.displacement, large.displacement, rtol=0, atol=1e-6)
