"""The same correlations with two versions of chunkdic: fields equal to round-off, and times.

A behaviour-preserving change of the code (a refactor) must leave every field where it was.
This script runs one set of correlations with the chunkdic found in a source tree
(``--base``: another checkout, e.g. ``git archive main | tar -x -C /tmp/base``, put first on
``PYTHONPATH`` of a child process) and with this checkout's, each in fresh processes, and
prints the largest ``|Δu|`` of each (voxels of the result's level; NaN where both are NaN):

- the 100³ cases of ``bench_vs_aldvc.py --cases wave24 wave32 slip band --sizes 100
  --spacings 8`` (grains and concrete, chunkdic's defaults, the same scans for both);
- a masked run (a cylinder mask of the grains band pair);
- a resumed run (interrupted by ``KeyboardInterrupt`` at the second iteration of level 0,
  then the same call again: it resumes from the checkpoint);
- a loading series of three scans (``mode="both"``: every step field compared).

``--time`` adds the wall time and the CPU seconds of a 300³ correlation (grains band,
ℓ = 12) for each version, alternated, ``--repeats`` times (medians printed; the machine's
load moves the wall times much more than the CPU seconds); ``--time-only`` runs that alone.

The other version's dump (``WORKDIR/base``) is reused when it is there.

Usage::

    git archive main | tar -x -C /tmp/method-main
    python benchmarks/compare_fields.py --base /tmp/method-main --workdir /tmp/method-cmp [--time]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent.parent / "validation" / "scripts"  # bench_vs_aldvc.py
CASES = ("wave24", "wave32", "slip", "band")
SPECIMENS = ("grains", "concrete")


def _case_args(n: int):
    return argparse.Namespace(seed=1, dtype="uint16", noise=0.02, band_lateral=None, feature_offset=0.0)


def build_scans(workdir: Path, n: int) -> dict:
    """The scans of every case (written once, shared by both versions)."""
    sys.path.insert(0, str(HERE))
    from bench_vs_aldvc import build_case

    out = {}
    for specimen in SPECIMENS:
        for name in CASES:
            c = build_case(name, n, specimen, workdir / "scans", _case_args(n))
            out[f"{name}-{specimen}"] = (c.reference, c.deformed)
    return out


def _fields(res) -> dict:
    arrays = {"u": np.asarray(res.displacement, np.float64)}
    if res.uncertainty is not None:
        arrays["sigma_u"] = np.asarray(res.uncertainty, np.float64)
    return arrays


def dump(workdir: Path, out: Path) -> None:
    """Run every correlation with the chunkdic this process imports; save fields and facts."""
    import dask.config

    import chunkdic

    out.mkdir(parents=True, exist_ok=True)
    facts = {"chunkdic": chunkdic.__file__}
    scans = json.loads((workdir / "scans.json").read_text())
    saved = {}
    for name, (ref, dfm) in scans.items():
        res = chunkdic.correlate(ref, dfm, element_size=8)
        saved.update({f"{name}/{k}": v for k, v in _fields(res).items()})
        facts[name] = {"status": res.info["status"], "final_gap": res.info["final_gap"]}

    ref, dfm = scans["band-grains"]
    shape = chunkdic.open_scan(ref).shape(0)
    _, y, x = np.ogrid[: shape[0], : shape[1], : shape[2]]
    disc = (y - shape[1] / 2) ** 2 + (x - shape[2] / 2) ** 2 < (0.42 * shape[1]) ** 2
    mask = np.broadcast_to(disc, shape).astype(np.uint8)
    res = chunkdic.correlate(ref, dfm, element_size=8, mask=mask)
    saved.update({f"masked/{k}": v for k, v in _fields(res).items()})
    facts["masked"] = {"status": res.info["status"], "masked_nodes": res.info["masked_nodes"]}

    def interrupt(event):
        if event["stage"] == "iteration" and event["level"] == 0 and event["iteration"] == 1:
            raise KeyboardInterrupt

    scratch = out / "scratch"
    scratch.mkdir(exist_ok=True)
    target = out / "resumed.zarr"
    with dask.config.set({"chunkdic.scratch-directory": str(scratch)}):
        try:
            chunkdic.correlate(ref, dfm, element_size=8, output=target, overwrite=True, progress=interrupt)
            raise SystemExit("the run to resume was not interrupted")
        except KeyboardInterrupt:
            pass
        stages = []
        res = chunkdic.correlate(ref, dfm, element_size=8, output=target, progress=stages.append)
    if not any(e["stage"] == "resume" for e in stages):
        raise SystemExit("the second run did not resume")
    saved.update({f"resumed/{k}": v for k, v in _fields(res).items()})
    facts["resumed"] = {"status": res.info["status"]}

    series_scans = [scans["band-grains"][0], scans["wave24-grains"][1], scans["band-grains"][1]]
    ser = chunkdic.series(series_scans, out / "series.zarr", element_size=8, overwrite=True)
    for row in ser.rows:
        r = chunkdic.open_result(Path(ser.path) / row["group"])
        saved.update({f"series-{row['group']}/{k}": v for k, v in _fields(r).items()})
    facts["series"] = [dict(r) for r in ser.rows]
    np.savez(out / "fields.npz", **saved)
    (out / "facts.json").write_text(json.dumps(facts, indent=1, default=str))


def compare(a: Path, b: Path) -> float:
    """Print the largest |Δ| of every array of two dumps; return the overall largest."""
    fa, fb = np.load(a / "fields.npz"), np.load(b / "fields.npz")
    worst = 0.0
    if set(fa.files) != set(fb.files):
        print(f"different arrays: {sorted(set(fa.files) ^ set(fb.files))}")
        worst = np.inf
    for k in sorted(set(fa.files) & set(fb.files)):
        x, y = fa[k], fb[k]
        if x.shape != y.shape or not np.array_equal(np.isnan(x), np.isnan(y)):
            print(f"{k:40s} shape or NaN pattern differs")
            worst = np.inf
            continue
        d = float(np.nanmax(np.abs(x - y))) if np.isfinite(x).any() else 0.0
        worst = max(worst, d)
        print(f"{k:40s} max |Δ| = {d:.3e}")
    return worst


def _child(tree: Path | None, *argv: str, env_extra: dict | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    if tree is not None:
        env["PYTHONPATH"] = str(tree) + os.pathsep + env.get("PYTHONPATH", "")
        env["NUMBA_CACHE_DIR"] = str(Path("/tmp") / f"{tree.name}-numba")
    env.update(env_extra or {})
    out = subprocess.run([sys.executable, __file__, *argv], env=env, text=True, capture_output=True)
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed:\n{out.stderr[-3000:]}")
    return out


def time_one(ref: str, dfm: str, ell: int) -> None:
    import chunkdic
    import chunkdic.engine.driver  # noqa: F401  imported before the clock starts

    t0, c0 = time.perf_counter(), time.process_time()
    res = chunkdic.correlate(ref, dfm, element_size=ell)
    print(json.dumps({"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0, "status": res.info["status"],
                      "chunkdic": chunkdic.__file__}))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--base", type=Path, help="source tree of the other version (its chunkdic/ inside)")
    p.add_argument("--workdir", type=Path, default=Path("/tmp/compare-fields"))
    p.add_argument("--time", action="store_true", help="also time a 300³ run of each version")
    p.add_argument("--time-only", action="store_true", help="only the 300³ times (no fields compared)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--size", type=int, default=100)
    p.add_argument("--dump", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--time-one", nargs=3, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.dump:
        dump(args.workdir, args.dump)
        return 0
    if args.time_one:
        time_one(args.time_one[0], args.time_one[1], int(args.time_one[2]))
        return 0
    if args.base is None:
        p.error("--base is required")
    args.workdir.mkdir(parents=True, exist_ok=True)
    scans = build_scans(args.workdir, args.size)
    (args.workdir / "scans.json").write_text(json.dumps(scans))
    runs = {"base": args.base.resolve(), "this": None}
    worst = 0.0
    for name, tree in ({} if args.time_only else runs).items():
        t0 = time.perf_counter()
        if name == "base" and (args.workdir / name / "fields.npz").exists():  # the other version's, kept
            print(f"# base: the dump in {args.workdir / name} reused", flush=True)
            continue
        shutil.rmtree(args.workdir / name, ignore_errors=True)
        _child(tree, "--workdir", str(args.workdir), "--dump", str(args.workdir / name))
        facts = json.loads((args.workdir / name / "facts.json").read_text())
        print(f"# {name}: chunkdic from {facts['chunkdic']}, {time.perf_counter() - t0:.0f} s", flush=True)
    if not args.time_only:
        worst = compare(args.workdir / "base", args.workdir / "this")
        print(f"largest |Δ| over every field: {worst:.3e} voxel ({'within' if worst <= 1e-9 else 'BEYOND'} 1e-9)")
    if args.time or args.time_only:
        sys.path.insert(0, str(HERE))
        from bench_vs_aldvc import build_case

        c = build_case("band", 300, "grains", args.workdir / "scans", _case_args(300))
        times = {name: {"wall": [], "cpu": []} for name in runs}
        for _ in range(args.repeats):
            for name, tree in runs.items():
                out = json.loads(_child(tree, "--time-one", c.reference, c.deformed, "12").stdout.strip().splitlines()[-1])
                for key in ("wall", "cpu"):
                    times[name][key].append(out[key])
        for name, t in times.items():
            for key, what in (("wall", "wall"), ("cpu", "CPU seconds of the process, every thread")):
                print(f"300³ grains band, ℓ = 12, {name}, {what}: median {statistics.median(t[key]):.2f} s of "
                      f"{', '.join(f'{v:.2f}' for v in t[key])}")
    return 0 if worst <= 1e-9 else 1


if __name__ == "__main__":
    sys.exit(main())
