"""Why the automatic regularisation length goes long on coarse textures: the captured problems.

Usage::

    python validation/scripts/bench_length_texture.py capture --pairs PAIRDIR --workdir DIR \
        [--cases band slip wave32 ...] [--specimens concrete] [--scales 1 2 4] [--spacings 8] [--noise-free]
    python validation/scripts/bench_length_texture.py evaluate --workdir DIR [--json PATH]
    python validation/scripts/bench_length_texture.py grid --workdir DIR [--json PATH]

``capture`` runs the defaults on the ``bench_vs_aldvc.py`` pairs of ``PAIRDIR`` (100³, seed
1; ``-tsS`` for a texture scale S) up to the length choice and stores the linearised problem
(:mod:`_capture`); with ``--noise-free`` the same pair is rendered again without noise (same
seed, texture and field) and captured too (``…-nf``).

``evaluate`` solves every candidate length on the whole mesh (:func:`_oracle.candidate_fields`),
scores each between the nodes (every voxel ≥ ℓ from the faces), and prints, per case, the
error curve, the engine's rule's pick and curves (``choose_length(..., sweep=True)``), and —
with a noise-free twin — how much of the misfit the noise really makes:
``‖a − a_nf‖²_M`` against the budget ``κ σ_r² · 3N`` the rule uses.

``grid`` applies the engine's default rule (``discrepancy-texture``, from the level's length
2ℓ as the engine does) with the candidates √2 apart and 2^(1/4) apart, every length of the
finer grid solved on the whole mesh and scored, each choice's error over the best fixed
length of the √2 grid (docs/engine.md, "The candidates' grid").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

#: the pairs' directory names (bench_vs_aldvc.py's tags)
TAG = "{case}-100-{specimen}-uint16-n{noise:g}-s1{suffix}"


def _pair_dir(pairs: Path, case: str, specimen: str, scale: float, noise: float = 0.02) -> Path:
    suffix = f"-ts{scale:g}" if scale != 1.0 else ""
    return pairs / TAG.format(case=case, specimen=specimen, noise=noise, suffix=suffix)


def _noise_free_twin(pair: Path, work: Path) -> Path:
    """The pair rendered again without noise (same seed, texture, field), under ``work``."""
    from chunkdic.synth import synthetic
    from chunkdic.synth.fields import Field

    out = work / (pair.name + "-nf")
    if (out / "field.json").exists():
        return out
    meta = synthetic.load_metadata(pair)
    field = Field.from_json(meta["field"])
    spec = dict(meta["specimen"])
    name = spec.pop("specimen")
    seed = spec.pop("seed")
    synthetic.synthesize(out, tuple(meta["shape"]), field=field, specimen=name, seed=seed, noise=0.0,
                         dtype=meta["dtype"], overwrite=True, **spec)
    return out


def capture(args) -> None:
    import chunkdic
    from _capture import capture_choice

    importlib_shear()
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    for scale in args.scales:
        for specimen in args.specimens:
            for case in args.cases:
                pair = _pair_dir(Path(args.pairs), case, specimen, scale)
                pairs = [(pair, "")]
                if args.noise_free:
                    pairs.append((_noise_free_twin(pair, work), "-nf"))
                for ell in args.spacings:
                    for src, tag in pairs:
                        out = work / f"{case}-{specimen}-ts{scale:g}-l{ell}{tag}.npz"
                        if out.exists():
                            continue

                        def save(problem, penalty, src=src, out=out):
                            np.savez(out, **problem, length=penalty.length,
                                     field=(src / "field.json").read_text(), shape=np.array([100, 100, 100]))

                        seconds = capture_choice(
                            lambda src=src, ell=ell: chunkdic.correlate(str(src / "ref.zarr"), str(src / "def.zarr"),
                                                                        element_size=ell),
                            save, engine_choice=True)
                        print(f"{out.name}: " + ("no choice" if seconds is None else f"{seconds:.1f} s"), flush=True)


def importlib_shear() -> None:
    import importlib

    importlib.import_module("chunkdic.synth.shear")  # registers the wave and slip fields


def load(path: Path) -> dict:
    from chunkdic.synth.fields import Field

    importlib_shear()
    d = dict(np.load(path))
    d["field"] = Field.from_json(json.loads(str(d["field"]))["field"])
    for k in ("ell", "scale", "noise_variance", "kappa", "length"):
        d[k] = float(d[k])
    d["kind"] = str(d["kind"])
    return d


def errors(problem: dict, fields: np.ndarray) -> np.ndarray:
    """RMS vector error (σ pooled for a translation) of each field, between the nodes, every
    voxel ≥ ℓ from the faces (level-0 voxels)."""
    from chunkdic.analysis.scoring import score_between_nodes

    axes = [problem["az"], problem["ay"], problem["ax"]]
    ell0 = problem["ell"] * problem["scale"]
    out = []
    for u in fields:
        s = score_between_nodes(axes, u, problem["field"], tuple(problem["shape"]), ell0)
        out.append(s.sigma if problem["field"].kind == "translation" else s.rms)
    return np.array(out)


def engine_rule(problem: dict, rule: str = "discrepancy", sweep: bool = True, guess: float | None = None) -> object:
    """The engine's choice on the captured problem; with ``sweep``, every candidate solved (its curves)."""
    from chunkdic.solve.cg import StencilSolver
    from chunkdic.solve.regchoice import choose_length

    cache = {}  # one solver per region's matrix, for this problem only

    def solve_with(half, reg, weight, rhs):
        key = id(half)
        if key not in cache:
            cache.clear()
            cache[key] = StencilSolver(half.copy(), rtol=1e-7)
        cache[key].regularize(reg, weight)
        return cache[key].solve(rhs)[0]

    return choose_length(problem["kind"], problem["half"], problem["ell"], problem["a"], problem["b"],
                         problem["noise_variance"], solve_with, rule=rule, kappa=problem["kappa"], sweep=sweep,
                         guess=guess)


