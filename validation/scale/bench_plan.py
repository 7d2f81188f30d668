"""The plan's estimates against measured time, memory and scratch disk.

For each ``--size``: synthesize a uint16 foam pair with the band field (``chunkdic synth``,
level 0 only, so the run builds its pyramid in scratch as a user's raw scans would),
print the plan of ``chunkdic correlate`` (calibrated), then run it ``--repeats`` times,
each in a fresh process, and measure its wall time, the process's peak RSS (``VmHWM``)
and the scratch directory's peak size (sampled every 0.1 s, in total and per store:
pyramid levels ``scan-*``, haloed ``f`` ``f-level*``, prepared ``g`` ``g-level*``).
Medians of the repeats. Writes a JSON record with ``--record``.

With ``--plan-only`` nothing runs: each size gets a pair of scan groups holding only
metadata (uint16, no chunk written: no disk), and the plan of a level-0 run is printed,
uncalibrated; ``--free`` plans as if the scratch disk had that much free space (e.g.
what is left once the scans are written), so the scratch layout the plan would choose
shows (e.g. the 2048³ pair on this machine's disk). ``--schedulers`` plans each size
for each scheduler (``threads``: the embedded pool; ``local:N``: N single-threaded
workers, as a cluster of N workers), ``--element-sizes`` at each length, and ends with a
table of the figures per process: the client's (base and mesh data), a worker's (base,
its tasks at once and its share of the node blocks), the scratch disk (the node blocks'
files of the embedded scheduler apart) and the time, the voxel passes' and the solves'
parts apart (docs/distributed.md, "Scaling").

Usage::

    python validation/scale/bench_plan.py --sizes 128 256 512 --repeats 2 --record validation/scale/records/bench_plan.json
    python validation/scale/bench_plan.py --plan-only --sizes 2048 --free 39GB
    python validation/scale/bench_plan.py --plan-only --sizes 4096 --element-sizes 16 8 --free 100TB \
        --memory-target 4GiB --schedulers threads local:4 local:16 local:256
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


def empty_pair(workdir: Path, n: int) -> Path:
    """A uint16 pair of ``n``³ scan groups with metadata only (chunks never written)."""
    import zarr

    d = workdir / f"empty{n}"
    for name in ("ref.zarr", "def.zarr"):
        g = zarr.open_group(str(d / name), mode="w", zarr_format=3)
        g.create_array("0", shape=(n,) * 3, chunks=(128,) * 3, dtype="uint16", fill_value=0)
    return d


def plan_only(args, workdir: Path) -> None:
    import dask.utils

    import chunkdic
    from chunkdic.engine import runplan

    if args.free:
        free = int(dask.utils.parse_bytes(args.free))
        runplan._free = lambda path: free
    rows = []
    for n in args.sizes:
        d = empty_pair(workdir, n)
        for ell in args.element_sizes or [args.element_size]:
            for scheduler in args.schedulers:
                p = chunkdic.plan(d / "ref.zarr", d / "def.zarr", element_size=ell,
                                  memory_target=args.memory_target or None, calibrate=False,
                                  scheduler=None if scheduler == "threads" else scheduler)
                print(f"{n}³ uint16 pair ({2 * n**3 * 2 / 1e9:.1f} GB of scans), level 0, ell {ell}, {scheduler}"
                      + (f", scratch disk free {args.free} (simulated)" if args.free else ""))
                print(p.summary())
                print(f"  scratch {p.scratch_bytes / 1e9:.1f} GB ({p.layout}; fast layout "
                      f"{p.fast_scratch_bytes / 1e9:.1f} GB), with the scans "
                      f"{(p.scratch_bytes + 2 * n**3 * 2) / 1e9:.1f} GB")
                rows.append((f"{n}³ ℓ {ell}", scheduler, per_process(p)))
    print(f"\n{'case':<11} {'scheduler':<10} {'nodes':>7} {'mesh data':<8} {'client':>9} {'worker':>9} "
          f"{'scratch':>9} {'blocks':>9} {'output':>9} {'passes':>8} {'solves':>8} {'refused':<8}")
    for case, scheduler, f in rows:
        sizes = ("client", "worker", "scratch", "blocks", "output")
        gib = [f"{f[k] / 2**30:.2f}" if f[k] is not None else "-" for k in sizes]
        print(f"{case:<11} {scheduler:<10} {f['nodes'] / 1e6:>6.1f}M {f['mesh_data']:<8} {gib[0]:>9} {gib[1]:>9} "
              f"{gib[2]:>9} {gib[3]:>9} {gib[4]:>9} {f['passes'] / 60:>7.0f}m {f['solves'] / 60:>7.0f}m {f['refused']}")
    print("(GiB; client: its base and mesh data; worker: its base, tasks at once and share of the node blocks; "
          "blocks: the node blocks' files under the scratch, counted in it; output: the result store; minutes)")


def per_process(p) -> dict:
    """A plan's figures per process (bytes) and its time's parts (seconds): the client's
    (``process_bytes`` when the tasks run in it), a worker's (None with the embedded pool),
    the scratch, the node blocks' files (embedded scheduler; part of ``scratch_bytes``), the
    output, the voxel passes and the solves, and whether :meth:`Plan.check` refuses it and
    why (``memory``, ``disk``; ``no``)."""
    import math

    from chunkdic.errors import DiskSpaceError, InputError

    client = p.base_bytes + p.client_bytes
    worker = None
    if p.separate_client:
        held = p.blocks_bytes / p.workers if p.mesh_data == "workers" else 0
        worker = p.base_bytes + p.task_bytes + held
    else:
        client = p.process_bytes
    try:
        p.check()
        refused = "no"
    except DiskSpaceError:
        refused = "disk"
    except InputError:
        refused = "memory"
    return {"nodes": math.prod(p.levels[-1].nodes), "mesh_data": p.mesh_data, "client": client, "worker": worker,
            "scratch": p.scratch_bytes, "blocks": p.blocks_bytes if p.mesh_data == "disk" else None,
            "output": p.output_bytes,
            "passes": p.seconds - p.solve_seconds, "solves": p.solve_seconds, "refused": refused}


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
    ap.add_argument("--plan-only", action="store_true", help="plan metadata-only pairs, run nothing")
    ap.add_argument("--free", default="", help="with --plan-only: free scratch disk to plan for (e.g. 39GB)")
    ap.add_argument("--element-sizes", type=int, nargs="+", help="with --plan-only: plan each (default --element-size)")
    ap.add_argument("--schedulers", nargs="+", default=["threads"],
                    help="with --plan-only: plan each (threads, local:N)")
    args = ap.parse_args()
    import dask.config

    import chunkdic

    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bench-plan-"))
    if args.plan_only:
        plan_only(args, workdir)
        return
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
