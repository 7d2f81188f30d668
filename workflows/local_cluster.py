"""Local-cluster workflow: start a ``LocalCluster`` yourself and hand its ``Client`` to chunkdic.

Worth it over the embedded default when you want the Dask dashboard (task stream,
per-worker memory), worker processes with a memory limit each, or to keep one cluster
for several correlations (a loading series, a parameter sweep). Everything listens on
127.0.0.1 only: nothing is reachable from the network. To watch the dashboard of a
workstation from your laptop, tunnel it::

    ssh -L 8787:localhost:8787 workstation     # then open http://localhost:8787/status

Run here (a 64³ synthetic pair)::

    python workflows/local_cluster.py

On real scans, e.g. a 16-core, 128 GB workstation::

    python workflows/local_cluster.py ref.zarr def.zarr --element-size 16 \\
        --workers 8 --threads-per-worker 2 --memory-limit 12GiB --workdir run1

The synthetic scans are written by the cluster's workers too (``dask.compute`` uses the
active client). Re-running resumes an interrupted correlation; ``--overwrite`` starts over.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from distributed import Client, LocalCluster

import chunkdic
from chunkdic.results.strain import strain_summary
from chunkdic.synth import synthetic


def show(event: dict) -> None:
    """Print one line per correlation event (``chunkdic correlate`` prints richer ones)."""
    stage = event["stage"]
    if stage == "iteration":
        print(f"  level {event['level']} iteration {event['iteration']:2d}: gap {100 * event['gap']:.3f} %", flush=True)
    elif stage == "level":
        print(f"  level {event['level']}: {event['status']} in {event['seconds']:.1f} s", flush=True)
    elif stage == "resume":
        print(f"  resuming from the checkpoint: level {event['level']}, iteration {event['iteration']}", flush=True)


def start_cluster(workers: int, threads_per_worker: int, memory_limit: str, dashboard_port: int):
    """A LocalCluster of worker processes on loopback (scheduler, workers and dashboard)."""
    cluster = LocalCluster(
        n_workers=workers,
        threads_per_worker=threads_per_worker,
        processes=True,               # one process per worker: a worker's memory is its own
        memory_limit=memory_limit,    # per worker; Dask pauses / restarts a worker above it
        host="127.0.0.1",             # scheduler and workers on loopback only
        dashboard_address=f"127.0.0.1:{dashboard_port}",
    )
    return cluster, Client(cluster)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("ref", nargs="?", help="reference scan (default: a synthetic pair)")
    p.add_argument("deformed", nargs="?", help="deformed scan")
    p.add_argument("--workdir", default="chunkdic-local-cluster", help="output directory")
    p.add_argument("--size", type=int, default=64, help="edge of the synthetic scans (no scans given)")
    p.add_argument("--element-size", type=int, default=8, help="element edge, voxels of --level")
    p.add_argument("--level", type=int, default=0, help="pyramid level (2 = the paper's 4^3 compression)")
    p.add_argument("--workers", type=int, default=2, help="worker processes")
    p.add_argument("--threads-per-worker", type=int, default=1)
    p.add_argument("--memory-limit", default="auto", help="per worker, e.g. 4GiB (auto: RAM / workers)")
    p.add_argument("--dashboard-port", type=int, default=8787, help="0 picks a free port")
    p.add_argument("--overwrite", action="store_true", help="start over instead of resuming / reusing")
    args = p.parse_args(argv)
    if (args.ref is None) != (args.deformed is None):
        p.error("give both scans or none")
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    output = workdir / "result.zarr"

    cluster, client = start_cluster(args.workers, args.threads_per_worker, args.memory_limit, args.dashboard_port)
    try:
        print(f"scheduler {client.scheduler.address}, {len(client.scheduler_info()['workers'])} workers")
        print(f"dashboard: {client.dashboard_link}")
        field = None
        if args.ref is None:
            c = (args.size - 1) / 2.0
            field = synthetic.Affine(matrix=((-0.01, 0.0, 0.0), (0.0, 0.003, 0.0), (0.0, 0.0, 0.003)),
                                     center=(c, c, c), translation=(-0.6, 1.2, 0.3))
            pair = workdir / "pair"
            if not (pair / "field.json").exists() or args.overwrite:
                synthetic.synthesize(pair, (args.size,) * 3, field=field, seed=2, overwrite=True)
            ref, deformed = pair / "ref.zarr", pair / "def.zarr"
        else:
            ref, deformed = args.ref, args.deformed
        t0 = time.perf_counter()
        if output.exists() and not args.overwrite and _complete(output):
            result = chunkdic.open_result(output)
            print(f"{output} is complete: reused (--overwrite to redo)")
        else:
            result = chunkdic.correlate(ref, deformed, element_size=args.element_size, level=args.level,
                                        scheduler=client, output=output, overwrite=args.overwrite, progress=show)
        print(f"{result!r} in {time.perf_counter() - t0:.1f} s")
        s = strain_summary(result)
        print(f"mean strain without the outermost elements: eps_zz {s.eps_zz:+.5f}, tr {s.volume_change:+.5f}")
        out = {"result": result, "strain": s, "scheduler_address": client.scheduler.address,
               "worker_addresses": sorted(client.scheduler_info()["workers"]),
               "dashboard_link": client.dashboard_link}
        if field is not None:
            f = float(result.info["scale"])
            truth = field.displacement(*(f * result.node_coords + (f - 1) / 2)) / f
            out["rms_error"] = np.sqrt(((result.displacement - truth) ** 2).mean(axis=(1, 2, 3)))
            print("RMS nodal error vs the known field (Uz, Uy, Ux): "
                  + ", ".join(f"{v:.4f}" for v in out["rms_error"]) + " voxel")
        return out
    finally:
        client.close()
        cluster.close()


def _complete(path: Path) -> bool:
    try:
        chunkdic.open_result(path)
        return True
    except chunkdic.InputError:
        return False  # an interrupted run: correlate() resumes it


if __name__ == "__main__":
    main()
