"""CPU seconds and wall of the level-0 ``M`` pass and of the prefilter of ``g``, by how the
scans' chunks are read: through zarr-python (``zarr``, as before), from the chunk files
with no cache (``direct``) or through the process's cache of decoded chunks (``cache``,
the default, ``chunkdic.chunk-cache``).

Each mode runs in its own process on the embedded thread pool: a level-0
:class:`chunkdic.passes.level.LevelPasses` of the pair's scans is built (its ``M`` pass), then its
prefilter of ``g`` over the box a zero field reaches; the process's CPU seconds
(``ru_utime + ru_stime``, its threads included) and wall time of each, its peak RSS, and
the chunks decoded and found in the cache are printed. ``--repeats`` alternates the modes.

Usage (docs/distributed.md, "Reading the scans' chunks")::

    python validation/scale/bench_level0_reads.py /big/grains512 -l 16 --repeats 2
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = r"""
import json, resource, sys, tempfile, time
from pathlib import Path
import numpy as np
import dask
pair, ell, mode, threads = Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3], int(sys.argv[4])
from chunkdic.passes.level import LevelPasses
from chunkdic.method.settings import Settings
from chunkdic.io import chunkread, handles
from chunkdic.io.handles import ArrayRef
from chunkdic.kernels.jit import warmup
from chunkdic.mesh import Mesh
from chunkdic.scheduler import ThreadRunner

if mode == "zarr":
    def no_layout(path, key):  # every read through zarr-python, as before
        return None
    no_layout.cache_clear = lambda: None
    handles.layout_of = no_layout
cache = 0 if mode in ("zarr", "direct") else None
refs = []
for name in ("ref.zarr", "def.zarr"):
    meta = json.loads((pair / name / "0" / "zarr.json").read_text())
    refs.append(ArrayRef("zarr", str(pair / name), "0", tuple(meta["shape"]), meta["data_type"]))
shape = refs[0].shape
n = [(s - 16) // ell for s in shape]  # the run's ROI: whole elements, 8 voxels or more from the faces
mesh = Mesh(tuple((s - k * ell) // 2 for s, k in zip(shape, n)), ell, tuple(n))
warmup()

def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime

out = {"mode": mode}
with dask.config.set({} if cache is None else {"chunkdic.chunk-cache": cache}), \
        tempfile.TemporaryDirectory() as scratch:
    runner = ThreadRunner(threads)
    u = np.zeros((3,) + mesh.nodes_shape)
    c0, w0 = cpu(), time.perf_counter()
    lvl = LevelPasses(0, mesh, refs[0], refs[1], runner, Settings(element_size=ell), Path(scratch))
    lvl.assemble_m(u)
    out["m_cpu"], out["m_wall"] = cpu() - c0, time.perf_counter() - w0
    c = chunkread.chunk_cache()
    counts = (0, 0) if c is None else (c.decoded, c.hits)
    c1, w1 = cpu(), time.perf_counter()
    lvl.prepare(u)
    out["g_cpu"], out["g_wall"] = cpu() - c1, time.perf_counter() - w1
    c = chunkread.chunk_cache()
    out["decoded"], out["hits"] = (None, None) if c is None else (c.decoded - counts[0], c.hits - counts[1])
    out["m_decoded"] = counts[0]
    out["blocks"] = len(lvl.jobs)
    lvl.release()
    runner.close()
out["peak_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(out))
"""


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("pair", type=Path, help="directory holding ref.zarr and def.zarr (level 0 read)")
    p.add_argument("-l", "--element-size", type=int, default=16)
    p.add_argument("--modes", nargs="*", default=["zarr", "direct", "cache"], choices=["zarr", "direct", "cache"])
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--record", type=Path)
    args = p.parse_args(argv)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[2]),
                                                       os.environ.get("PYTHONPATH", "")]))
    runs = []
    for r in range(args.repeats):
        for mode in args.modes:
            load = os.getloadavg()
            done = subprocess.run([sys.executable, "-c", CHILD, str(args.pair), str(args.element_size), mode,
                                   str(args.threads)], env=env, capture_output=True, text=True,
                                  cwd=tempfile.gettempdir())
            if done.returncode:
                print(done.stderr[-2000:], file=sys.stderr)
                return 1
            run = json.loads(done.stdout.strip().splitlines()[-1])
            run["load"] = load
            runs.append(run)
            print(f"{mode:7s} run {r + 1}: M {run['m_cpu']:6.1f} CPU-s {run['m_wall']:6.1f} s wall, "
                  f"prefilter {run['g_cpu']:6.1f} CPU-s {run['g_wall']:6.1f} s wall, peak {run['peak_mib']:.0f} MiB, "
                  f"decoded M {run['m_decoded']} / prefilter {run['decoded']}, hits {run['hits']}; "
                  f"load {load[0]:.1f}", flush=True)
    print("medians:")
    for mode in args.modes:
        rs = [r for r in runs if r["mode"] == mode]
        med = {k: statistics.median(r[k] for r in rs) for k in ("m_cpu", "m_wall", "g_cpu", "g_wall", "peak_mib")}
        print(f"{mode:7s} M {med['m_cpu']:.1f} CPU-s / {med['m_wall']:.1f} s, prefilter {med['g_cpu']:.1f} CPU-s / "
              f"{med['g_wall']:.1f} s, peak {med['peak_mib']:.0f} MiB")
    if args.record:
        args.record.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "runs": runs},
                                          indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
