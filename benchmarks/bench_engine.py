"""Engine speed and memory: M build, one b iteration, solve, client peak memory.

Builds synthetic foam pairs in Zarr (chunk by chunk) and correlates them on level 0,
printing medians over ``--repeats`` runs:

- M build and one b iteration in voxels per second per core (ROI voxels / wall / cores),
  and, for the thread pool, per CPU-second of the process (robust to a busy machine);
- solve time per iteration and CG iterations;
- peak resident memory of the client process, for the embedded thread pool (tasks run in
  the client process, so this is client + tasks) and for a LocalCluster (client alone);

at each ``--sizes`` (default 256 and 512), so that their growth can be compared with the
growth of the scan (×8) and of the mesh.

Usage::

    python benchmarks/bench_engine.py --sizes 256 512 --repeats 3 --workdir /tmp/chunkdic-bench
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _child(args) -> None:
    """One measured run in a fresh process (so that peak RSS is this run's own)."""
    import resource

    import numpy as np

    import chunkdic

    events = []
    t0 = time.perf_counter()
    res = chunkdic.correlate(
        args.ref, args.deformed, element_size=args.element_size, scheduler=args.scheduler,
        interpolation=args.interpolation, max_iterations=args.iterations, tolerance=0.0,
        progress=events.append,
    )
    wall = time.perf_counter() - t0
    m = [e for e in events if e["stage"] == "matrix" and e["level"] == 0][-1]
    its = [e for e in events if e["stage"] == "iteration" and e["level"] == 0 and e.get("assemble_seconds")]
    out = {
        "voxels": m["voxels"],
        "nodes": int(np.prod(res.displacement.shape[1:])),
        "m_seconds": m["seconds"],
        "m_cpu": m["cpu_seconds"],
        "b_seconds": statistics.median(e["assemble_seconds"] for e in its),
        "b_cpu": statistics.median(e["assemble_cpu_seconds"] for e in its),
        "solve_seconds": statistics.median(e["solve_seconds"] for e in its),
        "cg_iterations": statistics.median(e["cg_iterations"] for e in its),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "wall": wall,
    }
    print(json.dumps(out))


def cpu_rate(med: dict, key: str, scheduler: str) -> str:
    """Voxels per CPU-second: independent of other load on a shared machine. Only for the
    thread pool, where the tasks run in the measured process."""
    if scheduler != "threads":
        return "-"
    return f"{med['voxels'] / med[key] / 1e6:.1f}"


def _make_pair(size: int, workdir: Path) -> dict:
    from chunkdic.synth import synthetic

    out = workdir / f"pair{size}"
    if (out / "field.json").exists():
        return {"reference": str(out / "ref.zarr"), "deformed": str(out / "def.zarr")}
    field = synthetic.Affine(
        matrix=((-0.01, 0.0, 0.005), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
        center=(size / 2,) * 3, translation=(0.4, -0.3, 0.2),
    )
    t0 = time.perf_counter()
    paths = synthetic.synthesize(out, (size,) * 3, field=field, seed=5, overwrite=True)
    print(f"# synthesized {size}^3 pair in {time.perf_counter() - t0:.1f} s", flush=True)
    return paths


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    p.add_argument("--element-size", type=int, default=16)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--iterations", type=int, default=3, help="b iterations per run")
    p.add_argument("--interpolation", default="cubic")
    p.add_argument("--schedulers", nargs="+", default=["threads", "local:2"])
    p.add_argument("--workdir", default=None)
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--ref"), p.add_argument("--deformed"), p.add_argument("--scheduler")
    args = p.parse_args()
    if args.child:
        _child(args)
        return
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="chunkdic-bench-"))
    cores = os.cpu_count()
    print(f"# cores {cores}, element size {args.element_size}, interpolation {args.interpolation}, "
          f"medians of {args.repeats} runs, workdir {workdir}")
    header = (f"{'size':>5} {'scheduler':>9} {'nodes':>7} {'M Mvox/s/core':>14} {'b Mvox/s/core':>14} "
              f"{'M Mvox/cpu-s':>13} {'b Mvox/cpu-s':>13} {'solve s':>8} {'CG it':>6} {'peak RSS MB':>12}")
    rows = []
    for size in args.sizes:
        paths = _make_pair(size, workdir)
        for sched in args.schedulers:
            runs = []
            for _ in range(args.repeats):
                cmd = [sys.executable, __file__, "--child", "--ref", paths["reference"], "--deformed",
                       paths["deformed"], "--scheduler", sched, "--element-size", str(args.element_size),
                       "--iterations", str(args.iterations), "--interpolation", args.interpolation]
                out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
                runs.append(json.loads(out.strip().splitlines()[-1]))
            med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
            rows.append(
                f"{size:>5} {sched:>9} {int(med['nodes']):>7} "
                f"{med['voxels'] / med['m_seconds'] / cores / 1e6:>14.1f} "
                f"{med['voxels'] / med['b_seconds'] / cores / 1e6:>14.1f} "
                f"{cpu_rate(med, 'm_cpu', sched):>13} {cpu_rate(med, 'b_cpu', sched):>13} "
                f"{med['solve_seconds']:>8.3f} {med['cg_iterations']:>6.0f} {med['peak_rss_mb']:>12.0f}"
            )
            print(rows[-1] if len(rows) > 1 else header + "\n" + rows[-1], flush=True)


if __name__ == "__main__":
    main()
