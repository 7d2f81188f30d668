"""A correlation killed with SIGKILL resumes from its checkpoint and ends where an
uninterrupted run ends (issue 5)."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest
import zarr

import chunkdic
from chunkdic.cli.app import main
from chunkdic.results.result import FLAG_WEAK
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


# --------------------------------------------------------------------------- what a resume reuses (issue 21, item 5)

#: runs the CLI and SIGKILLs itself while the level-0 M is written into the output: after its
#: arrays, with the stencil's first chunk cut short, before the record that marks it complete
_DIE_WRITING_M = r'''
import os, signal, sys
from chunkdic.passes import stored_matrix
from chunkdic.cli.app import main

real = stored_matrix.StoredMatrix._set_record

def set_record(self, root, record):
    if record is not None and record["key"]["level"] == 0:
        stencil = self.path / "checkpoint" / "matrix_stencil"
        chunk = next(p for p in sorted(stencil.rglob("*")) if p.is_file() and p.name != "zarr.json")
        chunk.write_bytes(chunk.read_bytes()[:100])
        os.kill(os.getpid(), signal.SIGKILL)
    real(self, root, record)

stored_matrix.StoredMatrix._set_record = set_record
sys.exit(main(sys.argv[1:]))
'''


def _killed(cmd, at: str, scratch) -> list[str]:
    """Run ``cmd`` with its scratch under ``scratch``, SIGKILL it at the first stderr line
    starting with ``at`` (None: let it kill itself); the lines it printed."""
    env = dict(os.environ, DASK_CHUNKDIC__SCRATCH_DIRECTORY=str(scratch))
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, env=env)
    lines = []
    for line in proc.stderr:
        lines.append(line)
        if at is not None and line.startswith(at):
            os.kill(proc.pid, signal.SIGKILL)
            break
    assert proc.wait() == -signal.SIGKILL, "".join(lines)
    return lines


def _resume(cmd, scratch, capsys) -> list[str]:
    """The same command run again in this process (scratch under ``scratch``): its stderr lines."""
    import dask.config

    with dask.config.set({"chunkdic.scratch-directory": str(scratch)}):
        assert main(cmd[3:]) in (0, 1)
    return capsys.readouterr().err.splitlines()


def _count(lines, start: str) -> int:
    return sum(line.startswith(start) for line in lines)


@pytest.fixture(scope="module")
def uninterrupted(pair):
    """The uninterrupted run's result and its number of level-0 passes (iteration events)."""
    events = []
    res = chunkdic.correlate(pair / "f.npy", pair / "g.npy", element_size=8, tolerance=1e-5, progress=events.append)
    return res, sum(e["stage"] == "iteration" and e["level"] == 0 for e in events)


def _scratch_dirs(scratch) -> list:
    return sorted(p.name for p in scratch.iterdir())


