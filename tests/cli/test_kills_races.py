"""Kills at commits, races on in-place outputs, a series on a full disk, a Dask worker
killed (issue 24, the cases left open by ``test_faults``).

Kills are real ``SIGKILL``\\ s of a real ``python -m chunkdic``-like process: a small
wrapper (:data:`_DIE`) runs the CLI with a hook that kills the process at one exact point
of a commit (before the first rename, between the two renames, after them, half-way
through removing the old checkpoint) or after a number of chunk writes into a staged
copy. The same command then runs again in this process and must complete to the fields
of an uninterrupted run within 1e-6 voxel, leaving no lock, staged copy or scratch.
Scans are 32³ (chunks 16³).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr
from processes import descendants
from test_data_safety import N, T, tree
from test_fault_paths import _listing

import chunkdic
from chunkdic.cli.app import main
from chunkdic.io.kinds import kind_of
from chunkdic.synth import synthetic

pytestmark = pytest.mark.slow

_SERIES_OPTS = ["-l", "6", "--tolerance", "1e-4", "--block-elements", "2", "--incremental"]

#: runs the CLI (argv after the point and target) and SIGKILLs itself at one point of a commit
_DIE = r'''
import os, shutil, signal, sys
point, target = sys.argv[1], sys.argv[2]
from chunkdic.io import outputs
from chunkdic.cli.app import main

def die():
    os.kill(os.getpid(), signal.SIGKILL)

def ours(p):
    return str(p).rstrip("/").endswith(target)

real_rename, real_replace, real_remove = os.rename, os.replace, outputs.remove

def rename(src, dst, *a, **k):
    if point == "before-rename" and ours(src):
        die()
    real_rename(src, dst, *a, **k)
    if point == "between-renames" and ours(src):
        die()  # the output is absent now: the old checkpoint and the new result both carry partial names
    if point == "after-renames" and ours(dst):
        die()

def replace(src, dst, *a, **k):
    if point == "before-rename" and ours(dst):
        die()
    real_replace(src, dst, *a, **k)

def remove(path):
    if point == "half-removed" and ".chunkdic-partial-" in path.name and target.split("/")[-1] in path.name:
        shutil.rmtree(path / "checkpoint", ignore_errors=True)
        die()
    real_remove(path)

os.rename, os.replace, outputs.remove = rename, replace, remove

if point == "chunk-writes":  # target: how many chunk writes into a staged copy before the kill
    from zarr.storage import LocalStore
    real_set, count = LocalStore.set, [0]

    async def counted(self, key, value):
        await real_set(self, key, value)
        if ".chunkdic-partial-" in str(self.root) and "/c/" in "/" + key:
            count[0] += 1
            if count[0] >= int(target):
                die()
    LocalStore.set = counted

sys.exit(main(sys.argv[3:]))
'''


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A 32³ synthetic pair (Zarr, chunks 16³), its result, and an uninterrupted series."""
    d = tmp_path_factory.mktemp("kills")
    pair = synthetic.synthesize(d / "s", (N,) * 3, field=synthetic.Translation(T), seed=4, chunks=16)
    chunkdic.correlate(pair["reference"], pair["deformed"], element_size=8, output=d / "r.zarr")
    code = main(["series", *_scans(d), "-o", str(d / "full.zarr"), *_SERIES_OPTS])
    (d / "full.code").write_text(str(code))
    return d


def _scans(d: Path) -> list[str]:
    return [str(d / "s/ref.zarr"), str(d / "s/def.zarr"), str(d / "s/def.zarr")]


def _die(point: str, target: str, argv: list, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _DIE, point, str(target), *map(str, argv)], capture_output=True,
                          text=True, timeout=600, cwd=cwd)


def _leftovers(*roots: Path) -> list[str]:
    """chunkdic's own working names (locks, staged copies, scratch) under ``roots``."""
    return sorted(str(p) for r in roots for p in [r, *r.rglob("*")] if "chunkdic-" in p.name)


# --------------------------------------------------------------------------- item 6: series killed at a commit


@pytest.mark.parametrize("point,target", [("before-rename", "steps/002-incremental"),
                                          ("between-renames", "steps/002-incremental"),
                                          ("after-renames", "steps/002-incremental"),
                                          ("half-removed", "steps/002-incremental"),
                                          ("before-rename", "composed/002")])
