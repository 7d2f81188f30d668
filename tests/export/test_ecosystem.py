"""The command line as a new user meets it (issue 13, item 7): --version, -v/-q anywhere,
defaults and descriptions in every help, ingest into new folders, terms explained."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

import chunkdic
from chunkdic.cli import common as _cli_common
from chunkdic.cli.app import build_parser, main


def _subparsers(parser):
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"chunkdic {chunkdic.__version__}"


@pytest.mark.parametrize("argv, verbosity", [
    (["correlate", "a", "b", "-o", "r", "-l", "8"], 0),
    (["correlate", "a", "b", "-o", "r", "-l", "8", "-v"], 1),
    (["-v", "correlate", "a", "b", "-o", "r", "-l", "8"], 1),
    (["correlate", "a", "b", "-o", "r", "-l", "8", "--quiet"], -1),
    (["-q", "correlate", "a", "b", "-o", "r", "-l", "8"], -1),
    (["-v", "correlate", "a", "b", "-o", "r", "-l", "8", "-q"], -1),  # after the subcommand wins
    (["strain", "r.zarr", "-v"], 1),
    (["ingest", "-q", "a.npy", "b.zarr"], -1),
])
def test_verbosity_before_or_after_the_subcommand(argv, verbosity):
    assert build_parser().parse_args(argv).verbosity == verbosity


def test_every_command_has_a_description_and_every_option_its_default():
    parser = build_parser()
    for name, sub in _subparsers(parser).items():
        assert sub.description and len(sub.description) > 20, name
        formatter = sub._get_formatter()
        for action in sub._actions:
            if (not action.option_strings and action.nargs != "?") or action.nargs == 0 or action.required \
                    or action.help is argparse.SUPPRESS or action.default is argparse.SUPPRESS:
                continue
            text = formatter._get_help_string(action) % {"default": action.default}
            assert "default" in text.lower(), (name, action.option_strings, text)
        sub.format_help()  # every help string formats (no stray %)
    assert "(default: 0.001)" in _subparsers(parser)["correlate"].format_help()


def test_ingest_creates_missing_parents_and_stays_safe(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    vol = np.arange(16**3, dtype=np.uint16).reshape(16, 16, 16)
    np.save("v.npy", vol)
    assert main(["ingest", "v.npy", "new/deeper/s.zarr", "-q"]) == 0
    assert capsys.readouterr().err == ""  # -q after the subcommand: no progress, no summary
    assert np.array_equal(chunkdic.open_scan("new/deeper/s.zarr").level(0).compute(), vol)
    # never inside an input (a file or a Zarr store), never under a file: refused, nothing made
    (tmp_path / "notes.txt").write_text("mine")
    for out in ("v.npy/x/s.zarr", "new/deeper/s.zarr/x/y.zarr", "notes.txt/x/s.zarr"):
        src = "new/deeper/s.zarr" if "deeper/s.zarr/" in out else "v.npy"
        assert main(["ingest", src, out]) == 2, out
        assert capsys.readouterr().err.startswith("chunkdic: error:")
    assert not (tmp_path / "new/deeper/s.zarr/x").exists()
    # a run refused half-way (NaN in float data) removes the folders it made
    bad = np.ones((8, 8, 8), np.float32)
    bad[5, 2, 3] = np.nan
    np.save("bad.npy", bad)
    assert main(["ingest", "bad.npy", "made/by/run/s.zarr"]) == 2
    assert "nan value" in capsys.readouterr().err
    assert not (tmp_path / "made").exists()
    assert (tmp_path / "notes.txt").read_text() == "mine" and np.array_equal(np.load("v.npy"), vol)


def _rigid(it, gap, level=1):
    return {"stage": "rigid", "level": level, "iteration": it, "gap": gap, "max_delta": 0.1,
            "translation": [0.0, 0.0, 0.0]}


def _iteration(excluded=0, status=None):
    event = {"stage": "iteration", "level": 0, "iteration": 3, "gap": 0.01, "max_delta": None if status else 0.01,
             "excluded": excluded, "seconds": 1.0}
    if status:
        event["status"] = status
    return event


def test_terms_are_explained_once_where_they_appear():
    _cli_common.new_run()
    assert "\n" not in _cli_common.format_event(_rigid(0, 0.05))
    assert "\n" not in _cli_common.format_event(_rigid(1, 0.04))  # the gap fell: nothing to explain
    rose = _cli_common.format_event(_rigid(2, 0.045))
    assert rose.count("\n") == 1 and "overshot" in rose.splitlines()[1]
    assert "\n" not in _cli_common.format_event(_rigid(3, 0.05))  # explained once per run
    assert "\n" not in _cli_common.format_event(_iteration())
    line = _cli_common.format_event(_iteration(excluded=120))
    assert line.count("\n") == 1 and "outside the deformed scan" in line
    stalled = _cli_common.format_event(_iteration(excluded=120, status="stalled"))
    assert stalled.count("\n") == 1 and "neither the gap nor the increments improved for 4 passes" in stalled
    assert "\n" not in _cli_common.format_event({"stage": "level", "level": 0, "status": "stalled", "gap": 0.01,
                                          "seconds": 2.0})
    gaps = _cli_common.format_event({"stage": "gaps", "level": 0, "initial_gap": 0.01, "rigid_gap": 0.02,
                              "translation": [0, 0, 0]})
    assert "worse than no motion" in gaps


# --------------------------------------------------------------------------- physical units (item 4, part)


class _Scan:
    def __init__(self, voxel_size, unit):
        self.voxel_size, self.unit = voxel_size, unit


def test_lengths_in_physical_units_hand_values():
    from chunkdic.errors import InputError
    from chunkdic.io.units import element_size_voxels, parse_length, roi_voxels

    assert parse_length("60um") == (60.0, "micrometer") and parse_length("60 µm") == (60.0, "micrometer")
    assert parse_length("0.06mm") == (0.06, "millimeter") and parse_length("12") == (12.0, None)
    scan = _Scan((4.91, 4.91, 4.91), "micrometer")
    assert element_size_voxels("12", scan) == (12, None)
    ell, note = element_size_voxels("60um", scan)  # 60 / 4.91 = 12.22
    assert ell == 12 and "12.220" in note and "58.92 micrometer" in note
    assert element_size_voxels("0.06mm", scan)[0] == 12  # 60 um
    assert element_size_voxels("60um", scan, level=1)[0] == 6  # 60 / 9.82 = 6.11
    roi, note = roi_voxels("0:491,49.1:982,98.2:491", scan, "um")
    assert roi == "0:100,10:200,20:100"
    assert roi_voxels("0:491,49.1:982,98.2:491um", scan)[0] == "0:100,10:200,20:100"
    assert roi_voxels("0:0.491,0:0.491,0:0.491", scan, "mm")[0] == "0:100,0:100,0:100"
    assert roi_voxels("1:9,1:9,1:9", scan) == ("1:9,1:9,1:9", None)
    for bad, scan_, match in [("60um", _Scan(None, None), "no voxel size"),
                              ("60um", _Scan((1.0, 2.0, 2.0), "micrometer"), "not the same"),
                              ("12.5", scan, "whole number"), ("abc", scan, "expected a number"),
                              ("60parsecs", scan, "unknown length unit")]:
        with pytest.raises(InputError, match=match):
            element_size_voxels(bad, scan_)


def test_correlate_summary_strain_and_exports_in_physical_units(tmp_path, capsys):
    import json

    import pandas as pd

    from chunkdic.synth import synthetic

    t = (1.0, 0.5, -0.5)
    pair = synthetic.synthesize(tmp_path / "s", (40, 40, 40), field=synthetic.Translation(t), seed=2,
                                dtype="float32", voxel_size=2.5, unit="um")
    out = tmp_path / "r.zarr"
    assert main(["correlate", pair["reference"], pair["deformed"], "-o", str(out), "-l", "30um",
                 "--roi", "10:90,10:90,10:90um", "--max-iterations", "10"]) in (0, 1)
    err = capsys.readouterr().err
    assert "--element-size 30um = 12.000 voxels of level 0: using 12 (30 micrometer)" in err
    assert "= 4:36,4:36,4:36 in level-0 voxels" in err
    assert "(+2.5, +1.25, -1.25 micrometer)" in err  # <U> times 2.5 um, rounded by %.4g
    res = chunkdic.open_result(out)
    assert res.info["roi"] == [[8, 32]] * 3  # 4:36 (32 voxels) trimmed to 2 whole elements of 12, centred
    assert main(["strain", str(out), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["element_size_physical"] == [30.0, 30.0, 30.0] and s["unit"] == "micrometer"
    assert main(["export", str(out), "--csv", str(tmp_path / "n.csv"), "--vtk", str(tmp_path / "m.vtu")]) == 0
    table = pd.read_csv(tmp_path / "n.csv")
    assert np.allclose(table["Uz_physical"], 2.5 * table["Uz"], rtol=1e-7)
    assert np.allclose(table["x_physical"], 2.5 * table["x"], rtol=1e-7)
    side = json.loads((tmp_path / "n.csv.json").read_text())
    assert side["columns"]["Ux_physical"] == "micrometer" and side["columns"]["Ux"] == "voxel, level 0"
    import meshio

    m = meshio.read(tmp_path / "m.vtu")
    assert np.allclose(m.point_data["displacement_physical"], 2.5 * m.point_data["displacement"])
