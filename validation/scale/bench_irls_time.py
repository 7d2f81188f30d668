"""Run time of the robust reweighting: the plain penalty against the default, alternated.

The target: the default takes at most 15 % more time than the plain penalty.

Usage::

    python validation/scale/bench_irls_time.py PAIRDIR [ELL] [REPEATS]

``PAIRDIR`` holds ``ref.zarr`` and ``def.zarr`` (e.g. a 300³ grains band written by
``chunkdic synth`` or :func:`chunkdic.synth.synthetic.synthesize` with
``standard_field("band", (300,) * 3)``). After a warm-up on a 100³ ROI (numba caches), the
plain penalty (``regularization_reweights=0``) and the defaults run alternately
``REPEATS`` times in this process; printed per run: wall and CPU seconds (the process's,
threads included: on a shared machine the CPU time is the figure that means something),
status, length, freed terms, Gauss–Newton passes on level 0, the load average; then the
medians. Writes ``time_l<ELL>.json`` into the current directory.
"""

import json
import statistics
import sys
import time
from pathlib import Path

import chunkdic


def main() -> None:
    pair = Path(sys.argv[1])
    ell = int(sys.argv[2]) if len(sys.argv) > 2 else 12
    reps = int(sys.argv[3]) if len(sys.argv) > 3 else 3
    ref, dfm = str(pair / "ref.zarr"), str(pair / "def.zarr")
    chunkdic.correlate(ref, dfm, element_size=ell, roi="100:200,100:200,100:200", regularization_reweights=0)
    out = {"plain": [], "default": []}
    for _ in range(reps):
        for name, opts in (("plain", {"regularization_reweights": 0}), ("default", {})):
            t0, c0 = time.perf_counter(), time.process_time()
            res = chunkdic.correlate(ref, dfm, element_size=ell, **opts)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            reg = res.info["regularization"]
            out[name].append({"wall": wall, "cpu": cpu, "status": res.info["status"], "length": reg["length"],
                              "freed": reg["freed_terms"], "passes": int((res.history["level"] == 0).sum()),
                              "load": open("/proc/loadavg").read().split()[:3]})
            print(name, json.dumps(out[name][-1]), flush=True)
    for name, rows in out.items():
        print(f"{name}: median wall {statistics.median(r['wall'] for r in rows):.1f} s, "
              f"cpu {statistics.median(r['cpu'] for r in rows):.1f} s", flush=True)
    Path(f"time_l{ell}.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
