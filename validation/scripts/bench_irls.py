"""The robust reweighting of the penalty in the engine, against the plain penalty.

Usage::

    python validation/scripts/bench_irls.py --pairs DIR [DIR ...] --cases band slip --spacings 8 \
        --offsets 0 2 4 6 --json out.json

For each pair (the 100³ seed-1 pairs of ``bench_vs_aldvc.py``, found by name in
the ``--pairs`` directories: ``<case>-100-<specimen>-uint16-n0.02-s1[-offN]``), runs
:func:`chunkdic.correlate` in this process at each ``--spacings`` ℓ with each of
``--settings`` (default: ``plain`` = ``regularization_reweights=0``, the penalty before the
reweighting, and ``default`` = the defaults of this checkout) and scores the field as
``bench_vs_aldvc.py``'s table does: between the nodes, trilinear on the node grid, on the
voxels common to both tools (≥ ℓ from the faces and inside al-dvc's node hull, the
``common_hull`` of the al-dvc record), RMS of the vector error (σ pooled for the translation
``noise``).

al-dvc is not run: its figures are the same from run to run (same scans, same
code; docs/engine.md), so the ratio is taken against the records (``--aldvc-record``
for offset 0, ``--aldvc-offset-record N=PATH`` for the others).

A run whose reweighting freed no term is the plain run exactly (the same length chosen, the
same solves: the only extra work is one linearised solve whose CG reference is restored);
``--skip-identical`` then reuses the default run's figures for ``plain`` instead of running it
again (marked ``"same": true``).
Scans and results are never written into the pair directories (the results stay in memory).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

RECORDS = Path(__file__).resolve().parent / "records"


def pair_dir(dirs, case, specimen, offset, n=100) -> Path:
    tag = f"{case}-{n}-{specimen}-uint16-n0.02-s1" + (f"-off{offset:g}" if offset else "")
    for d in dirs:
        if (Path(d) / tag / "field.json").exists():
            return Path(d) / tag
    raise SystemExit(f"no pair {tag} in {dirs}")


def aldvc_figures(path: Path) -> dict:
    """(case/specimen, ell) -> al-dvc's ``rms_common`` / ``sigma_common`` and the common hull."""
    out = {}
    for r in json.loads(Path(path).read_text())["results"]:
        a, c = r.get("al-dvc") or {}, r.get("chunkdic") or {}
        if "rms_common" in a:
            out[r["case"], r["ell"]] = {"rms": a["rms_common"], "sigma": a["sigma_common"],
                                        "hull": a.get("common_hull") or c.get("common_hull")}
    return out


