"""Output paths the file system cannot take (issue 24): a loop of symbolic links, a name
longer than ``NAME_MAX``, a working directory removed under the process.

Each refusal is checked as in ``test_data_safety``: exit status 2, one ``chunkdic: error:``
line and no traceback, nothing written (no output, staged copy or lock), and the inputs
byte-identical. Scans are 32³ (chunks 16³), elements of 8 voxels.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from test_data_safety import N, T, refused, tree

import chunkdic
from chunkdic.cli.app import main
from chunkdic.io.locks import OutputLock
from chunkdic.io.siblings import name_limits, partial_name
from chunkdic.synth import synthetic

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A 32³ synthetic pair (Zarr, chunks 16³) and its result."""
    d = tmp_path_factory.mktemp("paths")
    pair = synthetic.synthesize(d / "s", (N,) * 3, field=synthetic.Translation(T), seed=4, chunks=16)
    chunkdic.correlate(pair["reference"], pair["deformed"], element_size=8, output=d / "r.zarr")
    return d


def _commands(data: Path, out: str) -> dict:
    """Every command that writes, with ``out`` as its output."""
    ref, dfm, res = data / "s/ref.zarr", data / "s/def.zarr", data / "r.zarr"
    return {
        "correlate": ["correlate", ref, dfm, "-l", "8", "-o", f"{out}.zarr"],
        "series": ["series", ref, dfm, "-l", "8", "-o", f"{out}.zarr"],
        "export --vtk": ["export", res, "--vtk", f"{out}.vtu"],
        "export --csv": ["export", res, "--csv", f"{out}.csv"],
        "export --fields": ["export", res, "--fields", f"{out}.zarr"],
        "export --corrected": ["export", res, "--corrected", f"{out}.zarr"],
        "ingest": ["ingest", ref / "0", f"{out}.zarr"],
        "synth": ["synth", out, "--shape", "16"],
        "report": ["report", res, "-o", out],
    }


def _listing(d: Path) -> list[str]:
    return sorted(os.listdir(d))


@pytest.mark.parametrize("cmd", ["correlate", "series", "export --vtk", "export --csv", "export --fields",
                                 "export --corrected", "ingest", "synth", "report"])
def test_an_output_under_a_loop_of_symbolic_links_is_one_line(data, tmp_path, capsys, cmd):
    os.symlink(tmp_path / "b", tmp_path / "a")
    os.symlink(tmp_path / "a", tmp_path / "b")  # a -> b -> a: resolving either never ends
    before = tree(data / "s", data / "r.zarr")
    refused(_commands(data, str(tmp_path / "a" / "o"))[cmd], capsys, "loop of symbolic links")
    assert tree(data / "s", data / "r.zarr") == before
    assert _listing(tmp_path) == ["a", "b"] and os.readlink(tmp_path / "a") == str(tmp_path / "b")


def test_pyramid_of_a_scan_under_a_loop_is_one_line(tmp_path, capsys):
    os.symlink(tmp_path / "b", tmp_path / "a")
    os.symlink(tmp_path / "a", tmp_path / "b")
    refused(["pyramid", tmp_path / "a" / "ref.zarr", "--levels", "1"], capsys, "does not exist")
    assert _listing(tmp_path) == ["a", "b"]


@pytest.mark.parametrize("cmd", ["correlate", "series", "export --vtk", "export --csv", "export --fields",
                                 "ingest", "synth", "report"])
def test_a_300_character_output_name_is_refused_naming_enametoolong(data, tmp_path, capsys, cmd):
    before = tree(data / "s", data / "r.zarr")
    refused(_commands(data, str(tmp_path / ("a" * 296)))[cmd], capsys, r"\(\d{3} bytes\) .*ENAMETOOLONG")
    assert tree(data / "s", data / "r.zarr") == before
    assert _listing(tmp_path) == []


def test_a_longest_valid_name_works_though_its_lock_and_partial_would_not_fit(data, tmp_path, capsys):
    """A 255-byte output name is valid; ``.NAME.chunkdic-lock`` (271 bytes) and the staged
    ``.NAME.chunkdic-partial-HOST-PID-…`` are not: they are shortened (a digest of the name
    keeps them distinct), the output is written, and nothing else is left."""
    name_max = name_limits(tmp_path)[0]
    assert name_max == 255  # the limit this test is written for (ext4, tmpfs, xfs, btrfs)
    vtu = tmp_path / ("v" * (name_max - 4) + ".vtu")
    csv = tmp_path / ("c" * (name_max - 9) + ".csv")  # its sidecar NAME.csv.json: exactly 255 bytes
    fields = tmp_path / ("f" * (name_max - 5) + ".zarr")
    result = tmp_path / ("r" * (name_max - 5) + ".zarr")
    for p in (vtu, csv, fields, result):
        assert len(p.name) <= name_max < len(f".{p.name}.chunkdic-lock")  # the plain lock name would not fit
        assert len(OutputLock(p).path.name) <= name_max - 16  # room left for the ".stale-…" of a take-over
        assert len(partial_name(p).name) <= name_max - 16 and partial_name(p).suffix == p.suffix
    assert OutputLock(vtu).path == OutputLock(vtu).path != OutputLock(tmp_path / ("v" * 250 + "w.vtu")).path
    res = data / "r.zarr"
    assert main(["export", str(res), "--vtk", str(vtu), "--csv", str(csv), "--fields", str(fields)]) == 0
    assert main(["correlate", str(data / "s/ref.zarr"), str(data / "s/def.zarr"), "-l", "8", "-o",
                 str(result)]) == 0
    capsys.readouterr()
    assert _listing(tmp_path) == sorted([vtu.name, csv.name, csv.name + ".json", fields.name, result.name])
    r = chunkdic.open_result(result)
    assert abs(float(r.displacement[0].mean()) - T[0]) < 0.05
    # and the second writer of one of them is still refused by that (shortened) lock
    hold = ("import sys, time; from chunkdic.io.locks import OutputLock; "
            "OutputLock(sys.argv[1]).acquire(); print('locked', flush=True); time.sleep(60)")
    holder = subprocess.Popen([sys.executable, "-c", hold, str(vtu)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        refused(["export", res, "--vtk", vtu, "--overwrite"], capsys, "being written by another chunkdic run")
    finally:
        holder.kill()
        holder.wait()


def _run_in_removed_directory(argv: list, where: Path) -> subprocess.CompletedProcess:
    """``cd where; rm -r where; chunkdic ARGV`` (the shell keeps the removed directory as cwd)."""
    where.mkdir()
    script = 'cd "$1" && rmdir "$1" && shift && exec "$@"'
    return subprocess.run(["sh", "-c", script, "sh", str(where), sys.executable, "-m", "chunkdic", *map(str, argv)],
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("outname", ["o.zarr", "ABS"])
def test_correlate_from_a_removed_working_directory_is_one_line(data, tmp_path, outname):
    out = tmp_path / "o.zarr" if outname == "ABS" else outname
    before = tree(data / "s")
    proc = _run_in_removed_directory(["correlate", data / "s/ref.zarr", data / "s/def.zarr", "-l", "8", "-o", out],
                                     tmp_path / "gone")
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(err) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert err[0].startswith("chunkdic: error: the current directory no longer exists"), err
    assert "relative paths cannot be resolved" in err[0]
    assert tree(data / "s") == before
    assert _listing(tmp_path) == []
