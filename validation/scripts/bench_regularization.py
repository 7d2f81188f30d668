"""Regularisation on CT-like specimens: accuracy against ℓ and ℓ_reg, and its cost in the solve.

Usage::

    python validation/scripts/bench_regularization.py [--size 96] [--spacings 16 12 8 6 4]
                                              [--lengths 1 2 4 8] [--specimen grains]
                                              [--workdir DIR] [--json PATH]

On the standard cases of :func:`chunkdic.synth.synthetic.standard_case` (``noise``: a (0.5, 0.5,
0.5) translation with independent CT noise in each scan; ``band``: the −8 % compression
band), for every element size ``ℓ``: the correlation without regularisation and with the
default (curvature Tikhonov, automatic length), and at ``ℓ = 8`` with fixed lengths
``--lengths`` × ℓ. Prints per run: status, σ (noise case) or RMS error (band case) scored
by :func:`chunkdic.score_displacement` (nodes ≥ ℓ from the faces), the chosen length and
the L-curve corner (voxels; the automatic choice is run as a full sweep here so that the
corner is known, where the engine bisects), the noise correlation factor ``κ``, and for the finest level
the mean CG iterations and mean solve time per pass, from the engine's progress events.
The solve's cost ratio (regularised / unregularised, same ℓ) has a target
(≤ 2×). Memory: the regulariser is applied matrix-free by element loops on the client
(no stored matrix), so it adds only the CG's work vectors; the peak traced by
``tracemalloc`` in the client during the run is printed too (threads scheduler: the
tasks' arrays are included, so it is an upper bound on the client's share).
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import tracemalloc
from pathlib import Path



def _sweeping_choice() -> None:
    """Make the engine's automatic choice solve all candidates, so the L-curve corner is known.

    The engine bisects (a handful of solves); the corner needs the whole curve. Same
    chosen length either way (the misfit is monotone in the length).
    """
    import functools

    from chunkdic.method import length as steps
    from chunkdic.solve import regchoice

    steps.choose_length = functools.partial(regchoice.choose_length, sweep=True)


def run(pair: dict, ell: int, **options) -> dict:
    import chunkdic

    events: list[dict] = []
    tracemalloc.start()
    res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=ell, progress=events.append,
                             **options)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    size = pair["shape"][0] if "shape" in pair else chunkdic.open_scan(pair["reference"]).shape(0)[0]
    truth = pair["field"].displacement(*res.node_coords)
    score = chunkdic.score_displacement(res.node_coords, res.displacement, truth, (size,) * 3, ell)
    finest = [e for e in events if e.get("stage") == "iteration" and e.get("level") == res.info.get("level", 0)
              and e.get("cg_iterations") is not None]
    choice = next((e for e in events if e.get("stage") == "regularization"), {})
    reg = res.info["regularization"]
    return {
        "ell": ell, "options": options, "status": res.info["status"], "sigma": float(score.sigma),
        "rms": float(score.rms), "length": reg["length"], "l_curve_length": choice.get("l_curve_length"),
        "kappa": (res.info.get("noise") or {}).get("kappa"),
        "cg_iterations": statistics.mean(e["cg_iterations"] for e in finest) if finest else None,
        "solve_seconds": statistics.median(e["solve_seconds"] for e in finest) if finest else None,
        "passes": len(finest), "traced_peak_mb": peak / 2**20,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--spacings", type=int, nargs="+", default=[16, 12, 8, 6, 4])
    ap.add_argument("--lengths", type=float, nargs="+", default=[1, 2, 4, 8],
                    help="fixed regularisation lengths at ell = 8, in element sizes")
    ap.add_argument("--specimen", default="grains", choices=("grains", "concrete"))
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--json", default=None, help="write the rows here")
    args = ap.parse_args()

    from chunkdic.synth import synthetic

    _sweeping_choice()
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench-reg-"))
    rows = []
    print(f"{'case':6} {'ell':>3} {'regularisation':>22} {'status':>14} {'sigma':>8} {'rms':>8} {'l_reg':>7} "
          f"{'corner':>7} {'kappa':>6} {'CG it':>6} {'solve s':>8} {'peak MB':>8}")
    for case in ("noise", "band"):
        name = "shift" if case == "noise" else "band"
        target = work / f"{args.specimen}-{name}-{args.size}"
        pair = synthetic.standard_case(target, name, args.size, specimen=args.specimen, noise=0.02)
        variants = [(ell, {"regularization": "none"}) for ell in args.spacings]
        variants += [(ell, {}) for ell in args.spacings]
        variants += [(8, {"regularization_length": 8 * k}) for k in args.lengths]
        for ell, options in variants:
            row = run(pair, ell, **options)
            row["case"] = case
            rows.append(row)
            label = options.get("regularization", "tikhonov " + (
                f"fixed {options['regularization_length']:g}" if "regularization_length" in options else "auto"))
            fmt = lambda v, spec: "-" if v is None else format(v, spec)  # noqa: E731
            print(f"{case:6} {ell:3d} {label:>22} {row['status']:>14} {row['sigma']:8.4f} {row['rms']:8.4f} "
                  f"{fmt(row['length'], '7.1f')} {fmt(row['l_curve_length'], '7.1f')} {fmt(row['kappa'], '6.1f')} "
                  f"{fmt(row['cg_iterations'], '6.1f')} {fmt(row['solve_seconds'], '8.3f')} "
                  f"{row['traced_peak_mb']:8.1f}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
