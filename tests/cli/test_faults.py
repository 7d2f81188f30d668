"""Faults and races (issue 24): outputs nobody else owns, one writer per output, damaged
chunks, full disks, resume after a kill at any stage line.

Every refusal is checked as in ``test_data_safety``: exit status 2, one
``chunkdic: error:`` line and no traceback, nothing left at the output (nor a staged copy
or lock), and the inputs and foreign files byte-identical (SHA-256). Scans are 32³
(chunks 16³), elements of 8 voxels.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import meshio
import numpy as np
import pytest
import zarr
from test_data_safety import N, T, nothing_left, refused, tree

import chunkdic
from chunkdic.cli.app import main
from chunkdic.errors import InputError
from chunkdic.io import owners, scratch
from chunkdic.io.integrity import content_identity
from chunkdic.io.outputrules import check_output
from chunkdic.synth import synthetic

# kills, races and full disks on whole commands: `pytest -m 'not slow'` leaves them out
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A 32³ synthetic pair (Zarr, chunks 16³) and its result."""
    d = tmp_path_factory.mktemp("faults")
    pair = synthetic.synthesize(d / "s", (N,) * 3, field=synthetic.Translation(T), seed=4, chunks=16)
    chunkdic.correlate(pair["reference"], pair["deformed"], element_size=8, output=d / "r.zarr")
    return d


def _foreign_mesh() -> meshio.Mesh:
    pts = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=float)
    return meshio.Mesh(pts, [("hexahedron", np.array([[0, 1, 3, 2, 4, 5, 7, 6]]))])


# --------------------------------------------------------------------------- foreign files


def test_pyramid_display_never_removes_a_users_display_array(data, tmp_path, capsys):
    scan = tmp_path / "ref.zarr"
    shutil.copytree(data / "s/ref.zarr", scan)
    zarr.open_group(str(scan), mode="r+").create_array("display", data=np.arange(10))  # the user's own
    before = tree(scan)
    refused(["pyramid", scan, "--levels", "1", "--display"], capsys, "display exists and chunkdic did not write it")
    assert tree(scan) == before
    # a rebuild of the sums (which drops chunkdic's own display/) keeps the user's array too
    assert main(["pyramid", str(scan), "--levels", "1", "--overwrite"]) == 0
    assert zarr.open_array(str(scan / "display"), mode="r")[...].tolist() == list(range(10))
    assert not (tmp_path / ".ref.zarr.chunkdic-lock").exists()
    # chunkdic's own display/ is replaced as before
    own = tmp_path / "own.zarr"
    shutil.copytree(data / "s/ref.zarr", own)
    assert main(["pyramid", str(own), "--levels", "1", "--display"]) == 0
    assert main(["pyramid", str(own), "--levels", "1", "--display", "--overwrite"]) == 0
    assert zarr.open_group(str(own / "display"), mode="r").attrs["chunkdic"]["kind"] == "display"


@pytest.mark.parametrize("name", ["mine.vtu", "mine.vtk"])
def test_overwrite_never_replaces_a_vtk_another_tool_wrote(data, tmp_path, capsys, name):
    foreign = tmp_path / name
    _foreign_mesh().write(str(foreign))  # carries meshio's own signature, not chunkdic's mark
    before = tree(foreign, data / "r.zarr")
    refused(["export", data / "r.zarr", "--vtk", foreign, "--overwrite"], capsys, "chunkdic did not write")
    assert tree(foreign, data / "r.zarr") == before
    assert not [p.name for p in tmp_path.iterdir() if "chunkdic" in p.name]
    # chunkdic's own file is marked, read back by meshio, and replaced by --overwrite
    own = tmp_path / f"own{foreign.suffix}"
    assert main(["export", str(data / "r.zarr"), "--vtk", str(own)]) == 0
    assert meshio.read(str(own)).points.shape == (64, 3)  # 4³ nodes
    assert main(["export", str(data / "r.zarr"), "--vtk", str(own), "--overwrite"]) == 0
    capsys.readouterr()


