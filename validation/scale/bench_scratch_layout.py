"""The scratch layouts of a level-0 run side by side: disk, pass times, field.

For each ``--layout`` (``fast``: uncompressed 16-bit stores; ``compact``: a 16× coarser grid,
compressed, :mod:`chunkdic.passes.scratchstore`) and each repeat, a fresh process runs
``chunkdic.correlate`` on a CT-like pair (``chunkdic synth --specimen grains --case band
--noise 0.02``, uint16) with ``chunkdic.scratch-layout`` forced, and reports

- the peak bytes on disk of each level-0 scratch store (sampled every 0.1 s) and per voxel;
- the level-0 ``M`` pass (with the low-pass of ``f`` and the write of its haloed copy), the
  prefilter of ``g`` (from the log) and the median full ``b`` pass, seconds, and the
  process's CPU seconds of the passes (the embedded pool's threads are in it): the CPU
  time depends far less on the load of a shared machine than the wall time;
- the field's error at the nodes against the truth (nodes at least one element inside),
  and the largest change of a node against the first layout's field.

Medians over ``--repeats`` (the layouts' runs interleaved); the load average is printed. Usage::

    python validation/scale/bench_scratch_layout.py PAIR_DIR --repeats 3 --record out.json
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

sys.path.insert(0, str(Path(__file__).parent))
from bench_plan import ScratchSampler  # noqa: E402

RUN = r"""
import json, logging, re, sys, time
import numpy as np
import chunkdic
from chunkdic.analysis.scoring import score_displacement
from chunkdic.synth.fields import Field
events, prep = [], []
class H(logging.Handler):
    def emit(self, rec):
        m = re.search(r"level (\d+): g prepared over .* in ([0-9.]+) s", rec.getMessage())
        if m:
            prep.append((int(m.group(1)), float(m.group(2))))
logging.getLogger("chunkdic").addHandler(H()); logging.getLogger("chunkdic").setLevel(logging.INFO)
pair = sys.argv[1]
t0 = time.perf_counter()
res = chunkdic.correlate(pair + "/ref.zarr", pair + "/def.zarr", element_size=int(sys.argv[2]),
                         progress=lambda e: events.append(e))
seconds = time.perf_counter() - t0
field = Field.from_json(json.load(open(pair + "/field.json"))["field"])
X = res.node_coords
truth = field.displacement(*X)
shape = json.load(open(pair + "/field.json"))["shape"]
score = score_displacement(X, res.displacement, truth, shape, int(sys.argv[2]))
np.save(sys.argv[3], res.displacement)
m = [(e["seconds"], e["cpu_seconds"]) for e in events if e.get("stage") == "matrix" and e["level"] == 0]
b = [(e["assemble_seconds"], e["assemble_cpu_seconds"]) for e in events if e.get("stage") == "iteration"
     and e["level"] == 0 and "assemble_seconds" in e and e["voxels"] > 0]
b = [x for x in b if x[0] > 0.1 * max(y[0] for y in b)]  # not the sampled gap passes (one element in 8)
print(json.dumps({"seconds": seconds, "m_pass": m[0][0], "m_cpu": m[0][1], "b_passes": [x[0] for x in b],
                  "b_cpu": [x[1] for x in b], "prefilter": [p for l, p in prep if l == 0],
                  "status": res.info["status"], "score": score.as_dict()}))
"""


def one_run(pair: Path, ell: int, layout: str, scratch: Path, field_path: Path) -> dict:
    scratch.mkdir(exist_ok=True)
    env = dict(os.environ, DASK_CHUNKDIC__SCRATCH_DIRECTORY=str(scratch), DASK_CHUNKDIC__SCRATCH_LAYOUT=layout)
    sampler = ScratchSampler(scratch)
    sampler.start()
    out = subprocess.run([sys.executable, "-c", RUN, str(pair), str(ell), str(field_path)], env=env,
                         capture_output=True, text=True)
    sampler.stop.set()
    sampler.join()
    if out.returncode:
        raise SystemExit(out.stderr)
    rec = json.loads(out.stdout.strip().splitlines()[-1])
    rec.update(scratch_peak=sampler.peak, scratch_per_store=sampler.per_store)
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("pair", help="folder of a chunkdic synth pair (ref.zarr, def.zarr, field.json)")
    ap.add_argument("--layouts", nargs="+", default=["fast", "compact"])
    ap.add_argument("--element-size", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--record", default=None)
    args = ap.parse_args()
    import numpy as np

    pair = Path(args.pair)
    n = json.loads((pair / "field.json").read_text())["shape"]
    voxels = float(np.prod(n))
    work = Path(tempfile.mkdtemp(prefix="bench-layout-"))
    print(f"load average at start: {os.getloadavg()}")
    rows, first = [], None
    runs_of = {layout: [] for layout in args.layouts}
    for k in range(args.repeats):  # layouts interleaved: the machine's load changes by the minute
        for layout in args.layouts:
            runs_of[layout].append(one_run(pair, args.element_size, layout, work / f"scratch-{layout}-{k}",
                                           work / f"u-{layout}.npy"))
    for layout in args.layouts:
        runs = runs_of[layout]
        u = np.load(work / f"u-{layout}.npy")
        first = u if first is None else first
        change = np.abs(u - first)
        med = {
            "seconds": statistics.median(r["seconds"] for r in runs),
            "m_pass": statistics.median(r["m_pass"] for r in runs),
            "b_pass": statistics.median(statistics.median(r["b_passes"]) for r in runs),
            "m_cpu": statistics.median(r["m_cpu"] for r in runs),
            "b_cpu": statistics.median(statistics.median(r["b_cpu"]) for r in runs),
            "prefilter": statistics.median(r["prefilter"][0] for r in runs if r["prefilter"]),
        }
        stores = {k: max(r["scratch_per_store"].get(k, 0) for r in runs) for k in ("f-level0", "g-level0")}
        row = {"layout": layout, "shape": n, "median": med, "stores_level0": stores,
               "bytes_per_voxel": {k: v / voxels for k, v in stores.items()},
               "scratch_peak": max(r["scratch_peak"] for r in runs), "score": runs[-1]["score"],
               "max_change": float(change.max()), "rms_change": float(np.sqrt((change**2).mean())),
               "statuses": [r["status"] for r in runs], "runs": runs, "load": os.getloadavg()}
        rows.append(row)
        s = row["score"]
        print(f"{layout}: total {med['seconds']:.1f} s, M pass {med['m_pass']:.2f} s (CPU {med['m_cpu']:.2f} s), "
              f"prefilter {med['prefilter']:.2f} s, b pass {med['b_pass']:.2f} s (CPU {med['b_cpu']:.2f} s); level-0 stores f {stores['f-level0'] / 2**20:.1f} MiB "
              f"({stores['f-level0'] / voxels:.2f} B/voxel), g {stores['g-level0'] / 2**20:.1f} MiB "
              f"({stores['g-level0'] / voxels:.2f} B/voxel); peak scratch {row['scratch_peak'] / 2**20:.1f} MiB; "
              f"error rms {s['rms']:.7f} sigma {s['sigma']:.7f} max {s['max_error']:.7f}; change vs {args.layouts[0]} max "
              f"{row['max_change']:.2e} rms {row['rms_change']:.2e}; {row['statuses']}; load {os.getloadavg()[0]:.1f}")
    if args.record:
        Path(args.record).write_text(json.dumps(rows, indent=1, default=str))


if __name__ == "__main__":
    main()
