"""Data safety and honest failure (issue 14): one test per defect class.

Every refusal is checked the same way: exit status 2, one ``chunkdic: error:`` line on
stderr (the only line when the refusal comes before any work) and no traceback, nothing
left at the output (nor a staged copy or a lock next to it), and every input's bytes
unchanged (SHA-256 of every file under the input paths). Scans are 32³ (chunks 16³),
elements of 8 voxels, the threaded scheduler.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import dask.config
import numpy as np
import pytest
import tifffile
import zarr

import chunkdic
from chunkdic.cli.app import main
from chunkdic.io.integrity import MissingChunksWarning
from chunkdic.synth import foam, synthetic

# end-to-end runs (whole commands, clusters, kills): `pytest -m 'not slow'` leaves them out
pytestmark = pytest.mark.slow

N = 32
T = (0.6, -0.4, 0.3)


# --------------------------------------------------------------------------- helpers


def tree(*paths) -> dict:
    """SHA-256 of every file under ``paths`` (and the names of the directories)."""
    out = {}
    for p in map(Path, paths):
        items = [p] if p.is_file() else [p, *sorted(p.rglob("*"))]
        for f in items:
            out[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest() if f.is_file() else "dir"
    return out


def refused(argv, capsys, match: str | None = None, *, only_line: bool = True) -> str:
    """Run the CLI in this process; assert the promise; return the error line."""
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    errors = [ln for ln in err.splitlines() if ln.startswith("chunkdic: error:")]
    assert code == 2, err
    assert "Traceback" not in err, err
    assert len(errors) == 1 and err.strip().splitlines()[-1] == errors[0], err
    if only_line:
        assert len(err.strip().splitlines()) == 1, err
    if match is not None:
        assert re.search(match, errors[0]), errors[0]
    return errors[0]


def nothing_left(out) -> None:
    """Nothing at ``out``, and no staged copy or lock of it in its directory."""
    out = Path(out)
    assert not out.exists() and not out.is_symlink(), sorted(os.listdir(out)) if out.is_dir() else out
    if out.parent.is_dir():
        stray = [p.name for p in out.parent.iterdir()
                 if p.name.startswith(f".{out.stem}.chunkdic-") or p.name == f".{out.name}.chunkdic-lock"]
        assert not stray, stray


def corrupt_chunk(array_dir: Path, key: str = "c/0/0/0") -> None:
    """Overwrite one chunk file with bytes no codec decodes (same size)."""
    f = Path(array_dir) / key
    f.write_bytes(b"\xde\xad\xbe\xef" * (f.stat().st_size // 4 + 1))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A 32³ synthetic pair (Zarr, chunks 16³), its result, a float copy and a node table."""
    d = tmp_path_factory.mktemp("safety")
    pair = synthetic.synthesize(d / "s", (N,) * 3, field=synthetic.Translation(T), seed=4, chunks=16)
    res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=8, output=d / "r.zarr")
    assert res.converged and np.abs(res.displacement - np.array(T)[:, None, None, None]).max() < 0.1
    np.save(d / "f.npy", foam.render((N,) * 3, seed=4).astype(np.float32))
    np.save(d / "g.npy", foam.render((N,) * 3, seed=4, field=synthetic.Translation(T),
                                     which="deformed").astype(np.float32))
    (d / "notes.txt").write_text("a user's notes\n")
    return d


@pytest.fixture()
def pair(data, tmp_path):
    """A private copy of the pair and its result (for tests that damage them)."""
    shutil.copytree(data / "s", tmp_path / "s")
    shutil.copytree(data / "r.zarr", tmp_path / "r.zarr")
    res = zarr.open_group(str(tmp_path / "r.zarr"), mode="r+")
    info = dict(res.attrs["chunkdic"])
    info["inputs"] = {"reference": str(tmp_path / "s/ref.zarr"), "deformed": str(tmp_path / "s/def.zarr")}
    res.attrs["chunkdic"] = info
    return tmp_path


def correlate_args(ref, dfm, out, *extra):
    return ["correlate", ref, dfm, "-o", out, "-l", "8", *extra]


#: the kill/interrupt tests need a run that passes "level 0 iter  1": with the automatic
#: length this pair's translation takes 256 voxels and converges in the first pass after
#: the choice (max|da| 4e-7), so they fix a short length (3 passes after it, 16 voxels)
ITERATING = ("--tolerance", "1e-6", "--regularization-length", "16")


