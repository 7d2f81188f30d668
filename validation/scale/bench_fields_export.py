"""``chunkdic export --fields`` of one result on the scan's level-0 grid and on coarser grids.

For each ``--fields-level`` asked (default 0 and 2), ``--runs`` times: run
``chunkdic export RESULT --fields OUT --fields-level S`` in a child process (so the
embedded scheduler and the page cache state are those a user gets), time it, read the
estimate it printed first, and measure what it wrote (``du``: bytes on disk after Blosc)
against that estimate (the uncompressed upper bound). Prints the median time per level,
the size on disk, the estimate and their ratio, with ``/proc/loadavg`` before and after
(the machine is shared: say the load with the figures).

Usage::

    python validation/scale/bench_fields_export.py RESULT.zarr --levels 0 2 --runs 2 --workdir /tmp/x
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path


def disk_bytes(path: Path) -> int:
    """Bytes the tree at ``path`` occupies on disk (allocated blocks, as ``du``)."""
    total = 0
    for root, _, files in os.walk(path):
        for name in files:
            total += os.stat(os.path.join(root, name)).st_blocks * 512
    return total


def export_once(result: str, out: Path, level: int) -> tuple[float, str]:
    """One export in a child process: ``(seconds, its stderr)``."""
    if out.exists():
        shutil.rmtree(out)
    cmd = [sys.executable, "-m", "chunkdic", "export", result, "--fields", str(out), "--fields-level", str(level)]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"export failed ({done.returncode}): {done.stderr.strip()}")
    return seconds, done.stderr


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("result")
    ap.add_argument("--levels", type=int, nargs="+", default=[0, 2])
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--workdir", default=".")
    args = ap.parse_args()
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    print(f"load before: {Path('/proc/loadavg').read_text().strip()}")
    rows = []
    for level in args.levels:
        out = work / f"fields-level{level}.zarr"
        times, estimate = [], ""
        for _ in range(args.runs):
            seconds, err = export_once(args.result, out, level)
            times.append(seconds)
            estimate = next((line for line in err.splitlines() if "channels on the scan's" in line), "")
        from chunkdic.export.fields_reader import open_levels

        levels, attrs = open_levels(out)
        meta = attrs["chunkdic"]
        from chunkdic.export.images import image_bytes

        bound = image_bytes([tuple(a.shape[1:]) for a in levels], len(meta["channels"]),
                            int(levels[0].chunks[-1]))
        rows.append((level, tuple(levels[0].shape[1:]), statistics.median(times), times, disk_bytes(out), bound,
                     estimate.split(": ", 1)[-1]))
    print(f"load after: {Path('/proc/loadavg').read_text().strip()}")
    print(f"{'S':>2} {'grid':>14} {'median s':>9} {'runs s':>18} {'on disk MiB':>12} {'bound MiB':>10} {'ratio':>6}")
    for level, shape, med, times, size, bound, _ in rows:
        print(f"{level:>2} {'x'.join(map(str, shape)):>14} {med:9.1f} {' '.join(f'{t:.1f}' for t in times):>18} "
              f"{size / 2**20:12.1f} {bound / 2**20:10.1f} {size / bound:6.3f}")
    for level, *_, estimate in rows:
        print(f"estimate said first, level {level}: {estimate}")


if __name__ == "__main__":
    main()
