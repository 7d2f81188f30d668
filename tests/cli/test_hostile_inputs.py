"""Hostile and odd inputs, round 4 (issue 40): edited result metadata, malformed JSON where
chunkdic reads its own records, HDF5 links and storage, names no file system takes, voxel
sizes, writes through links, a re-run on its own complete output.

Every refusal keeps the promise of test_data_safety.py: exit status 2, one ``chunkdic:
error:`` line, no traceback, nothing left at the output and every file under the case's
folder unchanged (SHA-256 before and after).
"""

from __future__ import annotations

import json
import os
import shutil
import socket

import numpy as np
import pytest
import zarr
from test_data_safety import data, nothing_left, pair, refused, tree  # noqa: F401  (fixtures)

from chunkdic.cli.app import main
from chunkdic.io.owntree import link_out_of, remove


def _set_attr_raw(zarr_json, key: str, raw: str) -> None:
    """``attributes.chunkdic[key]`` set to the JSON text ``raw`` (``1e400`` reads as infinity, ``NaN``)."""
    doc = json.loads(zarr_json.read_text())
    doc["attributes"]["chunkdic"][key] = "@@"
    zarr_json.write_text(json.dumps(doc).replace('"@@"', raw))


READERS = {"strain": ["strain", "r.zarr"], "table": ["table", "r.zarr"], "report": ["report", "r.zarr", "-o", "fig"],
           "export": ["export", "r.zarr", "--csv", "n.csv", "--units", "physical"],
           "init": ["correlate", "s/ref.zarr", "s/def.zarr", "-l", "8", "--init", "r.zarr", "-o", "o.zarr"]}
EDITS = {"element_size 1e400": ("element_size", "1e400"), "level 5000": ("level", "5000"),
         "level x": ("level", '"x"'), "voxel_size NaN": ("voxel_size", "[NaN, 1, 1]"),
         "voxel_size -20": ("voxel_size", "[-20, -20, -20]")}


@pytest.mark.parametrize("edit", EDITS)
@pytest.mark.parametrize("reader", READERS)
def test_edited_result_metadata_is_one_line(pair, capsys, monkeypatch, edit, reader):
    """A result's attributes edited by hand, read by each command that reads a result."""
    monkeypatch.chdir(pair)
    _set_attr_raw(pair / "r.zarr/zarr.json", *EDITS[edit])
    before = tree(pair)
    refused(READERS[reader], capsys, r"a damaged result|not a chunkdic result", only_line=False)
    assert tree(pair) == before


@pytest.mark.parametrize("reader", READERS)
def test_a_result_whose_metadata_nest_100000_deep_is_one_line(pair, capsys, monkeypatch, reader):
    monkeypatch.chdir(pair)
    (pair / "r.zarr/zarr.json").write_text('{"attributes": ' + "[" * 100_000 + "]" * 100_000 + "}")
    before = tree(pair)
    refused(READERS[reader], capsys, only_line=False)
    assert tree(pair) == before


@pytest.mark.parametrize("argv", [["export", "r.zarr", "--corrected", "c.zarr"], ["report", "r.zarr", "-o", "fig"],
                                  ["cutcheck", "r.zarr", "-o", "cut"]])
def test_a_recorded_reference_that_is_a_fifo_is_refused_without_opening_it(pair, capsys, monkeypatch, argv):
    """The scan a result records is replaced by a FIFO: opening it would wait for a writer for ever."""
    monkeypatch.chdir(pair)
    shutil.rmtree(pair / "s/ref.zarr")
    os.mkfifo(pair / "s/ref.zarr")
    before = tree(pair)
    refused(argv, capsys, "FIFO|not a (file|folder|directory)|named pipe", only_line=False)
    assert tree(pair) == before


@pytest.mark.parametrize("where", ["result", "lock", "marker"])
@pytest.mark.parametrize("text", ["[" * 1_000_000 + "]" * 1_000_000, "[1, 2]", "1e400",
                                  '{"attributes": [1]}', '{"kind": ["result"], "pid": 1e400, "host": "h"}'])