def test_resume_reuses_m_and_the_prepared_scans(pair, uninterrupted, tmp_path, capsys):
    """Killed during a level-0 pass: the resumed run neither builds the level's M nor
    prefilters g again (counted from its own progress lines), and ends on the field of an
    uninterrupted run; the complete result holds no M and the adopted scratch is gone."""
    out, scratch = tmp_path / "res.zarr", tmp_path / "scratch"
    scratch.mkdir()
    before = _killed(_cmd(pair, out), "level 0 iter  2", scratch)
    # the killed run built both (the test can see them), and left its scratch and M behind
    assert _count(before, "level 0: M built over") == 1 and _count(before, "level 0: g prepared over") == 1
    assert len(_scratch_dirs(scratch)) == 1

    err = _resume(_cmd(pair, out), scratch, capsys)
    text = "\n".join(err)
    assert re.search(r"level 0, iteration \d+; reusing M and the prepared scans of the interrupted run", text), text
    assert _count(err, "level 0: M built over") == 0, text
    assert _count(err, "level 0: M read from the checkpoint of the interrupted run; its low-passed f blocks "
                       "reused") == 1, text
    assert _count(err, "level 0: f low-passed again") == 0, text
    assert _count(err, "level 0: g prepared over") == 0, text
    # at most one pass lost: the passes of both runs are those of an uninterrupted run, plus one at most
    reference, passes = uninterrupted
    assert passes <= _count(before, "level 0 iter") + _count(err, "level 0 iter") <= passes + 1, text

    resumed = chunkdic.open_result(out)
    np.testing.assert_allclose(resumed.displacement, reference.displacement, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(resumed.history["iteration"], reference.history["iteration"])
    # the M read back is the one the pass summed (weak nodes and uncertainty come from it)
    np.testing.assert_array_equal(resumed.flags, reference.flags)
    np.testing.assert_allclose(resumed.uncertainty, reference.uncertainty, rtol=1e-6)
    # the complete result holds no M, and the scratch went with the run
    assert not [p for p in out.rglob("*") if "matrix" in p.name]
    assert "matrix" not in zarr.open_group(str(out), mode="r").attrs["chunkdic"]
    assert _scratch_dirs(scratch) == []


def test_m_read_back_is_the_one_the_pass_summed_weak_nodes_included(pair, tmp_path, capsys):
    """A pair with an untextured corner (weak nodes, whose blocks the solver holds in place in
    the stencil): the resumed run finds the same weak nodes and uncertainty as an
    uninterrupted run, so the M it read is the pass's, not the solver's held copy."""
    d = tmp_path / "flat"
    d.mkdir()
    for name in ("f.npy", "g.npy"):
        a = np.load(pair / name)
        a[:20, :20, :20] = a.mean()
        np.save(d / name, a)
    reference = chunkdic.correlate(d / "f.npy", d / "g.npy", element_size=8, tolerance=1e-5)
    assert reference.flags is not None and (reference.flags & FLAG_WEAK).any()  # the case has weak nodes
    out, scratch = tmp_path / "res.zarr", tmp_path / "scratch"
    scratch.mkdir()
    _killed(_cmd(d, out), "level 0 iter  1", scratch)
    err = _resume(_cmd(d, out), scratch, capsys)
    assert _count(err, "level 0: M read from the checkpoint") == 1, "\n".join(err)
    resumed = chunkdic.open_result(out)
    np.testing.assert_array_equal(resumed.flags, reference.flags)
    np.testing.assert_allclose(resumed.uncertainty, reference.uncertainty, rtol=1e-6)
    np.testing.assert_allclose(resumed.displacement, reference.displacement, rtol=0, atol=1e-6)


def test_resume_without_the_scratch_reads_m_and_low_passes_f_again(pair, uninterrupted, tmp_path, capsys):
    """The interrupted run's scratch is gone (another host's disk, a cleaned /tmp): M still
    comes from the output; only f is low-passed again (no M sums) and g prepared again."""
    out, scratch = tmp_path / "res.zarr", tmp_path / "scratch"
    scratch.mkdir()
    _killed(_cmd(pair, out), "level 0 iter  1", scratch)
    for leftover in scratch.iterdir():
        shutil.rmtree(leftover)

    err = _resume(_cmd(pair, out), scratch, capsys)
    text = "\n".join(err)
    assert "reusing M (the interrupted run's prepared scans are gone: prepared again)" in text, text
    assert _count(err, "level 0: M built over") == 0, text
    assert _count(err, "level 0: M read from the checkpoint of the interrupted run (") == 1, text
    assert _count(err, "level 0: f low-passed again over") == 1, text
    assert _count(err, "level 0: g prepared over") == 1, text
    resumed = chunkdic.open_result(out)
    np.testing.assert_allclose(resumed.displacement, uninterrupted[0].displacement, rtol=0, atol=1e-6)


def test_kill_while_m_is_written_builds_it_again(pair, uninterrupted, tmp_path, capsys):
    """Killed after M's arrays were written (one chunk cut short) but before its record: the
    resumed run does not read that M, builds it again and ends on the uninterrupted field."""
    out, scratch = tmp_path / "res.zarr", tmp_path / "scratch"
    scratch.mkdir()
    cmd = _cmd(pair, out)
    _killed([sys.executable, "-c", _DIE_WRITING_M, *cmd[3:]], None, scratch)
    # killed as it kept level 0's M: the arrays are there, the record that marks them complete is not
    assert (out / "checkpoint" / "matrix_stencil").is_dir()
    assert "matrix" not in zarr.open_group(str(out), mode="r").attrs["chunkdic"]

    err = _resume(cmd, scratch, capsys)
    text = "\n".join(err)
    assert _count(err, "level 0: M built over") == 1, text
    assert "M read from the checkpoint" not in text, text
    resumed = chunkdic.open_result(out)
    np.testing.assert_allclose(resumed.displacement, uninterrupted[0].displacement, rtol=0, atol=1e-6)


def test_the_scratch_of_another_run_is_never_adopted(pair, uninterrupted, tmp_path, capsys):
    """The only dead scratch left holds stores this run could use, but its recorded run
    identity is another run's (other inputs or settings, another output): the resumed run
    does not adopt it (it prepares the scans again) and reclaims it (its owner is dead)."""
    import json

    from chunkdic.io.ownership import SCRATCH_MARKER

    out, scratch = tmp_path / "res.zarr", tmp_path / "scratch"
    scratch.mkdir()
    _killed(_cmd(pair, out), "level 0 iter  1", scratch)
    (own,) = scratch.iterdir()
    other = scratch / "chunkdic-another"
    own.rename(other)
    marker = json.loads((other / SCRATCH_MARKER).read_text())
    marker["run"] = marker["run"][::-1]  # another run's identity, everything else as it was
    (other / SCRATCH_MARKER).write_text(json.dumps(marker))

    err = _resume(_cmd(pair, out), scratch, capsys)
    text = "\n".join(err)
    assert "reusing M (the interrupted run's prepared scans are gone: prepared again)" in text, text
    assert _count(err, "level 0: g prepared over") == 1, text
    assert _scratch_dirs(scratch) == [], "the other run's scratch is reclaimed (dead owner), this run's removed"
    resumed = chunkdic.open_result(out)
    np.testing.assert_allclose(resumed.displacement, uninterrupted[0].displacement, rtol=0, atol=1e-6)


# --------------------------------------------------------------------------- a whole job killed, Ctrl-C, a kill at the end


def _killed_job(cmd, at: str, scratch) -> list[str]:
    """Run ``cmd`` in a session of its own (scratch under ``scratch``) and SIGKILL its whole
    process group at the first stderr line starting with ``at``, as the end of a batch job or
    ``kill -9 -- -PGID`` does: the client and, with ``--scheduler local:N``, its cluster's
    scheduler, nannies and workers. Returns once every process of the group is gone."""
    import time

    env = dict(os.environ, DASK_CHUNKDIC__SCRATCH_DIRECTORY=str(scratch))
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, env=env, start_new_session=True)
    lines = []
    for line in proc.stderr:
        lines.append(line)
        if line.startswith(at):
            os.killpg(proc.pid, signal.SIGKILL)
            break
    assert proc.wait() == -signal.SIGKILL, "".join(lines)
    deadline = time.time() + 60
    while time.time() < deadline:  # the workers, reparented, are reaped by init
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        raise AssertionError("processes of the killed job outlived it")
    return lines


