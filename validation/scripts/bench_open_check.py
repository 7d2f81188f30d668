"""What ``open_scan``'s checks of the chunk files cost on a large scan (docs/safety.md).

Usage::

    python validation/scripts/bench_open_check.py SCAN.zarr [MORE.zarr ...] [--repeats 5] [--threads 8]

For every stored level of each scan: the chunk files' listing (``os.walk`` + ``stat``, one
per file: the missing- and empty-chunk checks), the Blosc frame-header check
(:func:`chunkdic.io.integrity.check_blosc_frames`: one open and 16 bytes per file,
``--threads`` threads) and the whole :func:`chunkdic.open_scan`, each the median of
``--repeats`` runs; the first ``open_scan`` apart (the only run that may find the files'
metadata and headers out of the page cache; this script never evicts anything, so a scan
another process has just read is warm from the start). Reads the scans only.
"""

from __future__ import annotations

import argparse
import statistics
import time


def timed(fn, repeats: int) -> tuple[float, float]:
    """(first run, median of the runs after it) in seconds."""
    times = []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times[0], statistics.median(times[1:])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scans", nargs="+")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None, help="header-reading threads (default: the module's)")
    args = ap.parse_args()

    import chunkdic
    from chunkdic.io import integrity

    if args.threads:
        integrity.HEADER_THREADS = args.threads
    print(f"load {open('/proc/loadavg').read().split()[:3]}, header threads {integrity.HEADER_THREADS}")
    for path in args.scans:
        first, whole = timed(lambda: chunkdic.open_scan(path), args.repeats)  # the first run before anything else
        print(f"{path}: open_scan {whole * 1e3:.0f} ms (first run {first * 1e3:.0f} ms)", flush=True)
        for s, ref in sorted(chunkdic.open_scan(path).stored_refs().items()):
            adir = integrity._array_dir(ref.path, ref.key)
            files = integrity._chunk_files(adir)
            listing = timed(lambda: integrity._chunk_files(adir), args.repeats)[1]
            headers = timed(lambda: integrity.check_blosc_frames(ref.path, ref.key, files=files), args.repeats)[1]
            print(f"  {adir}: level {s}, {len(files)} chunk files: listing {listing * 1e3:.0f} ms, headers "
                  f"{headers * 1e3:.0f} ms ({headers / max(len(files), 1) * 1e6:.1f} µs per file)", flush=True)

if __name__ == "__main__":
    main()
