"""The scripted workflows of ``workflows/`` run end to end on small synthetic specimens.

Each script is imported from its file and its ``main(argv)`` is called with small sizes;
the numbers it returns are checked against the known fields of the synthetic scans.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from urllib.parse import urlparse

import numpy as np
import pytest

# end-to-end runs (whole commands, clusters, kills): `pytest -m 'not slow'` leaves them out
pytestmark = pytest.mark.slow

WORKFLOWS = Path(__file__).resolve().parents[1] / "workflows"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"workflow_{name}", WORKFLOWS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_laptop_embedded_default(tmp_path, capsys):
    laptop = _load("laptop")
    out = laptop.main(["--workdir", str(tmp_path), "--size", "48"])
    res = out["result"]
    assert res.converged
    assert "thread pool" in capsys.readouterr().out  # the embedded scheduler ran it
    assert np.all(out["rms_error"] < 0.05)
    assert out["strain"].eps_zz == pytest.approx(-0.01, abs=1e-3)
    # a second run reuses the complete result instead of refusing or recomputing it
    again = laptop.main(["--workdir", str(tmp_path), "--size", "48"])
    assert "reused" in capsys.readouterr().out
    np.testing.assert_array_equal(again["result"].displacement, res.displacement)


def test_local_cluster_on_loopback(tmp_path, capsys):
    out = _load("local_cluster").main(["--workdir", str(tmp_path), "--size", "48", "--workers", "2",
                                       "--dashboard-port", "0"])
    assert out["result"].converged
    assert np.all(out["rms_error"] < 0.05)
    assert urlparse(out["scheduler_address"]).hostname == "127.0.0.1"
    assert len(out["worker_addresses"]) == 2
    assert all(urlparse(a).hostname == "127.0.0.1" for a in out["worker_addresses"])
    assert urlparse(out["dashboard_link"]).hostname == "127.0.0.1"
    assert "dashboard: http://127.0.0.1:" in capsys.readouterr().out


def test_slurm_with_local_standin(tmp_path):
    has_jobqueue = importlib.util.find_spec("dask_jobqueue") is not None
    argv = ["--workdir", str(tmp_path), "--size", "48", "--local-standin", "--jobs", "1", "--processes", "1",
            "--cores", "2", "--memory", "2GiB", "--dashboard-port", "0", "--account", "proj",
            "--job-extra=--exclusive"]
    out = _load("slurm").main(argv + (["--print-job-script"] if has_jobqueue else []))
    assert not out["slurm"]
    if has_jobqueue:  # the batch script that SLURM would run (dask-jobqueue renders it)
        script = out["job_script"]
        assert "#SBATCH -A proj" in script and "#SBATCH --exclusive" in script and "--nthreads 2" in script
    # the stand-in has the layout of the job: one worker of 2 threads and 2 GiB
    assert list(out["workers"].values()) == [(2, 2 * 2**30)]
    assert all(urlparse(a).hostname == "127.0.0.1" for a in out["workers"])
    assert out["result"].converged
    assert np.all(out["rms_error"] < 0.05)
    assert (tmp_path / "scratch").is_dir()  # the shared scratch directory it configured


def test_whole_specimen_raw_to_strain(tmp_path):
    out = _load("whole_specimen").main(["--workdir", str(tmp_path), "--size", "160", "--field", "affine",
                                        "--no-report"])
    res = out["result"]
    assert res.info["level"] == 2 and res.info["element_size"] == 8
    assert out["scans"]["ref"].stored_levels() == [0, 1, 2, 3, 4]
    assert out["scans"]["ref"].dtype(0).name == "uint16"
    assert res.info["status"] != "diverged"
    # level 2 of a foam with 8-voxel cells: the 4^3 sums alias the cell walls (gap ~6 %), so the
    # boundary nodes are off by a few tenths of a level-2 voxel; the mean strain is right
    assert np.all(out["rms_error"] < 0.15)
    s = out["strain"]
    assert s.eps_zz == pytest.approx(-0.02, abs=2e-3)
    assert (tmp_path / "strain.json").exists()


def test_loading_series_cumulative_matches_direct(tmp_path):
    out = _load("loading_series").main(["--workdir", str(tmp_path), "--size", "48", "--steps", "2",
                                        "--step-strain", "-0.02"])
    rows = out["rows"]
    assert [r["step"] for r in rows] == [1, 2]
    assert rows[0]["cumulative_vs_direct_rms"] == 0.0  # step 1: the same correlation
    last = rows[-1]
    assert last["cumulative_vs_direct_rms"] < 0.05
    assert last["cumulative_error_rms"] < 0.06 and last["direct_error_rms"] < 0.05
    assert (tmp_path / "series.json").exists()
