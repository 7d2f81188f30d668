"""Criteria for the automatic regularisation length, compared by measurement.

Usage::

    python validation/scripts/bench_reg_criteria.py capture --specimen grains --size 96 \
        --spacings 16 12 8 --workdir DIR
    python validation/scripts/bench_reg_criteria.py evaluate --workdir DIR [--json PATH]

``capture`` correlates each case (waves of period 24/32/48/64 voxels, amplitude 0.5, a
compression band, a shear slip, a translation; CT-like specimen, independent 2 % noise
in each scan) with the defaults up to the point where the engine chooses the length
(the finest level converged to the coarse tolerance, unregularised on that level) and
stores what the choice sees: the half stencil of ``M``, the field ``a``, ``b``,
``κ σ_r²`` and the node axes. ``evaluate`` then, on the client and for every candidate
length ``ℓ · 2^(k/2)``, solves the linearised regularised problem on the whole mesh
(``(M + λR) x = M a + b``: the first regularised Gauss–Newton step, which the following
passes change by less than the coarse tolerance) and scores ``x`` between the nodes
(trilinear on the node grid, every voxel ≥ ℓ from the faces, RMS vector error), then
applies every criterion of :mod:`chunkdic.solve.regchoice` to the same data and reports
the error of the length each one picks, with the best candidate (the oracle) beside it.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # validation/scripts/_capture.py, next to this file

CASES = ("wave24", "wave32", "wave48", "wave64", "band", "slip", "shift")


def field_of(case: str, n: int):
    from chunkdic.synth import synthetic
    from chunkdic.synth.ctpair import standard_field

    c = (n - 1) / 2
    if case.startswith("wave"):
        return synthetic.Wave(period=float(case[4:]), amplitude=0.5, phase=c)
    if case == "slip":
        return synthetic.Slip(center=c, jump=1.0, edge=3.0)
    return standard_field(case, (n, n, n))[0]


def capture(args) -> None:
    import chunkdic
    from _capture import capture_choice
    from chunkdic.synth import synthetic

    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    n = args.size
    for case in args.cases:
        fld = field_of(case, n)
        pair_dir = work / f"{args.specimen}-{case}-{n}"
        if not (pair_dir / "field.json").exists():
            synthetic.synthesize(pair_dir, (n,) * 3, field=fld, specimen=args.specimen, noise=0.02,
                                 overwrite=True)
        for ell in args.spacings:
            out = work / f"{args.specimen}-{case}-{n}-{ell}.npz"
            if out.exists():
                continue

            def save(problem, penalty, out=out):
                np.savez(out, **problem, n=n, field=json.dumps(fld.to_json()))

            seconds = capture_choice(lambda ell=ell: chunkdic.correlate(str(pair_dir / "ref.zarr"),
                                                                         str(pair_dir / "def.zarr"), element_size=ell),
                                     save)
            print(f"{case} {ell}: " + ("no choice made (not converged before the choice?)" if seconds is None
                                       else f"captured in {seconds:.1f} s"), flush=True)


def evaluate_one(path: Path) -> dict:
    from chunkdic.analysis.scoring import score_between_nodes
    from chunkdic.solve import regchoice
    from chunkdic.solve.cg import StencilSolver
    from chunkdic.solve.regularizer import Regularizer, plane_wave_weight
    from chunkdic.solve.stencil import stencil_matvec
    importlib.import_module("chunkdic.synth.shear")  # registers the wave and slip fields
    from chunkdic.synth.fields import Field

    d = np.load(path)
    half, a, b = d["half"], d["a"], d["b"]
    ell, scale, n = float(d["ell"]), float(d["scale"]), int(d["n"])
    kind, fld = str(d["kind"]), Field.from_json(json.loads(str(d["field"])))
    axes = [d["az"], d["ay"], d["ax"]]
    lengths = np.array([c * ell for c in regchoice.CANDIDATES])
    # the error of every candidate: linearised solve on the whole mesh, scored between the nodes
    solver = StencilSolver(half.copy())
    reg = Regularizer(kind, half.shape[:3], ell)
    matvec = lambda v: stencil_matvec(half, v)  # noqa: E731
    rhs = matvec(a) + b
    errors = []
    for L in lengths:
        solver.regularize(reg, plane_wave_weight(reg, matvec, L))
        x = solver.solve(rhs)[0]
        errors.append(score_between_nodes(axes, np.moveaxis(x, -1, 0) * scale, fld, (n,) * 3, ell * scale).rms)
    errors = np.array(errors)
    # every criterion on the same data (the engine's sub-meshes and solver settings)
    last = {"half": None}

    def solve_with(h, r, w, rr):
        if last["half"] is not h:
            last["half"], last["solver"] = h, StencilSolver(h.copy(), rtol=1e-5)
        last["solver"].regularize(r, w)
        return last["solver"].solve(rr)[0]

    t0 = time.perf_counter()
    ch = regchoice.choose_length(kind, half, ell, a, b, float(d["noise_variance"]), solve_with, sweep=True)
    sweep_seconds = time.perf_counter() - t0
    picks = apply_rules(ch.curves, float(d["kappa"]))
    return {"file": path.name, "ell": ell * scale, "lengths": (lengths * scale).tolist(), "errors": errors.tolist(),
            "picks": picks, "sweep_seconds": sweep_seconds, "kappa": float(d["kappa"])}


#: the criteria compared (per region, then the shortest over regions unless "-sum")
CRITERIA = ("discrepancy", "discrepancy-0.5", "discrepancy-0.25", "upre", "upre-sum", "gcv", "l-curve")


def apply_rules(curves: list[dict], kappa: float) -> dict:
    """Index picked by each criterion from the sweep's per-region curves."""
    from chunkdic.solve.regchoice import _corner

    picks = {}
    for rule in CRITERIA:
        per_region = []
        for c in curves:
            m, pen, budget = c["misfit"], c["penalty"], c["budget"]
            if rule.startswith("discrepancy"):
                tau = float(rule.split("-")[1]) if "-" in rule else 1.0
                per_region.append(int(np.flatnonzero(m <= tau * budget).max()))
            elif rule == "upre":
                per_region.append(int(np.argmin(m + pen)))
            elif rule == "gcv":
                per_region.append(int(np.argmin(m + pen / kappa)))
            elif rule == "l-curve":
                per_region.append(_corner(m, c["roughness"]))
        if rule == "upre-sum":
            picks[rule] = int(np.argmin(sum(c["misfit"] + c["penalty"] for c in curves)))
        else:
            picks[rule] = min(per_region)
    return picks


def evaluate(args) -> None:
    rows = []
    print(f"{'case':28} {'oracle':>12} " + " ".join(f"{r:>12}" for r in CRITERIA))
    for path in sorted(Path(args.workdir).glob("*.npz")):
        row = evaluate_one(path)
        rows.append(row)
        e = np.array(row["errors"])
        best = int(np.argmin(e))
        cells = " ".join(f"{row['lengths'][k]:5.0f}:{e[k]:.4f}" for r, k in row["picks"].items())
        print(f"{row['file']:28} {row['lengths'][best]:5.0f}:{e[best]:.4f} {cells}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    c = sub.add_parser("capture")
    c.add_argument("--specimen", default="grains", choices=("grains", "concrete"))
    c.add_argument("--size", type=int, default=96)
    c.add_argument("--spacings", type=int, nargs="+", default=[16, 12, 8])
    c.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    c.add_argument("--workdir", required=True)
    e = sub.add_parser("evaluate")
    e.add_argument("--workdir", required=True)
    e.add_argument("--json", default=None)
    args = ap.parse_args()
    capture(args) if args.command == "capture" else evaluate(args)


if __name__ == "__main__":
    main()
