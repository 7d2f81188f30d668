"""A dead run's scratch directory is adopted only by a run of the same identity, claimed by a
rename, and reclaimed otherwise (chunkdic.io.scratch; issue 21, item 5)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from chunkdic.io import owners, scratch
from chunkdic.io.owners import Owner, host_tag
from chunkdic.io.scratch import SCRATCH_MARKER, adopt_scratch, make_scratch, reclaim_stale_scratch


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
    host = host_tag()
    grave = _left_by(tmp_path, ".chunkdic-reclaimed-0123abcd", dead_pid, "run-a")
    claimed = _left_by(tmp_path, f".chunkdic-adopting-{host}-{dead_pid}-0123abcd", dead_pid, "run-a")
    alive = _left_by(tmp_path, f".chunkdic-adopting-{host}-{os.getpid()}-4567abcd", dead_pid, "run-a")
    reclaim_stale_scratch(tmp_path)
    assert not grave.exists() and not claimed.exists()
    assert alive.exists()  # a live adopter's claim, between its two renames


# --------------------------------------------------------------------------- a killed owner not yet reaped


def test_a_killed_owner_its_parent_has_not_reaped_is_dead(tmp_path):
    """A run killed with SIGKILL stays a zombie until its parent waits for it (a notebook's
    ``Popen``, a batch script's background job): it holds and writes nothing, so its scratch
    is adopted and its lock taken over, though ``kill(pid, 0)`` still succeeds."""
    import signal
    import time

    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    try:
        time.sleep(0.2)
        owner = Owner(Owner.me().host, proc.pid, owners._start_time(proc.pid))
        assert not owner.is_dead()  # alive
        os.kill(proc.pid, signal.SIGKILL)
        deadline = time.time() + 10
        while time.time() < deadline and owners._stat_fields(f"/proc/{proc.pid}/stat")[0] != "Z":
            time.sleep(0.05)
        assert owners._stat_fields(f"/proc/{proc.pid}/stat")[0] == "Z"  # killed, not reaped: a zombie
        assert owner.is_dead() and Owner(owner.host, proc.pid).is_dead()
        left = _left_by(tmp_path, "chunkdic-zombie", proc.pid, "run-a")
        assert adopt_scratch("run-a", tmp_path) is not None and not left.exists()
    finally:
        proc.kill()
        proc.wait()


# --------------------------------------------------------------------------- kept for its output's resume


def _interrupted_output(path, fingerprint: str, complete: bool = False):
    """A correlation output as its checkpoint leaves it (only the group metadata matters here)."""
    path.mkdir(parents=True, exist_ok=True)
    meta = {"zarr_format": 3, "node_type": "group",
            "attributes": {"chunkdic": {"kind": "result", "complete": complete, "fingerprint": fingerprint}}}
    (path / "zarr.json").write_text(json.dumps(meta))
    return path


def _kept_for(root, name: str, pid: int, output, fingerprint: str = "fp-a", size: int = 0):
    path = _left_by(root, name, pid, "run-a")
    record = json.loads((path / SCRATCH_MARKER).read_text())
    record["resume"] = {"output": str(output.resolve()), "fingerprint": fingerprint}
    (path / SCRATCH_MARKER).write_text(json.dumps(record))
    with open(path / "f-level0.zarr" / "big", "wb") as fh:
        fh.truncate(size)  # its size, without the disk (sparse)
    return path


def test_the_scratch_of_an_interrupted_output_is_kept_from_other_runs(tmp_path, dead_pid):
    """The cause of the LocalCluster resume that prepared its scans again (issue 21, item 5):
    any chunkdic run that made scratch in the same root between the kill and the resume (a
    test, a report, another correlation) reclaimed the killed run's directory. Now it stays
    while its output holds that run's interrupted checkpoint; only the run writing that
    output adopts or releases it."""
    import dask.config

    root, out = tmp_path / "scratch", _interrupted_output(tmp_path / "res.zarr", "fp-a")
    root.mkdir()
    kept = _kept_for(root, "chunkdic-kept", dead_pid, out, size=5000)
    plain = _left_by(root, "chunkdic-plain", dead_pid, "run-b")  # a dead run without an output to resume
    assert reclaim_stale_scratch(root) == [plain] and kept.exists()
    with dask.config.set({"chunkdic.scratch-directory": str(root)}):
        other = make_scratch()  # another run (a report, a correlation without output) starts meanwhile
    assert kept.exists() and scratch.reclaimable_scratch_bytes(root) == 0
    # the run writing that output counts it as its own (it adopts it, or starts the run over)
    marker_bytes = (kept / SCRATCH_MARKER).stat().st_size
    assert scratch.reclaimable_scratch_bytes(root, release=out) == 5000 + len("data") + marker_bytes
    got = adopt_scratch("run-a", root, resume=(str(out), "fp-a"))
    assert got is not None and sorted(root.iterdir()) == sorted([other, got])
    marker = json.loads((got / SCRATCH_MARKER).read_text())
    assert marker["resume"] == {"output": str(out.resolve()), "fingerprint": "fp-a"}  # kept again if this run dies


@pytest.mark.parametrize("case", ["output removed", "output complete", "another run's checkpoint", "released"])
def test_a_kept_scratch_is_reclaimed_once_nobody_can_resume_it(tmp_path, dead_pid, case):
    root, out = tmp_path / "scratch", _interrupted_output(tmp_path / "res.zarr", "fp-a")
    root.mkdir()
    kept = _kept_for(root, "chunkdic-kept", dead_pid, out)
    if case == "output removed":
        import shutil

        shutil.rmtree(out)
        gone = reclaim_stale_scratch(root)
    elif case == "output complete":
        _interrupted_output(out, "fp-a", complete=True)
        gone = reclaim_stale_scratch(root)
    elif case == "another run's checkpoint":  # --overwrite with other settings
        _interrupted_output(out, "fp-b")
        gone = reclaim_stale_scratch(root)
    else:  # the output's own run, starting it over (it holds the lock)
        gone = reclaim_stale_scratch(root, release=out)
    assert gone == [kept] and not kept.exists()


def test_a_scratch_left_by_an_interrupted_call_is_adopted_even_by_the_same_process(tmp_path):
    """Ctrl-C in a notebook, then the same call again in the same kernel: the interrupted call
    left its scratch (``leave_scratch``), so its live process does not keep it from the resume;
    other runs keep it while the output is interrupted."""
    import dask.config

    out = _interrupted_output(tmp_path / "res.zarr", "fp-a")
    root = tmp_path / "scratch"
    root.mkdir()
    with dask.config.set({"chunkdic.scratch-directory": str(root)}):
        path = make_scratch(run="run-a", resume=(str(out), "fp-a"))
        assert adopt_scratch("run-a") is None  # a live run's: never
        scratch.leave_scratch(path)
        assert reclaim_stale_scratch() == [] and path.exists()  # kept for the resume
        got = adopt_scratch("run-a", resume=(str(out), "fp-a"))
    assert got is not None and not path.exists()
    assert "released" not in json.loads((got / SCRATCH_MARKER).read_text())  # the resumed run's, live


def test_another_hosts_scratch_is_adopted_only_by_the_run_holding_its_outputs_lock(tmp_path):
    """A batch job re-queued on another node with the scratch on a shared file system: the owner
    check cannot see the first node's processes, so no run ever judges that directory dead. The
    run that holds the lock of the output it was kept for (the lock of the dead run taken over,
    or removed by the user) adopts it, or removes it when it starts that run over; every other
    run leaves it alone."""
    root, out = tmp_path / "scratch", _interrupted_output(tmp_path / "res.zarr", "fp-a")
    other_out = _interrupted_output(tmp_path / "other.zarr", "fp-a")
    root.mkdir()
    left = _kept_for(root, "chunkdic-node7", 4242, out)
    record = json.loads((left / SCRATCH_MARKER).read_text())
    (left / SCRATCH_MARKER).write_text(json.dumps({**record, "host": "node7-elsewhere"}))
    assert reclaim_stale_scratch(root) == [] and adopt_scratch("run-a", root) is None
    assert adopt_scratch("run-a", root, resume=(str(other_out), "fp-a")) is None  # another output's
    assert reclaim_stale_scratch(root, release=other_out) == [] and left.exists()
    got = adopt_scratch("run-a", root, resume=(str(out), "fp-a"))
    assert got is not None and not left.exists()
    # started over instead (another identity): removed by the output's own run only
    (got / SCRATCH_MARKER).write_text(json.dumps({**record, "host": "node7-elsewhere"}))
    assert reclaim_stale_scratch(root) == [] and reclaim_stale_scratch(root, release=out) == [got]