def test_malformed_json_where_chunkdic_reads_its_records(pair, capsys, monkeypatch, where, text):
    """Nested a million deep, a list, a number, attributes or a kind of the wrong type, a pid of
    1e400: as a result's ``zarr.json`` replaced with --overwrite, an output's lock, a folder's marker."""
    monkeypatch.chdir(pair)
    if where == "result":
        (pair / "r.zarr/zarr.json").write_text(text)
        argv = ["correlate", "s/ref.zarr", "s/def.zarr", "-l", "8", "-o", "r.zarr", "--overwrite"]
    elif where == "lock":
        (pair / ".o.zarr.chunkdic-lock").write_text(text)
        os.utime(pair / ".o.zarr.chunkdic-lock", (0, 0))  # not one being written this instant
        argv = ["correlate", "s/ref.zarr", "s/def.zarr", "-l", "8", "-o", "o.zarr"]
    else:
        (pair / "fig").mkdir()
        (pair / "fig/.chunkdic.json").write_text(text)
        argv = ["report", "r.zarr", "-o", "fig", "--overwrite"]
    before = tree(pair)
    refused(argv, capsys, only_line=False)
    assert tree(pair) == before


@pytest.mark.parametrize("pid", ["1e400", "-5", "99999999999999999999", '"x"', "true"])
def test_a_lock_naming_a_pid_no_process_can_have(pair, capsys, monkeypatch, pid):
    monkeypatch.chdir(pair)
    lock = pair / ".o.zarr.chunkdic-lock"
    lock.write_text(f'{{"host": "{socket.gethostname()}", "pid": {pid}, "start": null}}')
    os.utime(lock, (0, 0))
    refused(["correlate", "s/ref.zarr", "s/def.zarr", "-l", "8", "-o", "o.zarr"], capsys, "unreadable lock",
            only_line=False)
    assert lock.exists() and not (pair / "o.zarr").exists()


def test_a_foreign_scratch_record_is_left_alone(pair, capsys, monkeypatch):
    """A ``chunkdic-*`` directory whose owner record names pid 1e400 (or is nested a million deep):
    the run completes, and the directory is neither removed nor adopted."""
    monkeypatch.chdir(pair)
    root = pair / "scratch"
    for i, text in enumerate([f'{{"host": "{socket.gethostname()}", "pid": 1e400}}', "[" * 10**6 + "]" * 10**6]):
        (root / f"chunkdic-planted{i}").mkdir(parents=True)
        (root / f"chunkdic-planted{i}/.chunkdic-scratch.json").write_text(text)
    monkeypatch.setenv("DASK_CHUNKDIC__SCRATCH_DIRECTORY", str(root))
    import dask.config

    with dask.config.set({"chunkdic.scratch-directory": str(root)}):
        assert main(["correlate", "s/ref.zarr", "s/def.zarr", "-l", "8", "-o", "o.zarr"]) == 0
    assert sorted(p.name for p in root.iterdir()) == ["chunkdic-planted0", "chunkdic-planted1"]


@pytest.mark.parametrize("case", ["input", "mask", "ingest parent", "path_max input", "path_max result"])
def test_names_no_file_system_takes_are_one_line(pair, capsys, monkeypatch, case):
    monkeypatch.chdir(pair)
    long, deep = "a" * 300, "/".join(["d" * 200] * 24)
    argv = {"input": ["correlate", f"{long}.zarr", "s/def.zarr", "-l", "8", "-o", "o.zarr"],
            "mask": ["correlate", "s/ref.zarr", "s/def.zarr", "-l", "8", "--mask", f"{long}.npy", "-o", "o.zarr"],
            "ingest parent": ["ingest", "s/ref.zarr/0", f"{long}/x/o.zarr"],
            "path_max input": ["correlate", f"{deep}/f.npy", "s/def.zarr", "-l", "8", "-o", "o.zarr"],
            "path_max result": ["strain", f"{deep}/r.zarr"]}[case]
    before = tree(pair)
    refused(argv, capsys, "ENAMETOOLONG", only_line=False)
    assert tree(pair) == before


H5 = {"an external link to a missing file": "extlink.h5:/v", "a soft-link loop": "loop.h5:/a",
      "external storage that is a FIFO": "fifo.h5:/v", "a virtual dataset with a missing source": "vds.h5:/v"}