def test_series_killed_while_a_step_commits_resumes_to_the_same_fields(data, tmp_path, capsys, monkeypatch, point,
                                                                      target):
    out = tmp_path / "ser.zarr"
    argv = ["series", *_scans(data), "-o", str(out), *_SERIES_OPTS]
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    monkeypatch.setenv("DASK_CHUNKDIC__SCRATCH_DIRECTORY", str(scratch))  # the killed run's
    before = tree(data / "s")
    killed = _die(point, target, argv)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    assert kind_of(out) == ("series", False)
    # what the kill left: a stale lock and staged copies, reclaimed by the next run (below)
    assert _leftovers(tmp_path), "the kill left nothing to reclaim: not at a commit"
    import dask.config

    with dask.config.set({"chunkdic.scratch-directory": str(scratch)}):
        code = main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err and code == int((data / "full.code").read_text()), err
    assert list(scratch.iterdir()) == []  # the killed run's scratch reclaimed, even when only steps were skipped
    a, b = chunkdic.open_series(out), chunkdic.open_series(data / "full.zarr")
    assert sorted(a.cumulative) == sorted(b.cumulative) == [1, 2]
    for k in a.cumulative:
        np.testing.assert_allclose(a.cumulative[k].displacement, b.cumulative[k].displacement, rtol=0, atol=1e-6)
    assert [r["group"] for r in a.rows] == [r["group"] for r in b.rows]
    assert _leftovers(tmp_path) == []  # no lock, staged copy or half-removed checkpoint
    assert _listing(tmp_path) == ["scratch", "ser.zarr"]
    assert tree(data / "s") == before


# --------------------------------------------------------------------------- item 9: export killed mid-write


@pytest.mark.parametrize("what", ["fields", "corrected"])
def test_export_killed_mid_write_is_reclaimed_and_completed_by_the_same_command(data, tmp_path, capsys, what):
    out = tmp_path / f"{what}.zarr"
    argv = ["export", str(data / "r.zarr"), f"--{what}", str(out)]
    before = tree(data / "s", data / "r.zarr")
    killed = _die("chunk-writes", "2", argv)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    partials = [p for p in tmp_path.iterdir() if ".chunkdic-partial-" in p.name]
    assert partials and not out.exists(), _listing(tmp_path)
    assert sum(len([c for c in p.rglob("*") if c.is_file() and "/c/" in str(c)]) for p in partials) >= 2  # mid-write
    assert main(argv) == 0
    capsys.readouterr()
    assert _listing(tmp_path) == [out.name]  # the dead run's partial and lock reclaimed
    # the completed output equals an uninterrupted export, array by array
    ref = tmp_path.parent / f"{tmp_path.name}-ref" / f"{what}.zarr"
    ref.parent.mkdir()
    assert main(["export", str(data / "r.zarr"), f"--{what}", str(ref)]) == 0
    capsys.readouterr()
    got, want = zarr.open_group(str(out), mode="r"), zarr.open_group(str(ref), mode="r")
    names = sorted(n for n, _ in want.arrays()) + sorted(f"{g}/{n}" for g, sub in want.groups()
                                                            for n, _ in sub.arrays())
    assert names and names == sorted(n for n, _ in got.arrays()) + sorted(f"{g}/{n}" for g, sub in got.groups()
                                                                         for n, _ in sub.arrays())
    for name in names:
        np.testing.assert_array_equal(got[name][...], want[name][...], err_msg=name)
    assert tree(data / "s", data / "r.zarr") == before


# --------------------------------------------------------------------------- item 8: races on in-place outputs


def _holds(lock: Path) -> bool:
    """Whether ``lock`` holds its owner's record: a lock file is created, then written."""
    try:
        return "pid" in json.loads(lock.read_text())
    except (OSError, ValueError):
        return False


def _first_and_second(first: list, second: list, lock: Path, out: Path, cwd: Path):
    """Start ``first``; once it holds ``lock``, stop it (SIGSTOP), run ``second`` to its end,
    then let ``first`` finish. Returns both completed processes' (code, stderr)."""
    proc = subprocess.Popen([sys.executable, "-m", "chunkdic", *map(str, first)], cwd=cwd, stderr=subprocess.PIPE,
                            stdout=subprocess.DEVNULL, text=True)
    deadline = time.time() + 300
    while not _holds(lock) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    assert _holds(lock), f"the first run never took its lock: {proc.poll()}"
    os.kill(proc.pid, signal.SIGSTOP)
    try:
        other = subprocess.run([sys.executable, "-m", "chunkdic", *map(str, second)], cwd=cwd, capture_output=True,
                               text=True, timeout=300)
    finally:
        os.kill(proc.pid, signal.SIGCONT)
    err = proc.stderr.read()
    return (proc.wait(timeout=600), err), (other.returncode, other.stderr)


