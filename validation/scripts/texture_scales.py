"""Statistics of the CT specimens' texture at each ``texture_scale`` (docs/synthetic.md, "Texture scale").

Usage::

    python validation/scripts/texture_scales.py [--size 192] [--specimens grains concrete] [--scales 1 2 4]
        [--workdir DIR] [--json PATH]

For each specimen and scale, a reference scan (seed 1, noise 0.02, uint16) is synthesized
and read whole (a benchmark on scans of a few hundred voxels, not the product), converted to
phase units, and measured: the autocorrelation length per axis (the whole scan's 3-D FFT,
mean removed, each lag divided by its number of pairs, 1/e interpolated linearly) and, for
elements of edge ℓ = 4, 8, 12, 16 tiling the scan, the per-element mean of ``|∇f|²``
(centred differences): its median, its 10 % quantile over the median, and the fraction of
elements below a tenth of the median.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def autocorrelation_length(v: np.ndarray) -> list[float]:
    v = v.astype(np.float64) - v.mean()
    shape = [2 * n for n in v.shape]
    axes = (0, 1, 2)
    acov = np.fft.irfftn(np.abs(np.fft.rfftn(v, s=shape, axes=axes)) ** 2, s=shape, axes=axes)
    pairs = np.fft.irfftn(np.abs(np.fft.rfftn(np.ones(v.shape), s=shape, axes=axes)) ** 2, s=shape, axes=axes)
    rho = acov / np.maximum(pairs, 1.0)
    rho /= rho[0, 0, 0]
    out = []
    for ax in range(3):
        line = np.moveaxis(rho, ax, 0)[: v.shape[ax] // 2, 0, 0]
        j = int(np.flatnonzero(line < 1 / math.e)[0])
        out.append(float(j - 1 + (line[j - 1] - 1 / math.e) / (line[j - 1] - line[j])))
    return out


def gradient_statistics(v: np.ndarray, ell: int) -> dict:
    e = sum(g * g for g in np.gradient(v.astype(np.float64)))
    n = [s // ell for s in v.shape]
    e = e[: n[0] * ell, : n[1] * ell, : n[2] * ell].reshape(n[0], ell, n[1], ell, n[2], ell).mean(axis=(1, 3, 5))
    med = float(np.median(e))
    return {"median": med, "q10_over_median": float(np.quantile(e, 0.1)) / med,
            "below_tenth_of_median": float(np.mean(e < med / 10))}


def main() -> None:
    from chunkdic.io.scan import open_scan
    from chunkdic.synth import synthetic

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=192)
    ap.add_argument("--specimens", nargs="+", default=["grains", "concrete"])
    ap.add_argument("--scales", type=float, nargs="+", default=[1.0, 2.0, 4.0])
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    work = Path(args.workdir or tempfile.mkdtemp(prefix="texture-scales-"))
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    record = {"meta": {"date": time.strftime("%Y-%m-%d %H:%M:%S"), "host": platform.node(), "commit": commit,
                       "argv": sys.argv[1:]}, "rows": []}
    for specimen in args.specimens:
        for scale in args.scales:
            out = work / f"{specimen}-{scale:g}-{args.size}"
            if not (out / "field.json").exists():
                synthetic.synthesize(out, args.size, specimen=specimen, field=None, seed=1, noise=0.02,
                                     overwrite=True, texture_scale=scale)
            f = open_scan(str(out / "ref.zarr")).refs([0])[0].open()[...].astype(np.float64)
            f = f / 65535.0 * 2.0 - 0.5  # uint16 -> phase units (chunkdic.synth.ctpair.INTENSITY_RANGE)
            row = {"specimen": specimen, "scale": scale, "size": args.size, "acl": autocorrelation_length(f),
                   "gradient": {ell: gradient_statistics(f, ell) for ell in (4, 8, 12, 16)}}
            record["rows"].append(row)
            print(json.dumps(row), flush=True)
            if args.json:
                Path(args.json).write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
