"""Loading series (``chunkdic.series``, ``chunkdic series``) and ``correlate --init``.

A 3-scan series of a 48³ synthetic foam (float32, elements of 8 voxels): scan 1 is scan 0
under a known affine field (−1 % along z, +0.3 % laterally, a drift), scan 2 under twice
that field. Truths are the analytic fields ``u_0→k``; the direct correlation of scan 0
with scan 2 (rigid start) is the independent check of the cumulative fields.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

import chunkdic
from chunkdic.cli.app import main
from chunkdic.method.study_events import SeriesStep
from chunkdic.synth import synthetic

# end-to-end runs (whole commands, clusters, kills): `pytest -m 'not slow'` leaves them out
pytestmark = pytest.mark.slow

N, ELL = 48, 8
OPTIONS = dict(element_size=ELL, regularization="none")  # no automatic length choice: fast, same objective
C = (N - 1) / 2


def field(k: int):
    """``u_0→k``: axial compression, lateral expansion, a slow drift of the specimen."""
    e = -0.01 * k
    return synthetic.Affine(matrix=((e, 0, 0), (0, -0.3 * e, 0), (0, 0, -0.3 * e)), center=(C, C, C),
                            translation=(0.4 * k, -0.25 * k, 0.15 * k))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("series")
    scans = []
    for k in range(3):
        p = d / f"scan{k}.zarr"
        lazy = synthetic.as_dask((N,) * 3, chunks=N, field=None if k == 0 else field(k), seed=5,
                                 which="reference" if k == 0 else "deformed", dtype="float32")
        chunkdic.write_scan(p, lazy)
        scans.append(p)
    s = chunkdic.series(scans, d / "series.zarr", **OPTIONS)
    direct = chunkdic.correlate(scans[0], scans[2], **OPTIONS)
    return {"dir": d, "scans": scans, "series": s, "direct": direct}


def inner(u):
    """Nodes at least one element from the ROI faces (docs/engine.md, comparing fields)."""
    return u[:, 1:-1, 1:-1, 1:-1]


def test_cumulative_equals_direct_and_truth(run):
    s, direct = run["series"], run["direct"]
    assert [(r["group"], r["status"]) for r in s.rows] == [
        ("steps/001-incremental", "converged"), ("steps/002-incremental", "converged"),
        ("composed/002", "composed"), ("steps/002-cumulative", "converged")]
    cum = s.cumulative[2].displacement
    assert np.abs(cum - direct.displacement).max() < 0.01  # measured: 2e-4
    composed = chunkdic.open_result(run["dir"] / "series.zarr" / "composed" / "002").displacement
    assert np.abs(composed - direct.displacement).max() < 0.03  # measured 0.019 (at a corner node)
    assert np.abs(inner(composed - direct.displacement)).max() < 0.01
    X = direct.node_coords
    for u in (cum, composed):
        err = inner(u - field(2).displacement(*X))
        assert np.sqrt((err**2).mean()) < 0.01 and np.abs(err).max() < 0.03
    # the table: mean displacement and strain of the composed truth
    last = s.rows[-1]
    assert last["pair"] == "0→2" and last["eps_zz"] == pytest.approx(-0.02, abs=5e-4)
    assert last["mean"] == pytest.approx(list(np.mean(field(2).displacement(*X), axis=(1, 2, 3))), abs=0.01)
    import zarr

    attrs = zarr.open_group(str(run["dir"] / "series.zarr"), mode="r").attrs["chunkdic"]
    assert attrs["kind"] == "series" and attrs["complete"] and len(attrs["summary"]) == 4
    # each step records the result it started from
    step2 = chunkdic.open_result(run["dir"] / "series.zarr" / "steps" / "002-cumulative")
    assert step2.info["init"]["path"].endswith("composed/002")
    assert step2.info["settings"]["init"]["displacement_sha256"] == step2.info["init"]["displacement_sha256"]


def increment(x: np.ndarray) -> np.ndarray:
    """``u_1→2`` at positions ``x`` (3, ...) of scan 1, from the analytic fields:
    ``u_1→2(X + u_0→1(X)) = u_0→2(X) - u_0→1(X)``, ``X`` by inverting the affine ``u_0→1``."""
    X = field(1).inverse(*x)
    return field(2).displacement(*X) - field(1).displacement(*X)


def test_real_increment_matches_its_known_field(run):
    """The increment 1→2, started from the increment 0→1 (the same motion again, which its
    start gap prefers to no motion and to a translation), against ``u_1→2`` computed from the
    analytic fields, at scan 1's nodes."""
    inc = chunkdic.open_result(run["dir"] / "series.zarr" / "steps" / "002-incremental")
    assert inc.converged
    err = inner(inc.displacement - increment(inc.node_coords))
    assert np.sqrt((err**2).mean()) < 0.01 and np.abs(err).max() < 0.03
    # not a zero field passing for the increment: it moves by 0.4-0.6 voxel, strains by -1 %
    assert np.abs(inner(increment(inc.node_coords))).max() > 0.4


