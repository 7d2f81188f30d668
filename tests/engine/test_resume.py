"""A correlation killed with SIGKILL resumes from its checkpoint and ends where an
uninterrupted run ends (issue 5)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import numpy as np
import pytest

import chunkdic
from chunkdic.cli.app import main
from chunkdic.synth import foam, synthetic

# end-to-end runs (whole commands, clusters, kills): `pytest -m 'not slow'` leaves them out
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("resume")
    n = 64
    field = synthetic.Affine(matrix=((-0.01, 0, 0.005), (0, 0.004, 0), (0, 0, 0)), center=(32, 32, 32),
                             translation=(0.6, -0.4, 0.3))
    np.save(d / "f.npy", foam.render((n, n, n), seed=21))
    np.save(d / "g.npy", foam.render((n, n, n), seed=21, field=field, which="deformed"))
    return d


def _cmd(d, out, *extra):
    return [sys.executable, "-m", "chunkdic", "correlate", str(d / "f.npy"), str(d / "g.npy"), "-o", str(out),
            "--element-size", "8", "--tolerance", "1e-5", *extra]


def _run_and_kill(d, out, at: str) -> int:
    """Run the CLI in a subprocess and SIGKILL it when its progress line starts with ``at``."""
    proc = subprocess.Popen(_cmd(d, out), stderr=subprocess.PIPE, text=True)
    for line in proc.stderr:
        if line.startswith(at):
            os.kill(proc.pid, signal.SIGKILL)
            break
    return proc.wait()


def test_killed_client_resumes_and_matches_an_uninterrupted_run(pair, tmp_path, capsys):
    out = tmp_path / "res.zarr"
    assert _run_and_kill(pair, out, "level 0 iter  2") == -signal.SIGKILL
    with pytest.raises(chunkdic.InputError, match="incomplete"):
        chunkdic.open_result(out)  # clearly marked incomplete, never mistaken for a result

    assert main(_cmd(pair, out)[3:]) in (0, 1)
    err = capsys.readouterr().err
    assert "resuming the interrupted run from its checkpoint: level 0, iteration" in err, err
    resumed = chunkdic.open_result(out)

    reference = chunkdic.correlate(pair / "f.npy", pair / "g.npy", element_size=8, tolerance=1e-5)
    np.testing.assert_allclose(resumed.displacement, reference.displacement, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(resumed.history["iteration"], reference.history["iteration"])

    # complete now: the same command has nothing to do (exit 0, the result untouched, issue 24);
    # other settings are refused without --overwrite
    saved = sorted((p.relative_to(out), p.read_bytes()) for p in out.rglob("*") if p.is_file())
    assert main(_cmd(pair, out)[3:]) == 0
    assert "already complete" in capsys.readouterr().err
    assert main(_cmd(pair, out, "--interpolation", "linear")[3:]) == 2
    assert "complete result" in capsys.readouterr().err
    assert sorted((p.relative_to(out), p.read_bytes()) for p in out.rglob("*") if p.is_file()) == saved


def test_interrupted_run_with_other_settings_is_refused(pair, tmp_path, capsys):
    out = tmp_path / "res.zarr"
    _run_and_kill(pair, out, "level 0 iter  1")
    assert main(_cmd(pair, out, "--interpolation", "linear")[3:]) == 2
    assert "other inputs or settings" in capsys.readouterr().err


def test_worker_killed_during_an_iteration_does_not_change_the_result(pair):
    """Dask reschedules the dead worker's tasks; partial sums are only added once."""
    import threading
    import time

    from distributed import Client, LocalCluster

    reference = chunkdic.correlate(pair / "f.npy", pair / "g.npy", element_size=8, block_elements=2)
    killed = []
    with LocalCluster(n_workers=2, threads_per_worker=1, host="127.0.0.1", dashboard_address=None) as cluster, \
            Client(cluster) as client:
        pids = client.run(os.getpid)

        def kill_a_busy_worker():
            deadline = time.time() + 120
            while not killed and time.time() < deadline:
                for address, keys in client.processing().items():
                    if any("b_task" in str(k) for k in keys) and address in pids:
                        os.kill(pids[address], signal.SIGKILL)
                        killed.append(address)
                        return
                time.sleep(0.01)

        killer = threading.Thread(target=kill_a_busy_worker, daemon=True)
        killer.start()
        res = chunkdic.correlate(pair / "f.npy", pair / "g.npy", element_size=8, block_elements=2,
                                 scheduler=client)
        killer.join()
    assert killed, "no worker was killed during a b pass"
    np.testing.assert_allclose(res.displacement, reference.displacement, rtol=0, atol=1e-6)


@pytest.fixture(scope="module")
def band_pair(tmp_path_factory):
    """The CT-like band (64³ grains, independent 2 % noise): at ℓ = 8 the robust reweighting frees
    the band's curvature terms (a run with nothing freed would not exercise their checkpoint)."""
    d = tmp_path_factory.mktemp("resume-band")
    return synthetic.standard_case(d / "band", "band", 64, specimen="grains", noise=0.02)


def test_killed_after_the_robust_reweighting_resumes_with_the_same_freed_terms(band_pair, tmp_path, capsys):
    """Killed two passes after the reweighting (so that a checkpoint holds the freed terms), the
    same command ends where the uninterrupted run ends, with the same length and freed terms."""
    cmd = [sys.executable, "-m", "chunkdic", "correlate", band_pair["reference"], band_pair["deformed"], "-o",
           str(tmp_path / "res.zarr"), "--element-size", "8"]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    seen, passes = False, 0
    for line in proc.stderr:
        seen = seen or "robust reweighting" in line
        passes += seen and line.startswith("level 0 iter")
        if passes == 2:
            os.kill(proc.pid, signal.SIGKILL)
            break
    assert proc.wait() == -signal.SIGKILL, "the run ended before two passes after the reweighting"

    assert main(cmd[3:]) in (0, 1)
    err = capsys.readouterr().err
    assert "resuming the interrupted run from its checkpoint: level 0, iteration" in err, err
    assert "robust reweighting" not in err  # the length and the freed terms came from the checkpoint
    resumed = chunkdic.open_result(tmp_path / "res.zarr")
    reference = chunkdic.correlate(band_pair["reference"], band_pair["deformed"], element_size=8)
    assert reference.info["regularization"]["freed_terms"] > 0
    assert resumed.info["regularization"] == reference.info["regularization"]
    np.testing.assert_allclose(resumed.displacement, reference.displacement, rtol=0, atol=1e-6)