@pytest.mark.parametrize("what", H5)
def test_hdf5_links_and_storage_are_refused_before_reading(tmp_path, capsys, monkeypatch, what):
    h5py = pytest.importorskip("h5py")
    monkeypatch.chdir(tmp_path)
    v = (np.random.default_rng(0).random((16, 16, 16)) * 200).astype(np.uint8)
    with h5py.File("src.h5", "w") as f:
        f["v"] = v
    with h5py.File("extlink.h5", "w") as f:
        f["v"] = h5py.ExternalLink("missing.h5", "/v")
    with h5py.File("loop.h5", "w") as f:
        f["a"], f["b"] = h5py.SoftLink("/b"), h5py.SoftLink("/a")
    os.mkfifo("fifo.raw")
    with h5py.File("fifo.h5", "w") as f:
        f.create_dataset("v", shape=v.shape, dtype=v.dtype, external=[("fifo.raw", 0, v.nbytes)])
    layout = h5py.VirtualLayout(shape=v.shape, dtype=v.dtype)
    layout[:8] = h5py.VirtualSource("gone.h5", "v", shape=(8, 16, 16))
    layout[8:] = h5py.VirtualSource("src.h5", "v", shape=v.shape)[8:]
    with h5py.File("vds.h5", "w") as f:
        f.create_virtual_dataset("v", layout, fillvalue=0)
    refused(["ingest", H5[what], "o.zarr"], capsys, only_line=False)
    nothing_left(tmp_path / "o.zarr")


# --------------------------------------------------------------------------- voxel sizes


@pytest.fixture()
def sized(pair):
    """Scans of the pair at 20 µm, 21 µm, 20 x 21 x 20 µm and 0.02 mm (level 0 copied, metadata set)."""
    from chunkdic.io.formats.ingest import ingest

    for name, src, vs, unit in (("r20", "ref", 20, "um"), ("d21", "def", 21, "um"), ("da", "def", (20, 21, 20), "um"),
                                ("dmm", "def", 0.02, "mm"), ("d25", "def", 25, "um")):
        ingest(str(pair / f"s/{src}.zarr/0"), str(pair / f"vs/{name}.zarr"), voxel_size=vs, unit=unit)
    return pair


@pytest.mark.parametrize("argv", [["correlate", "vs/r20.zarr", "vs/d21.zarr", "-l", "8", "-o", "o.zarr"],
                                  ["correlate", "vs/r20.zarr", "vs/da.zarr", "-l", "8", "-o", "o.zarr"],
                                  ["series", "vs/r20.zarr", "vs/dmm.zarr", "vs/d25.zarr", "-l", "8", "-o", "o.zarr"]])
def test_scans_of_other_voxel_sizes_are_refused(sized, capsys, monkeypatch, argv):
    """21 µm against 20 µm (an unmoved specimen would read -4.7 % strain), 20 x 21 x 20 µm, a series
    with one scan at 25 µm (0.02 mm counts as 20 µm): one line naming both sizes and how to resample."""
    monkeypatch.chdir(sized)
    line = refused(argv, capsys, "voxel size", only_line=False)
    assert "--resample" in line and ("21" in line or "25" in line)
    nothing_left(sized / "o.zarr")


def test_resampled_scan_is_accepted_and_exact_on_a_linear_field(tmp_path, capsys, monkeypatch):
    """``ingest --resample 20um`` of a 21 µm scan holding a linear function of position gives that
    function at the new voxel centres ``j * 20/21`` (trilinear: exact for a linear field)."""
    monkeypatch.chdir(tmp_path)
    z, y, x = np.indices((22, 21, 20), dtype=np.float64)
    np.save("lin.npy", (1.5 * z - 0.75 * y + 2.0 * x + 10).astype(np.float32))
    assert main(["ingest", "lin.npy", "a21.zarr", "--voxel-size", "21um", "--chunks", "8"]) == 0
    assert main(["ingest", "a21.zarr", "a20.zarr", "--resample", "20um", "--chunks", "8"]) == 0
    out = zarr.open_array("a20.zarr/0", mode="r")[...]
    assert out.shape == (23, 22, 20)  # every centre j * 20/21 within 0 … n - 1
    j = [np.arange(n) * 20 / 21 for n in out.shape]
    zz, yy, xx = np.meshgrid(*j, indexing="ij")
    assert np.abs(out - (1.5 * zz - 0.75 * yy + 2.0 * xx + 10)).max() < 1e-4
    from chunkdic.io.scan import open_scan

    assert open_scan("a20.zarr").voxel_size == (20.0, 20.0, 20.0)


def test_an_element_size_too_small_names_the_value_given(sized, capsys, monkeypatch):
    monkeypatch.chdir(sized)
    refused(["correlate", "vs/r20.zarr", "vs/r20.zarr", "-l", "1e-300um", "-o", "o.zarr"], capsys, "'1e-300um' is")