# --------------------------------------------------------------------------- A: data loss


def test_A1_overwrite_never_deletes_a_folder_holding_the_inputs(data, capsys, monkeypatch):
    s = data / "s"
    before = tree(data)
    refused(correlate_args(s / "ref.zarr", s / "def.zarr", s, "--overwrite"), capsys, "contains the input")
    monkeypatch.chdir(s)
    refused(correlate_args("ref.zarr", "def.zarr", ".", "--overwrite"), capsys, "current directory")
    refused(correlate_args("ref.zarr", "def.zarr", "..", "--overwrite"), capsys, "current directory")
    assert tree(data) == before


def test_A2_overwrite_never_replaces_a_level_of_an_input(data, capsys):
    s = data / "s"
    before = tree(s)
    for out in (s / "def.zarr" / "0", s / "def.zarr" / "5"):
        refused(correlate_args(s / "ref.zarr", s / "def.zarr", out, "--overwrite"), capsys, "inside the input")
    refused(correlate_args(s / "ref.zarr", s / "def.zarr/0", s / "def.zarr/1", "--overwrite"), capsys,
            "inside the input")
    assert tree(s) == before


def test_A3_export_never_writes_onto_its_own_inputs(data, capsys):
    before = tree(data / "s", data / "r.zarr")
    refused(["export", data / "r.zarr", "--corrected", data / "s/ref.zarr", "--overwrite"], capsys, "is the input")
    refused(["export", data / "r.zarr", "--corrected", data / "r.zarr", "--overwrite"], capsys, "is the input")
    refused(["export", data / "r.zarr", "--csv", data / "r.zarr/zarr.json", "--overwrite"], capsys,
            "inside the input")
    assert tree(data / "s", data / "r.zarr") == before


def test_A4_overwrite_replaces_only_what_chunkdic_wrote(data, tmp_path, capsys):
    user = tmp_path / "d"
    user.mkdir()
    (user / "notes.txt").write_text("keep\n")
    (tmp_path / "file.txt").write_text("keep too\n")
    before = tree(tmp_path, data / "s")
    s = data / "s"
    refused(correlate_args(s / "ref.zarr", s / "def.zarr", user, "--overwrite"), capsys, "chunkdic did not write")
    refused(correlate_args(s / "ref.zarr", s / "def.zarr", tmp_path / "file.txt", "--overwrite"), capsys,
            "chunkdic did not write")
    refused(["export", data / "r.zarr", "--csv", tmp_path / "file.txt", "--overwrite"], capsys,
            "chunkdic did not write")
    refused(["export", data / "r.zarr", "--corrected", user, "--overwrite"], capsys, "chunkdic did not write")
    # a scan that chunkdic wrote is still not a result: kinds must match
    shutil.copytree(s / "ref.zarr", tmp_path / "scan.zarr")
    before = tree(tmp_path, data / "s")
    refused(correlate_args(s / "ref.zarr", s / "def.zarr", tmp_path / "scan.zarr", "--overwrite"), capsys,
            "holds a chunkdic scan, not a result")
    assert tree(tmp_path, data / "s") == before


# --------------------------------------------------------------------------- E: outputs in inputs, existing files


@pytest.mark.parametrize("argv", [
    ["correlate", "s/ref.zarr", "s/def.zarr", "-o", "s/ref.zarr/out.zarr", "-l", "8"],
    ["uncertainty", "s/ref.zarr", "-l", "8", "-o", "s/ref.zarr/unc"],
    ["sweep", "s/ref.zarr", "s/def.zarr", "-l", "8", "--no-a-priori", "-o", "s/def.zarr/sweep"],
    ["table", "r.zarr", "-o", "r.zarr/table"],
    ["report", "r.zarr", "-o", "r.zarr/figures"],
    ["export", "r.zarr", "--vtk", "r.zarr/mesh.vtu"],
    ["export", "r.zarr", "--corrected", "s/def.zarr/corrected.zarr"],
    ["ingest", "s/ref.zarr", "s/ref.zarr/copy.zarr"],
])
def test_E1_no_output_inside_an_input(data, capsys, monkeypatch, argv):
    monkeypatch.chdir(data)
    before = tree(data / "s", data / "r.zarr")
    out = argv[argv.index("-o") + 1] if "-o" in argv else argv[-1]
    refused(argv, capsys, "inside the input")
    assert tree(data / "s", data / "r.zarr") == before
    nothing_left(data / out)