@pytest.mark.parametrize("cmd", ["series", "synth", "report"])
def test_a_second_writer_of_a_new_in_place_output_is_refused_and_the_first_completes(data, tmp_path, cmd):
    out = tmp_path / {"series": "ser.zarr", "synth": "pair", "report": "figs"}[cmd]
    argv = {"series": ["series", *_scans(data)[:2], "-o", out, *_SERIES_OPTS],
            "synth": ["synth", out, "--shape", "32", "--chunks", "16"],
            "report": ["report", data / "r.zarr", "-o", out]}[cmd]
    before = tree(data / "s", data / "r.zarr")
    (code1, err1), (code2, err2) = _first_and_second(argv, argv, tmp_path / f".{out.name}.chunkdic-lock", out,
                                                     tmp_path)
    lines = err2.strip().splitlines()
    assert code2 == 2 and len(lines) == 1 and "Traceback" not in err2, err2
    assert re.match(r"chunkdic: error: output .* is being written by another chunkdic run \(pid \d+ ", lines[0])
    assert code1 == 0 and "Traceback" not in err1, err1
    # the first run's output, whole
    assert kind_of(out)[1] is True
    if cmd == "series":
        res = chunkdic.open_series(out).cumulative[1]
        assert np.abs(res.displacement - np.array(T)[:, None, None, None]).max() < 0.1
    elif cmd == "synth":
        assert chunkdic.open_scan(out / "ref.zarr").shape(0) == (32,) * 3 and (out / "field.json").is_file()
    else:
        assert any(p.suffix == ".png" for p in out.iterdir())
    assert _listing(tmp_path) == [out.name]
    assert tree(data / "s", data / "r.zarr") == before


# --------------------------------------------------------------------------- item 7: a series on a full disk


def _unshare_ok() -> bool:
    import shutil

    return shutil.which("unshare") is not None and \
        subprocess.run(["unshare", "-m", "true"], capture_output=True).returncode == 0