def evaluate(args) -> None:
    from _oracle import candidate_fields

    from chunkdic.solve.stencil import stencil_matvec

    work = Path(args.workdir)
    rows = []
    for path in sorted(work.glob("*.npz")):
        if path.stem.endswith("-nf"):
            continue
        p = load(path)
        lengths, fields = candidate_fields(p)
        err = errors(p, fields)
        choice = engine_rule(p)
        row = {"case": path.stem, "lengths": lengths.tolist(), "errors": err.tolist(),
               "oracle": float(err.min()), "oracle_length": float(lengths[int(np.argmin(err))]),
               "rule_length": choice.length * p["scale"],
               "rule_error": float(err[int(np.argmin(np.abs(lengths - choice.length * p["scale"])))]),
               "budget": choice.budget, "kappa": p["kappa"], "noise_variance": p["noise_variance"],
               "curves": [{k: np.asarray(v).tolist() if not np.isscalar(v) else v for k, v in c.items()}
                          for c in choice.curves]}
        twin = path.with_name(path.stem + "-nf.npz")
        if twin.exists():
            q = load(twin)
            if q["a"].shape == p["a"].shape:
                d = p["a"] - q["a"]
                row["noise_misfit"] = float(np.sum(d * stencil_matvec(p["half"], d)))
                row["twin_errors"] = errors(q, candidate_fields(q)[1]).tolist()
        rows.append(row)
        extra = (f" noise misfit / budget {row['noise_misfit'] / row['budget']:.2f}" if "noise_misfit" in row else "")
        print(f"{path.stem:32s} rule {row['rule_length']:6.1f} err {row['rule_error']:.4f} | oracle "
              f"{row['oracle_length']:6.1f} err {row['oracle']:.4f} ratio {row['rule_error'] / row['oracle']:.2f}"
              f" κ {p['kappa']:.1f}{extra}", flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps({"argv": sys.argv[1:], "rows": rows}, indent=1))


def grid(args) -> None:
    from _oracle import candidate_fields

    import chunkdic.solve.regchoice as regchoice

    coarse = tuple(float(2.0 ** (k / 2)) for k in range(0, 11))
    fine = tuple(float(2.0 ** (k / 4)) for k in range(0, 21))
    engine_grid = regchoice.CANDIDATES

    def choose(p, candidates):
        regchoice.CANDIDATES = candidates  # choose_length reads the module's grid
        return p["scale"] * engine_rule(p, "discrepancy-texture", sweep=False, guess=2 * p["ell"]).length

    rows = []
    try:
        for path in sorted(Path(args.workdir).glob("*.npz")):
            if path.stem.endswith("-nf"):
                continue
            p = load(path)
            regchoice.CANDIDATES = fine
            lengths, fields = candidate_fields(p)
            err = errors(p, fields)
            at = lambda length: float(err[int(np.argmin(np.abs(np.log(lengths / length))))])  # noqa: E731
            oracle = float(err[::2].min())  # the √2 grid's every other length
            row = {"case": path.stem, "oracle": oracle, "sqrt2": choose(p, coarse), "fourth_root": choose(p, fine)}
            row["sqrt2_ratio"], row["fourth_root_ratio"] = at(row["sqrt2"]) / oracle, at(row["fourth_root"]) / oracle
            rows.append(row)
            print(f"{path.stem:32s} √2 grid {row['sqrt2']:6.1f} ({row['sqrt2_ratio']:.2f})  2^(1/4) grid "
                  f"{row['fourth_root']:6.1f} ({row['fourth_root_ratio']:.2f})", flush=True)
    finally:
        regchoice.CANDIDATES = engine_grid
    for key in ("sqrt2_ratio", "fourth_root_ratio"):
        r = np.array([row[key] for row in rows])
        print(f"{key}: geometric mean {np.exp(np.mean(np.log(r))):.3f}, above 1.15: {int(np.sum(r > 1.15))} "
              f"of {len(r)}")
    if args.json:
        Path(args.json).write_text(json.dumps({"argv": sys.argv[1:], "rows": rows}, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    c = sub.add_parser("capture")
    c.add_argument("--pairs", required=True)
    c.add_argument("--workdir", required=True)
    c.add_argument("--cases", nargs="+", default=["band", "slip", "wave32", "wave64", "crack", "noise"])
    c.add_argument("--specimens", nargs="+", default=["concrete"])
    c.add_argument("--scales", type=float, nargs="+", default=[1.0, 2.0, 4.0])
    c.add_argument("--spacings", type=int, nargs="+", default=[8])
    c.add_argument("--noise-free", action="store_true")
    e = sub.add_parser("evaluate")
    e.add_argument("--workdir", required=True)
    e.add_argument("--json", default=None)
    g = sub.add_parser("grid")
    g.add_argument("--workdir", required=True)
    g.add_argument("--json", default=None)
    args = ap.parse_args()
    {"capture": capture, "evaluate": evaluate, "grid": grid}[args.command](args)


if __name__ == "__main__":
    main()