def test_E2_report_and_table_refuse_existing_outputs_without_overwrite(data, tmp_path, capsys):
    fig, tab = tmp_path / "fig", tmp_path / "tab"
    assert main(["report", str(data / "r.zarr"), "-o", str(fig)]) == 0
    assert main(["table", str(data / "r.zarr"), "-o", str(tab)]) == 0
    capsys.readouterr()
    (fig / "notes.txt").write_text("mine\n")
    before = tree(fig, tab)
    # the same command again: its own complete output, nothing to do; another option or input: refused
    assert main(["report", str(data / "r.zarr"), "-o", str(fig)]) == 0
    assert main(["table", str(data / "r.zarr"), "-o", str(tab)]) == 0
    assert capsys.readouterr().err.count("nothing to do") == 2
    refused(["report", data / "r.zarr", "-o", fig, "--dpi", "50"], capsys, "pass --overwrite")
    shutil.copytree(data / "r.zarr", tmp_path / "r2.zarr")
    refused(["table", tmp_path / "r2.zarr", "-o", tab], capsys, "pass --overwrite")
    assert tree(fig, tab) == before
    # --overwrite replaces what the earlier run wrote and nothing else
    (fig / "gap.png").unlink()
    assert main(["report", str(data / "r.zarr"), "-o", str(fig), "--overwrite"]) == 0
    assert (fig / "notes.txt").read_text() == "mine\n" and (fig / "gap.png").is_file()
    assert main(["table", str(data / "r.zarr"), "-o", str(tab), "--overwrite"]) == 0


def test_E3_two_outputs_on_one_path_are_refused(data, tmp_path, capsys):
    x = tmp_path / "x.vtu"
    refused(["export", data / "r.zarr", "--vtk", x, "--csv", x], capsys, "given for two outputs")
    nothing_left(x)
    refused(["export", data / "r.zarr", "--vtk", tmp_path / "c.zarr/m.vtu", "--corrected", tmp_path / "c.zarr"],
            capsys, "overlap|does not exist")
    nothing_left(tmp_path / "c.zarr")


# --------------------------------------------------------------------------- B: concurrency and resume


def _cli_process(*argv, env=None):
    return subprocess.Popen([sys.executable, "-m", "chunkdic", *map(str, argv)], stderr=subprocess.PIPE,
                            text=True, env={**os.environ, **(env or {})})


def _wait_for(proc, prefix: str) -> None:
    for line in proc.stderr:
        if line.startswith(prefix):
            return
    raise AssertionError(f"the run ended before printing {prefix!r} (exit {proc.wait()})")


def test_B1_one_writer_per_output(data, tmp_path, capsys):
    out = tmp_path / "r.zarr"
    argv = correlate_args(data / "f.npy", data / "g.npy", out, *ITERATING)
    first = _cli_process(*argv)
    try:
        _wait_for(first, "level 0 iter  1")
        os.kill(first.pid, signal.SIGSTOP)  # the first run holds the output: paused, alive
        refused(argv, capsys, rf"being written by another chunkdic run \(pid {first.pid} ")
        refused([*argv, "--overwrite"], capsys, "being written by another chunkdic run")
        os.kill(first.pid, signal.SIGCONT)
        first.stderr.read()
        assert first.wait() in (0, 1)  # converged, or stalled at this tight tolerance
    finally:
        first.kill()
    res = chunkdic.open_result(out)  # the first run's result, complete and right
    assert np.abs(res.displacement - np.array(T)[:, None, None, None]).max() < 0.1
    assert not (tmp_path / ".r.zarr.chunkdic-lock").exists()


