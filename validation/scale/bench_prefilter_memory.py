"""Peak memory of the prefilter of ``g`` per task, measured alone and two at once.

The plan (``chunkdic/engine/costs.py``) counts a prefilter task as a number of float32
copies of its haloed region. This script measures what one task really adds to a
process's resident memory, on a real scan, in a fresh process per case:

- ``phases`` (one task, alone): the peak over the process's resident memory just before,
  of each step of :func:`chunkdic.passes.prefilter.prepare_task` — the raw read (zarr's
  decoded chunks included), the low-pass/B-spline sweeps, the quantisation and the
  write into the memory-mapped ``.npy`` store (its touched pages count in RSS) — each
  measured by resetting the kernel's high-water mark (``/proc/self/clear_refs``, ``5``)
  before the step and reading ``VmHWM`` after it;
- ``concurrent``: ``--tasks`` tasks at once on a thread pool, as the embedded pool runs
  them (``2 × --tasks`` tasks in all, ``malloc_trim`` after each result as the passes do),
  peak over the resident memory before;
- the seconds per task (median) for the throughput.

``--level``: a level the scan does not store is built first in the temporary directory,
as a run builds its scratch pyramid (uint32 sums in ``chunkdic.chunk-size`` chunks).

The store is a sparse ``.npy`` file of the box of ``g`` a level-0 run prepares (the whole
scan for these pairs: ROI plus margins reach the faces), so the row stride of its mapping
is the run's: the pages a task touches when writing depend on it. The tasks are those of
:func:`chunkdic.passes.prefilter.build_prepared` whose reads decode the most chunks of the
scan (the run's largest), nearest the centre among them.

Usage::

    python validation/scale/bench_prefilter_memory.py /work/big/grains1024/def.zarr --tasks 1 2 --repeats 3
    python validation/scale/bench_prefilter_memory.py /work/big/grains512/def.zarr --edge 128 --tasks 2

The scan is read only; the store goes to a temporary directory (``--tmp``), deleted.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np

MiB = 2**20

CASE = textwrap.dedent(r"""
    import concurrent.futures, json, sys, time
    import numpy as np
    from chunkdic.io.scan import open_scan
    from chunkdic.passes import prefilter as P
    from chunkdic.scheduler import release_freed_memory

    scan, tmp, edge_max, tasks, sigma, interp, halo, per_thread, level = sys.argv[1], sys.argv[2], int(sys.argv[3]), \
        int(sys.argv[4]), float(sys.argv[5]), sys.argv[6], int(sys.argv[7]), int(sys.argv[8]), int(sys.argv[9])
    # a level the scan lacks is built in scratch first, as a run does (uint32 sums, chunkdic.chunk-size chunks)
    g = open_scan(scan).refs([level], scratch_dir=tmp)[level]
    box = tuple((0, n) for n in g.shape)
    grid = P.prepared_grid(g.dtype, sigma, interp)
    dtype = "uint16" if grid[1] > 0 else "float32"
    path = f"{tmp}/g.npy"
    np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=g.shape).flush()
    from chunkdic.io.handles import ArrayRef
    out = ArrayRef("npy", path, "", g.shape, dtype)
    edges = [P.task_edge(n, 1, edge_max) for n in g.shape]
    starts = [range(0, n, e) for n, e in zip(g.shape, edges)]
    regions = [tuple(slice(s, min(s + e, n)) for s, e, n in zip(c, edges, g.shape))
               for c in ((z, y, x) for z in starts[0] for y in starts[1] for x in starts[2])]
    centre = [n / 2 for n in g.shape]
    chunks = g.open().chunks if g.kind == "zarr" else g.shape

    def touched(r):  # chunks of the scan a task's read (its region grown by the halo) decodes
        out = 1
        for s, c, n in zip(r, chunks, g.shape):
            out *= (min(s.stop + halo, n) - 1) // c - max(s.start - halo, 0) // c + 1
        return out

    # the tasks that decode the most chunks first (the run's worst), nearest the centre among them
    regions.sort(key=lambda r: (-touched(r), sum(((s.start + s.stop) / 2 - c) ** 2 for s, c in zip(r, centre))))
    P.prepare_deformed(np.zeros((8, 8, 8), np.float32), sigma, interp)  # kernels loaded

    def status(key):
        return [int(l.split()[1]) * 1024 for l in open("/proc/self/status") if l.startswith(key + ":")][0]

    def reset():
        release_freed_memory()
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return status("VmRSS")

    result = {"chunks_touched": touched(regions[0]), "edges": edges, "haloed": [min(e + 2 * halo, n) for e, n in zip(edges, g.shape)], "tasks": tasks,
              "n_regions": len(regions), "item": np.dtype(dtype).itemsize}
    if tasks == 1:  # the steps of prepare_task, one by one, each with its own peak
        region = regions[0]
        grown = tuple(slice(max(r.start - halo, 0), min(r.stop + halo, n)) for r, n in zip(region, g.shape))
        phases = {}
        r0 = reset(); t0 = time.perf_counter()
        data = g.read(grown)
        phases["read"] = status("VmHWM") - r0; t1 = time.perf_counter()
        r0 = reset()
        prepared = P.prepare_deformed(data, sigma, interp)
        phases["filter"] = status("VmHWM") - r0; t2 = time.perf_counter()
        crop = tuple(slice(r.start - s.start, r.stop - s.start) for r, s in zip(region, grown))
        r0 = reset()
        q = P.quantize(prepared[crop], grid)
        phases["quantize"] = status("VmHWM") - r0
        r0 = reset(); t3 = time.perf_counter()
        local = tuple(slice(r.start - a, r.stop - a) for r, (a, _) in zip(region, box))
        P.write_region(out, local, q)
        phases["write"] = status("VmHWM") - r0; t4 = time.perf_counter()
        held = {"raw": data.nbytes, "float32": prepared.nbytes, "quantized": q.nbytes}
        del data, prepared, q
        result.update(phases=phases, held=held, step_seconds={"read": t1 - t0, "filter": t2 - t1, "write": t4 - t3})
        # the whole task, as the pass runs it
        r0 = reset(); t0 = time.perf_counter()
        P.prepare_task(g, out, box, regions[1], halo, sigma, interp, grid)
        result["task_peak"] = status("VmHWM") - r0
        result["task_seconds"] = time.perf_counter() - t0
    else:
        jobs = regions[: per_thread * tasks]
        seconds = []

        def one(region):
            t = time.perf_counter()
            P.prepare_task(g, out, box, region, halo, sigma, interp, grid)
            return time.perf_counter() - t

        r0 = reset(); t0 = time.perf_counter()
        with concurrent.futures.ThreadPoolExecutor(tasks) as pool:
            for s in pool.map(one, jobs):
                seconds.append(s)
                release_freed_memory()
        result["task_peak"] = status("VmHWM") - r0
        result["wall"] = time.perf_counter() - t0
        result["task_seconds"] = sorted(seconds)[len(seconds) // 2]
    print(json.dumps(result))
""")


def run_case(scan: str, edge: int, tasks: int, sigma: float, interp: str, halo: int, tmp: str,
             per_thread: int, level: int = 0) -> dict:
    with tempfile.TemporaryDirectory(dir=tmp) as d:
        out = subprocess.run([sys.executable, "-c", CASE, scan, d, str(edge), str(tasks), str(sigma), interp,
                              str(halo), str(per_thread), str(level)], capture_output=True, text=True, env=dict(os.environ))
    if out.returncode:
        raise SystemExit(out.stderr)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scan", help="a scan group or array (level 0 is read)")
    p.add_argument("--edge", type=int, nargs="+", default=[None],
                   help="largest task edge(s) (default chunkdic.prepare-voxels)")
    p.add_argument("--tasks", type=int, nargs="+", default=[1, 2], help="tasks at once (1: with the steps' peaks)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--level", type=int, default=0, help="pyramid level of g (built in --tmp if the scan lacks it)")
    p.add_argument("--per-thread", type=int, default=2, help="tasks per thread in the concurrent case")
    p.add_argument("--sigma", type=float, default=1.0)
    p.add_argument("--interpolation", default="cubic")
    p.add_argument("--tmp", default=tempfile.gettempdir(), help="where the sparse store goes (deleted)")
    p.add_argument("--record", type=Path, default=None)
    a = p.parse_args(argv)

    from chunkdic import config
    from chunkdic.engine.costs import prepare_bytes, read_buffer_bytes
    from chunkdic.passes.prefilter import prepare_voxels, prepared_grid, prepared_halo
    from chunkdic.io.scan import open_scan

    scan = open_scan(a.scan)

    def model(edges) -> int:
        """The plan's estimate of one task (costs.prepare_bytes, the read's buffers included)."""
        shape, dtype = scan.shape(a.level), scan.dtype(a.level)
        grown = [min(e + 2 * halo, n) for e, n in zip(edges, shape)]
        return prepare_bytes(edges, a.sigma, a.interpolation, shape=shape, raw_itemsize=np.dtype(dtype).itemsize,
                             quantized=prepared_grid(dtype, a.sigma, a.interpolation)[1] > 0,
                             read_bytes=read_buffer_bytes(scan, a.level, grown))

    halo = prepared_halo(a.sigma, a.interpolation, int(config.get("bspline-halo")))
    print(f"load before: {open('/proc/loadavg').read().split()[:3]}")
    record = {"scan": a.scan, "halo": halo, "cases": {}}
    for edge, tasks in ((e or prepare_voxels(), t) for e in a.edge for t in a.tasks):
        runs = [run_case(a.scan, edge, tasks, a.sigma, a.interpolation, halo, a.tmp, a.per_thread, a.level)
                for _ in range(a.repeats)]
        first = runs[0]
        haloed = first["haloed"]
        float32_copy = 4 * haloed[0] * haloed[1] * haloed[2]
        peak = statistics.median(r["task_peak"] for r in runs)
        secs = statistics.median(r["task_seconds"] for r in runs)
        planned = model(first["edges"]) * tasks
        line = (f"{tasks} task(s) of {'x'.join(map(str, first['edges']))} (haloed {'x'.join(map(str, haloed))}, "
                f"{first['chunks_touched']} chunks read, "
                f"float32 copy {float32_copy / MiB:.1f} MiB): peak +{peak / MiB:.1f} MiB "
                f"({[round(r['task_peak'] / MiB, 1) for r in runs]}), {peak / float32_copy / tasks:.2f} copies per task; "
                f"plan's model {planned / MiB:.1f} MiB; {secs:.2f} s per task")
        print(line)
        if tasks == 1:
            for step in first["phases"]:
                vals = [r["phases"][step] / MiB for r in runs]
                print(f"    {step:9s} peak +{statistics.median(vals):6.1f} MiB  {[round(v, 1) for v in vals]}")
            read = statistics.median((r["phases"]["read"] - r["held"]["raw"]) / MiB for r in runs)
            print(f"    read beyond the raw region (zarr's decoded chunks): +{read:.1f} MiB")
            print(f"    held: {({k: round(v / MiB, 1) for k, v in first['held'].items()})}, step seconds "
                  f"{({k: round(v, 2) for k, v in first['step_seconds'].items()})}")
        record["cases"][f"{edge}/{tasks}"] = {"runs": runs, "peak": peak, "task_seconds": secs, "planned": planned,
                                       "float32_copy": float32_copy}
    print(f"load after: {open('/proc/loadavg').read().split()[:3]}")
    if a.record:
        a.record.write_text(json.dumps(record, indent=1))
    return record


if __name__ == "__main__":
    main()
