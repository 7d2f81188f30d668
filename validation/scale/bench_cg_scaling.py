"""The partitioned CG on a cluster: time per iteration measured on a LocalCluster, and a model
fitted to it that predicts larger meshes on more workers (docs/distributed.md, "Scaling").

``measure`` runs ``bench_client_memory.py --element-size 8 --regularize 2 --solves 1
--mesh-data blocks --workers W`` for every ``--cases`` × ``--workers`` ``--repeats`` times
(a case ``SIZE`` or ``SIZE:M``, ``M`` the elements per node block side, else the plan's rule) (each a fresh process and cluster) and keeps, for the solve alone,
the median over the repeats of the wall time, bytes the workers sent each other and tasks
they ran per CG iteration; ``--record`` writes them as JSON.

``predict`` fits :func:`iteration_seconds` to a record (least squares) and prints its
constants, its residuals on the record, and its predictions for 4096³ at ℓ = 8 and 16 on
``--predict-workers`` workers.

The model of one CG iteration on ``W`` single-threaded workers holding ``B`` node blocks
of ``N`` nodes in all::

    t = R · t_rt + T · t_task + N · c / W + H / β

- ``R`` = :data:`ROUND_TRIPS`: the client's round trips through the scheduler per
  iteration (two steps of ``PartitionedSolver._pcg``, each a ``persist`` waited for and a
  ``compute`` of its dot products);
- ``T`` the tasks per iteration, counted (``τ · B``: tasks per node block and iteration,
  the halo exchanges' slices and the dot products' sums included), ``t_task`` the
  scheduler's and workers' overhead per task;
- ``c`` the kernels' seconds per node and iteration (the product of ``M + λR``,
  block-Jacobi, the vector updates), spread over the workers (over at most ``--cores``
  workers when fitting: the machine's cores);
- ``H`` the halo bytes a worker sends per iteration, ``β`` the network bandwidth
  (``--bandwidth``): the vector's halo of each block, ``PENALTY_DEPTH`` nodes deep, 24 B a
  node, for the share ``1 - 1/W`` of the blocks whose neighbours sit on other workers,
  times ``--halo-factor`` (the measured bytes over that geometric count: Dask moves other
  blocks too, e.g. when it balances tasks). On loopback ``β`` is too large to fit: the
  exchange term is a prediction only.

Usage::

    nice -n 10 python validation/scale/bench_cg_scaling.py measure --record validation/scale/records/cg_scaling.json
    python validation/scale/bench_cg_scaling.py predict validation/scale/records/cg_scaling.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
from pathlib import Path

#: client round trips through the scheduler per CG iteration (PartitionedSolver._pcg: two
#: holder steps, each a persist waited for and a compute of its dot products)
ROUND_TRIPS = 4
#: bytes per node of a vector's halo (three float64 components)
NODE_BYTES = 24
#: nodes deep the halo of a product's vector (the penalty R reaches two nodes)
HALO_DEPTH = 2
#: the mesh and element size the measurements use (``bench_client_memory.py --element-size``)
ELEMENT_SIZE = 8

BENCH = Path(__file__).with_name("bench_client_memory.py")


def iteration_seconds(nodes: float, blocks: float, workers: int, *, t_rt: float, t_task: float, c: float,
                      tasks_per_block: float, halo_bytes: float = 0.0, bandwidth: float = math.inf) -> dict:
    """Predicted wall seconds of one CG iteration, and its three parts.

    Parameters
    ----------
    nodes, blocks : float
        Nodes of the mesh; node blocks.
    workers : int
        Single-threaded workers (each running its share of the kernels).
    t_rt, t_task, c : float
        Seconds per round trip, per task, per node and iteration.
    tasks_per_block : float
        Tasks per node block and iteration.
    halo_bytes, bandwidth : float
        Bytes a worker sends per iteration; bytes per second of its link.

    Returns
    -------
    dict
        ``fixed`` (round trips and tasks), ``compute``, ``exchange`` and ``total``, seconds.
    """
    fixed = ROUND_TRIPS * t_rt + tasks_per_block * blocks * t_task
    compute = nodes * c / workers
    exchange = halo_bytes / bandwidth
    return {"fixed": fixed, "compute": compute, "exchange": exchange, "total": fixed + compute + exchange}


def halo_bytes_per_worker(nodes_shape, block_edge: int, workers: int, depth: int = HALO_DEPTH) -> float:
    """Bytes of the vector's halos one worker receives per product: every block's shell
    ``depth`` nodes deep (24 B a node), of which the share ``1 - 1/workers`` comes from
    other workers, spread over the workers (blocks of ``block_edge`` nodes, the last ones
    clipped to the mesh)."""
    shell = 0
    counts = [[min(block_edge, n - i) for i in range(0, n, block_edge)] for n in nodes_shape]
    for bz in counts[0]:
        for by in counts[1]:
            for bx in counts[2]:
                shell += math.prod(b + 2 * depth for b in (bz, by, bx)) - bz * by * bx
    return shell * NODE_BYTES * (1 - 1 / workers) / workers


def node_blocks(size: int, element_size: int, workers: int) -> tuple[tuple[int, int, int], int, int]:
    """The level-0 mesh's node shape, node block edge (elements) and node blocks of a ``size``³
    scan at ``element_size`` with the plan's rule for ``workers`` tasks at once."""
    from chunkdic import config
    from chunkdic.engine.meshes import plan_meshes
    from chunkdic.solve.nodeblocks import node_block_elements

    mesh = plan_meshes((size,) * 3, element_size=element_size, level=0, coarsest=0)[0]
    m0 = max(1, config.get("block-voxels") // element_size)
    m = node_block_elements(mesh.shape, m0, workers)
    return tuple(mesh.nodes_shape), m, math.prod(-(-e // m) for e in mesh.shape)


def measure(args) -> list[dict]:
    rows = []
    for case in args.cases:
        size, _, edge = case.partition(":")
        size, edge = int(size), int(edge or 0)
        for w in args.workers:
            runs = [_one_run(size, w, edge) for _ in range(args.repeats)]
            row = {k: runs[0][k] for k in ("nodes", "node_blocks", "workers", "iterations")}
            row.update(size=size, node_block_elements=edge or None, runs=runs, load=os.getloadavg())
            row.update({k: statistics.median(r[k] for r in runs)
                        for k in ("seconds_per_iteration", "bytes_per_iteration", "tasks_per_iteration")})
            rows.append(row)
            print(f"{size}³ ℓ {ELEMENT_SIZE}, {row['nodes']} nodes in {row['node_blocks']} blocks, {w} workers: "
                  f"{row['seconds_per_iteration']:.3f} s, {row['bytes_per_iteration'] / 2**20:.2f} MiB, "
                  f"{row['tasks_per_iteration']:.0f} tasks per CG iteration (median of {len(runs)}; "
                  f"load {row['load'][0]:.1f})", flush=True)
    return rows


def _one_run(size: int, workers: int, edge: int) -> dict:
    out = subprocess.run([sys.executable, str(BENCH), "--sizes", str(size), "--element-size", str(ELEMENT_SIZE),
                          "--regularize", "2", "--solves", "1", "--mesh-data", "blocks", "--workers", str(workers),
                          "--node-block-elements", str(edge)], capture_output=True, text=True, check=True)
    line = next(ln for ln in out.stdout.splitlines() if ln.strip().startswith("cg: "))
    return json.loads(line.strip()[4:])


def fit(rows: list[dict], cores: int) -> dict:
    """Least-squares ``t_rt``, ``t_task`` and ``c`` of :func:`iteration_seconds` (the
    exchange left out: loopback) over the record's rows, and ``tasks_per_block``."""
    import numpy as np

    A = np.array([[ROUND_TRIPS, r["tasks_per_iteration"], r["nodes"] / min(r["workers"], cores)] for r in rows])
    t = np.array([r["seconds_per_iteration"] for r in rows])
    (t_rt, t_task, c), *_ = np.linalg.lstsq(A, t, rcond=None)
    tau = statistics.median(r["tasks_per_iteration"] / r["node_blocks"] for r in rows)
    return {"t_rt": float(t_rt), "t_task": float(t_task), "c": float(c), "tasks_per_block": tau}


def halo_factor(rows: list[dict]) -> float:
    """Median of the measured bytes per iteration over the geometric halo count (rows with
    several workers)."""
    ratios = []
    for r in rows:
        if r["workers"] > 1:
            n = round(r["nodes"] ** (1 / 3))
            edge = r["node_block_elements"] or node_blocks(r["size"], ELEMENT_SIZE, r["workers"])[1]
            ratios.append(r["bytes_per_iteration"] / (halo_bytes_per_worker((n,) * 3, edge, r["workers"])
                                                      * r["workers"]))
    return statistics.median(ratios) if ratios else 1.0


def predict(args) -> None:
    rows = json.loads(Path(args.record).read_text())
    k = fit(rows, args.cores)
    factor = halo_factor(rows)
    print(f"fitted on {len(rows)} cases: round trip {k['t_rt'] * 1e3:.1f} ms, per task {k['t_task'] * 1e3:.2f} ms, "
          f"{k['c'] * 1e9:.0f} ns per node; {k['tasks_per_block']:.1f} tasks per node block and iteration; "
          f"bytes sent {factor:.2f} × the geometric halo")
    print("  measured / fitted s per iteration:")
    for r in rows:
        p = iteration_seconds(r["nodes"], r["node_blocks"], min(r["workers"], args.cores), **k)
        print(f"    {r['nodes']:>8} nodes, {r['node_blocks']:>3} blocks, {r['workers']} workers: "
              f"{r['seconds_per_iteration']:.3f} / {p['total']:.3f}")
    beta = args.bandwidth * 1e9 / 8
    print(f"predicted, {args.predict_workers} workers, {args.bandwidth:g} Gbit/s per worker's link, "
          f"{args.iterations} CG iterations per solve, {args.solves} solves per run:")
    for size, ell in ((4096, 16), (4096, 8)):
        shape, m, blocks = node_blocks(size, ell, args.predict_workers)
        nodes = math.prod(shape)
        h = halo_bytes_per_worker(shape, m, args.predict_workers) * factor
        p = iteration_seconds(nodes, blocks, args.predict_workers, **k, halo_bytes=h, bandwidth=beta)
        print(f"  {size}³ ℓ {ell}: {nodes / 1e6:.1f} M nodes, {blocks} node blocks of {m}³ elements; per iteration "
              f"{p['total']:.2f} s (fixed {p['fixed']:.2f}, compute {p['compute']:.3f}, exchange "
              f"{p['exchange']:.4f} for {h / 2**20:.1f} MiB per worker); per solve {p['total'] * args.iterations:.0f} s, "
              f"per run {p['total'] * args.iterations * args.solves / 60:.1f} min")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("measure", help="run the cases on LocalClusters")
    m.add_argument("--cases", nargs="+", default=["256", "512", "512:16"],
                   help="SIZE or SIZE:M (M elements per node block side; else the plan's rule)")
    m.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    m.add_argument("--repeats", type=int, default=3)
    m.add_argument("--record")
    p = sub.add_parser("predict", help="fit the model to a record and predict 4096³")
    p.add_argument("record")
    p.add_argument("--cores", type=int, default=os.cpu_count() or 1, help="cores of the machine that measured")
    p.add_argument("--predict-workers", type=int, default=256)
    p.add_argument("--bandwidth", type=float, default=10.0, help="Gbit/s")
    p.add_argument("--iterations", type=int, default=11, help="CG iterations per solve")
    p.add_argument("--solves", type=int, default=14, help="solves per run")
    args = ap.parse_args(argv)
    if args.cmd == "measure":
        rows = measure(args)
        if args.record:
            Path(args.record).write_text(json.dumps(rows, indent=1))
    else:
        predict(args)


if __name__ == "__main__":
    main()
