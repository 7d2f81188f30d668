"""The figures of docs/statistics.md, docs/gauges.md and docs/cracks.md (docs/images/*.png).

- ``stats_profile.png``: ``chunkdic report --profile`` of a compression band (64³ foam, noise
  0.02 of the range in each scan, band 12 voxels wide of −3 %, ℓ = 8, defaults): U and the
  normal strains along z through the centre, ± one standard uncertainty.
- ``gauge_series.png``: ``chunkdic gauge --planes`` over a 4-scan series (48³ foam, scan k
  under −0.5 k % along z), the curve with its 95 % intervals.
- ``cracks.png``: ``chunkdic crack`` on a 0.3 voxel crack normal to z with 0.15 sliding
  (64³ foam, noise 0.02, ℓ = 8, defaults): the element jump on the mid-plane normal to x and
  the opening over the crack surface.

Usage::

    nice -n 10 python benchmarks/mechanics_images.py --workdir /tmp/mech-images --out docs/images
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def profile_figure(work: Path, out: Path) -> None:
    import chunkdic
    from chunkdic.analysis.regions import line_region
    from chunkdic.analysis.stats import profile
    from chunkdic.synth import synthetic
    from chunkdic.plot.mechplots import plot_profile

    pair = work / "band"
    if not (pair / "field.json").exists():
        field = synthetic.Band(width=12.0, strain=-0.03, center_z=31.5)
        synthetic.synthesize(pair, 64, field=field, seed=3, dtype="float32", noise=0.02, overwrite=True)
    res = chunkdic.correlate(pair / "ref.zarr", pair / "def.zarr", element_size=8, output=work / "band.zarr",
                             overwrite=True)
    prof = profile(res, line_region(res, (6, 32, 32), (58, 32, 32), step=2))
    plot_profile([prof.as_dict()], out / "stats_profile.png", dpi=100)


def gauge_figure(work: Path, out: Path) -> None:
    import chunkdic
    from chunkdic.analysis.gauge import gauge
    from chunkdic.synth import synthetic
    from chunkdic.plot.mechplots import plot_gauge

    scans = []
    for k in range(4):
        f = synthetic.Affine(matrix=((-0.005 * k, 0, 0), (0, 0, 0), (0, 0, 0)), center=(23.5,) * 3)
        lazy = synthetic.as_dask((48,) * 3, chunks=48, field=None if k == 0 else f, seed=6,
                                 which="reference" if k == 0 else "deformed", dtype="float32", noise=0.02)
        scans.append(work / f"scan{k}.zarr")
        if not scans[-1].exists():
            chunkdic.write_scan(scans[-1], lazy, voxel_size=2.5, unit="micrometer")
    series = work / "series.zarr"
    if not series.exists():
        chunkdic.series(scans, series, element_size=8, mode="cumulative")
    curve = gauge(series, planes=["z=8", "z=40"])
    print(curve.text())
    plot_gauge(curve.as_dict(), out / "gauge_series.png", dpi=100)


def cracks_figure(work: Path, out: Path) -> None:
    import chunkdic
    from chunkdic.analysis.cracks import find_cracks
    from chunkdic.analysis.residuals import element_residuals
    from chunkdic.synth import synthetic
    from chunkdic.synth.fields import Crack
    from chunkdic.plot.figures import figure, save

    pair = work / "crack"
    if not (pair / "field.json").exists():
        field = Crack(normal=(1, 0, 0), point=(30.3, 0, 0), opening=0.3, sliding=(0, 0, 0.15))
        synthetic.synthesize(pair, 64, field=field, seed=7, dtype="float32", noise=0.02, overwrite=True)
    res = chunkdic.correlate(pair / "ref.zarr", pair / "def.zarr", element_size=8, output=work / "crack.zarr",
                             overwrite=True)
    cmap = find_cracks(res, residual=element_residuals(res))
    print(cmap.text("crack"))
    ez, ey, ex = (a for a in res.mesh.element_axes())
    fig = figure(11.5, 3.8)
    ax1, ax2, ax3 = (fig.add_subplot(1, 3, k) for k in (1, 2, 3))
    mid = cmap.jump.shape[2] // 2
    im = ax1.imshow(cmap.jump[:, :, mid], origin="lower", extent=(ey[0] - 4, ey[-1] + 4, ez[0] - 4, ez[-1] + 4))
    fig.colorbar(im, ax=ax1, shrink=0.8, label="jump ℓ σ₁(ΔH) (voxel)")
    ax1.axhline(30.3, color="w", ls="--", lw=0.8)
    ax1.set_title("jump per element (x mid-plane;\ndashed: the true plane)", fontsize=9)
    ax1.set_xlabel("y (voxel)")
    ax1.set_ylabel("z (voxel)")
    ratio = np.where(np.isfinite(cmap.residual_ratio), cmap.residual_ratio, np.nan)
    im = ax2.imshow(ratio[:, :, mid], origin="lower", extent=(ey[0] - 4, ey[-1] + 4, ez[0] - 4, ez[-1] + 4),
                    cmap="magma")
    fig.colorbar(im, ax=ax2, shrink=0.8, label="RMS residual / median")
    ax2.axhline(30.3, color="w", ls="--", lw=0.8)
    ax2.set_title("residual per element (x mid-plane)", fontsize=9)
    ax2.set_xlabel("y (voxel)")
    layer = np.where(cmap.labels > 0, cmap.opening, np.nan)
    top = np.nanmax(layer, axis=0)
    im = ax3.imshow(top, origin="lower", extent=(ex[0] - 4, ex[-1] + 4, ey[0] - 4, ey[-1] + 4), cmap="viridis")
    fig.colorbar(im, ax=ax3, shrink=0.8, label="opening (voxel)")
    ax3.set_title(f"opening over the surface (true 0.3;\nmean {cmap.cracks[0].opening:.3f} ± "
                  f"{cmap.cracks[0].sigma_opening:.3f})", fontsize=9)
    ax3.set_xlabel("x (voxel)")
    ax3.set_ylabel("y (voxel)")
    save(fig, out / "cracks.png", 100)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", default="/tmp/chunkdic-mech-images")
    ap.add_argument("--out", default="docs/images")
    ap.add_argument("--only", nargs="+", choices=("profile", "gauge", "cracks"), help="these figures only")
    args = ap.parse_args()
    work, out = Path(args.workdir), Path(args.out)
    work.mkdir(parents=True, exist_ok=True)
    chosen = {"profile": profile_figure, "gauge": gauge_figure, "cracks": cracks_figure}
    for name in args.only or chosen:
        chosen[name](work, out)


if __name__ == "__main__":
    main()