def test_overwrite_needs_chunkdics_own_mark_for_tables_and_folders(data, tmp_path, capsys):
    table = tmp_path / "nodes.csv"  # chunkdic's column line, but no chunkdic sidecar: anyone's table
    table.write_text("iz,iy,ix,z,y,x,Uz,Uy,Ux,flags\n0,0,0,0,0,0,1,2,3,0\n")
    before = tree(table)
    refused(["export", data / "r.zarr", "--csv", table, "--overwrite"], capsys, "chunkdic did not write")
    assert tree(table) == before
    figures = tmp_path / "figs"  # a user's folder holding only names that `report` writes: no marker
    figures.mkdir()
    (figures / "uz_map.png").write_bytes(b"\x89PNG a user's figure")
    with pytest.raises(InputError, match="chunkdic did not write"):
        check_output(figures, "figures", overwrite=True)
    # chunkdic's own table (with its sidecar) is replaced
    own = tmp_path / "own.csv"
    assert main(["export", str(data / "r.zarr"), "--csv", str(own)]) == 0
    assert main(["export", str(data / "r.zarr"), "--csv", str(own), "--overwrite"]) == 0
    capsys.readouterr()


# --------------------------------------------------------------------------- one writer


def _hold_lock(output: Path) -> subprocess.Popen:
    """Another process that holds the one-writer lock of ``output`` (as any chunkdic writer does)."""
    code = ("import sys, time; from chunkdic.io.locks import OutputLock; "
            "OutputLock(sys.argv[1]).acquire(); print('locked', flush=True); time.sleep(120)")
    proc = subprocess.Popen([sys.executable, "-c", code, str(output)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_a_lock_its_owner_is_still_writing_is_waited_for(tmp_path):
    """A lock file exists before its owner's record is in it (created, then written): a second
    writer that finds it empty waits for the record and names the owner; on a loaded machine
    the owner may stay descheduled between the two steps for longer than a moment."""
    from chunkdic.io.locks import OutputLock

    lock = OutputLock(tmp_path / "o.zarr")
    lock.path.write_text("")
    holder = _hold_lock(tmp_path / "other.zarr")  # a live chunkdic process, the owner to be
    record = OutputLock(tmp_path / "other.zarr").path.read_text()

    def finish_writing():
        time.sleep(1.5)
        lock.path.write_text(record)

    import threading

    writer = threading.Thread(target=finish_writing)
    writer.start()
    try:
        with pytest.raises(InputError, match=rf"being written by another chunkdic run \(pid {holder.pid} "):
            OutputLock(tmp_path / "o.zarr").acquire()
    finally:
        writer.join()
        holder.kill()
        holder.wait()
    assert lock.path.read_text() == record  # the owner's lock is left as it is


@pytest.mark.parametrize("what", ["vtk", "fields", "ingest", "pyramid"])
def test_every_writer_takes_the_one_writer_lock(data, tmp_path, capsys, what):
    out = {"vtk": tmp_path / "m.vtu", "fields": tmp_path / "f.zarr", "ingest": tmp_path / "i.zarr",
           "pyramid": tmp_path / "ref.zarr"}[what]
    if what == "pyramid":
        shutil.copytree(data / "s/ref.zarr", out)
    argv = {"vtk": ["export", data / "r.zarr", "--vtk", out],
            "fields": ["export", data / "r.zarr", "--fields", out],
            "ingest": ["ingest", data / "s/ref.zarr/0", out],
            "pyramid": ["pyramid", out, "--levels", "2"]}[what]
    before = tree(data / "s", data / "r.zarr", *([out] if out.exists() else []))
    holder = _hold_lock(out)
    try:
        refused(argv, capsys, rf"being written by another chunkdic run \(pid {holder.pid} ")
    finally:
        holder.kill()
        holder.wait()
    assert tree(data / "s", data / "r.zarr", *([out] if what == "pyramid" else [])) == before
    if what != "pyramid":
        (tmp_path / f".{out.name}.chunkdic-lock").unlink()  # the holder was killed: its lock stays...
        nothing_left(out)
    # ...and is stale now: the next run takes it over and writes
    assert main([str(a) for a in argv]) == 0
    assert not (tmp_path / f".{out.name}.chunkdic-lock").exists()
    capsys.readouterr()


@pytest.mark.parametrize("what", ["vtk", "csv", "fields"])
def test_an_output_that_appears_while_a_run_writes_is_never_replaced(data, tmp_path, capsys, monkeypatch, what):
    """The other writer published first: the later run refuses to publish over it (no --overwrite)."""
    from chunkdic.io import outputs

    out = tmp_path / {"vtk": "m.vtu", "csv": "n.csv", "fields": "f.zarr"}[what]
    other = tmp_path / "other"
    other.mkdir()
    assert main(["export", str(data / "r.zarr"), f"--{what}", str(other / out.name)]) == 0
    published = tree(other)
    real_begin = outputs.Outputs._begin

    def begin_then_the_other_run_publishes(self, e):
        real_begin(self, e)
        if e.final == out:  # this run has checked and begun writing: the other one publishes now
            for f in list(other.iterdir()):
                os.rename(f, tmp_path / f.name)

    monkeypatch.setattr(outputs.Outputs, "_begin", begin_then_the_other_run_publishes)
    capsys.readouterr()
    refused(["export", data / "r.zarr", f"--{what}", out], capsys, "appeared while this run was (starting|writing it)",
            only_line=False)
    assert not [p.name for p in tmp_path.iterdir() if "chunkdic-" in p.name]
    for f in list(tmp_path.iterdir()):
        if f != other:
            os.rename(f, other / f.name)
    assert tree(other) == published  # the other run's output, intact


def test_two_ingests_racing_for_one_new_path(data, tmp_path):
    """Two real processes: exactly one publishes, the other is refused in one line; the result is whole."""
    out = tmp_path / "scan.zarr"
    before = tree(data / "s")
    procs = [subprocess.Popen([sys.executable, "-m", "chunkdic", "ingest", str(data / "s" / src / "0"), str(out)],
                              stderr=subprocess.PIPE, text=True) for src in ("ref.zarr", "def.zarr")]
    results = [(p.wait(), p.stderr.read()) for p in procs]
    codes = sorted(code for code, _ in results)
    assert codes == [0, 2], results
    err = next(e for code, e in results if code == 2)
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("chunkdic: error:"), err
    assert chunkdic.open_scan(out).shape(0) == (N,) * 3
    assert tree(data / "s") == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan.zarr"]


# --------------------------------------------------------------------------- damaged inputs, full disks


def test_empty_chunk_file_is_named_and_refused(data, tmp_path, capsys):
    scan = tmp_path / "ref.zarr"
    shutil.copytree(data / "s/ref.zarr", scan)
    (scan / "0/c/1/0/1").write_bytes(b"")
    before = tree(scan)
    refused(["pyramid", scan, "--levels", "1"], capsys, r"chunk file c/1/0/1 is empty \(0 bytes\)")
    assert tree(scan) == before
    refused(["correlate", scan, data / "s/def.zarr", "-o", tmp_path / "o.zarr", "-l", "8"], capsys,
            "is empty")
    nothing_left(tmp_path / "o.zarr")


def test_content_identity_reads_every_chunk_key_layout(tmp_path):
    """A v2 array or a v3 array with '.'-separated keys rewritten with other data: another identity."""
    a = np.random.default_rng(0).random((32, 32, 32)).astype(np.float32)
    for name, kw in (("v2.zarr", {"zarr_format": 2}),
                     ("dot.zarr", {"chunk_key_encoding": {"name": "default", "separator": "."}})):
        z = zarr.create_array(str(tmp_path / name), shape=a.shape, chunks=(16, 16, 16), dtype="float32", **kw)
        z[...] = a
        before = content_identity("zarr", str(tmp_path / name))
        assert content_identity("zarr", str(tmp_path / name)) == before
        z[...] = np.roll(a, 3, axis=0)
        assert content_identity("zarr", str(tmp_path / name)) != before, name


def test_scratch_on_a_full_disk_leaves_nothing(tmp_path, monkeypatch):
    import dask.config

    def full(*_):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(owners.Owner, "me", classmethod(full))
    with dask.config.set({"chunkdic.scratch-directory": str(tmp_path)}):
        with pytest.raises(InputError, match="No space left on device"):
            scratch.make_scratch()
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- kills and resume

#: the issue's command on a 32³ pair with two levels: rigid step, M, passes, the automatic
#: regularisation length, the level ends
_RESUME_ARGS = ["-l", "6", "--tolerance", "1e-4", "--block-elements", "2", "--coarsest", "1"]
_STAGES = ["level 1 rigid  0", "level 1: converged", "level 0 iter  0", "regularisation length",
           "level 0: converged"]


@pytest.fixture(scope="module")
def uninterrupted(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("uninterrupted") / "full.zarr"
    assert main(["correlate", str(data / "s/ref.zarr"), str(data / "s/def.zarr"), "-o", str(out),
                 *_RESUME_ARGS]) == 0
    return chunkdic.open_result(out)


@pytest.mark.parametrize("stage", _STAGES)
def test_kill_at_a_stage_line_resumes_to_the_uninterrupted_field(data, uninterrupted, tmp_path, capsys, stage):
    out = tmp_path / "out.zarr"
    argv = ["correlate", str(data / "s/ref.zarr"), str(data / "s/def.zarr"), "-o", str(out), *_RESUME_ARGS]
    before = tree(data / "s")
    proc = subprocess.Popen([sys.executable, "-m", "chunkdic", *argv], stderr=subprocess.PIPE, text=True)
    for line in proc.stderr:
        if stage in line:
            os.kill(proc.pid, signal.SIGKILL)
            break
    assert proc.wait() == -signal.SIGKILL, f"the run ended before {stage!r}"
    capsys.readouterr()
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    res = chunkdic.open_result(out)
    np.testing.assert_allclose(res.displacement, uninterrupted.displacement, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(res.flags, uninterrupted.flags)
    np.testing.assert_allclose(res.uncertainty, uninterrupted.uncertainty, rtol=1e-6, atol=1e-9)
    assert res.info["regularization"] == uninterrupted.info["regularization"]
    assert res.info["level_status"] == uninterrupted.info["level_status"]
    assert tree(data / "s") == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.zarr"]  # the dead run's lock reclaimed


def test_the_same_command_on_its_own_complete_result_has_nothing_to_do(data, uninterrupted, tmp_path, capsys):
    out = tmp_path / "full.zarr"
    shutil.copytree(uninterrupted.path, out, copy_function=shutil.copy2)
    argv = ["correlate", str(data / "s/ref.zarr"), str(data / "s/def.zarr"), "-o", str(out), *_RESUME_ARGS]
    # the copy's fingerprint names the first output's inputs, which are these: it is this run's result
    before = tree(out)
    assert main(argv) == 0
    assert "is already complete (the same inputs and settings): nothing to do" in capsys.readouterr().err
    assert tree(out) == before
    # other settings on a complete result: refused, untouched
    refused([*argv[:-1], "3"], capsys, "is a complete result")
    assert tree(out) == before


def test_a_garbled_checkpoint_is_refused_in_one_line(data, tmp_path, capsys):
    out = tmp_path / "out.zarr"
    argv = ["correlate", str(data / "s/ref.zarr"), str(data / "s/def.zarr"), "-o", str(out), *_RESUME_ARGS]
    proc = subprocess.Popen([sys.executable, "-m", "chunkdic", *argv], stderr=subprocess.PIPE, text=True)
    for line in proc.stderr:
        if "level 0 iter  0" in line:
            os.kill(proc.pid, signal.SIGKILL)
            break
    proc.wait()
    rng = np.random.default_rng(1)
    for f in (out / "checkpoint").rglob("*"):  # every chunk of every checkpoint array: noise
        if f.is_file() and f.name != "zarr.json":
            f.write_bytes(rng.bytes(f.stat().st_size))
    before = tree(out)
    refused(argv, capsys, "holds a checkpoint that cannot be read .*pass --overwrite to start again")
    assert tree(out) == before
    assert main([*argv, "--overwrite"]) == 0
    capsys.readouterr()


def test_partials_of_dead_runs_are_reclaimed_by_the_next_writer_in_the_directory(data, tmp_path, capsys):
    import socket

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # a pid that no process holds any more (a run killed with SIGKILL)
    host = socket.gethostname().replace("-", "_").replace(".", "_")
    left = [tmp_path / f".f.chunkdic-partial-{host}-{dead.pid}-0a1b2c.zarr",  # export --fields
            tmp_path / f".c.chunkdic-partial-{host}-{dead.pid}-3d4e5f.zarr"]  # export --corrected
    for p in left:
        (p / "0").mkdir(parents=True)
        (p / "0" / "zarr.json").write_text("{}")
    live = tmp_path / f".g.chunkdic-partial-{host}-{os.getpid()}-abcdef.zarr"  # a live run's: never touched
    live.mkdir()
    user = tmp_path / ".f.chunkdic-partial-notes.txt"  # not chunkdic's name pattern: never touched
    user.write_text("a user's file")
    assert main(["export", str(data / "r.zarr"), "--vtk", str(tmp_path / "m.vtu")]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([live.name, user.name, "m.vtu"])


def test_series_killed_after_a_steps_regularisation_line_resumes(data, tmp_path, capsys):
    scans = [str(data / "s/ref.zarr"), str(data / "s/def.zarr"), str(data / "s/def.zarr")]
    opts = ["-l", "6", "--tolerance", "1e-4", "--block-elements", "2"]
    full = tmp_path / "full.zarr"
    assert main(["series", *scans, "-o", str(full), *opts]) == 0
    out = tmp_path / "ser.zarr"
    proc = subprocess.Popen([sys.executable, "-m", "chunkdic", "series", *scans, "-o", str(out), *opts],
                            stderr=subprocess.PIPE, text=True)
    for line in proc.stderr:
        if "regularisation length" in line:
            os.kill(proc.pid, signal.SIGKILL)
            break
    assert proc.wait() == -signal.SIGKILL
    capsys.readouterr()
    assert main(["series", *scans, "-o", str(out), *opts]) == 0
    assert "Traceback" not in capsys.readouterr().err
    a, b = chunkdic.open_series(out), chunkdic.open_series(full)
    assert sorted(a.cumulative) == sorted(b.cumulative)
    for k in a.cumulative:
        np.testing.assert_allclose(a.cumulative[k].displacement, b.cumulative[k].displacement, rtol=0, atol=1e-6)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["full.zarr", "ser.zarr"]
    assert not [p for p in out.rglob("*") if "chunkdic-" in p.name]  # no lock or partial inside the series


# --------------------------------------------------------------------------- one line, never a hang


@pytest.mark.parametrize("overwrite", [False, True])
def test_output_naming_a_fifo_is_refused_without_opening_it(data, tmp_path, capsys, overwrite):
    fifo = tmp_path / "o.zarr"
    os.mkfifo(fifo)  # opening it for reading would wait for a writer for ever
    argv = ["correlate", data / "s/ref.zarr", data / "s/def.zarr", "-l", "8", "-o", fifo]
    t0 = time.perf_counter()
    refused([*argv, *(["--overwrite"] if overwrite else [])], capsys, "exists|chunkdic did not write")
    vtu = tmp_path / "o.vtu"
    os.mkfifo(vtu)
    refused(["export", data / "r.zarr", "--vtk", vtu, *(["--overwrite"] if overwrite else [])], capsys)
    assert time.perf_counter() - t0 < 30
    assert fifo.is_fifo() and vtu.is_fifo()


@pytest.mark.parametrize("option", [["-l", "1e999um"], ["-l", "1e999"], ["-l=-160um"], ["-l", "0um"],
                                    ["-l", "8", "--roi", "0:nan,0:32,0:32", "--roi-unit", "um"],
                                    ["-l", "8", "--roi", "0:1e999,0:32,0:32", "--roi-unit", "um"]])
def test_non_finite_lengths_are_one_line(data, tmp_path, capsys, option):
    ref = tmp_path / "ref.zarr"
    shutil.copytree(data / "s/ref.zarr", ref)
    assert main(["ingest", str(ref / "0"), str(tmp_path / "vs.zarr"), "--voxel-size", "2", "--unit", "um"]) == 0
    capsys.readouterr()  # a scan with a voxel size (2 um), so that lengths may carry units
    before = tree(tmp_path / "vs.zarr", data / "s")
    for cmd in (["correlate", tmp_path / "vs.zarr", data / "s/def.zarr"], ["series", tmp_path / "vs.zarr",
                                                                            data / "s/def.zarr"]):
        refused([*cmd, *option, "-o", tmp_path / "o.zarr"], capsys, "positive finite|finite number")
        nothing_left(tmp_path / "o.zarr")
    assert tree(tmp_path / "vs.zarr", data / "s") == before


def test_a_result_whose_element_size_is_zero_is_refused_in_one_line(data, tmp_path, capsys):
    res = tmp_path / "r.zarr"
    shutil.copytree(data / "r.zarr", res)
    meta = json.loads((res / "zarr.json").read_text())
    meta["attributes"]["chunkdic"]["element_size"] = 0
    (res / "zarr.json").write_text(json.dumps(meta))
    before = tree(res, data / "s")
    refused(["strain", res], capsys, "do not describe a mesh: a damaged result")
    refused(["correlate", data / "s/ref.zarr", data / "s/def.zarr", "-l", "8", "--init", res, "-o",
             tmp_path / "o.zarr"], capsys, "do not describe a mesh")
    nothing_left(tmp_path / "o.zarr")
    assert tree(res, data / "s") == before


def test_two_level_scans_are_refused_in_one_line(tmp_path, capsys):
    """A bool scan has no sub-voxel information (a 0.28-voxel error was once called converged):
    refused by correlate and correlate2d, one line, exit 2, nothing written; a bool mask stays fine."""
    rng = np.random.default_rng(0)
    b = rng.random((32, 32, 32)) > 0.5
    np.save(tmp_path / "b.npy", b)
    np.save(tmp_path / "g.npy", np.roll(b, 1, axis=0))
    out = tmp_path / "o.zarr"
    assert main(["correlate", str(tmp_path / "b.npy"), str(tmp_path / "g.npy"), "-l", "8", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "two-level (bool)" in err[0] and "Traceback" not in err[0]
    assert not out.exists()
    np.save(tmp_path / "b2.npy", b[16])
    assert main(["correlate2d", str(tmp_path / "b2.npy"), str(tmp_path / "b2.npy"), "-l", "8"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "two-level (bool)" in err[0]


def test_correlate2d_refuses_a_coarsest_level_the_image_cannot_hold(tmp_path, capsys):
    """--coarsest 99 was silently clamped by the 2-D check; the 3-D engine refuses it, so does 2-D."""
    f = np.random.default_rng(1).random((64, 64)).astype(np.float32)
    np.save(tmp_path / "f.npy", f)
    assert main(["correlate2d", str(tmp_path / "f.npy"), str(tmp_path / "f.npy"), "-l", "8", "--coarsest", "99"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "coarsest level 99 is too coarse" in err[0]
