"""Mid-slices of the CT-like specimens for docs/synthetic.md (docs/images/ct_*.png).

Usage::

    python docs/tools/ct_images.py [--size 128] [--out docs/images]

One figure per specimen: the noise-free phase map, the default CT scan (ramp filter,
noise 0.02), a softer scan (ramp x Hann, detector blur 0.8 px, rings 0.02) and the
deformed scan of the band case (-8 %, 6 voxels, lateral 0.3) with a grey-level change
(gain 1.1, offset 0.05, drift 0.03), all at mid-height, float32 phase units.
"""

from __future__ import annotations

import argparse
import os


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--out", default=os.path.join("docs", "images"))
    a = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from chunkdic.synth import microstructure as M
    from chunkdic.synth.ctpair import render_ct, standard_field

    n = a.size
    shape = (n, n, n)
    z = (n // 2, n // 2 + 1)
    band, _ = standard_field("band", shape)
    for name in ("grains", "concrete"):
        P = M.specimen_params(name)
        panels = [
            ("phase map (no imaging)", M.render_phantom(P, (1, n, n), origin=(n // 2, 0, 0))[0]),
            ("CT: ramp, noise 0.02", render_ct(shape, specimen=name, z_range=z, dtype="float32")[0]),
            ("ramp x Hann, blur 0.8, rings 0.02",
             render_ct(shape, specimen=name, z_range=z, dtype="float32", filter="hann", blur=0.8,
                       rings=0.02)[0]),
            ("deformed: band + gain 1.1, offset 0.05",
             render_ct(shape, specimen=name, z_range=z, dtype="float32", field=band,
                       which="deformed", gain=1.1, offset=0.05, drift=0.03)[0]),
        ]
        fig, axes = plt.subplots(1, 4, figsize=(12, 3.3))
        for ax, (title, img) in zip(axes, panels):
            ax.imshow(img, cmap="gray", vmin=-0.2, vmax=1.25, interpolation="nearest")
            ax.set_title(title, fontsize=9)
            ax.set_axis_off()
        fig.suptitle(f"{name}: slice z = {n // 2} of a {n}^3 scan", fontsize=10)
        fig.tight_layout()
        path = os.path.join(a.out, f"ct_{name}.png")
        fig.savefig(path, dpi=72)
        plt.close(fig)
        print(path)


if __name__ == "__main__":
    main()