def test_B1_lock_and_scratch_of_a_killed_run_are_reclaimed(data, tmp_path, capsys):
    out, scratch = tmp_path / "r.zarr", tmp_path / "scratch"
    scratch.mkdir()
    (scratch / "chunkdic-not-ours").mkdir()  # no owner record: never touched
    argv = correlate_args(data / "f.npy", data / "g.npy", out, *ITERATING)
    first = _cli_process(*argv, env={"DASK_CHUNKDIC__SCRATCH_DIRECTORY": str(scratch)})
    _wait_for(first, "level 0 iter  1")
    os.kill(first.pid, signal.SIGKILL)
    first.wait()
    lock = tmp_path / ".r.zarr.chunkdic-lock"
    assert json.loads(lock.read_text())["pid"] == first.pid
    left = [p for p in scratch.iterdir() if (p / ".chunkdic-scratch.json").exists()]
    assert left and sum(f.stat().st_size for p in left for f in p.rglob("*") if f.is_file()) > 0
    with dask.config.set({"chunkdic.scratch-directory": str(scratch)}):
        assert main([str(a) for a in argv]) in (0, 1)
    assert "resuming the interrupted run" in capsys.readouterr().err
    assert not lock.exists()
    assert sorted(p.name for p in scratch.iterdir()) == ["chunkdic-not-ours"]
    chunkdic.open_result(out)


def _interrupt_at(monkeypatch, iteration: int):
    """Make the CLI's progress printer raise KeyboardInterrupt at a level-0 iteration."""
    from chunkdic.cli import app as cli

    real = cli.print_progress

    def printer(event):
        real(event)
        if event.get("stage") == "iteration" and event.get("level") == 0 and event["iteration"] == iteration:
            raise KeyboardInterrupt

    monkeypatch.setattr(cli, "print_progress", printer)


def test_B2_resume_refuses_a_changed_input(data, tmp_path, capsys, monkeypatch):
    shutil.copytree(data / "s", tmp_path / "s", copy_function=shutil.copy2)
    other = tmp_path / "other"
    synthetic.synthesize(other, (N,) * 3, field=synthetic.Translation(T), seed=5, chunks=16)
    s, out = tmp_path / "s", tmp_path / "r.zarr"
    argv = correlate_args(s / "ref.zarr", s / "def.zarr", out, *ITERATING)
    with monkeypatch.context() as m:
        _interrupt_at(m, 1)
        assert main([str(a) for a in argv]) == 130  # interrupted: checkpoint kept, marked incomplete
    capsys.readouterr()
    with pytest.raises(chunkdic.InputError, match="incomplete"):
        chunkdic.open_result(out)
    shutil.move(s / "def.zarr", tmp_path / "def-original.zarr")
    shutil.copytree(other / "def.zarr", s / "def.zarr")  # same shape and dtype, other content
    checkpoint = tree(out)
    refused(argv, capsys, r"other inputs or settings \(the deformed scan changed since\)")
    assert tree(out) == checkpoint
    shutil.rmtree(s / "def.zarr")
    shutil.move(tmp_path / "def-original.zarr", s / "def.zarr")  # the same bytes and times again
    assert main([str(a) for a in argv]) in (0, 1)
    assert "resuming the interrupted run" in capsys.readouterr().err


# --------------------------------------------------------------------------- D: hangs


@pytest.mark.parametrize("spec", ["local:0", "local:-1", "local:x", "nonsense"])
def test_D1_local_cluster_needs_workers(data, tmp_path, capsys, spec):
    s = data / "s"
    refused(correlate_args(s / "ref.zarr", s / "def.zarr", tmp_path / "o.zarr", "--scheduler", spec), capsys,
            "scheduler")
    nothing_left(tmp_path / "o.zarr")


def test_D1_cluster_without_workers_is_refused_after_a_bounded_wait(data, tmp_path, capsys):
    from distributed import LocalCluster

    s = data / "s"
    with LocalCluster(n_workers=0, processes=False, host="127.0.0.1", protocol="tcp://",
                      dashboard_address=":0") as cluster, dask.config.set({"chunkdic.worker-timeout": 1}):
        refused(correlate_args(s / "ref.zarr", s / "def.zarr", tmp_path / "o.zarr", "--scheduler",
                               cluster.scheduler_address), capsys, r"has no workers \(waited 1 s", only_line=False)
    nothing_left(tmp_path / "o.zarr")