@pytest.mark.skipif(not _unshare_ok(), reason="needs a private mount namespace (unshare -m) for a full disk")
def test_a_lock_on_a_full_disk_is_a_disk_error_with_its_cause(tmp_path):
    """An output's lock made on a full disk (a 64 KiB tmpfs filled) is refused as a disk error
    (``DiskSpaceError``, whose cause a command that keeps its work on a full disk, ``series``,
    reports as such: a series whose disk fills as a step takes its lock keeps its complete
    steps and says so), and no lock file is left behind."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    probe = ("import sys; from chunkdic.errors import DiskSpaceError; from chunkdic.io.locks import OutputLock\n"
             "try:\n    OutputLock(sys.argv[1]).acquire()\nexcept DiskSpaceError as e:\n"
             "    print('disk', e.cause)\nelse:\n    print('taken')\n")
    script = ('mount -t tmpfs -o size=64k tmpfs "$1" || exit 90; dd if=/dev/zero of="$1/filler" bs=4k 2>/dev/null; '
              '"$2" -c "$3" "$1/out.zarr"; ls -A "$1"')
    proc = subprocess.run(["unshare", "-m", "sh", "-c", script, "sh", str(mnt), sys.executable, probe],
                          capture_output=True, text=True, timeout=120)
    out = proc.stdout.splitlines()
    assert proc.returncode == 0 and out[0].startswith("disk No space left on device ("), (proc.stdout, proc.stderr)
    assert out[0].endswith(".out.zarr.chunkdic-lock)") and out[1:] == ["filler"], out


#: in a private mount namespace: a 4 MiB tmpfs at $1; the series runs in the background until
#: the line $2, then the disk is filled; after the run the filler goes, the same command runs
#: again, and the series is copied out for the test to compare
_FULL = r'''
mnt=$1; at=$2; copy=$3; shift 3
mount -t tmpfs -o size=4m tmpfs "$mnt" || exit 90
: > "$mnt.err"
"$@" > /dev/null 2> "$mnt.err" &
pid=$!
while ! grep -q "$at" "$mnt.err"; do kill -0 $pid 2>/dev/null || break; sleep 0.02; done
dd if=/dev/zero of="$mnt/filler" bs=4k 2>/dev/null
wait $pid; echo "first=$?"
rm -f "$mnt/filler"
ls -A "$mnt" | tr '\n' ' '; echo
ls -A "$mnt/ser.zarr/steps" | tr '\n' ' '; echo
"$@" > /dev/null 2> "$mnt.err2"; echo "second=$?"
cp -a "$mnt/ser.zarr" "$copy"
ls -A "$mnt" | tr '\n' ' '; echo
'''


@pytest.mark.skipif(not _unshare_ok(), reason="needs a private mount namespace (unshare -m) for a full disk")
# the second point is inside step 2, as it chose its start and solves (its "iter  1" line was one of the
# stalled passes between identical scans that the start of lowest gap removed: it converges at pass 0)
@pytest.mark.parametrize("at", ["correlating 002-incremental", "lowest gap of earlier field"])
def test_series_on_a_full_disk_keeps_what_resumes_and_says_so(data, tmp_path, at):
    """The disk fills on the line ``at`` (asynchronously: the step may still complete, or keep its
    checkpoint); either way the series is kept, said so in one line, and resumed."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    copy = tmp_path / "copy.zarr"
    cmd = [sys.executable, "-m", "chunkdic", "series", *_scans(data), "-o", str(mnt / "ser.zarr"), *_SERIES_OPTS]
    proc = subprocess.run(["unshare", "-m", "sh", "-c", _FULL, "sh", str(mnt), at, str(copy), *cmd],
                          capture_output=True, text=True, timeout=900)
    report = proc.stdout.splitlines()
    first = (mnt.parent / "mnt.err").read_text()
    lines = [ln for ln in first.splitlines() if ln.startswith("chunkdic: error:")]
    assert report[0] == "first=2" and "Traceback" not in first, first[-3000:]
    assert len(lines) == 1 and first.strip().splitlines()[-1] == lines[0], first[-2000:]
    # the step's plan may see the full disk first (chunkdic.engine.costs): the same promise
    assert re.search(rf"(No space left on device|not enough disk).*; the series in {re.escape(str(mnt / 'ser.zarr'))} is kept "
                     r"\(marked incomplete, [01] steps? complete\): free space and run the same command again to "
                     "resume", lines[0]), lines[0]
    assert report[1].split() == ["ser.zarr"]  # kept, and no lock or staged copy beside it
    steps = report[2].split()  # step 1 complete or its checkpoint (and maybe step 2's), nothing else
    assert "001-incremental" in steps and not [s for s in steps if "chunkdic-" in s], steps
    assert report[3] == f"second={(data / 'full.code').read_text()}", (mnt.parent / "mnt.err2").read_text()[-2000:]
    assert report[4].split() == ["ser.zarr"]  # no lock or staged copy left on the disk
    a, b = chunkdic.open_series(copy), chunkdic.open_series(data / "full.zarr")
    for k in b.cumulative:
        np.testing.assert_allclose(a.cumulative[k].displacement, b.cumulative[k].displacement, rtol=0, atol=1e-6)


# --------------------------------------------------------------------------- item 5: a Dask worker killed



@pytest.mark.parametrize("at", ["correlating 002-incremental", "level 0: starting from"])
def test_series_survives_a_local_worker_killed_when_a_step_starts(data, tmp_path, at):
    """The kernels' warm-up skips the dead worker (it used to raise CommClosedError), the
    scheduler re-runs its tasks: the series completes to the uninterrupted fields."""
    out = tmp_path / "ser.zarr"
    argv = ["series", *_scans(data), "-o", str(out), *_SERIES_OPTS, "--scheduler", "local:2"]
    proc = subprocess.Popen([sys.executable, "-m", "chunkdic", *argv], stderr=subprocess.PIPE, text=True)
    victim = None
    lines = []
    for line in proc.stderr:
        lines.append(line)
        if victim is None and at in line:
            workers = [p for p, c in descendants(proc.pid).items() if "spawn_main" in c]
            assert workers, descendants(proc.pid)
            victim = workers[-1]
            os.kill(victim, signal.SIGKILL)
    code = proc.wait(timeout=600)
    err = "".join(lines)
    assert victim is not None and "Traceback" not in err, err[-3000:]
    assert code == int((data / "full.code").read_text()), err[-2000:]
    a, b = chunkdic.open_series(out), chunkdic.open_series(data / "full.zarr")
    for k in b.cumulative:
        np.testing.assert_allclose(a.cumulative[k].displacement, b.cumulative[k].displacement, rtol=0, atol=1e-6)
    assert _leftovers(tmp_path) == []


