"""Cost of choosing the start by its gap (docs/engine.md, "The start").

A correlation started from an earlier result (``init``) now measures three candidate
starts (the earlier field, no motion, the phase-correlation translation) before it
iterates; one started from its own converged result is the case where that is pure
overhead. Prints the median wall and client CPU time of ``--runs`` such correlations on a
``--size``³ synthetic foam pair (a (2.3, -1.4, 0.7) voxel translation, ℓ = 8) and the
start chosen. Run it on two checkouts (``PYTHONPATH``) to compare; quote ``/proc/loadavg``.

Usage::

    python validation/scripts/bench_start_choice.py --size 64 --runs 5 --workdir /tmp/start
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import chunkdic
from chunkdic.synth import synthetic


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--workdir", type=Path, required=True)
    args = ap.parse_args(argv)
    pair = args.workdir / f"pair{args.size}"
    if not (pair / "def.zarr").exists():
        synthetic.synthesize(pair, (args.size,) * 3, field=synthetic.Translation((2.3, -1.4, 0.7)), seed=0)
    ref, dfm = pair / "ref.zarr", pair / "def.zarr"
    first = chunkdic.correlate(ref, dfm, element_size=8)
    walls, cpus, chosen = [], [], []
    for _ in range(args.runs):
        events = []
        t0, c0 = time.perf_counter(), time.process_time()
        res = chunkdic.correlate(ref, dfm, element_size=8, init=first, progress=events.append)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
        chosen += [e["chosen"] for e in events if e["stage"] == "start-choice"]
    print(f"{args.size}³, init = its own result, {args.runs} runs: wall median {statistics.median(walls):.2f} s, "
          f"client CPU median {statistics.median(cpus):.2f} s, status {res.info['status']}, "
          f"start chosen {sorted(set(chosen)) or 'n/a (no choice on this checkout)'}")
    with open("/proc/loadavg") as fh:
        print("load:", fh.read().strip())


if __name__ == "__main__":
    main()
