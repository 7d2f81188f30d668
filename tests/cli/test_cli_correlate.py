"""`chunkdic correlate`: a real run, and bad input refused in one line with exit 2."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from textures import smooth_noise

import chunkdic
from chunkdic.cli.app import main


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("pair")
    f = smooth_noise((48, 48, 48), sigma=1.2, seed=5).astype(np.float32)
    g = np.roll(f, (1, 2, -1), axis=(0, 1, 2))
    np.save(d / "ref.npy", f)
    np.save(d / "def.npy", g)
    np.save(d / "flat.npy", f[0])
    return d


def test_correlate_command_writes_a_result(pair, tmp_path, capsys):
    out = tmp_path / "res.zarr"
    # -v after the subcommand, as before it (issue 13)
    code = main(["correlate", str(pair / "ref.npy"), str(pair / "def.npy"), "-o", str(out), "--element-size", "8",
                 "-v"])
    assert code == 0
    err = capsys.readouterr().err
    assert "iter" in err and "converged" in err
    res = chunkdic.open_result(out)
    err = res.displacement - np.array([1, 2, -1.0])[:, None, None, None]
    assert np.abs(err).max() < 1e-3
    assert res.info["element_size"] == 8 and res.info["level"] == 0 and res.info["scale"] == 1
    assert res.history["gap"][-1] == pytest.approx(res.info["final_gap"])


@pytest.mark.parametrize(
    "args, message",
    [
        (["missing.npy", "def.npy"], "does not exist"),
        (["flat.npy", "def.npy"], "3-D"),
        (["ref.npy", "def.npy", "--roi", "0:40,0:40,10:60"], "outside"),
        (["ref.npy", "def.npy", "--element-size", "64"], "element size"),
        (["ref.npy", "def.npy", "--roi", "0:40,0:40"], "ROI"),
    ],
)
def test_bad_input_is_one_line_exit_2_nothing_written(pair, tmp_path, capsys, args, message):
    out = tmp_path / "res.zarr"
    argv = ["correlate", *[str(pair / a) if a.endswith(".npy") else a for a in args], "-o", str(out)]
    if "--element-size" not in argv:
        argv += ["--element-size", "8"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert not out.exists()


def test_quiet_run_prints_the_result_path_only(pair, tmp_path, capsys):
    out = tmp_path / "res.zarr"
    assert main(["correlate", str(pair / "ref.npy"), str(pair / "def.npy"), "-o", str(out), "-l", "8", "-q"]) == 0
    captured = capsys.readouterr()
    assert captured.err == "" and captured.out.strip() == str(out)
    # the same command again has nothing to do (issue 24), quietly
    assert main(["correlate", str(pair / "ref.npy"), str(pair / "def.npy"), "-o", str(out), "-l", "8", "-q"]) == 0
    captured = capsys.readouterr()
    assert captured.err == "" and captured.out.strip() == str(out)
    # other settings on the complete result: refused, and the error is still shown
    assert main(["correlate", str(pair / "ref.npy"), str(pair / "def.npy"), "-o", str(out), "-l", "8", "-q",
                 "--tolerance", "1e-4"]) == 2
    assert capsys.readouterr().err.startswith("chunkdic: error: output")  # errors still shown


def test_existing_output_is_refused_without_overwrite(pair, tmp_path, capsys):
    out = tmp_path / "res.zarr"
    out.mkdir()
    (out / "keep.txt").write_text("user data")
    argv = ["correlate", str(pair / "ref.npy"), str(pair / "def.npy"), "-o", str(out), "--element-size", "8"]
    assert main(argv) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert (out / "keep.txt").read_text() == "user data"


def test_no_traceback_from_the_installed_command(pair, tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "chunkdic", "correlate", str(pair / "nope.npy"), str(pair / "def.npy"),
         "-o", str(tmp_path / "r.zarr"), "--element-size", "8"],
        capture_output=True, text=True,
    )
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


def test_long_passes_report_blocks_rate_and_eta(pair, tmp_path, capsys, monkeypatch):
    from chunkdic.passes import level
    from chunkdic.passes import prefilter

    monkeypatch.setattr(level, "PROGRESS_SECONDS", 0.0)  # every block counts as "long"
    monkeypatch.setattr(prefilter, "TASK_EDGE", 16)  # several prefilter tasks on this small pair
    argv = ["correlate", str(pair / "ref.npy"), str(pair / "def.npy"), "-o", str(tmp_path / "r.zarr"),
            "--element-size", "8", "--block-elements", "2", "--grey-level-cell", "0"]  # blocks of 2: no 4³ cells
    assert main(argv) == 0
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "blocks, " in ln]
    assert any("level 0 b pass: 1/27 blocks" in ln and "Mvoxel/s, ETA" in ln for ln in lines), lines
    assert any("level 0 M pass: 1/27 blocks" in ln for ln in lines), lines
    assert any("level 0 prefilter of g: 1/" in ln and "Mvoxel/s, ETA" in ln for ln in lines), lines


def test_python_api_takes_physical_lengths_as_the_cli(pair, tmp_path, caplog):
    """Issue 23 item 6: correlate(element_size="80um", roi in um) is the CLI's run of the same command."""
    import logging

    f, g = np.load(pair / "ref.npy"), np.load(pair / "def.npy")
    for name, data in (("ref.zarr", f), ("def.zarr", g)):
        chunkdic.write_scan(tmp_path / name, data, voxel_size=(10.0, 10.0, 10.0), unit="micrometer")
    ref, dfm = str(tmp_path / "ref.zarr"), str(tmp_path / "def.zarr")
    assert main(["correlate", ref, dfm, "-o", str(tmp_path / "cli.zarr"), "-l", "80um",
                 "--roi", "40:440,40:440,40:440", "--roi-unit", "um"]) == 0
    cli = chunkdic.open_result(tmp_path / "cli.zarr")
    with caplog.at_level(logging.INFO, logger="chunkdic"):
        api = chunkdic.correlate(ref, dfm, element_size="80um", roi="40:440,40:440,40:440um")
    assert api.info["element_size"] == cli.info["element_size"] == 8
    assert api.info["roi"] == cli.info["roi"] == [[4, 44]] * 3
    np.testing.assert_allclose(api.displacement, cli.displacement, rtol=0, atol=1e-9)
    assert np.abs(api.displacement - np.array([1, 2, -1.0])[:, None, None, None]).max() < 1e-3
    # the conversion and the events are logged as the CLI words them, not as raw dicts
    messages = [r.getMessage() for r in caplog.records]
    assert any(m.startswith("--element-size 80um = 8.000 voxels of level 0: using 8") for m in messages), messages
    assert any(m.startswith("running on ") for m in messages)
    assert any(" iter " in m and "gap" in m for m in messages)
    assert not any("'stage'" in m for m in messages)
    # a physical length without a voxel size, or a fraction of a voxel, is refused in one line
    with pytest.raises(chunkdic.InputError, match="no voxel size"):
        chunkdic.correlate(f, g, element_size="80um")
    with pytest.raises(chunkdic.InputError, match="whole number"):
        chunkdic.correlate(ref, dfm, element_size="8.5")
