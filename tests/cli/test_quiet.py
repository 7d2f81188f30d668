"""Quiet and explicit (issue 23, item 7): Dask's cluster logs only with ``-v``, no voxel size
without its unit, progress lines at most one per 5 s."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from chunkdic.cli.app import main
from chunkdic.cli.common import PROGRESS_SECONDS, Progress

#: lines that only Dask's distributed loggers print (scheduler, nanny, workers, client)
DASK_LINES = ("Nanny", "Register worker", "Scheduler at", "requests to cancel", "Starting worker",
              "Receive client connection", "Remove client", "State start")


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def test_progress_lines_at_most_one_per_5_seconds(capsys):
    clock = Clock()
    p = Progress("fields", clock=clock)
    times = []
    for i in range(600):  # a 60 s step reporting every 0.1 s: the old printer said every 10 %
        clock.now += 0.1
        p((i + 1) / 600 * 0.999, "level 1")
        if capsys.readouterr().err:
            times.append(clock.now)
    p.done()
    last = capsys.readouterr().err
    assert len(times) == 11 and np.all(np.diff(times) >= PROGRESS_SECONDS - 1e-9)
    assert last == ""  # the 100 % line would come 0.9 s after the previous one: the summary says it
    # a step shorter than 5 s: its 100 % line only
    p = Progress("corrected image", clock=clock)
    for i in range(50):
        clock.now += 0.05
        p((i + 1) / 50)
    p.done()
    err = capsys.readouterr().err
    assert err == "  corrected image: 100% (2.5 s)\n"


@pytest.mark.parametrize("args", [["--voxel-size", "6.5"], ["--voxel-size", "5,2.5,2.5"],
                                  ["--voxel-size", "6.5um", "--unit", "mm"], ["--voxel-size", "0um"]])
def test_ingest_refuses_a_voxel_size_without_its_unit(tmp_path, capsys, args):
    np.save(tmp_path / "v.npy", np.zeros((8, 8, 8), np.uint8))
    out = tmp_path / "o.zarr"
    assert main(["ingest", str(tmp_path / "v.npy"), str(out), *args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("chunkdic: error: --voxel-size") and not out.exists()
    if args == ["--voxel-size", "6.5"]:
        assert "has no unit" in err and "6.5um" in err


@pytest.mark.parametrize("args", [["--voxel-size", "6.5um"], ["--voxel-size", "6.5", "--voxel-unit", "um"],
                                  ["--voxel-size", "6.5", "--unit", "micrometer"]])
def test_ingest_takes_the_unit_as_suffix_or_option(tmp_path, capsys, args):
    from chunkdic.io.scan import open_scan

    np.save(tmp_path / "v.npy", np.zeros((8, 8, 8), np.uint8))
    assert main(["ingest", str(tmp_path / "v.npy"), str(tmp_path / "o.zarr"), *args]) == 0
    scan = open_scan(tmp_path / "o.zarr")
    assert scan.voxel_size == (6.5,) * 3 and scan.unit == "micrometer"


def test_synth_refuses_a_voxel_size_without_its_unit(tmp_path, capsys):
    assert main(["synth", str(tmp_path / "p"), "--shape", "16", "--voxel-size", "2"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "has no unit" in err and not (tmp_path / "p").exists()


@pytest.mark.slow
def test_dask_cluster_logs_only_with_verbose(tmp_path):
    """``correlate --scheduler local:2``: ~70 stderr lines before, 50 of them Dask's."""
    from chunkdic.synth import synthetic

    pair = synthetic.synthesize(tmp_path / "p", (32,) * 3, field=synthetic.Translation((0.3, -0.2, 0.1)), seed=1)
    cmd = [sys.executable, "-m", "chunkdic", "correlate", str(pair["reference"]), str(pair["deformed"]),
           "-l", "8", "--regularization", "none", "--scheduler", "local:2"]
    quiet = subprocess.run(cmd + ["-o", str(tmp_path / "q.zarr")], capture_output=True, text=True)
    assert quiet.returncode == 0, quiet.stderr
    lines = quiet.stderr.splitlines()
    assert not [line for line in lines if any(s in line for s in DASK_LINES)], quiet.stderr
    assert len(lines) <= 20, quiet.stderr  # measured: 16 (start, plan, M, g prepared, rigid and affine steps, iterations, summary)
    verbose = subprocess.run(cmd + ["-o", str(tmp_path / "v.zarr"), "-v"], capture_output=True, text=True)
    assert verbose.returncode == 0 and any(s in verbose.stderr for s in DASK_LINES)


def test_verbose_prints_each_progress_line_once(tmp_path):
    """``-v`` adds the engine's details (its regularisation weights) to the progress lines, and
    prints each of those once: the engine's log of its events repeated every line."""
    from chunkdic.synth import synthetic

    pair = synthetic.synthesize(tmp_path / "p", (32,) * 3, field=synthetic.Translation((0.3, -0.2, 0.1)), seed=1)
    cmd = [sys.executable, "-m", "chunkdic", "correlate", str(pair["reference"]), str(pair["deformed"]),
           "-l", "8", "-o", str(tmp_path / "v.zarr"), "-v"]
    run = subprocess.run(cmd, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    lines = run.stderr.splitlines()
    assert any("regularisation over" in line for line in lines), run.stderr  # a detail only -v shows
    iterations = [line for line in lines if " iter " in line]
    assert iterations and len(iterations) == len(set(iterations)), run.stderr
    assert not [a for a, b in zip(lines, lines[1:]) if a == b], run.stderr


def test_demo_says_it_is_compiling_every_5_seconds(capsys):
    """A first run of the demo waits for its compiling processes: a line every 5 s, not silence."""
    from chunkdic.cli.app import _wait_for_compile

    clock = Clock()

    class Compiling:
        def __init__(self, seconds):
            self.end = clock.now + seconds

        def poll(self):
            return 0 if clock.now >= self.end else None

    def sleep(dt):
        clock.now += dt

    waited = _wait_for_compile([Compiling(7.0), Compiling(16.0)], clock=clock, sleep=sleep)
    lines = capsys.readouterr().err.splitlines()
    assert waited == pytest.approx(16.0, abs=0.3)
    assert [line.split(":")[1].split("(")[0].strip() for line in lines] == [
        "0 of 2 processes done", "1 of 2 processes done", "1 of 2 processes done"]