@pytest.fixture()
def foreign_servers():
    """An HTTP server (waits for a request), a banner server (speaks first), a closed port."""
    import http.server

    http_srv = http.server.HTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    threading.Thread(target=http_srv.serve_forever, daemon=True).start()
    banner = socket.socket()
    banner.bind(("127.0.0.1", 0))
    banner.listen()

    def speak():
        while True:
            try:
                conn, _ = banner.accept()
            except OSError:
                return
            conn.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")  # read as a frame length: 3.5 EiB
            conn.close()

    threading.Thread(target=speak, daemon=True).start()
    closed = socket.socket()
    closed.bind(("127.0.0.1", 0))
    dead = closed.getsockname()[1]
    closed.close()
    yield {"http": http_srv.server_port, "banner": banner.getsockname()[1], "dead": dead}
    http_srv.shutdown()
    banner.close()


@pytest.mark.parametrize("server, message", [("http", "no Dask handshake within 1 s"),
                                             ("banner", "is not a Dask scheduler"),
                                             ("dead", "cannot reach scheduler")])
def test_D2_foreign_or_dead_address_fails_fast(data, tmp_path, capsys, foreign_servers, server, message):
    import time

    s = data / "s"
    address = f"tcp://127.0.0.1:{foreign_servers[server]}"
    t0 = time.perf_counter()
    with dask.config.set({"chunkdic.connect-timeout": 1}):
        for argv in (correlate_args(s / "ref.zarr", s / "def.zarr", tmp_path / "o.zarr", "--scheduler", address),
                     ["ingest", s / "ref.zarr", tmp_path / "o.zarr", "--scheduler", address],
                     ["synth", tmp_path / "o.zarr", "--shape", "16", "--scheduler", address]):
            refused(argv, capsys, message)
            nothing_left(tmp_path / "o.zarr")
    assert time.perf_counter() - t0 < 20


# --------------------------------------------------------------------------- F: one line, not a traceback


def test_F1_non_finite_voxels(data, tmp_path, capsys):
    f = np.load(data / "f.npy")
    f[20, 5, 7] = np.nan
    np.save(tmp_path / "nan.npy", f)
    before = tree(tmp_path / "nan.npy")
    refused(["uncertainty", tmp_path / "nan.npy", "-l", "8", "-o", tmp_path / "unc"], capsys,
            r"nan value at voxel \(z, y, x\) = \(20, 5, 7\)", only_line=False)
    nothing_left(tmp_path / "unc")
    assert tree(tmp_path / "nan.npy") == before


@pytest.mark.parametrize("cmd", ["correlate", "sweep"])
def test_F1_non_finite_voxels_in_correlate_and_sweep(data, tmp_path, capsys, cmd):
    g = np.load(data / "g.npy")
    g[16, 16, 16] = np.inf
    np.save(tmp_path / "inf.npy", g)
    if cmd == "correlate":
        argv = correlate_args(data / "f.npy", tmp_path / "inf.npy", tmp_path / "o")
    else:
        argv = ["sweep", data / "f.npy", tmp_path / "inf.npy", "-l", "8", "--no-a-priori", "-o", tmp_path / "o"]
    # the check inside the passes is the engine's (its own wording)
    refused(argv, capsys, r"NaN or Inf voxels \(the first at voxel \(16, 16, 16\)", only_line=False)
    nothing_left(tmp_path / "o")


def test_F1_strain_of_a_result_with_non_finite_nodes(pair, capsys):
    u = zarr.open_array(str(pair / "r.zarr/displacement"), mode="r+")
    u[0, 1, 1, 1] = np.nan
    refused(["strain", pair / "r.zarr"], capsys, r"no finite displacement \(first: node \(1, 1, 1\)\)")
    refused(["table", pair / "r.zarr"], capsys, "no finite displacement")


def test_F2_damaged_chunk_is_named(pair, tmp_path, capsys):
    s = pair / "s"
    corrupt_chunk(s / "ref.zarr/0")
    before = tree(s)
    chunk = r"ref.zarr/0: chunk \(0, 0, 0\) \(file .*ref.zarr/0/c/0/0/0\) cannot be read"
    refused(correlate_args(s / "ref.zarr", s / "def.zarr", tmp_path / "o.zarr"), capsys, chunk, only_line=False)
    nothing_left(tmp_path / "o.zarr")
    refused(["ingest", s / "ref.zarr", tmp_path / "i.zarr"], capsys, chunk, only_line=False)
    nothing_left(tmp_path / "i.zarr")
    refused(["pyramid", s / "ref.zarr", "--levels", "1"], capsys, chunk, only_line=False)
    assert tree(s) == before  # the level this run began is removed again
    corrupt_chunk(pair / "r.zarr/displacement", "c/0/0/0/0")
    for argv in (["strain", pair / "r.zarr"], ["table", pair / "r.zarr"]):
        refused(argv, capsys, "cannot be read.*damaged result")
    refused(["report", pair / "r.zarr", "-o", tmp_path / "fig"], capsys, "damaged result")
    nothing_left(tmp_path / "fig")


