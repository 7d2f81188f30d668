"""HPC workflow: Dask workers as SLURM jobs (dask-jobqueue), chunkdic driven from the login node.

This script runs on a login (or interactive) node. It starts a Dask scheduler there,
submits ``--jobs`` SLURM jobs that each start ``--processes`` Dask workers sharing
``--cores`` cores and ``--memory``, waits for them, and hands the ``Client`` to
``chunkdic.correlate``. Tasks receive file paths and mesh-sized arrays only, so:

- the scans, the output and chunkdic's scratch directory must be on a file system that
  both the login node and the compute nodes see (``--scratch``, default
  ``WORKDIR/scratch``; the same as ``DASK_CHUNKDIC__SCRATCH_DIRECTORY``);
- ``--local-directory`` is node-local disk for Dask's own spill files (``$TMPDIR``);
- workers must reach the scheduler: ``--interface`` names the cluster network of the
  login node (e.g. ``ib0``); the dashboard then listens there too: reach it with
  ``ssh -L 8787:localhost:8787 login-node`` if it is on ``localhost``, or ask your site.

Needs ``pip install dask-jobqueue``. Example on a real cluster (4 nodes, 2 workers of 16
cores each)::

    python workflows/slurm.py ref.zarr def.zarr --element-size 8 --level 2 \\
        --jobs 4 --cores 32 --processes 2 --memory 180GB --walltime 02:00:00 \\
        --queue compute --account myproj --interface ib0 --local-directory '$TMPDIR' --job-extra=--exclusive \\
        --prologue 'source ~/venvs/chunkdic/bin/activate' --workdir /scratch/$USER/run1

``--print-job-script`` shows the batch script that would be submitted. Where ``sbatch``
is missing (this machine), or with ``--local-standin``, a ``LocalCluster`` with the same
worker layout (``jobs x processes`` workers of ``cores / processes`` threads and
``memory / processes`` each, on 127.0.0.1) stands in for SLURM, so the script runs here::

    python workflows/slurm.py                      # 64³ synthetic pair, stand-in cluster

Re-running resumes an interrupted correlation (e.g. after the walltime of the workers or
of the driver ran out); ``--overwrite`` starts over.
"""

from __future__ import annotations

import argparse
import importlib.util
import shutil
import time
from pathlib import Path

import dask.config
import numpy as np
from dask.utils import format_bytes, parse_bytes
from distributed import Client, LocalCluster

import chunkdic
from chunkdic.results.strain import strain_summary
from chunkdic.synth import synthetic


def show(event: dict) -> None:
    """Print one line per correlation event (``chunkdic correlate`` prints richer ones)."""
    stage = event["stage"]
    if stage == "start":
        print(f"  running on {event['scheduler']}", flush=True)
    elif stage == "iteration":
        print(f"  level {event['level']} iteration {event['iteration']:2d}: gap {100 * event['gap']:.3f} %", flush=True)
    elif stage == "level":
        print(f"  level {event['level']}: {event['status']} in {event['seconds']:.1f} s", flush=True)
    elif stage == "resume":
        print(f"  resuming from the checkpoint: level {event['level']}, iteration {event['iteration']}", flush=True)


def slurm_cluster(args, *, probe: bool = False):
    """A dask-jobqueue ``SLURMCluster`` (nothing is submitted until ``scale``).

    ``probe``: only to render the job script; its scheduler listens on 127.0.0.1.
    """
    from dask_jobqueue import SLURMCluster

    scheduler_options = {"dashboard_address": f":{args.dashboard_port}"}
    if probe:
        scheduler_options = {"host": "127.0.0.1", "dashboard_address": "127.0.0.1:0"}
    return SLURMCluster(
        cores=args.cores,                     # cores per job
        processes=args.processes,             # Dask worker processes per job
        memory=args.memory,                   # memory per job (split between its processes)
        walltime=args.walltime,
        queue=args.queue,
        account=args.account,
        interface=None if probe else args.interface,  # network the compute nodes reach the scheduler on
        local_directory=args.local_directory, # node-local spill space of the workers
        job_extra_directives=args.job_extra,  # more #SBATCH lines, e.g. --exclusive
        job_script_prologue=args.prologue,    # shell lines before the worker starts (venv, modules)
        python=args.python,
        scheduler_options=scheduler_options,
    )


