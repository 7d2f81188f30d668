"""Ingest a raw uint8 volume and build 4 pyramid levels; compare with a sequential read.

For each size N (default 512 and 1024), in a fresh child process (so that peak memory is
per size):

1. write ``N^3`` uint8 raw file (foam-like gyroid shells + noise), slab by slab through a
   ``numpy.memmap`` (skipped when the file exists);
2. drop the file from the page cache (``fsync`` + ``posix_fadvise(DONTNEED)``) and time a
   plain sequential read of it (64 MiB ``readinto``): the reference MB/s;
3. drop it again and time ``chunkdic.ingest`` (raw -> Zarr level 0);
4. drop level 0 from the page cache and time ``build_pyramid(levels=4)``.

Throughputs are level-0 bytes per second; the median of ``--runs`` runs is printed, with
the peak resident memory of the process during each phase (psutil, sampled every 20 ms)
and over its whole life (``getrusage``).

Usage::

    python validation/scale/bench_ingest_pyramid.py --sizes 512 1024 --runs 3
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def make_raw(path: Path, n: int, slab: int = 32) -> None:
    """Foam-like uint8 volume: thin gyroid shells (walls ~200) in pores (~30) plus CT-like noise.

    Written slab by slab through a ``numpy.memmap`` window (a few planes mapped at a time).
    """
    if path.exists() and path.stat().st_size == n**3:
        return
    tmp = path.with_suffix(".part")
    with open(tmp, "wb") as f:
        f.truncate(n**3)
    rng = np.random.default_rng(0)
    k = np.float32(2 * np.pi / 24.0)  # ~24-voxel cells
    ax = np.arange(n, dtype=np.float32) * k
    sy, cy = np.sin(ax)[:, None], np.cos(ax)[:, None]
    sx, cx = np.sin(ax)[None, :], np.cos(ax)[None, :]
    sxcy = sx * cy
    for z0 in range(0, n, slab):
        z1 = min(n, z0 + slab)
        mm = np.memmap(tmp, dtype=np.uint8, mode="r+", offset=z0 * n * n, shape=(z1 - z0, n, n))
        for i, z in enumerate(range(z0, z1)):
            sz, cz = np.sin(z * k), np.cos(z * k)
            g = sxcy + (sy * cz + sz * cx)
            plane = np.where(np.abs(g) < 0.35, np.int16(200), np.int16(30))
            plane += rng.integers(-12, 13, (n, n), dtype=np.int16)  # uniform noise, sigma ~7
            mm[i] = np.clip(plane, 0, 255).astype(np.uint8)
        mm.flush()
        del mm
    os.replace(tmp, path)


def drop_cache(path: Path) -> None:
    """Evict ``path`` (a file, or every file under a folder) from the page cache."""
    files = [path] if path.is_file() else [Path(r) / f for r, _, fs in os.walk(path) for f in fs]
    for f in files:
        fd = os.open(f, os.O_RDONLY)
        try:
            os.fsync(fd)
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def sequential_read(path: Path, block: int = 64 * 2**20) -> float:
    buf = bytearray(block)
    view = memoryview(buf)
    t0 = time.perf_counter()
    with open(path, "rb", buffering=0) as f:
        while f.readinto(view):
            pass
    return time.perf_counter() - t0


class PeakRSS:
    """Peak resident set size of this process while the context is open (bytes)."""

    def __init__(self, every: float = 0.02):
        import psutil

        self.proc, self.every, self.peak = psutil.Process(), every, 0
        self._stop = threading.Event()

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self.proc.memory_info().rss)
            self._stop.wait(self.every)

    def __enter__(self):
        self.peak = self.proc.memory_info().rss
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, self.proc.memory_info().rss)


def cpu() -> float:
    """CPU seconds (user + system) used so far by all threads of this process."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def child(n: int, workdir: Path, runs: int) -> dict:
    from chunkdic.io.formats.ingest import ingest
    from chunkdic.io.pyramid import build_pyramid

    raw = workdir / f"foam_{n}.raw"
    t0 = time.perf_counter()
    make_raw(raw, n)
    make_s = time.perf_counter() - t0
    out = workdir / f"foam_{n}.zarr"
    res = {"size": n, "bytes": n**3, "make_s": make_s, "read_s": [], "ingest_s": [], "pyramid_s": [],
           "ingest_rss": [], "pyramid_rss": [], "ingest_cpu": [], "pyramid_cpu": []}
    for module in ("dask.array", "h5py", "tifffile", "zarr"):  # imports out of the timings
        importlib.import_module(module)

    from chunkdic.io.coarsen import coarsen_block

    coarsen_block(np.zeros((4, 4, 4), np.uint8), np.uint16)  # numba import + cached kernel load

    base_rss = PeakRSS().proc.memory_info().rss
    for _ in range(runs):
        drop_cache(raw)
        res["read_s"].append(sequential_read(raw))
        drop_cache(raw)
        shutil.rmtree(out, ignore_errors=True)
        with PeakRSS() as m:
            t0, c0 = time.perf_counter(), cpu()
            ingest(raw, out, shape=(n, n, n), dtype="uint8", voxel_size=4.91, unit="um")
            res["ingest_s"].append(time.perf_counter() - t0)
            res["ingest_cpu"].append(cpu() - c0)
        res["ingest_rss"].append(m.peak)
        drop_cache(out)
        with PeakRSS() as m:
            t0, c0 = time.perf_counter(), cpu()
            build_pyramid(out, 4)
            res["pyramid_s"].append(time.perf_counter() - t0)
            res["pyramid_cpu"].append(cpu() - c0)
        res["pyramid_rss"].append(m.peak)
    res["disk_bytes"] = sum(os.path.getsize(Path(r) / f) for r, _, fs in os.walk(out) for f in fs)
    res["level0_bytes"] = sum(os.path.getsize(Path(r) / f) for r, _, fs in os.walk(out / "0") for f in fs)
    res["base_rss"] = base_rss
    res["maxrss"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    ap.add_argument("--runs", type=int, default=3, help="runs per size (median reported)")
    ap.add_argument("--dir", type=Path, default=None, help="work directory (default: a temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep the raw files and scans")
    ap.add_argument("--compressor", choices=("auto", "zstd", "lz4", "none"), default=None,
                    help="override chunkdic.compressor (default: the package default)")
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child, args.dir, args.runs)))
        return 0
    if args.compressor:
        os.environ["DASK_CHUNKDIC__COMPRESSOR"] = args.compressor
    workdir = args.dir or Path(tempfile.mkdtemp(prefix="chunkdic-bench-"))
    workdir.mkdir(parents=True, exist_ok=True)
    results = []
    load0 = f"{os.getloadavg()[0]:.2f}"
    try:
        for n in args.sizes:
            print(f"size {n}^3 ...", file=sys.stderr, flush=True)
            cmd = [sys.executable, __file__, "--child", str(n), "--dir", str(workdir), "--runs", str(args.runs)]
            out = subprocess.run(cmd, capture_output=True, text=True)
            if out.returncode:
                sys.stderr.write(out.stderr)
                return out.returncode
            results.append(json.loads(out.stdout.strip().splitlines()[-1]))
            if not args.keep:
                for p in workdir.glob(f"foam_{n}.*"):
                    shutil.rmtree(p) if p.is_dir() else p.unlink()
    finally:
        if not args.keep and args.dir is None:
            shutil.rmtree(workdir, ignore_errors=True)
    med = statistics.median
    rows = [
        ("volume (MB)", lambda r: f"{r['bytes'] / 1e6:.0f}"),
        ("runs", lambda r: f"{len(r['read_s'])}"),
        ("sequential read (s)", lambda r: f"{med(r['read_s']):.2f}"),
        ("sequential read (MB/s)", lambda r: f"{r['bytes'] / 1e6 / med(r['read_s']):.0f}"),
        ("ingest (s)", lambda r: f"{med(r['ingest_s']):.2f}"),
        ("ingest (MB/s)", lambda r: f"{r['bytes'] / 1e6 / med(r['ingest_s']):.0f}"),
        ("pyramid 4 levels (s)", lambda r: f"{med(r['pyramid_s']):.2f}"),
        ("pyramid (MB/s of level 0)", lambda r: f"{r['bytes'] / 1e6 / med(r['pyramid_s']):.0f}"),
        ("ingest CPU cores busy", lambda r: f"{med(r['ingest_cpu']) / med(r['ingest_s']):.2f}"),
        ("pyramid CPU cores busy", lambda r: f"{med(r['pyramid_cpu']) / med(r['pyramid_s']):.2f}"),
        ("ingest CPU s per GB", lambda r: f"{med(r['ingest_cpu']) / (r['bytes'] / 1e9):.1f}"),
        ("pyramid CPU s per GB", lambda r: f"{med(r['pyramid_cpu']) / (r['bytes'] / 1e9):.1f}"),
        ("ratio ingest / seq. read", lambda r: f"{med(r['read_s']) / med(r['ingest_s']):.2f}"),
        ("ratio pyramid / seq. read", lambda r: f"{med(r['read_s']) / med(r['pyramid_s']):.2f}"),
        ("level 0 compression ratio", lambda r: f"{r['bytes'] / max(r['level0_bytes'], 1):.2f}"),
        ("disk, all levels (MB)", lambda r: f"{r['disk_bytes'] / 1e6:.0f}"),
        ("RSS after import (MB)", lambda r: f"{r['base_rss'] / 1e6:.0f}"),
        ("peak RSS ingest (MB)", lambda r: f"{max(r['ingest_rss']) / 1e6:.0f}"),
        ("peak RSS pyramid (MB)", lambda r: f"{max(r['pyramid_rss']) / 1e6:.0f}"),
        ("peak RSS process (MB)", lambda r: f"{r['maxrss'] / 1e6:.0f}"),
    ]
    width = max(len(name) for name, _ in rows)
    print(f"{'':{width}}  " + "  ".join(f"{r['size']:>8d}^3" for r in results))
    for name, fmt in rows:
        print(f"{name:{width}}  " + "  ".join(f"{fmt(r):>10s}" for r in results))
    import dask.config

    print(f"cores: {os.cpu_count()}, load average before: {load0}, after: {os.getloadavg()[0]:.2f}; chunk edge 128; "
          f"compressor {dask.config.get('chunkdic.compressor', default='auto')}; "
          "page cache dropped before each read/ingest/pyramid")
    return 0


if __name__ == "__main__":
    sys.exit(main())