def score(res, field, shape, ell, hull) -> dict:
    from bench_vs_aldvc import _crop_grid, _to_grid

    from chunkdic.analysis.scoring import score_between_nodes

    scale = float(res.info.get("scale", 1))
    points = res.node_coords.reshape(3, -1) * scale + (scale - 1) / 2
    u = res.displacement.reshape(3, -1) * scale
    axes, grid = _to_grid(points, u)
    s = score_between_nodes(*_crop_grid(axes, grid, hull), field, shape, ell)
    return {"rms": s.rms, "sigma": s.sigma}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", nargs="+", required=True)
    ap.add_argument("--cases", nargs="+", default=["band", "slip"])
    ap.add_argument("--specimen", nargs="+", default=["grains", "concrete"])
    ap.add_argument("--spacings", nargs="+", type=int, default=[8])
    ap.add_argument("--offsets", nargs="+", type=float, default=[0.0])
    ap.add_argument("--settings", nargs="+", default=['plain={"regularization_reweights": 0}', "default={}"],
                    help="NAME=JSON keywords of chunkdic.correlate")
    ap.add_argument("--aldvc-record", default=str(RECORDS / "bench_vs_aldvc_100_session27.json"))
    ap.add_argument("--aldvc-offset-record", nargs="*", default=[
        f"{k}={RECORDS / f'bench_vs_aldvc_100_issue20_offset{k}.json'}" for k in (2, 4, 6)])
    ap.add_argument("--skip-identical", action="store_true",
                    help="reuse the default run for 'plain' when the reweighting freed nothing")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()

    import importlib

    import chunkdic
    from chunkdic.synth import synthetic

    importlib.import_module("chunkdic.synth.shear")
    peers = {0.0: aldvc_figures(Path(args.aldvc_record))}
    for item in args.aldvc_offset_record:
        k, _, path = item.partition("=")
        peers[float(k)] = aldvc_figures(Path(path))
    settings = [(s.partition("=")[0], json.loads(s.partition("=")[2] or "{}")) for s in args.settings]
    rows = []
    print("# case specimen offset ell | " + " | ".join(f"{n}: error (ratio) length status freed wall" for n, _ in
                                                     settings), flush=True)
    for case in args.cases:
        for specimen in args.specimen:
            for offset in args.offsets:
                d = pair_dir(args.pairs, case, specimen, offset)
                field = synthetic.load_field(d)
                for ell in args.spacings:
                    peer = peers.get(offset, {}).get((f"{case}/{specimen}", ell))
                    hull = peer["hull"] if peer else [[ell, 99 - ell]] * 3
                    key = "sigma" if case == "noise" else "rms"
                    row = {"case": case, "specimen": specimen, "offset": offset, "ell": ell,
                           "aldvc": peer[key] if peer else None, "hull": hull}
                    order = sorted(settings, key=lambda s: s[0] != "default")  # the default first
                    for name, options in order:
                        if (args.skip_identical and name == "plain" and "default" in row
                                and row["default"]["freed_terms"] == 0):
                            row[name] = dict(row["default"], same=True)
                            continue
                        t0 = time.perf_counter()
                        res = chunkdic.correlate(str(d / "ref.zarr"), str(d / "def.zarr"), element_size=ell,
                                                 **options)
                        wall = time.perf_counter() - t0
                        reg = res.info.get("regularization") or {}
                        err = score(res, field, (100,) * 3, ell, hull)[key]
                        row[name] = {"error": err, "ratio": err / peer[key] if peer else None,
                                     "length": reg.get("length"), "status": res.info.get("status"),
                                     "freed_terms": reg.get("freed_terms", 0), "wall": wall,
                                     "iterations": int(np.sum(res.history["level"] == res.info["level"]))}
                    rows.append(row)
                    cells = []
                    for name, _ in settings:
                        r = row[name]
                        ratio = f"{r['ratio']:.2f}" if r["ratio"] is not None else "-"
                        length = f"{r['length']:.1f}" if r["length"] is not None else "-"
                        cells.append(f"{r['error']:.4f} ({ratio}) {length} {r['status']} {r['freed_terms']}"
                                     f" {r['wall']:.1f}s" + (" same" if r.get("same") else ""))
                    print(f"{case} {specimen} {offset:g} {ell} | " + " | ".join(cells), flush=True)
                    if args.json:
                        Path(args.json).write_text(json.dumps({"argv": sys.argv[1:], "rows": rows}, indent=1))
    _summary(rows, [n for n, _ in settings])
    return 0


def _summary(rows, names) -> None:
    """Mean ratio over offsets per case and specimen (the band and slip table)."""
    groups = {}
    for r in rows:
        groups.setdefault((r["case"], r["specimen"], r["ell"]), []).append(r)
    for (case, specimen, ell), rs in groups.items():
        if len(rs) < 2:
            continue
        means = {n: float(np.mean([r[n]["ratio"] for r in rs if r[n]["ratio"] is not None])) for n in names}
        print(f"# mean ratio over offsets {case} {specimen} ell {ell}: "
              + ", ".join(f"{n} {v:.2f}" for n, v in means.items() if math.isfinite(v)), flush=True)


if __name__ == "__main__":
    sys.exit(main())