def test_a_killed_local_cluster_job_resumes_on_its_prepared_scans(pair, uninterrupted, tmp_path):
    """Issue 21, item 5 on a LocalCluster of 2 worker processes: the whole job killed during a
    level-0 pass, another chunkdic run in the same scratch root before the restart (a test, a
    report, a second correlation: before this was kept, its start reclaimed the killed run's
    scratch, and the restart prepared both scans again), then the same command: it adopts the
    prepared scans, repeats at most the interrupted pass and ends on the uninterrupted field."""
    import dask.config

    out, scratch = tmp_path / "res.zarr", tmp_path / "scratch"
    scratch.mkdir()
    cmd = _cmd(pair, out, "--scheduler", "local:2")
    before = _killed_job(cmd, "level 0 iter  1", scratch)
    assert _count(before, "level 0: M built over") == 1 and _count(before, "level 0: g prepared over") == 1
    (left,) = _scratch_dirs(scratch)

    with dask.config.set({"chunkdic.scratch-directory": str(scratch)}):  # another run meanwhile
        other = chunkdic.correlate(pair / "f.npy", pair / "g.npy", element_size=16, tolerance=1e-2)
    assert other.info["status"] == "converged" and _scratch_dirs(scratch) == [left], "the kept scratch went"

    env = dict(os.environ, DASK_CHUNKDIC__SCRATCH_DIRECTORY=str(scratch))
    again = subprocess.run(cmd, stderr=subprocess.PIPE, text=True, env=env)
    err = again.stderr.splitlines()
    text = again.stderr
    assert again.returncode in (0, 1), text
    assert re.search(r"level 0, iteration \d+; reusing M and the prepared scans of the interrupted run", text), text
    assert _count(err, "level 0: M built over") == 0, text
    assert _count(err, "level 0: f low-passed again") == 0 and _count(err, "level 0: g prepared over") == 0, text
    reference, passes = uninterrupted
    assert passes <= _count(before, "level 0 iter") + _count(err, "level 0 iter") <= passes + 1, text
    resumed = chunkdic.open_result(out)
    np.testing.assert_allclose(resumed.displacement, reference.displacement, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(resumed.history["iteration"], reference.history["iteration"])
    assert _scratch_dirs(scratch) == []  # the scratch went with the completed run


#: runs the CLI and SIGKILLs itself when it saves the result: the finest level has converged
#: and its end is in the checkpoint ("level 0: converged" printed), the result not yet written
_DIE_SAVING_RESULT = r'''
import os, signal, sys
from chunkdic.results import result
from chunkdic.cli.app import main

def save(self, *args, **kwargs):
    os.kill(os.getpid(), signal.SIGKILL)

result.Result.save = save
sys.exit(main(sys.argv[1:]))
'''


def test_killed_after_the_finest_level_converged_runs_no_pass_and_prepares_nothing(pair, uninterrupted, tmp_path,
                                                                                      capsys):
    """Killed once level 0 converged (its end checkpointed, the result not yet saved; the level's
    prepared g and haloed f were already released): the restart only assembles the result from
    the checkpoint and the kept M. It used to prefilter g again for a level with no pass to run."""
    out, scratch = tmp_path / "res.zarr", tmp_path / "scratch"
    scratch.mkdir()
    cmd = _cmd(pair, out)
    before = _killed([sys.executable, "-c", _DIE_SAVING_RESULT, *cmd[3:]], None, scratch)
    assert _count(before, "level 0: converged") == 1, "".join(before)

    err = _resume(cmd, scratch, capsys)
    text = "\n".join(err)
    assert "resuming the interrupted run from its checkpoint: level 0" in text, text
    assert _count(err, "level 0: g prepared over") == 0, text
    assert _count(err, "level 0 iter") == 0 and _count(err, "level 0: M built over") == 0, text
    assert _count(err, "level 0: f low-passed again") == 0, text
    reference = uninterrupted[0]
    resumed = chunkdic.open_result(out)
    np.testing.assert_allclose(resumed.displacement, reference.displacement, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(resumed.flags, reference.flags)
    np.testing.assert_allclose(resumed.uncertainty, reference.uncertainty, rtol=1e-6)
    assert _scratch_dirs(scratch) == []


def test_ctrl_c_keeps_the_prepared_scans_for_the_resume(pair, uninterrupted, tmp_path, capsys):
    """Ctrl-C (SIGINT) during a level-0 pass: the run says its prepared scans are kept and where;
    the same command adopts them (it used to remove them on the way out, so a resume after
    Ctrl-C prepared both scans again) and ends on the uninterrupted field."""
    out, scratch = tmp_path / "res.zarr", tmp_path / "scratch"
    scratch.mkdir()
    cmd = _cmd(pair, out)
    env = dict(os.environ, DASK_CHUNKDIC__SCRATCH_DIRECTORY=str(scratch))
    # SIGINT as at a terminal: a suite started in the background (``pytest &``) ignores it, and
    # so would the child (an ignored signal stays ignored across exec; Python then installs no handler)
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines = []
    for line in proc.stderr:
        lines.append(line)
        if line.startswith("level 0 iter  1") and _count(lines, "level 0 iter  1") == 1:
            proc.send_signal(signal.SIGINT)  # once: the run goes on until the signal lands
    assert proc.wait() == 130, "".join(lines)
    text = "".join(lines)
    assert "chunkdic: interrupted" in text and _count(lines, "the prepared scans (") == 1, text
    (left,) = _scratch_dirs(scratch)
    assert f"in {scratch / left})" in text and f"remove {out}" in text, text

    err = _resume(cmd, scratch, capsys)
    text = "\n".join(err)
    assert re.search(r"level 0, iteration \d+; reusing M and the prepared scans of the interrupted run", text), text
    assert _count(err, "level 0: g prepared over") == 0 and _count(err, "level 0: M built over") == 0, text
    resumed = chunkdic.open_result(out)
    np.testing.assert_allclose(resumed.displacement, uninterrupted[0].displacement, rtol=0, atol=1e-6)
    assert _scratch_dirs(scratch) == []


def test_an_interrupted_call_leaves_its_scratch_only_when_it_can_resume(pair, uninterrupted, tmp_path):
    """In a notebook: a KeyboardInterrupt during a call with an output on scans on disk leaves the
    scratch, and the same call again in the same process (the interrupted call's owner is
    alive) adopts it. With in-memory scans (an identity of their own each call: never resumed)
    the scratch goes on the way out, as it did for every interrupted run before."""
    import dask.config

    def interrupt(event):
        if event["stage"] == "iteration" and event["level"] == 0:
            raise KeyboardInterrupt

    scratch = tmp_path / "scratch"
    scratch.mkdir()
    arrays = (np.load(pair / "f.npy"), np.load(pair / "g.npy"))
    with dask.config.set({"chunkdic.scratch-directory": str(scratch)}):
        with pytest.raises(KeyboardInterrupt):
            chunkdic.correlate(*arrays, element_size=8, tolerance=1e-5, output=tmp_path / "mem.zarr",
                               progress=interrupt)
        assert _scratch_dirs(scratch) == []

        paths = (pair / "f.npy", pair / "g.npy")
        events = []
        with pytest.raises(KeyboardInterrupt):
            chunkdic.correlate(*paths, element_size=8, tolerance=1e-5, output=tmp_path / "res.zarr",
                               progress=lambda e: (events.append(e), interrupt(e)))
        kept = [e for e in events if e["stage"] == "scratch-kept"]
        assert len(kept) == 1 and _scratch_dirs(scratch) == [os.path.basename(kept[0]["path"])]
        assert kept[0]["bytes"] > 0

        events.clear()
        res = chunkdic.correlate(*paths, element_size=8, tolerance=1e-5, output=tmp_path / "res.zarr",
                                 progress=events.append)
    (resume,) = [e for e in events if e["stage"] == "resume"]
    assert resume["reused"] == ["M", "scans"], resume
    assert not [e for e in events if e["stage"] == "prepared" and e["level"] == 0]
    np.testing.assert_allclose(res.displacement, uninterrupted[0].displacement, rtol=0, atol=1e-6)
    assert _scratch_dirs(scratch) == []
