"""Speed of the per-block kernels on one core: Mvoxel/s, median of 5 runs.

A 128^3 block (ell = 16) inside a 160^3 volume, with its 1-voxel halo; f is float32 and
uint8, g uint8; a smooth nodal field of a few voxels. ``cubic`` rows include the
per-window prefilter (halo 12, ``prefiltered=False``); ``cubic pf`` rows read a window of
float32 B-spline coefficients of the whole deformed volume computed once outside the
timing (``prefiltered=True``, what the engine does). The summary line gives the cubic
(prefiltered) / linear cost ratio of the b pass. Run::

    python benchmarks/bench_kernels.py [--block 128] [--ell 16] [--repeat 5] [--numpy]

``--numpy`` also times the NumPy twins (slow, ~seconds per run). Mvox/s is from the
wall time; ``(cpu)`` from the CPU time of the calling thread, which stays meaningful when
other processes share the machine. The NumPy twins may use more than one thread inside
SciPy/BLAS unless ``OMP_NUM_THREADS=1`` (set here by default).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

# one core: the kernels are serial, but keep BLAS/SciPy from using the second core
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
import scipy.ndimage as ndi  # noqa: E402

from chunkdic.kernels.b import b_block  # noqa: E402
from chunkdic.kernels.jit import warmup  # noqa: E402
from chunkdic.kernels.m import m_block  # noqa: E402
from chunkdic.kernels.warp import warp_block  # noqa: E402
from chunkdic.kernels.window import g_window, prepare_window  # noqa: E402


def _median_time(fn, repeat):
    """Median wall time and median CPU time of this thread (robust to a busy machine)."""
    wall, cpu = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.thread_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.thread_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--block", type=int, default=128)
    ap.add_argument("--ell", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--numpy", action="store_true", help="also time the NumPy twins")
    args = ap.parse_args(argv)
    n, ell = args.block, args.ell
    pad = 16
    shape = (n + 2 * pad,) * 3
    rng = np.random.default_rng(0)
    vol = ndi.gaussian_filter(rng.random(shape, dtype=np.float32), 1.2)
    vol = ((vol - vol.min()) / (vol.max() - vol.min()) * 255).astype(np.float32)
    f32 = vol[pad - 1:pad + n + 1, pad - 1:pad + n + 1, pad - 1:pad + n + 1]
    f8 = f32.astype(np.uint8)
    g8 = np.roll(vol, (1, -2, 1), axis=(0, 1, 2)).astype(np.uint8)
    lo = hi = (1, 1, 1)
    c0 = (pad, pad, pad)
    core = (n, n, n)
    ne = n // ell + 1
    grid = np.meshgrid(*[np.linspace(-1, 1, ne)] * 3, indexing="ij")
    u = np.stack([1.3 + 0.8 * grid[1], -2.2 + 0.5 * grid[0] * grid[2], 0.7 - 0.6 * grid[2]])
    halo = 12
    # B-spline coefficients of the whole deformed volume, float32 (computed once)
    coef = ndi.spline_filter(g8.astype(np.float32), order=3, mode="mirror",
                             output=np.float32)
    warmup()
    nvox = n**3
    print(f"block {n}^3, ell {ell}, one core, median of {args.repeat} runs")
    print(f"  {'kernel':<42s} {'Mvox/s':>8s} {'(cpu)':>8s}   wall ms")
    rows = []

    def bench(name, fn):
        t, c = _median_time(fn, args.repeat)
        rows.append((name, nvox / t / 1e6, nvox / c / 1e6))
        print(f"  {name:<42s} {nvox / t / 1e6:8.1f} {nvox / c / 1e6:8.1f}   {t * 1e3:7.1f}",
              flush=True)

    impls = ["numba"] + (["numpy"] if args.numpy else [])
    for impl in impls:
        bench(f"M build        f float32  [{impl}]", lambda: m_block(f32, lo, hi, ell,
                                                                          impl=impl))
        bench(f"M build        f uint8    [{impl}]", lambda: m_block(f8, lo, hi, ell,
                                                                          impl=impl))
        for interp in ("linear", "cubic"):
            win = g_window(c0, core, u, shape, interpolation=interp, halo=halo)
            gw = g8[win]
            go = tuple(w.start for w in win)
            bench(f"b pass {interp:<7s} f float32  [{impl}]",
                  lambda: b_block(f32, lo, hi, ell, u, c0, gw, go, shape,
                                    interpolation=interp, impl=impl))
            bench(f"b pass {interp:<7s} f uint8    [{impl}]",
                  lambda: b_block(f8, lo, hi, ell, u, c0, gw, go, shape,
                                    interpolation=interp, impl=impl))
            bench(f"warp   {interp:<7s}            [{impl}]",
                  lambda: warp_block(ell, u, c0, core, gw, go, shape,
                                       interpolation=interp, impl=impl))
        # cubic on precomputed coefficients (the engine's path): prefilter not timed
        win = g_window(c0, core, u, shape, interpolation="cubic", halo=halo)
        cw = coef[win]
        go = tuple(w.start for w in win)
        bench(f"b pass cubic pf f float32  [{impl}]",
              lambda: b_block(f32, lo, hi, ell, u, c0, cw, go, shape,
                                interpolation="cubic", impl=impl, prefiltered=True))
        bench(f"b pass cubic pf f uint8    [{impl}]",
              lambda: b_block(f8, lo, hi, ell, u, c0, cw, go, shape,
                                interpolation="cubic", impl=impl, prefiltered=True))
        bench(f"warp   cubic pf            [{impl}]",
              lambda: warp_block(ell, u, c0, core, cw, go, shape, interpolation="cubic",
                                   impl=impl, prefiltered=True))
        gw = g8[win]
        if impl == "numba":
            bench("  (cubic prefilter alone, window incl. halo)",
                  lambda: prepare_window(gw, "cubic"))
        by = {name: (wall, cpu) for name, wall, cpu in rows}
        lin = by[f"b pass linear  f float32  [{impl}]"]
        cub = by[f"b pass cubic pf f float32  [{impl}]"]
        print(f"  b pass cost cubic pf / linear [{impl}]: {lin[0] / cub[0]:.2f} (wall), "
              f"{lin[1] / cub[1]:.2f} (cpu)")
    return rows


if __name__ == "__main__":
    main()
