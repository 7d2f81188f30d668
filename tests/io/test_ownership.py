"""A dead run's scratch directory is adopted only by a run of the same identity, claimed by a
rename, and reclaimed otherwise (chunkdic.io.ownership; issue 21, item 5)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from chunkdic.io import ownership
from chunkdic.io.ownership import SCRATCH_MARKER, Owner, adopt_scratch, make_scratch, reclaim_stale_scratch


@pytest.fixture(scope="module")
def dead_pid() -> int:
    """A pid no process holds any more (a child that has exited and been reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _left_by(root, name: str, pid: int, run: str | None, payload: str = "data"):
    """A scratch directory as a run ``pid`` of identity ``run`` leaves it (marker and a store)."""
    path = root / name
    path.mkdir()
    record = {**Owner.me().__dict__, "pid": pid, "start": None}
    if run is not None:
        record["run"] = run
    (path / SCRATCH_MARKER).write_text(json.dumps(record))
    (path / "f-level0.zarr").mkdir()
    (path / "f-level0.zarr" / "chunk").write_text(payload)
    return path


def test_a_dead_runs_scratch_of_the_same_identity_is_adopted(tmp_path, dead_pid):
    left = _left_by(tmp_path, "chunkdic-dead0001", dead_pid, "run-a")
    got = adopt_scratch("run-a", tmp_path)
    assert got is not None and got.name.startswith("chunkdic-") and got != left and not left.exists()
    assert (got / "f-level0.zarr" / "chunk").read_text() == "data"  # its stores, untouched
    marker = json.loads((got / SCRATCH_MARKER).read_text())
    assert (marker["pid"], marker["run"]) == (os.getpid(), "run-a")  # ours now: never reclaimed while we live
    assert reclaim_stale_scratch(tmp_path) == [] and got.exists()
    assert adopt_scratch("run-a", tmp_path) is None  # adopted once


@pytest.mark.parametrize("case", ["other identity", "no identity", "live owner", "not chunkdic's name", "a link"])
def test_no_other_scratch_is_ever_adopted(tmp_path, dead_pid, case):
    if case == "other identity":
        _left_by(tmp_path, "chunkdic-x", dead_pid, "run-b")
    elif case == "no identity":  # a run without an output, or of an older chunkdic
        _left_by(tmp_path, "chunkdic-x", dead_pid, None)
    elif case == "live owner":
        _left_by(tmp_path, "chunkdic-x", os.getpid(), "run-a")
    elif case == "not chunkdic's name":
        _left_by(tmp_path, "mine-x", dead_pid, "run-a")
    else:  # a link to a dead run's directory elsewhere: never followed
        (tmp_path / "elsewhere").mkdir()
        (tmp_path / "chunkdic-x").symlink_to(_left_by(tmp_path / "elsewhere", "chunkdic-target", dead_pid, "run-a"))
    before = sorted(p.name for p in tmp_path.iterdir())
    assert adopt_scratch("run-a", tmp_path) is None
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing renamed or written


def test_other_dead_runs_scratch_is_reclaimed_and_a_users_folder_kept(tmp_path, dead_pid):
    import dask.config

    _left_by(tmp_path, "chunkdic-other", dead_pid, "run-b")
    (tmp_path / "chunkdic-users-own").mkdir()  # no owner record: never touched
    with dask.config.set({"chunkdic.scratch-directory": str(tmp_path)}):
        assert adopt_scratch("run-a") is None
        new = make_scratch(run="run-a")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["chunkdic-users-own", new.name])
    assert json.loads((new / SCRATCH_MARKER).read_text())["run"] == "run-a"


def test_leftovers_of_a_dead_reclaimer_or_adopter_are_removed(tmp_path, dead_pid):
    host = ownership.re.sub(r"[^A-Za-z0-9_]", "_", ownership.socket.gethostname())
    grave = _left_by(tmp_path, ".chunkdic-reclaimed-0123abcd", dead_pid, "run-a")
    claimed = _left_by(tmp_path, f".chunkdic-adopting-{host}-{dead_pid}-0123abcd", dead_pid, "run-a")
    alive = _left_by(tmp_path, f".chunkdic-adopting-{host}-{os.getpid()}-4567abcd", dead_pid, "run-a")
    reclaim_stale_scratch(tmp_path)
    assert not grave.exists() and not claimed.exists()
    assert alive.exists()  # a live adopter's claim, between its two renames
