"""The plan's estimates against measured time, memory and scratch disk (issue 21 item 4).

For each ``--size``: synthesize a uint16 foam pair with the band field (``chunkdic synth``,
level 0 only, so the run builds its pyramid in scratch as a user's raw scans would),
print the plan of ``chunkdic correlate`` (calibrated), then run it ``--repeats`` times,
each in a fresh process, and measure its wall time, the process's peak RSS (``VmHWM``)
and the scratch directory's peak size (sampled every 0.1 s, in total and per store:
pyramid levels ``scan-*``, haloed ``f`` ``f-level*``, prepared ``g`` ``g-level*``).
Medians of the repeats. Writes a JSON record with ``--record``.

Usage::

    python benchmarks/bench_plan.py --sizes 128 256 512 --repeats 2 --record benchmarks/records/bench_plan.json
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

RUN = """
import json, sys, time, chunkdic
t0 = time.perf_counter()
res = chunkdic.correlate(sys.argv[1], sys.argv[2], element_size=int(sys.argv[3]), memory_target=sys.argv[4] or None)
peak = [int(l.split()[1]) * 1024 for l in open("/proc/self/status") if l.startswith("VmHWM")][0]
print(json.dumps({"seconds": time.perf_counter() - t0, "peak": peak, "status": res.info["status"]}))
"""


def _store_kind(name: str) -> str:
    for prefix in ("scan-", "f-level", "g-level"):
        if name.startswith(prefix):
            return prefix + re.sub(r"\D.*", "", name[len(prefix):]) if prefix != "scan-" else "pyramids"
    return "other"


class ScratchSampler(threading.Thread):
    """Peak bytes under ``root`` (total and per store kind) while running."""

    def __init__(self, root: Path):
        super().__init__(daemon=True)
        self.root, self.stop, self.peak, self.per_store = root, threading.Event(), 0, {}

    def run(self):
        while not self.stop.is_set():
            sizes: dict = {}
            for dirpath, _, files in os.walk(self.root):
                rel = Path(dirpath).relative_to(self.root).parts
                for f in files:
                    kind = _store_kind(rel[1] if len(rel) > 1 else f)
                    try:
                        sizes[kind] = sizes.get(kind, 0) + os.stat(os.path.join(dirpath, f)).st_blocks * 512
                    except OSError:
                        pass
            total = sum(sizes.values())
            self.peak = max(self.peak, total)
            for k, v in sizes.items():
                self.per_store[k] = max(self.per_store.get(k, 0), v)
            time.sleep(0.1)


def synthesize(workdir: Path, n: int) -> Path:
    d = workdir / f"foam{n}"
    if not (d / "def.zarr").exists():
        subprocess.run([sys.executable, "-m", "chunkdic", "synth", str(d), "--shape", str(n), "--field", "band",
                        "--dtype", "uint16", "-q", "--overwrite"], check=True)
    return d


def one_run(d: Path, ell: int, target: str, scratch: Path) -> dict:
    scratch.mkdir(exist_ok=True)
    env = dict(os.environ, DASK_CHUNKDIC__SCRATCH_DIRECTORY=str(scratch))
    sampler = ScratchSampler(scratch)
    sampler.start()
    out = subprocess.run([sys.executable, "-c", RUN, str(d / "ref.zarr"), str(d / "def.zarr"), str(ell), target],
                         env=env, capture_output=True, text=True, check=True)
    sampler.stop.set()
    sampler.join()
    rec = json.loads(out.stdout.strip().splitlines()[-1])
    rec.update(scratch_peak=sampler.peak, scratch_per_store=sampler.per_store)
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    ap.add_argument("--element-size", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--memory-target", default="")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--record", default=None)
    args = ap.parse_args()
    import dask.config

    import chunkdic

    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bench-plan-"))
    rows = []
    print(f"load average at start: {os.getloadavg()}")
    for n in args.sizes:
        d = synthesize(workdir, n)
        scratch = workdir / f"scratch{n}"
        scratch.mkdir(exist_ok=True)
        with dask.config.set({"chunkdic.scratch-directory": str(scratch)}):
            plan = chunkdic.plan(d / "ref.zarr", d / "def.zarr", element_size=args.element_size,
                                 memory_target=args.memory_target or None)
        print(plan.summary())
        runs = [one_run(d, args.element_size, args.memory_target, scratch) for _ in range(args.repeats)]
        med = {k: statistics.median(r[k] for r in runs) for k in ("seconds", "peak", "scratch_peak")}
        per_store = {k: max(r["scratch_per_store"].get(k, 0) for r in runs)
                     for k in set().union(*(r["scratch_per_store"] for r in runs))}
        row = {"size": n, "element_size": args.element_size, "estimate_seconds": plan.seconds,
               "estimate_peak": plan.process_bytes, "estimate_scratch": plan.scratch_bytes,
               "estimate_level_scratch": {lv.level: [lv.f_copy_bytes, lv.prepared_bytes] for lv in plan.levels},
               "estimate_pyramids": plan.pyramid_bytes, "calibration": plan.calibration,
               "measured": runs, "median": med, "scratch_per_store_max": per_store,
               "statuses": [r["status"] for r in runs], "load": os.getloadavg()}
        rows.append(row)
        print(f"{n}³: time {plan.seconds:.1f} s est. / {med['seconds']:.1f} s measured; "
              f"peak {plan.process_bytes / 2**20:.0f} / {med['peak'] / 2**20:.0f} MiB; "
              f"scratch {plan.scratch_bytes / 2**20:.1f} / {med['scratch_peak'] / 2**20:.1f} MiB "
              f"({', '.join(f'{k} {v / 2**20:.1f}' for k, v in sorted(per_store.items()))}); load {os.getloadavg()[0]:.1f}")
    if args.record:
        Path(args.record).write_text(json.dumps(rows, indent=1, default=str))


if __name__ == "__main__":
    main()