def test_identical_last_scans_give_a_zero_increment(tmp_path, capsys):
    """``chunkdic series ref def def`` on the 48³ pair of ``chunkdic synth`` (a translation of
    (2.3, -1.4, 0.7) voxel), as in the issue-24 sweep: the increment 1→2 between identical
    scans started from the increment 0→1 (gap 13 % instead of 0.001 % with no motion) and
    stalled at 0.4-0.6 % with 0.01-0.02 voxel of spurious motion, exit 1. The start is now
    chosen by its gap: no motion wins, the increment converges to zero at every node, and the
    cumulative 0→2 field is the translation."""
    assert main(["synth", str(tmp_path / "pair"), "--shape", "48", "-q"]) == 0
    ref, dfm = str(tmp_path / "pair" / "ref.zarr"), str(tmp_path / "pair" / "def.zarr")
    out = tmp_path / "same.zarr"
    code = main(["series", ref, dfm, dfm, "-o", str(out), "-l", str(ELL)])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "level 0: start no motion (lowest gap of earlier field" in err
    s = chunkdic.open_series(out)
    assert [(r["group"], r["status"]) for r in s.rows] == [
        ("steps/001-incremental", "converged"), ("steps/002-incremental", "converged"),
        ("composed/002", "composed"), ("steps/002-cumulative", "converged")]
    inc = chunkdic.open_result(out / "steps" / "002-incremental")
    assert np.abs(inc.displacement).max() < 1e-3  # every node, the ROI's faces included
    t = np.array([2.3, -1.4, 0.7])[:, None, None, None]
    assert np.abs(inner(s.cumulative[2].displacement - t)).max() < 0.01


def test_resume_after_a_kill_skips_finished_steps(run, tmp_path):
    out = tmp_path / "series.zarr"

    def killer(event):
        if event.get("group") == "002-incremental" and event.get("stage") == "iteration" and event["iteration"] == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        chunkdic.series(run["scans"], out, progress=killer, **OPTIONS)
    with pytest.raises(chunkdic.InputError, match="incomplete"):
        chunkdic.open_result(out / "steps" / "002-incremental")
    events = []
    s = chunkdic.series(run["scans"], out, progress=events.append, **OPTIONS)
    assert [r["run"] for r in s.rows] == ["done before", "resumed", "computed", "computed"]
    assert any(e["stage"] == "resume" and e["group"] == "002-incremental" for e in events)
    # one SeriesStep per step, saying what the kill left; no correlation event from the skipped step
    assert [(e.group, e.run) for e in events if isinstance(e, SeriesStep)] == [
        ("001-incremental", "done before"), ("002-incremental", "resumed"), ("002-cumulative", "computed")]
    assert {e.group for e in events if not isinstance(e, SeriesStep)} == {"002-incremental", "002-cumulative"}
    for k, ref in run["series"].cumulative.items():  # identical to the uninterrupted series
        np.testing.assert_allclose(s.cumulative[k].displacement, ref.displacement, rtol=0, atol=1e-9)
    # done: the same series again has nothing to do (its fields as they are); other settings are refused
    mtimes = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    said = []
    assert [r["run"] for r in chunkdic.series(run["scans"], out, progress=said.append, **OPTIONS).rows] == \
        [r["run"] for r in s.rows]
    assert [e["stage"] for e in said] == ["complete"] and {p: p.stat().st_mtime_ns for p in out.rglob("*")} == mtimes
    with pytest.raises(chunkdic.InputError, match="complete loading series"):
        chunkdic.series(run["scans"], out, element_size=12, regularization="none")
    with pytest.raises(chunkdic.InputError, match="other scans or settings"):
        out2 = tmp_path / "other.zarr"
        with pytest.raises(KeyboardInterrupt):
            chunkdic.series(run["scans"], out2, progress=killer, **OPTIONS)
        chunkdic.series(run["scans"], out2, element_size=12, regularization="none")


def test_init_from_its_own_result_converges_at_once(run, tmp_path):
    own = run["dir"] / "series.zarr" / "steps" / "001-incremental"
    first = chunkdic.open_result(own)
    res = chunkdic.correlate(run["scans"][0], run["scans"][1], init=own, output=tmp_path / "again.zarr", **OPTIONS)
    finest = res.history["level"] == res.info["level"]
    assert res.info["levels"] == [0] and res.converged
    assert finest.sum() - 1 <= 2  # Gauss-Newton updates at the finest level (measured: 1)
    # within the run's own tolerance (1e-3 voxel, the engine's promise): the first run's last
    # applied step was 7.6e-4 since the affine start (4.4e-4 before), so its field is converged to
    # that; the re-run moved one corner node by 1.6e-4 (before: 8.5e-5 against a 1e-4 bound)
    np.testing.assert_allclose(res.displacement, first.displacement, rtol=0, atol=1e-3)
    assert res.info["init"]["path"] == str(own.resolve())
    # another element size and a coarser level: evaluated at the new nodes, in that level's voxels
    coarse = chunkdic.correlate(run["scans"][0], run["scans"][1], init=own, level=1, element_size=6,
                                regularization="none")
    X0 = 2 * coarse.node_coords + 0.5  # level-1 node positions in level-0 voxels
    truth = field(1).displacement(*X0) / 2
    assert np.abs(inner(coarse.displacement - truth)).max() < 0.03