def standin_cluster(args):
    """The same worker layout as the SLURM jobs, as a LocalCluster on 127.0.0.1."""
    threads = max(1, args.cores // args.processes)
    memory = parse_bytes(args.memory) // args.processes
    return LocalCluster(n_workers=args.jobs * args.processes, threads_per_worker=threads,
                        memory_limit=memory, processes=True, host="127.0.0.1",
                        dashboard_address=f"127.0.0.1:{args.dashboard_port}")


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("ref", nargs="?", help="reference scan (default: a synthetic pair)")
    p.add_argument("deformed", nargs="?", help="deformed scan")
    p.add_argument("--workdir", default="chunkdic-slurm", help="output directory (shared file system)")
    p.add_argument("--scratch", default=None, help="chunkdic scratch directory (shared; default WORKDIR/scratch)")
    p.add_argument("--size", type=int, default=64, help="edge of the synthetic scans (no scans given)")
    p.add_argument("--element-size", type=int, default=8, help="element edge, voxels of --level")
    p.add_argument("--level", type=int, default=0, help="pyramid level (2 = the paper's 4^3 compression)")
    g = p.add_argument_group("SLURM jobs (dask-jobqueue)")
    g.add_argument("--jobs", type=int, default=1, help="SLURM jobs (each one node or part of one)")
    g.add_argument("--cores", type=int, default=2, help="cores per job")
    g.add_argument("--processes", type=int, default=2, help="Dask worker processes per job")
    g.add_argument("--memory", default="4GiB", help="memory per job")
    g.add_argument("--walltime", default="01:00:00")
    g.add_argument("--queue", default=None, help="partition (-p)")
    g.add_argument("--account", default=None, help="account (-A)")
    g.add_argument("--interface", default=None, help="network interface of the scheduler, e.g. ib0")
    g.add_argument("--local-directory", default=None, help="node-local disk for Dask spill, e.g. '$TMPDIR'")
    g.add_argument("--job-extra", action="append", default=[], help="extra #SBATCH directive (repeatable)")
    g.add_argument("--prologue", action="append", default=[], help="shell line run before the worker (repeatable)")
    g.add_argument("--python", default=None, help="python of the workers (default: this one)")
    g.add_argument("--dashboard-port", type=int, default=8787, help="0 picks a free port")
    g.add_argument("--wait-timeout", type=float, default=600, help="seconds to wait for the workers")
    p.add_argument("--local-standin", action="store_true", help="use a LocalCluster even if sbatch exists")
    p.add_argument("--print-job-script", action="store_true", help="print the SLURM batch script")
    p.add_argument("--overwrite", action="store_true", help="start over instead of resuming / reusing")
    args = p.parse_args(argv)
    if (args.ref is None) != (args.deformed is None):
        p.error("give both scans or none")
    workdir = Path(args.workdir).resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    scratch = Path(args.scratch or workdir / "scratch")
    scratch.mkdir(parents=True, exist_ok=True)
    output = workdir / "result.zarr"

    use_slurm = not args.local_standin and shutil.which("sbatch") is not None
    job_script = None
    if (args.print_job_script or use_slurm) and importlib.util.find_spec("dask_jobqueue") is None:
        p.error("dask-jobqueue is not installed: pip install dask-jobqueue")
    if args.print_job_script and not use_slurm:
        probe = slurm_cluster(args, probe=True)
        job_script = probe.job_script()
        probe.close()
    n_workers = args.jobs * args.processes
    if use_slurm:
        cluster = slurm_cluster(args)
        job_script = cluster.job_script()
        cluster.scale(jobs=args.jobs)  # or cluster.adapt(minimum_jobs=1, maximum_jobs=args.jobs)
    else:
        print("sbatch not available or --local-standin: a LocalCluster with the same worker layout stands in")
        cluster = standin_cluster(args)
    if job_script is not None and args.print_job_script:
        print("---- SLURM job script ----\n" + job_script + "--------------------------")
    client = Client(cluster)
    try:
        print(f"scheduler {cluster.scheduler_address}; dashboard {client.dashboard_link}")
        print(f"waiting for {n_workers} workers ({args.jobs} jobs x {args.processes} processes, "
              f"{format_bytes(parse_bytes(args.memory) // args.processes)} each)")
        client.wait_for_workers(n_workers, timeout=args.wait_timeout)
        field = None
        if args.ref is None:
            c = (args.size - 1) / 2.0
            field = synthetic.Affine(matrix=((-0.008, 0.0, 0.0), (0.0, 0.002, 0.0), (0.0, 0.0, 0.002)),
                                     center=(c, c, c), translation=(0.9, 0.2, -1.1))
            pair = workdir / "pair"
            if not (pair / "field.json").exists() or args.overwrite:
                synthetic.synthesize(pair, (args.size,) * 3, field=field, seed=3, overwrite=True)
            ref, deformed = pair / "ref.zarr", pair / "def.zarr"
        else:
            ref, deformed = args.ref, args.deformed
        t0 = time.perf_counter()
        with dask.config.set({"chunkdic.scratch-directory": str(scratch)}):
            try:
                if args.overwrite:
                    raise chunkdic.InputError("start over")
                result = chunkdic.open_result(output)
                print(f"{output} is complete: reused (--overwrite to redo)")
            except chunkdic.InputError:  # absent, interrupted (resumed) or --overwrite
                result = chunkdic.correlate(ref, deformed, element_size=args.element_size, level=args.level,
                                            scheduler=client, output=output, overwrite=args.overwrite,
                                            progress=show)
        print(f"{result!r} in {time.perf_counter() - t0:.1f} s")
        s = strain_summary(result)
        print(f"mean strain without the outermost elements: eps_zz {s.eps_zz:+.5f}, tr {s.volume_change:+.5f}")
        info = client.scheduler_info()
        out = {"result": result, "strain": s, "slurm": use_slurm, "job_script": job_script,
               "workers": {a: (w["nthreads"], w["memory_limit"]) for a, w in info["workers"].items()}}
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


if __name__ == "__main__":
    main()
