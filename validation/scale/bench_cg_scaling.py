"""The partitioned CG on a cluster: time per iteration measured on a LocalCluster, and a model
fitted to it that predicts larger meshes on more workers (docs/distributed.md, "Scaling").

``measure`` runs ``bench_client_memory.py --element-size 8 --regularize 2 --solves 1
--mesh-data blocks --workers W`` for every ``--cases`` × ``--workers``, ``--repeats`` times
each in a fresh process and cluster (a case is ``SIZE``, or ``SIZE:M`` with ``M`` elements
per node block side instead of the plan's rule), and keeps, for the solve alone, the median
over the repeats of the wall time, bytes the workers sent each other and tasks they ran per
CG iteration; ``--record`` writes them as JSON.

``predict`` fits :func:`iteration_seconds` to a record (:func:`fit`) and prints its
constants, its residuals on the record, and its predictions for 4096³ at ℓ = 8 and 16 on
``--machines`` × ``--workers-per-machine`` single-threaded workers.

The model of one CG iteration on ``W`` single-threaded workers on ``K`` machines, the mesh
of ``N`` nodes in node blocks on a ``g_z × g_y × g_x`` grid::

    t = R · t_rt + T · t_task + N · c / W + ν · N / (K · β)

- ``R`` = :data:`ROUND_TRIPS`: the client's round trips through the scheduler per
  iteration (two steps of ``PartitionedSolver._pcg``, each a ``persist`` waited for and a
  ``compute`` of its dot products);
- ``T`` the tasks per iteration, ``a · B + b · P`` for ``B`` blocks and ``P`` ordered pairs
  of neighbouring blocks (faces, edges and corners: the halo exchanges' slices), ``a`` and
  ``b`` fitted to the counted tasks; ``t_task`` the scheduler's and workers' time per task;
- ``c`` the kernels' seconds per node and iteration (the product of ``M + λR``,
  block-Jacobi, the vector updates), spread over the workers (over at most ``--cores``
  when fitting: the machine's cores);
- ``ν`` the bytes the workers send each other per node and iteration (measured: whole
  blocks move, not only halos; the solution gathered once per solve left out), ``β`` a
  machine's network bandwidth (``--bandwidth``), each machine sending its share ``1/K``.
  On loopback ``β`` is too large to fit: the exchange term is a prediction only.

``t_rt``, ``t_task`` and ``c`` are fitted by non-negative least squares on every measured
case (relative residuals); ``--task-seconds`` predicts with another ``t_task`` besides (a
scheduler on a core of its own). :data:`FITTED` holds the constants fitted on the record,
the defaults of :func:`iteration_seconds` and :func:`tasks_per_iteration`.

Usage::

    nice -n 10 python -m validation run cg_scaling     # measure: validation/scale/records/cg_scaling.json
    python validation/scale/bench_cg_scaling.py predict        # the record by default
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
#: the record the model is fitted on
RECORD = Path(__file__).with_name("records") / "cg_scaling.json"
#: :func:`fit` on :data:`RECORD` (9 cases: 32³ and 64³ nodes in 8 blocks, 64³ in 64; 1, 2, 4
#: workers; the shared 2-core machine, load 0.9-4.9): tasks per block and per pair of
#: touching blocks, seconds per round trip, per task, per node; bytes sent per node
FITTED = {"per_block": 32.4, "per_pair": 2.16, "t_rt": 0.049, "t_task": 1.53e-3, "c": 1.51e-6, "nu": 106.0}


def iteration_seconds(nodes: float, tasks: float, workers: int, *, t_rt: float = FITTED["t_rt"],
                      t_task: float = FITTED["t_task"], c: float = FITTED["c"], exchanged: float = 0.0,
                      machines: int = 1, bandwidth: float = math.inf) -> dict:
    """Predicted wall seconds of one CG iteration, and its parts.

    Parameters
    ----------
    nodes, tasks : float
        Nodes of the mesh; tasks per iteration (:func:`tasks_per_iteration`).
    workers : int
        Single-threaded workers (each running its share of the kernels).
    t_rt, t_task, c : float
        Seconds per round trip, per task, per node and iteration.
    exchanged : float
        Bytes the workers send each other per iteration, in all.
    machines, bandwidth : int, float
        Machines sharing them out; bytes per second of a machine's link.

    Returns
    -------
    dict
        ``fixed`` (round trips and tasks), ``compute``, ``exchange`` and ``total``, seconds.
    """
    fixed = ROUND_TRIPS * t_rt + tasks * t_task
    compute = nodes * c / workers
    exchange = exchanged / machines / bandwidth
    return {"fixed": fixed, "compute": compute, "exchange": exchange, "total": fixed + compute + exchange}


def neighbour_pairs(grid) -> int:
    """Ordered pairs of distinct blocks that touch (face, edge or corner) on a block ``grid``.

    >>> neighbour_pairs((2, 2, 2)), neighbour_pairs((4, 4, 4))  # every other block; (3g - 2)³ - g³
    (56, 936)
    """
    return math.prod(3 * g - 2 for g in grid) - math.prod(grid)


def tasks_per_iteration(grid, per_block: float = FITTED["per_block"], per_pair: float = FITTED["per_pair"]) -> float:
    """Tasks of one CG iteration on node blocks on ``grid``: ``per_block`` a block and
    ``per_pair`` a pair of neighbours (:func:`neighbour_pairs`)."""
    return per_block * math.prod(grid) + per_pair * neighbour_pairs(grid)


def halo_bytes_per_worker(nodes_shape, block_edge: int, workers: int, depth: int = HALO_DEPTH) -> float:
    """Bytes of the vector's halos one worker receives per product: every block's shell
    ``depth`` nodes deep within the mesh (24 B a node), of which the share ``1 - 1/workers``
    comes from other workers, spread over the workers (blocks of ``block_edge`` nodes from
    the mesh's first node, the last ones clipped to it).

    8 blocks, each with (4 + 2)³ - 4³ nodes of halo, half of them from the other worker:

    >>> halo_bytes_per_worker((8, 8, 8), 4, 2) / NODE_BYTES
    304.0
    """
    extents = []
    for n in nodes_shape:  # per axis: (block's nodes, its haloed nodes within the mesh)
        extents.append([(min(i + block_edge, n) - i, min(i + block_edge + depth, n) - max(i - depth, 0))
                        for i in range(0, n, block_edge)])
    shell = sum(math.prod(h for _, h in e) - math.prod(b for b, _ in e)
                for e in ((z, y, x) for z in extents[0] for y in extents[1] for x in extents[2]))
    return shell * NODE_BYTES * (1 - 1 / workers) / workers


def node_grid(size: int, element_size: int, workers: int) -> tuple[tuple[int, int, int], int, tuple]:
    """The level-0 mesh's node shape, node block edge (elements) and block grid of a ``size``³
    scan at ``element_size`` with the plan's rule for ``workers`` tasks at once."""
    from chunkdic import config
    from chunkdic.engine.meshes import plan_meshes
    from chunkdic.solve.nodeblocks import node_block_elements

    mesh = plan_meshes((size,) * 3, element_size=element_size, level=0, coarsest=0)[0]
    m0 = max(1, config.get("block-voxels") // element_size)
    m = node_block_elements(mesh.shape, m0, workers)
    return tuple(mesh.nodes_shape), m, tuple(-(-e // m) for e in mesh.shape)


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


def _grid(row) -> tuple:
    g = round(row["node_blocks"] ** (1 / 3))
    assert g**3 == row["node_blocks"], row
    return (g,) * 3


def fit(rows: list[dict], cores: int) -> dict:
    """The model's constants from the measured rows: ``per_block`` and ``per_pair`` (the
    counted tasks), ``t_rt``, ``t_task`` and ``c`` (non-negative least squares on the times'
    relative residuals, the exchange left out: loopback), ``nu`` (median bytes per node and iteration sent
    between workers, the solution's gather taken out, rows with several workers)."""
    import numpy as np
    from scipy.optimize import nnls

    X = np.array([[r["node_blocks"], neighbour_pairs(_grid(r))] for r in rows], dtype=float)
    (per_block, per_pair), *_ = np.linalg.lstsq(X, np.array([r["tasks_per_iteration"] for r in rows]), rcond=None)
    A = np.array([[ROUND_TRIPS, r["tasks_per_iteration"], r["nodes"] / min(r["workers"], cores)] for r in rows])
    t = np.array([r["seconds_per_iteration"] for r in rows])
    (t_rt, t_task, c), _ = nnls(A / t[:, None], np.ones_like(t))  # relative residuals: 0.8 s and 14 s alike
    nu = statistics.median((r["bytes_per_iteration"] - NODE_BYTES * r["nodes"] / r["iterations"]) / r["nodes"]
                           for r in rows if r["workers"] > 1)
    return {"per_block": float(per_block), "per_pair": float(per_pair), "t_rt": float(t_rt), "t_task": float(t_task),
            "c": float(c), "nu": float(nu)}


def predict(args) -> None:
    rows = json.loads(Path(args.record).read_text())["rows"]  # the raw JSON of measure, or the study's record
    k = fit(rows, args.cores)
    timing = {key: k[key] for key in ("t_rt", "t_task", "c")}
    print(f"fitted on {len(rows)} cases: {k['per_block']:.1f} tasks per node block and {k['per_pair']:.2f} per pair "
          f"of neighbours; round trip {k['t_rt'] * 1e3:.1f} ms, {k['t_task'] * 1e3:.2f} ms per task, "
          f"{k['c'] * 1e9:.0f} ns per node; {k['nu']:.0f} B per node sent between workers")
    print("  measured / model: tasks and s per iteration")
    for r in rows:
        tasks = tasks_per_iteration(_grid(r), k["per_block"], k["per_pair"])
        p = iteration_seconds(r["nodes"], r["tasks_per_iteration"], min(r["workers"], args.cores), **timing)
        print(f"    {r['nodes']:>8} nodes, {r['node_blocks']:>3} blocks, {r['workers']} workers: "
              f"{r['tasks_per_iteration']:.0f} / {tasks:.0f}; {r['seconds_per_iteration']:.3f} / {p['total']:.3f}")
    beta = args.bandwidth * 1e9 / 8
    workers = args.machines * args.workers_per_machine
    print(f"predicted: {args.machines} machines × {args.workers_per_machine} workers, {args.bandwidth:g} Gbit/s per "
          f"machine, {args.iterations} CG iterations per solve, {args.solves} solves per run")
    for t_task in [timing["t_task"], *args.task_seconds]:
        print(f" {t_task * 1e3:.2f} ms per task" + (" (fitted)" if t_task == timing["t_task"] else ""))
        _predict_4096(args, k, dict(timing, t_task=t_task), workers, beta)


def _predict_4096(args, k: dict, timing: dict, workers: int, beta: float) -> None:
    for size, ell in ((4096, 16), (4096, 8)):
        shape, m, grid = node_grid(size, ell, workers)
        nodes, tasks = math.prod(shape), tasks_per_iteration(grid, k["per_block"], k["per_pair"])
        halo = halo_bytes_per_worker(shape, m, workers) * workers
        p = iteration_seconds(nodes, tasks, workers, **timing, exchanged=k["nu"] * nodes, machines=args.machines,
                              bandwidth=beta)
        print(f"  {size}³ ℓ {ell}: {nodes / 1e6:.1f} M nodes, {math.prod(grid)} node blocks of {m}³ elements, "
              f"{tasks:.0f} tasks per iteration; per iteration {p['total']:.1f} s (round trips and tasks "
              f"{p['fixed']:.1f}, kernels {p['compute']:.2f}, exchange {p['exchange']:.2f}: "
              f"{k['nu'] * nodes / args.machines / 2**30:.2f} GiB per machine, halos alone "
              f"{halo / args.machines / 2**30:.3f}); per solve {p['total'] * args.iterations / 60:.1f} min, "
              f"per run {p['total'] * args.iterations * args.solves / 3600:.1f} h")


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
    p.add_argument("record", nargs="?", default=str(RECORD))
    p.add_argument("--cores", type=int, default=os.cpu_count() or 1, help="cores of the machine that measured")
    p.add_argument("--machines", type=int, default=16)
    p.add_argument("--workers-per-machine", type=int, default=16)
    p.add_argument("--bandwidth", type=float, default=10.0, help="Gbit/s per machine")
    p.add_argument("--iterations", type=int, default=11, help="CG iterations per solve")
    p.add_argument("--solves", type=int, default=14, help="solves per run")
    p.add_argument("--task-seconds", type=float, nargs="*", default=[1e-3],
                   help="also predict with these seconds per task")
    args = ap.parse_args(argv)
    if args.cmd == "measure":
        rows = measure(args)
        if args.record:
            Path(args.record).write_text(json.dumps({"rows": rows}, indent=1))
    else:
        predict(args)


if __name__ == "__main__":
    main()