def _refused(argv, capsys, match: str) -> None:
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse's own refusals (still one line, exit 2)
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("chunkdic") and " error: " in lines[0] and match in lines[0], err


def _nothing_at(out: Path) -> None:
    assert not out.exists()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}")]


def test_bad_inputs_exit_2_nothing_written(run, tmp_path, capsys):
    s0, s1, _ = run["scans"]
    out = tmp_path / "s.zarr"
    small = tmp_path / "small.zarr"
    chunkdic.write_scan(small, synthetic.as_dask((40,) * 3, chunks=40, seed=5, dtype="float32"))
    base = ["-o", out, "--element-size", ELL]
    _refused(["series", s0, *base], capsys, "at least 2 scans")
    _refused(["series", s0, tmp_path / "nope.zarr", *base], capsys, "does not exist")
    _refused(["series", s0, s1, small, *base], capsys, "must have the reference's shape")
    _refused(["series", s0, s1, *base, "--incremental", "--cumulative"], capsys, "not allowed with")
    _nothing_at(out)
    c = ["correlate", s0, s1, "-o", out, "--element-size", ELL]
    _refused([*c, "--init", s1], capsys, "is a chunkdic scan, not a result")
    _refused([*c, "--init", tmp_path / "nope.zarr"], capsys, "does not exist")
    other = tmp_path / "other.zarr"
    chunkdic.correlate(small, small, element_size=ELL, coarsest=0, regularization="none", output=other)
    _refused([*c, "--init", other], capsys, "computed on one of shape (40, 40, 40)")
    _refused([*c, "--init", out.parent], capsys, "not a chunkdic result")
    _nothing_at(out)


def test_cli_incremental_series(run, tmp_path, capsys):
    out = tmp_path / "inc.zarr"
    code = main([str(a) for a in ["series", *run["scans"], "-o", out, "--element-size", ELL, "--incremental",
                                  "--regularization", "none"]])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert captured.out.strip() == str(out)
    assert "0→2    composed" in captured.err and "done before" not in captured.err
    assert sorted(os.listdir(out / "steps")) == ["001-incremental", "002-incremental", "zarr.json"]
    composed = chunkdic.open_result(out / "composed" / "002")
    err = inner(composed.displacement - field(2).displacement(*composed.node_coords))
    assert np.sqrt((err**2).mean()) < 0.01
    shutil.rmtree(out)


def test_open_series_reads_the_summary_and_fields(run):
    s = chunkdic.open_series(run["dir"] / "series.zarr")
    assert s.rows == run["series"].rows
    np.testing.assert_array_equal(s.cumulative[2].displacement, run["series"].cumulative[2].displacement)
    with pytest.raises(chunkdic.InputError, match="not a chunkdic loading series"):
        chunkdic.open_series(run["scans"][0])


def test_series_takes_lengths_in_physical_units(tmp_path, capsys):
    """``series -l 30um --roi ... --roi-unit um``: converted as ``correlate`` does, with the
    first scan's voxel size (2.5 um: 12 voxels, ROI 4:36 trimmed to 2 elements, 8:32)."""
    pair = synthetic.synthesize(tmp_path / "s", (40, 40, 40), field=synthetic.Translation((1.0, 0.5, -0.5)),
                                seed=2, dtype="float32", voxel_size=2.5, unit="um")
    out = tmp_path / "series.zarr"
    assert main(["series", str(pair["reference"]), str(pair["deformed"]), "-o", str(out), "-l", "30um",
                 "--roi", "10:90,10:90,10:90", "--roi-unit", "um", "--regularization", "none",
                 "--max-iterations", "10"]) in (0, 1)
    err = capsys.readouterr().err
    assert "--element-size 30um = 12.000 voxels of level 0: using 12 (30 micrometer)" in err
    assert "= 4:36,4:36,4:36 in level-0 voxels" in err
    step = chunkdic.open_result(out / "steps" / "001-incremental")
    assert step.info["element_size"] == 12 and step.info["roi"] == [[8, 32]] * 3
    _refused(["series", pair["reference"], pair["deformed"], "-o", tmp_path / "x.zarr", "-l", "30 parsecs"],
             capsys, "unknown length unit")
