"""The equilibrium gap at small elements: convergence, error, and its solve.

Usage::

    python validation/scripts/bench_eqgap.py [--size 64] [--spacings 6 4] [--specimens grains concrete]
                                     [--kinds equilibrium-gap tikhonov] [--lengths 12 17 24]
                                     [--solver 24] [--workdir DIR]

Correlations: on the CT-like band pair (:func:`chunkdic.synth.synthetic.standard_case`
``"band"``, independent 2 % noise in each scan) of each specimen, for every ``ℓ`` and
regularisation kind, the defaults (automatic length) and, with ``--lengths``, fixed lengths
(voxels). Prints per run: status, Gauss–Newton passes on the correlated level, the last
finite increment ``max |δa|`` (below the tolerance, 1e-3: converged by the tolerance, not
at the noise level), the CG iterations of each pass, the largest increment of the run and
where it was (distance of that node to the nearest mesh face: 0 is a face, edge or corner
node), the chosen length and the field RMS error between the nodes
(:func:`chunkdic.analysis.scoring.score_between_nodes`, voxels ≥ ℓ from the faces).

Solver (``--solver N``): CG on a random mass-like ``M`` of ``N³`` nodes plus the
equilibrium gap at ℓ … 32ℓ, block-Jacobi against the multigrid V-cycle: iterations and
CPU ms (median of 3) of setup and solve; with and without the edge term.

Quote ``cat /proc/loadavg`` with the figures (docs/engine.md, "The equilibrium gap at
ℓ = 6 and 4", and "Solve").
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def correlate(pair: dict, field, size: int, ell: int, kind: str, length: float | None) -> str:
    import chunkdic
    from chunkdic.analysis.scoring import score_between_nodes
    from chunkdic.method import stopping

    worst = {"delta": 0.0, "dist": None}
    original = stopping.State.step

    def step(self, delta):  # where the largest increment of the run lands
        a = np.abs(delta).max(axis=-1)
        if a.max() > worst["delta"]:
            idx = np.unravel_index(int(np.argmax(a)), a.shape)
            worst.update(delta=float(a.max()), dist=min(min(i, n - 1 - i) for i, n in zip(idx, a.shape)))
        return original(self, delta)

    events: list[dict] = []
    stopping.State.step = step
    try:
        res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=ell, regularization=kind,
                                 regularization_length=length, progress=events.append)
    finally:
        stopping.State.step = original
    score = score_between_nodes(res.mesh.node_axes(), res.displacement, field, (size,) * 3, ell)
    h = res.history
    mine = h["level"] == res.info["level"]
    finite = h["max_delta"][mine & np.isfinite(h["max_delta"])]
    cg = [e["cg_iterations"] for e in events
          if e.get("stage") == "iteration" and e["level"] == res.info["level"] and e.get("cg_iterations")]
    chosen = res.info["regularization"]["length"]
    return (f"{kind:16s} ℓ={ell} L={'auto' if length is None else length:>5}: {res.info['status']:>14} "
            f"passes {int(mine.sum()):2d} last |δa| {finite[-1] if finite.size else float('nan'):.1e} "
            f"largest {worst['delta']:.3g} at face distance {worst['dist']} length {chosen and round(chosen, 1)} "
            f"RMS {score.rms:.4f} CG {cg}")


def solver_table(n: int) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "solve"))
    from test_multigrid import _mass_stencil

    from chunkdic.solve.cg import StencilSolver
    from chunkdic.solve.regularizer import Regularizer, plane_wave_weight
    from chunkdic.solve.stencil import stencil_matvec

    shape, ell = (n, n, n), 8.0
    H = _mass_stencil(shape, seed=4)
    b = np.random.default_rng(5).standard_normal(shape + (3,))
    for edges in (False, True):
        reg = Regularizer("equilibrium-gap", shape, ell)
        if not edges:
            reg.edge_weight = 0.0
        for k in (1, 2, 4, 8, 16, 32):
            lam = plane_wave_weight(reg, lambda v: stencil_matvec(H, v), k * ell)
            cells = []
            for multigrid in (False, True):
                times = []
                for _ in range(3):
                    solver = StencilSolver(H.copy(), rtol=1e-7, multigrid=multigrid)
                    t0 = time.process_time()
                    solver.regularize(reg, lam)
                    t1 = time.process_time()
                    _, iterations = solver.solve(b)
                    times.append((t1 - t0, time.process_time() - t1))
                cells.append(f"{'V-cycle' if multigrid else 'block-Jacobi'} {iterations:5d} it, setup "
                             f"{statistics.median(t[0] for t in times) * 1e3:5.0f} ms, solve "
                             f"{statistics.median(t[1] for t in times) * 1e3:6.0f} ms")
            print(f"edge term {'on ' if edges else 'off'} {k:2d}ℓ  " + " | ".join(cells), flush=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--spacings", type=int, nargs="+", default=[6, 4])
    ap.add_argument("--specimens", nargs="+", default=["grains", "concrete"])
    ap.add_argument("--kinds", nargs="+", default=["equilibrium-gap", "tikhonov"])
    ap.add_argument("--lengths", type=float, nargs="*", default=[])
    ap.add_argument("--solver", type=int, default=0, help="nodes per axis of the solver table (0: skip)")
    ap.add_argument("--workdir", type=Path, default=None)
    args = ap.parse_args(argv)

    from chunkdic.synth import synthetic

    with tempfile.TemporaryDirectory() as tmp:
        root = args.workdir or Path(tmp)
        for specimen in args.specimens:
            d = root / f"{specimen}-band-{args.size}"
            if (d / "field.json").exists():
                pair = {"reference": str(d / "ref.zarr"), "deformed": str(d / "def.zarr")}
            else:
                pair = synthetic.standard_case(d, "band", args.size, specimen=specimen, noise=0.02)
            field, _ = synthetic.standard_field("band", (args.size,) * 3)
            for ell in args.spacings:
                for kind in args.kinds:
                    for length in [None, *args.lengths]:
                        print(f"{specimen} {args.size}³ " + correlate(pair, field, args.size, ell, kind, length),
                              flush=True)
    if args.solver:
        solver_table(args.solver)


if __name__ == "__main__":
    main()