# --------------------------------------------------------------------------- links


def test_remove_never_follows_a_link(tmp_path):
    """A link to a folder is removed as a link; a folder holding links to outside files and folders
    is removed without touching them."""
    (tmp_path / "outside").mkdir()
    (tmp_path / "outside/keep.txt").write_text("keep")
    (tmp_path / "tree/sub").mkdir(parents=True)
    os.symlink(tmp_path / "outside", tmp_path / "tree/sub/dirlink")
    os.symlink(tmp_path / "outside/keep.txt", tmp_path / "tree/filelink")
    os.symlink(tmp_path / "outside", tmp_path / "toplink")
    assert link_out_of(tmp_path / "tree") is not None
    remove(tmp_path / "toplink")
    remove(tmp_path / "tree")
    remove(tmp_path / "missing")
    assert not (tmp_path / "tree").exists() and not (tmp_path / "toplink").is_symlink()
    assert (tmp_path / "outside/keep.txt").read_text() == "keep"


@pytest.mark.parametrize("link", ["1 -> outside", "1 -> def.zarr", "2 -> outside", "display -> outside",
                                  "1/c -> outside", "1/c/0 -> outside"])
def test_pyramid_writes_nothing_through_a_link_out_of_the_scan(pair, capsys, monkeypatch, link):
    """A level (or display/) of the scan that is a link to an outside folder or another store: refused,
    naming the link; the outside folder, the other store and the scan unchanged (it built the level
    inside the outside folder, or crashed on "Cannot call rmtree on a symbolic link"). A link deeper
    in a level left incomplete: the level is rebuilt inside the scan, nothing written outside."""
    monkeypatch.chdir(pair)
    name, target = link.split(" -> ")
    (pair / "outside").mkdir()
    if "/" in name:  # deeper: the level exists (complete), a folder of its chunks is a link
        assert main(["pyramid", "s/ref.zarr", "--levels", "1"]) == 0
        shutil.rmtree(pair / "s/ref.zarr" / name)
        zarr.open_group(str(pair / "s/ref.zarr"), mode="r+")["1"].attrs["chunkdic"] = {"level": 1, "complete": False}
    up = "../" * (name.count("/") + 2)
    os.symlink(f"{up}outside" if target == "outside" else "../def.zarr", pair / "s/ref.zarr" / name)
    before = tree(pair)
    extra = ["--display"] if name == "display" else []
    argv = ["pyramid", "s/ref.zarr", "--levels", "2", *extra]
    if "/" not in name:
        refused(argv, capsys, "symbolic link", only_line=False)
        assert tree(pair) == before
        return
    # inside an incomplete level of its own: the level is rebuilt, its link removed as a link
    assert main(argv) == 0
    assert not any(p.is_symlink() for p in (pair / "s/ref.zarr").rglob("*"))
    assert not any((pair / "outside").iterdir())
    assert zarr.open_group(str(pair / "s/ref.zarr"), mode="r")["1"].attrs["chunkdic"]["complete"]


def test_a_resumed_output_whose_checkpoint_is_a_link_out_of_it_is_refused(pair, capsys, monkeypatch):
    monkeypatch.chdir(pair)
    shutil.copytree(pair / "r.zarr", pair / "out.zarr")
    g = zarr.open_group(str(pair / "out.zarr"), mode="r+")
    g.attrs["chunkdic"] = {**dict(g.attrs["chunkdic"]), "complete": False}
    (pair / "outside").mkdir()
    shutil.rmtree(pair / "out.zarr/checkpoint", ignore_errors=True)
    os.symlink("../outside", pair / "out.zarr/checkpoint")
    before = tree(pair)
    refused(["correlate", "s/ref.zarr", "s/def.zarr", "-l", "8", "-o", "out.zarr"], capsys, "symbolic link")
    assert tree(pair) == before


# --------------------------------------------------------------------------- re-runs


@pytest.mark.parametrize("argv", [["ingest", "s/ref.zarr/0", "out.zarr"],
                                  ["export", "r.zarr", "--vtk", "out.vtu", "--csv", "out.csv"],
                                  ["export", "r.zarr", "--vtk", "out.vtk", "--corrected", "out.zarr"],
                                  ["cutcheck", "r.zarr", "-o", "out"],
                                  ["series", "s/ref.zarr", "s/def.zarr", "-l", "8", "-o", "out.zarr"],
                                  ["mask", "s/ref.zarr", "-o", "out.zarr"],
                                  ["synth", "out", "--shape", "16", "--chunks", "8"],
                                  ["table", "r.zarr", "-o", "out"],
                                  ["gauge", "r.zarr", "--points", "8,8,8", "24,24,24", "-o", "out"],
                                  ["crack", "r.zarr", "-o", "out", "--no-residual"]])