def test_F2_damaged_metadata_of_a_level(pair, tmp_path, capsys):
    corrupt_chunk(pair / "s/ref.zarr/0", "zarr.json")
    before = tree(pair / "s")
    damaged = r"cannot read .*ref.zarr as a Zarr store: .*the store is damaged"
    refused(correlate_args(pair / "s/ref.zarr", pair / "s/def.zarr", tmp_path / "o.zarr"), capsys, damaged)
    nothing_left(tmp_path / "o.zarr")
    # the result's recorded scan is on disk but unreadable: refused, not silently skipped
    refused(["report", pair / "r.zarr", "-o", tmp_path / "fig"], capsys, damaged)
    nothing_left(tmp_path / "fig")
    assert tree(pair / "s") == before


def test_F2_missing_chunk_file(pair, tmp_path, capsys):
    s = pair / "s"
    (s / "def.zarr/0/c/1/0/1").unlink()
    before = tree(s)
    refused(correlate_args(s / "ref.zarr", s / "def.zarr", tmp_path / "o.zarr"), capsys,
            r"def.zarr/0: 1 of 8 chunk files are missing \(first: c/1/0/1\)")
    nothing_left(tmp_path / "o.zarr")
    assert tree(s) == before
    # a Zarr array written by another tool may leave empty chunks out: a warning, not a refusal
    a = zarr.create_array(str(tmp_path / "foreign.zarr"), shape=(N,) * 3, chunks=(16,) * 3, dtype="uint8")
    a[:16] = 7
    with pytest.warns(MissingChunksWarning, match="4 of 8 chunks are absent") as caught:
        chunkdic.open_scan(tmp_path / "foreign.zarr")
    assert [w.filename for w in caught] == [__file__]  # the user's call, not chunkdic's line