def test_a_cluster_that_loses_its_workers_is_one_line_exit_1_and_the_same_command_resumes(
        data, tmp_path, capsys, monkeypatch):
    """When the scheduler gives up (every worker that ran a task died), the run stops with
    one line and status 1; what it saved stays, and the same command completes it."""
    from chunkdic import scheduler
    from chunkdic.errors import WorkerLostError

    out = tmp_path / "ser.zarr"
    argv = ["series", *_scans(data), "-o", str(out), *_SERIES_OPTS]
    real_map, calls = scheduler.ThreadRunner.map_unordered, [0]

    def dies_on_the_sixth_pass(self, fn, args):
        calls[0] += 1
        if calls[0] == 6:  # inside the first step's iterations: its checkpoint is saved
            raise WorkerLostError(scheduler._lost_message(None))
        return real_map(self, fn, args)

    monkeypatch.setattr(scheduler.ThreadRunner, "map_unordered", dies_on_the_sixth_pass)
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("chunkdic: error: the Dask cluster lost the workers this run needs") and \
        "run the same command again to resume" in err[-1]
    assert not any("Traceback" in ln for ln in err)
    assert kind_of(out) == ("series", False)
    monkeypatch.setattr(scheduler.ThreadRunner, "map_unordered", real_map)
    assert main(argv) == int((data / "full.code").read_text())
    capsys.readouterr()
    a, b = chunkdic.open_series(out), chunkdic.open_series(data / "full.zarr")
    for k in b.cumulative:
        np.testing.assert_allclose(a.cumulative[k].displacement, b.cumulative[k].displacement, rtol=0, atol=1e-6)
    assert _leftovers(tmp_path) == []


def test_the_distributed_runner_turns_a_task_that_kills_its_workers_into_one_error(monkeypatch):
    """A real worker death: a task that ends its worker process; with no retry allowed the
    scheduler gives up (KilledWorker), which the runner reports as WorkerLostError."""
    import dask.config

    from chunkdic.errors import WorkerLostError
    from chunkdic.scheduler import open_runner

    with dask.config.set({"distributed.scheduler.allowed-failures": 0}), open_runner("local:1") as runner:
        assert sorted(runner.map_unordered(abs, [(-1,), (-2,)])) == [1, 2]
        with pytest.raises(WorkerLostError, match="lost the workers this run needs .*KilledWorker"):
            list(runner.map_unordered(os._exit, [(3,)]))


def test_a_step_left_without_readable_metadata_is_computed_again(data, tmp_path, capsys):
    """A full disk can cut a step's ``zarr.json`` short while the step is being created (CI
    saw it once: the re-run said "resuming 002-incremental" and correlate refused the step
    as a foreign folder). The series owns everything under ``steps/``: such debris is
    removed and the step computed again, to the uninterrupted fields."""
    out = tmp_path / "ser.zarr"
    shutil.copytree(data / "full.zarr", out)
    root = zarr.open_group(str(out), mode="r+")
    root.attrs["chunkdic"] = {**dict(root.attrs["chunkdic"]), "complete": False}
    for gone in ("steps/002-incremental", "composed/002"):
        shutil.rmtree(out / gone)
    (out / "steps/002-incremental").mkdir()
    (out / "steps/002-incremental/zarr.json").write_bytes(b"")  # cut short by the full disk
    capsys.readouterr()
    code = main(["series", *_scans(data), "-o", str(out), *_SERIES_OPTS])
    err = capsys.readouterr().err
    assert code == int((data / "full.code").read_text()) and "Traceback" not in err, err[-2000:]
    a, b = chunkdic.open_series(out), chunkdic.open_series(data / "full.zarr")
    for k in b.cumulative:
        np.testing.assert_allclose(a.cumulative[k].displacement, b.cumulative[k].displacement, rtol=0, atol=1e-6)