def test_the_same_command_on_its_own_complete_output_has_nothing_to_do(pair, capsys, monkeypatch, argv):
    """Run twice: the second exits 0 saying "nothing to do" and changes nothing; with other options,
    or once an input changed, it is the usual refusal of a complete output, never a silent reuse."""
    monkeypatch.chdir(pair)
    assert main(argv) in (0, 1)
    capsys.readouterr()
    before = tree(pair)
    assert main(argv) == 0
    assert "nothing to do" in capsys.readouterr().err
    assert tree(pair) == before
    if argv[0] == "export":  # another strain measure: another output, refused over the complete one
        refused([*argv, "--strain", "small"], capsys, "complete", only_line=False)
    if argv[0] in ("mask", "crack"):  # what it read has changed since (a scan the result records)
        os.utime(pair / "s/ref.zarr/zarr.json", ns=(0, 0))
        refused(argv, capsys, "complete", only_line=False)


def test_pyramid_display_resumes_over_the_empty_folder_a_kill_leaves(pair, capsys, monkeypatch):
    monkeypatch.chdir(pair)
    (pair / "s/ref.zarr/display").mkdir()
    assert main(["pyramid", "s/ref.zarr", "--levels", "1", "--display"]) == 0
    meta = json.loads((pair / "s/ref.zarr/display/zarr.json").read_text())
    assert meta["attributes"]["chunkdic"]["kind"] == "display" and meta["attributes"]["chunkdic"]["complete"]


class _Killed(BaseException):
    """A kill: no handler of the interrupted code runs (not an Exception)."""


@pytest.mark.slow  # some 80 kills, each followed by a pyramid --display
def test_pyramid_display_resumes_after_a_kill_at_any_line(pair, capsys, monkeypatch):
    """``write_display`` over the scan's own complete display (so its removal runs too), interrupted
    at each line of ``write_display`` and of the removal of the old display, and before each file
    or folder removed, in turn: every time the next ``pyramid --display`` completes, and the display is the levels'
    means (sums / 8^s)."""
    import sys

    from chunkdic.io import display, owntree

    monkeypatch.chdir(pair)
    scan = pair / "s/ref.zarr"
    argv = ["pyramid", "s/ref.zarr", "--levels", "2", "--display"]
    assert main(argv) == 0
    where = {(display.__file__, "write_display"), (display.__file__, "remove_display"), (owntree.__file__, "remove")}
    kills, seen = 0, 0

    def place_to_die():
        nonlocal seen
        seen += 1
        if seen == kills + 1:
            raise _Killed

    def trace(frame, event, arg):
        if (frame.f_code.co_filename, frame.f_code.co_name) not in where:
            return None
        if event == "line":
            place_to_die()
        return trace

    for name in ("unlink", "rmdir"):  # shutil.rmtree's removals, one by one
        real = getattr(os, name)
        monkeypatch.setattr(os, name, lambda *a, _real=real, **k: (place_to_die(), _real(*a, **k))[1])
    while True:
        seen = 0
        sys.settrace(trace)
        try:
            display.write_display(str(scan))
            break  # ran to its end: every line has been a place to die
        except BaseException as exc:  # a cleanup on the way out may fail too (shutil closing a closed fd)
            if not isinstance(exc, _Killed) and not isinstance(exc.__context__, _Killed):
                raise
            kills += 1
        finally:
            sys.settrace(None)
        seen = -10**9  # the recovery is not interrupted
        assert main(argv) == 0, capsys.readouterr().err
        meta = json.loads((scan / "display/zarr.json").read_text())["attributes"]["chunkdic"]
        assert meta["complete"] and meta["levels"] == [1, 2]
    assert kills > 30
    for s in (1, 2):
        mean = zarr.open_array(str(scan / f"display/{s}"), mode="r")[...]
        level = zarr.open_array(str(scan / f"{s}"), mode="r")[...]
        assert np.array_equal(mean, (level / 8.0**s).astype(np.float32))
