"""Crack detection and opening on synthetic cracks: the true/false-positive table of docs/cracks.md.

Pairs (64³ by default, written once under ``--workdir``): a planar crack through the volume
(:class:`chunkdic.synth.fields.Crack`) of opening 0.1, 0.3 and 1.0 voxel, normal to z with a
sliding of half the opening, or oblique (normal ∝ (1, 0.6, 0.3), opening only), in two
textures (the smooth foam, float32 with noise 0.02 of its range; the CT-like grains, uint16
with the reconstruction noise 0.02), and crack-free pairs (−1 % along z with +0.3 %
laterally, and a (0.4, −0.3, 0.2) translation) in both textures. Each pair is correlated at
ℓ = 8 with the defaults (Tikhonov, automatic length, one robust reweighting) and without
regularisation, then ``chunkdic crack`` (:func:`chunkdic.analysis.cracks.find_cracks` with
the residual) runs on it.

Scored per pair:

- **elements**: an element is *cut* when the true plane passes through its cube; a detected
  element is a true positive when it lies within one element of the plane (the surface is
  smeared over about that), a false positive otherwise (every detection on a crack-free pair);
- **recall**: the share of the columns along the plane's main axis in which a true positive
  was found (the surface covered);
- **cracks**: the detected cracks (1 is right for a crack pair, 0 for a crack-free one);
- **opening / sliding**: the mean over the crack elements within one element of the plane,
  against the truth, with the mean of their standard uncertainties.

Usage::

    nice -n 10 python benchmarks/bench_cracks.py --workdir /tmp/cracks --record benchmarks/records/bench_cracks.json
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import time
from pathlib import Path

import numpy as np

OPENINGS = (0.1, 0.3, 1.0)


def cases():
    """``(name, field)``: the cracks and the crack-free fields."""
    from chunkdic.synth.fields import Affine, Crack, Translation

    out = []
    for opening in OPENINGS:
        out.append((f"z-{opening}", Crack(normal=(1, 0, 0), point=(30.3, 0, 0), opening=opening,
                                          sliding=(0, 0, opening / 2))))
        out.append((f"oblique-{opening}", Crack(normal=(1, 0.6, 0.3), point=(31.7, 30.2, 33.1), opening=opening)))
    out.append(("no-crack-affine", Affine(matrix=((-0.01, 0, 0), (0, 0.003, 0), (0, 0, 0.003)), center=(32, 32, 32))))
    out.append(("no-crack-translation", Translation((0.4, -0.3, 0.2))))
    return out


def pair(root: Path, name: str, field, texture: str, n: int) -> Path:
    from chunkdic.synth import synthetic

    out = root / f"{name}-{texture}-{n}"
    if not (out / "field.json").exists():
        options = {"dtype": "float32", "noise": 0.02} if texture == "foam" else {"dtype": "uint16", "noise": 0.02}
        synthetic.synthesize(out, (n,) * 3, field=field, specimen=texture, seed=7, overwrite=True, **options)
    return out


def score(result, cmap, field) -> dict:
    """The row of one pair (module docstring)."""
    from chunkdic.synth.fields import Crack

    ell = float(result.info["element_size"])
    centres = np.stack(np.meshgrid(*result.mesh.element_axes(), indexing="ij"))
    found = cmap.labels > 0
    row = {"cracks": len(cmap.cracks), "detected": int(found.sum())}
    if not isinstance(field, Crack):
        row.update(tp=0, fp=int(found.sum()), recall=None, opening=None, sliding=None, sigma=None,
                   residual_ratio=None)
        return row
    n = np.asarray(field.normal)
    dist = np.abs(np.tensordot(n, centres - np.asarray(field.point)[:, None, None, None], 1))
    reach = ell / 2 * np.abs(n).sum()
    near = dist <= reach + ell
    tp, fp = found & near, found & ~near
    axis = int(np.argmax(np.abs(n)))
    covered = tp.any(axis=axis)
    measured = tp & np.isfinite(cmap.opening)
    row.update(tp=int(tp.sum()), fp=int(fp.sum()), recall=float(covered.mean()),
               opening=float(np.mean(cmap.opening[measured])) if measured.any() else None,
               sliding=float(np.mean(cmap.sliding[measured])) if measured.any() else None,
               sigma=float(np.mean(cmap.sigma_opening[measured])) if measured.any() else None,
               residual_ratio=float(np.nanmean(cmap.residual_ratio[tp])) if tp.any() else None,
               true_opening=field.opening, true_sliding=float(np.linalg.norm(field.sliding)))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", default="/tmp/chunkdic-cracks")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--textures", nargs="+", default=["foam", "grains"])
    ap.add_argument("--record", help="write the rows as JSON there")
    args = ap.parse_args()

    import chunkdic
    from chunkdic.analysis.cracks import find_cracks
    from chunkdic.analysis.residuals import element_residuals

    root = Path(args.workdir)
    root.mkdir(parents=True, exist_ok=True)
    rows = []
    for texture in args.textures:
        for name, field in cases():
            p = pair(root, name, field, texture, args.size)
            for settings, options in (("default", {}), ("none", {"regularization": "none"})):
                t0 = time.perf_counter()
                res = chunkdic.correlate(str(p / "ref.zarr"), str(p / "def.zarr"), element_size=8, **options,
                                         output=p / f"r-{settings}.zarr", overwrite=True)
                cmap = find_cracks(res, residual=element_residuals(res))
                row = {"pair": name, "texture": texture, "regularization": settings,
                       "length": (res.info.get("regularization") or {}).get("length"),
                       "status": res.info["status"], **score(res, cmap, field),
                       "seconds": round(time.perf_counter() - t0, 1)}
                rows.append(row)
                print(json.dumps(row), flush=True)
    print()
    print("| pair | texture | regularisation | cracks | TP el. | FP el. | recall | opening (true) | sliding (true) "
          "| σ opening | residual ratio |")
    print("|" + "---|" * 11)
    for r in rows:
        def f(v, fmt):
            return "–" if v is None else format(v, fmt)
        truth_o = f"({r['true_opening']:g})" if "true_opening" in r else ""
        truth_s = f"({r['true_sliding']:g})" if "true_sliding" in r else ""
        reg = r["regularization"] if r["regularization"] == "none" else f"Tikhonov ℓ_reg {r['length']:.0f}"
        print(f"| {r['pair']} | {r['texture']} | {reg} | {r['cracks']} | {r['tp']} | {r['fp']} | {f(r['recall'], '.2f')} "
              f"| {f(r['opening'], '.3f')} {truth_o} | {f(r['sliding'], '.3f')} {truth_s} | {f(r['sigma'], '.3f')} "
              f"| {f(r['residual_ratio'], '.2f')} |")
    if args.record:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
        Path(args.record).write_text(json.dumps({"commit": commit, "machine": platform.node(),
                                                 "command": "python benchmarks/bench_cracks.py " + " ".join(
                                                     f"--{k} {' '.join(map(str, v)) if isinstance(v, list) else v}"
                                                     for k, v in vars(args).items() if k != "record"),
                                                 "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
