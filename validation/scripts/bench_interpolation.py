"""Linear versus cubic B-spline interpolation on the paper's sub-voxel test (section 4.2).

A periodic smooth random texture is translated by (0.5, 0.5, 0.5) voxel with a Fourier
phase shift (exact for a periodic texture) and correlated blindly at several element
sizes with each interpolation. Prints per element size and interpolation: bias and
standard deviation of the nodal displacement (max over components) and the median time
of one ``b`` iteration, and the cubic/linear time ratio. The default interpolation is the
more accurate one unless it costs more than twice the time.

Usage::

    python validation/scripts/bench_interpolation.py --size 128 --element-sizes 16 12 8
"""

from __future__ import annotations

import argparse
import statistics

import numpy as np

import chunkdic


def smooth_noise(shape, sigma, seed):
    rng = np.random.default_rng(seed)
    freqs = np.meshgrid(*[np.fft.fftfreq(n) for n in shape], indexing="ij", sparse=True)
    k2 = sum(f**2 for f in freqs)
    out = np.fft.ifftn(np.fft.fftn(rng.standard_normal(shape)) * np.exp(-2 * (np.pi * sigma) ** 2 * k2)).real
    return 100 * (out - out.min()) / np.ptp(out)


def fourier_shift(f, t):
    freqs = np.meshgrid(*[np.fft.fftfreq(n) for n in f.shape], indexing="ij", sparse=True)
    return np.fft.ifftn(np.fft.fftn(f) * np.exp(-2j * np.pi * sum(k * ti for k, ti in zip(freqs, t)))).real


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--element-sizes", type=int, nargs="+", default=[16, 12, 8])
    p.add_argument("--sigma", type=float, default=1.2, help="texture smoothing, voxels")
    p.add_argument("--shift", type=float, default=0.5)
    args = p.parse_args()
    f = smooth_noise((args.size,) * 3, args.sigma, 7)
    g = fourier_shift(f, (args.shift,) * 3)
    f, g = f.astype(np.float32), g.astype(np.float32)
    print(f"# {args.size}^3 smooth random texture (sigma {args.sigma}), shift {args.shift} voxel per axis")
    print(f"{'ell':>4} {'interp':>7} {'bias':>8} {'std':>8} {'gap %':>7} {'s/iter':>7} {'iters':>5}")
    for ell in args.element_sizes:
        times = {}
        for interp in ("linear", "cubic"):
            events = []
            res = chunkdic.correlate(f, g, element_size=ell, interpolation=interp, progress=events.append)
            u = res.displacement.reshape(3, -1)
            bias = np.abs(u.mean(axis=1) - args.shift).max()
            std = u.std(axis=1).max()
            its = [e["assemble_seconds"] for e in events if e["stage"] == "iteration" and e.get("assemble_seconds")
                   and e["level"] == 0]
            times[interp] = statistics.median(its) if its else float("nan")
            print(f"{ell:>4} {interp:>7} {bias:>8.4f} {std:>8.4f} {100 * res.final_gap:>7.3f} "
                  f"{times[interp]:>7.3f} {len(its):>5}", flush=True)
        print(f"{ell:>4} cubic/linear time ratio {times['cubic'] / times['linear']:.2f}")


if __name__ == "__main__":
    main()
