"""Statuses at small elements: a false "stalled", case by case.

The 24-voxel shear wave of ``bench_vs_aldvc.py`` (``Ux = 0.5 sin(2π (Z - c) / T)``, ``c``
the volume's centre) on the CT-like specimens with independent noise 0.02 in each scan,
correlated with chunkdic's defaults at a small element size (ℓ = 6), for several sizes and
noise seeds. Prints, per pair, the status, the between-node RMS error against the analytic wave
(:func:`chunkdic.analysis.scoring.score_between_nodes`, every voxel ≥ ℓ from the faces),
the finest level's passes, the chosen regularisation length and the nodes flagged weak.

Runs with whatever ``chunkdic`` is on ``PYTHONPATH``: point it at an older tree to compare
the stopping rules on the very same pairs (the pairs are kept in ``--workdir``)::

    python validation/scripts/bench_noise_stop.py --sizes 64 72 80 96 --workdir /tmp/noise-stop
    PYTHONPATH=/path/to/older python validation/scripts/bench_noise_stop.py --sizes 64 --workdir /tmp/noise-stop

docs/engine.md, "Iterations and stopping", states the stall rule it measured.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

RECORDS = Path(__file__).parent / "records"


def make_pair(root: Path, specimen: str, n: int, seed: int, period: float) -> tuple[dict, object]:
    """The wave pair (written once under ``root``) and its field."""
    from chunkdic.synth import synthetic

    field = synthetic.Wave(period=period, amplitude=0.5, phase=(n - 1) / 2.0)
    out = root / f"wave{period:g}-{n}-{specimen}-s{seed}"
    if not (out / "field.json").exists():
        synthetic.synthesize(out, (n,) * 3, field=field, specimen=specimen, seed=seed, dtype="uint16",
                             noise=0.02, overwrite=True)
    return {"reference": str(out / "ref.zarr"), "deformed": str(out / "def.zarr")}, field


def run(pair: dict, field, n: int, ell: int) -> dict:
    """One correlation with the defaults, scored between the nodes."""
    import chunkdic
    from chunkdic.analysis.scoring import score_between_nodes

    t0 = time.perf_counter()
    res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=ell)
    wall = time.perf_counter() - t0
    scale = float(res.info.get("scale", 1))
    axes = [np.unique(c) * scale + (scale - 1) / 2 for c in res.node_coords]
    score = score_between_nodes(axes, res.displacement * scale, field, (n,) * 3, ell)
    h = res.history
    fine = (np.asarray(h["level"]) == res.info["level"]) & (np.asarray(h["iteration"]) >= 0)
    return {"status": res.info["status"], "rms_between": score.rms, "passes": int(fine.sum()),
            "reg_length": (res.info.get("regularization") or {}).get("length"),
            "weak_nodes": res.info.get("weak_nodes"), "nodes": int(np.prod(res.displacement.shape[1:])),
            "final_gap": res.info["final_gap"], "wall": wall}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", type=int, default=[64, 72, 80, 96])
    ap.add_argument("--specimens", nargs="+", default=["grains", "concrete"], choices=["grains", "concrete"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--ell", type=int, default=6)
    ap.add_argument("--period", type=float, default=24.0)
    ap.add_argument("--workdir", help="pairs (kept between runs; default: a new temporary directory)")
    ap.add_argument("--record", help="write validation/scripts/records/bench_noise_stop_NAME.json")
    args = ap.parse_args(argv)
    if min(args.sizes) < 32 or args.ell < 4 or args.period <= 0:
        ap.error("--sizes must be >= 32, --ell >= 4, --period > 0")
    root = Path(args.workdir or tempfile.mkdtemp(prefix="noise-stop-"))
    rows = []
    print("| size | specimen | seed | status | between-node RMS | passes | ℓ_reg | weak nodes | wall s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for n in args.sizes:
        for specimen in args.specimens:
            for seed in args.seeds:
                pair, field = make_pair(root, specimen, n, seed, args.period)
                r = run(pair, field, n, args.ell)
                rows.append({"size": n, "specimen": specimen, "seed": seed, "ell": args.ell, **r})
                reg = f"{r['reg_length']:.1f}" if r["reg_length"] else "–"
                print(f"| {n} | {specimen} | {seed} | {r['status']} | {r['rms_between']:.4f} | {r['passes']} | "
                      f"{reg} | {r['weak_nodes']} of {r['nodes']} | {r['wall']:.1f} |", flush=True)
    if args.record:
        RECORDS.mkdir(exist_ok=True)
        path = RECORDS / f"bench_noise_stop_{args.record}.json"
        path.write_text(json.dumps({"argv": argv, "period": args.period, "rows": rows}, indent=1))
        print(f"record: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
