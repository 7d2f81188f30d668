"""The nodes flagged weak on CT-like pairs: how many, where, and how wrong.

For each pair (``chunkdic synth``-like CT specimen, independent noise 0.02 in each scan,
a 24-voxel shear wave ``Ux = 0.5 sin(2π (z - c) / 24)`` or a (0.5, 0.5, 0.5) translation)
and element size, correlates with the defaults and prints: status, between-node RMS error
(:func:`chunkdic.analysis.scoring.score_between_nodes`), the nodes flagged ``FLAG_WEAK`` (of
which the stop rule's *unsettled* ones, from the ``unsettled`` event), how many lie on the
ROI's faces, and the nodal error (against the analytic field at the nodes) of the flagged
nodes and of the others: median / max. docs/engine.md, "Nodes without texture", records
what it measured and what was decided from it.

Usage::

    python validation/scripts/bench_weak_nodes.py --sizes 64 100 --spacings 6 8 --workdir /tmp/weak
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np


def make_pair(root: Path, specimen: str, n: int, case: str, seed: int):
    """The pair (written once under ``root``) and its field."""
    from chunkdic.synth import synthetic
    from chunkdic.synth.fields import Translation
    from chunkdic.synth.shear import Wave

    field = Wave(period=24.0, amplitude=0.5, phase=(n - 1) / 2.0) if case == "wave24" else Translation((0.5,) * 3)
    out = root / f"{case}-{n}-{specimen}-s{seed}"
    if not (out / "field.json").exists():
        synthetic.synthesize(out, (n,) * 3, field=field, specimen=specimen, seed=seed, dtype="uint16",
                             noise=0.02, overwrite=True)
    return out, field


def run(pair: Path, field, n: int, ell: int) -> str:
    """One correlation with the defaults; the table row."""
    import chunkdic
    from chunkdic.analysis.scoring import score_between_nodes
    from chunkdic.results.result import FLAG_WEAK

    events = []
    res = chunkdic.correlate(str(pair / "ref.zarr"), str(pair / "def.zarr"), element_size=ell,
                             progress=events.append)
    unsettled = sum(e["nodes"] for e in events if e.get("stage") == "unsettled" and e.get("level") == res.info["level"])
    scale = float(res.info.get("scale", 1))
    axes = [np.unique(c) * scale + (scale - 1) / 2 for c in res.node_coords]
    score = score_between_nodes(axes, res.displacement * scale, field, (n,) * 3, ell)
    truth = field.displacement(*np.meshgrid(*axes, indexing="ij"))
    err = np.sqrt(((res.displacement * scale - truth) ** 2).sum(axis=0))
    weak = (res.flags & FLAG_WEAK) > 0
    face = np.ones(weak.shape, bool)
    face[1:-1, 1:-1, 1:-1] = False

    def spread(m):
        return f"{np.median(err[m]):.3f} / {err[m].max():.3f}" if m.any() else "–"

    return (f"{res.info['status']} | {score.rms:.4f} | {int(weak.sum())} of {weak.size} ({unsettled} unsettled, "
            f"{int((weak & face).sum())} on faces) | {spread(weak)} | {spread(~weak)} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 100])
    ap.add_argument("--specimen", nargs="+", default=["grains", "concrete"], choices=("grains", "concrete"))
    ap.add_argument("--spacings", type=int, nargs="+", default=[6, 8])
    ap.add_argument("--cases", nargs="+", default=["wave24", "shift"], choices=("wave24", "shift"))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workdir", default=None, help="pairs are kept here (default: a temporary directory)")
    args = ap.parse_args(argv)
    root = Path(args.workdir or tempfile.mkdtemp(prefix="weak-nodes-"))
    print("| size | specimen | ℓ | field | status | between-node RMS | flagged weak | flagged: median / max error "
          "| others: median / max |")
    print("|---|---|---|---|---|---|---|---|---|")
    for n in args.sizes:
        for specimen in args.specimen:
            for case in args.cases:
                pair, field = make_pair(root, specimen, n, case, args.seed)
                for ell in args.spacings:
                    print(f"| {n}³ | {specimen} | {ell} | {case} | {run(pair, field, n, ell)}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
