"""Speed of the synthetic specimens: texture kernel and ``synthesize`` (writer).

Usage::

    python validation/scale/bench_synth.py [--sizes 256 512 1024] [--repeat 3] [--field band]
                                     [--dtype uint8] [--chunks 128] [--dir DIR]

Prints, for the texture kernel on one thread (reference and deformed 128^3 blocks), the
rate in Mvoxel/s of CPU time; then for each size, ``synthesize`` of a reference +
deformed pair (Dask threads, all cores): wall time (median of ``--repeat`` runs, one run
for sizes >= 1024), voxels written per second, the same per core (wall time x threads)
and per CPU second, and the peak resident memory of the process. Voxels counted: both
scans, ``2 * N^3``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time


def _peak_rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def kernel_rates(field, n: int = 128, repeat: int = 3) -> dict:
    from chunkdic.synth import foam

    foam.render((8, 8, 8), field=field, which="deformed")  # compile / load the cache
    foam.render((8, 8, 8))
    out = {}
    for which in ("reference", "deformed"):
        rates = []
        for _ in range(repeat):
            t0 = time.process_time()
            foam.render((n, n, n), field=field, which=which)
            rates.append(n ** 3 / (time.process_time() - t0) / 1e6)
        out[which] = statistics.median(rates)
    return out


def bench_size(n: int, *, field, dtype: str, chunks: int, repeat: int, root: str) -> dict:
    from chunkdic import config
    from chunkdic.synth import synthetic as S

    threads = config.get("num-threads") or os.cpu_count() or 1
    walls, cpus = [], []
    for i in range(repeat):
        out = os.path.join(root, f"synth{n}")
        t0, c0 = time.perf_counter(), time.process_time()
        S.synthesize(out, (n, n, n), field=field, dtype=dtype, chunks=chunks, overwrite=True)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
        size = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(out) for f in fs)
        shutil.rmtree(out, ignore_errors=True)
        print(f"  run {i + 1}/{repeat}: {walls[-1]:.1f} s wall, {cpus[-1]:.1f} s CPU", flush=True)
    wall, cpu = statistics.median(walls), statistics.median(cpus)
    vox = 2.0 * n ** 3
    return {"n": n, "wall": wall, "cpu": cpu, "rate": vox / wall / 1e6,
            "per_core": vox / wall / threads / 1e6, "per_cpu_s": vox / cpu / 1e6,
            "threads": threads, "stored_mb": size / 1e6, "peak_rss_mb": _peak_rss_mb()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--field", choices=("translation", "affine", "band"), default="band")
    p.add_argument("--dtype", default="uint8")
    p.add_argument("--chunks", type=int, default=128)
    p.add_argument("--dir", default=None, help="scratch directory (default: system temp)")
    args = p.parse_args(argv)

    from chunkdic.synth import foam
    from chunkdic.synth import synthetic as S

    def field_for(n):
        c = (n - 1) / 2.0
        if args.field == "translation":
            return S.Translation((2.3, -1.4, 0.7))
        if args.field == "affine":
            return S.Affine(((-0.01, 0, 0.005), (0, 0, 0), (0.005, 0, 0)), center=(c, c, c))
        return S.Band(center_z=c, width=n / 4.0, strain=-0.05, lateral=0.3, center_y=c,
                      center_x=c)

    print(f"python {sys.version.split()[0]}, {os.cpu_count()} cores, texture "
          f"{foam.TextureParams().to_json()}")
    k = kernel_rates(field_for(128))
    print(f"texture kernel, one thread, 128^3: reference {k['reference']:.2f} Mvoxel/s, "
          f"deformed ({args.field}) {k['deformed']:.2f} Mvoxel/s (per CPU second)", flush=True)
    root = tempfile.mkdtemp(prefix="bench-synth-", dir=args.dir)
    rows = []
    try:
        for n in args.sizes:
            rep = 1 if n >= 1024 else args.repeat
            print(f"synthesize {n}^3 {args.dtype}, field {args.field}, chunks {args.chunks}, "
                  f"{rep} run(s)", flush=True)
            rows.append(bench_size(n, field=field_for(n), dtype=args.dtype, chunks=args.chunks,
                                   repeat=rep, root=root))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print()
    print(f"{'size':>6} {'wall s':>8} {'Mvox/s':>8} {'per core':>9} {'per CPU s':>10} "
          f"{'threads':>7} {'stored MB':>10} {'peak RSS MB':>12}")
    for r in rows:
        print(f"{r['n']:>5}³ {r['wall']:>8.1f} {r['rate']:>8.2f} {r['per_core']:>9.2f} "
              f"{r['per_cpu_s']:>10.2f} {r['threads']:>7d} {r['stored_mb']:>10.1f} "
              f"{r['peak_rss_mb']:>12.0f}")
    print("(voxels = both scans, 2 N^3; per core = Mvox/s / threads; wall = median of runs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