def test_F3_truncated_tiff(data, tmp_path, capsys):
    vol = np.load(data / "f.npy").astype(np.uint16)
    slices = tmp_path / "slices"
    slices.mkdir()
    for z in range(N):
        tifffile.imwrite(slices / f"s{z:03d}.tif", vol[z])
    f = slices / "s010.tif"
    f.write_bytes(f.read_bytes()[:-300])
    tifffile.imwrite(tmp_path / "stack.tif", vol)
    stack = tmp_path / "stack.tif"
    stack.write_bytes(stack.read_bytes()[: stack.stat().st_size // 2])
    before = tree(slices, stack)
    refused(["ingest", slices, tmp_path / "a.zarr"], capsys, r"s010.tif: truncated TIFF")
    refused(["ingest", stack, tmp_path / "b.zarr"], capsys, r"stack.tif: truncated TIFF")
    nothing_left(tmp_path / "a.zarr")
    nothing_left(tmp_path / "b.zarr")
    assert tree(slices, stack) == before


def _unshare_ok() -> bool:
    if shutil.which("unshare") is None:
        return False
    return subprocess.run(["unshare", "-m", "true"], capture_output=True).returncode == 0


@pytest.mark.skipif(not _unshare_ok(), reason="needs a private mount namespace (unshare -m) for a read-only/full disk")
@pytest.mark.parametrize("case", ["read-only output", "read-only scratch", "full disk", "full scratch"])
def test_F4_read_only_or_full_disk(data, tmp_path, case):
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    opts = "size=32k" if case.startswith("full") else "ro"
    out = mnt / "o.zarr" if case in ("read-only output", "full disk") else tmp_path / "o.zarr"
    if case == "full disk":
        cmd = [sys.executable, "-m", "chunkdic", "ingest", str(data / "f.npy"), str(out), "--chunks", "16"]
    else:
        cmd = [sys.executable, "-m", "chunkdic", *map(str, correlate_args(data / "f.npy", data / "g.npy", out))]
    env = {**os.environ, "DASK_CHUNKDIC__SCRATCH_DIRECTORY": str(mnt)}
    script = f'mount -t tmpfs -o {opts} tmpfs "$1" && shift && "$@"; rc=$?; ls -A "{mnt}"; exit $rc'
    before = tree(data / "f.npy", data / "g.npy")
    proc = subprocess.run(["unshare", "-m", "sh", "-c", script, "sh", str(mnt), *cmd], capture_output=True,
                          text=True, env=env)
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    errors = [ln for ln in err if ln.startswith("chunkdic: error:")]
    assert len(errors) == 1 and err[-1] == errors[0], proc.stderr
    # a correlation whose plan (chunkdic.engine.costs) sees the small scratch disk is refused before it starts
    expected = {"read-only": "Read-only file system", "full scratch": "No space left on device|not enough disk"}
    assert re.search(next((v for k, v in expected.items() if k in case), "No space left on device"), errors[0])
    assert proc.stdout.strip() == ""  # nothing left on the mounted disk
    nothing_left(out)
    assert tree(data / "f.npy", data / "g.npy") == before


def test_F5_output_under_a_regular_file(data, capsys):
    notes = data / "notes.txt"
    s = data / "s"
    for argv in (correlate_args(s / "ref.zarr", s / "def.zarr", notes / "o.zarr"),
                 ["export", data / "r.zarr", "--csv", notes / "n.csv"],
                 ["report", data / "r.zarr", "-o", notes / "fig"],
                 ["synth", notes / "pair", "--shape", "16"]):
        refused(argv, capsys, "lies under the file .*notes.txt")
    assert notes.read_text() == "a user's notes\n"


def test_F6_result_without_attributes_or_history(pair, capsys):
    r1, r2 = pair / "r.zarr", pair / "r2.zarr"
    shutil.copytree(r1, r2)
    meta = r1 / "zarr.json"
    doc = json.loads(meta.read_text())
    del doc["attributes"]["chunkdic"]["roi"]
    meta.write_text(json.dumps(doc))
    for argv in (["strain", r1], ["table", r1], ["export", r1, "--csv", pair / "n.csv"],
                 ["report", r1, "-o", pair / "fig"]):
        refused(argv, capsys, "lacks the attribute")
    nothing_left(pair / "n.csv")
    nothing_left(pair / "fig")
    shutil.rmtree(r2 / "history/gap")
    refused(["strain", r2], capsys, "lacks the array '(history/)?gap'")


@pytest.mark.parametrize("text", ["", "element_size,delta_eps\n8,abc\n", "a,b\n1,2\n", "\x00\xff\x00garbage"])
def test_F6_malformed_uncertainty_table(data, tmp_path, capsys, text):
    csv = tmp_path / "unc.csv"
    csv.write_bytes(text.encode("latin-1"))
    refused(["table", data / "r.zarr", "--uncertainty", csv], capsys, "uncertainty table")
    s = data / "s"
    refused(["sweep", s / "ref.zarr", s / "def.zarr", "-l", "8", "--uncertainty", csv, "-o", tmp_path / "sw"],
            capsys, "uncertainty table")
    nothing_left(tmp_path / "sw")


def test_F7_export_unknown_extension_and_wrong_reference(data, tmp_path, capsys):
    refused(["export", data / "r.zarr", "--vtk", tmp_path / "x.txt"], capsys, r"unknown extension '.txt'")
    nothing_left(tmp_path / "x.txt")
    np.save(tmp_path / "small.npy", np.zeros((20, 20, 20), np.uint8))
    refused(["export", data / "r.zarr", "--corrected", tmp_path / "c.zarr", "--ref", tmp_path / "small.npy"],
            capsys, r"reference scan \(--ref\) has shape \(20, 20, 20\) but the result was computed on one of "
                    r"shape \(32, 32, 32\)")
    nothing_left(tmp_path / "c.zarr")


# --------------------------------------------------------------------------- G: outputs left behind


def test_G1_correlate_leaves_nothing_after_a_refusal(data, tmp_path, capsys):
    np.save(tmp_path / "flat.npy", np.full((N,) * 3, 7, np.uint8))
    refused(correlate_args(tmp_path / "flat.npy", data / "g.npy", tmp_path / "o.zarr"), capsys,
            "reference is constant", only_line=False)
    nothing_left(tmp_path / "o.zarr")
    refused(correlate_args(data / "f.npy", data / "g.npy", tmp_path / "o.zarr", "--scheduler", "tcp://127.0.0.1:9"),
            capsys, "cannot reach")
    nothing_left(tmp_path / "o.zarr")


def test_G2_uncertainty_and_sweep_check_everything_first(pair, tmp_path, capsys):
    s = pair / "s"
    refused(["uncertainty", s / "ref.zarr", "-l", "8", "40", "-o", tmp_path / "unc"], capsys, "element size 40")
    nothing_left(tmp_path / "unc")
    refused(["sweep", s / "ref.zarr", s / "def.zarr", "-l", "8", "6", "6", "-o", tmp_path / "sw"], capsys, "distinct")
    # a failure after the first correlations (a damaged deformed scan): nothing of the run is left
    for key in ("c/0/0/0", "c/0/0/1", "c/0/1/0", "c/0/1/1", "c/1/0/0", "c/1/0/1", "c/1/1/0", "c/1/1/1"):
        corrupt_chunk(s / "def.zarr/0", key)
    refused(["sweep", s / "ref.zarr", s / "def.zarr", "-l", "8", "--no-a-priori", "-o", tmp_path / "sw"], capsys,
            "cannot be read", only_line=False)
    nothing_left(tmp_path / "sw")


def test_G3_synth_leaves_no_empty_folder(tmp_path, capsys):
    refused(["synth", tmp_path / "p", "--shape", "16", "--voxel-size", "1", "--unit", "furlong"], capsys,
            "unknown length unit")
    nothing_left(tmp_path / "p")
    refused(["synth", tmp_path / "p", "--shape", "8", "--levels", "5"], capsys, "pyramid levels")
    nothing_left(tmp_path / "p")


def test_G4_report_and_export_remove_earlier_steps_when_a_later_one_fails(pair, tmp_path, capsys):
    for key in ("c/0/0/0", "c/0/0/1", "c/0/1/0", "c/0/1/1", "c/1/0/0", "c/1/0/1", "c/1/1/0", "c/1/1/1"):
        corrupt_chunk(pair / "s/def.zarr/0", key)
    before = tree(pair / "s", pair / "r.zarr")
    refused(["report", pair / "r.zarr", "-o", tmp_path / "fig"], capsys, "cannot be read", only_line=False)
    nothing_left(tmp_path / "fig")
    refused(["export", pair / "r.zarr", "--vtk", tmp_path / "m.vtu", "--csv", tmp_path / "n.csv", "--corrected",
             tmp_path / "c.zarr"], capsys, "cannot be read", only_line=False)
    for out in ("m.vtu", "n.csv", "c.zarr"):
        nothing_left(tmp_path / out)
    assert tree(pair / "s", pair / "r.zarr") == before


# --------------------------------------------------------------------------- H: values that were accepted


def test_H1_report_refuses_a_reference_of_another_shape(data, tmp_path, capsys):
    np.save(tmp_path / "big.npy", np.zeros((40, 40, 40), np.uint8))
    np.save(tmp_path / "small.npy", np.zeros((16, 16, 16), np.uint8))
    for ref in ("big.npy", "small.npy"):
        refused(["report", data / "r.zarr", "-o", tmp_path / "fig", "--ref", tmp_path / ref], capsys,
                r"reference scan \(--ref\) has shape")
        nothing_left(tmp_path / "fig")


@pytest.mark.parametrize("option", [["--noise", "-1"], ["--noise", "nan"], ["--cell-size", "0"],
                                    ["--bead-size", "-3"], ["--wall-width", "inf"], ["--strain", "-1.5"],
                                    ["--band-width", "0"], ["--seed", "-2"], ["--translation", "1,nan,0"],
                                    ["--voxel-size", "0"], ["--levels", "-1"], ["--chunks", "0"]])
def test_H2_synth_numeric_options_in_range(tmp_path, capsys, option):
    refused(["synth", tmp_path / "p", "--shape", "16", *option], capsys, re.escape(option[0].replace("_", "-")))
    nothing_left(tmp_path / "p")
