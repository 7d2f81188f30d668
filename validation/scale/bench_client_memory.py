"""Client memory and solve time of a full-resolution 2048³ correlation, without the scans.

The client of a correlation never touches voxels: it receives mesh-sized partial sums
from the block tasks, adds them into the nodal stencil of ``M`` (float32), builds the
block-Jacobi preconditioner and solves. Its memory is therefore set by the mesh, and it
can be measured on the real client code (the ``M`` pass of ``LevelPasses`` and the solver)
with the tasks replaced by a stand-in runner that returns, for every block, the stencil
of a random texture block of the right shape (computed once per shape by the real
``kernels_m.m_block``; ``f`` is never read and no scan is needed).

Prints, for each ``--size`` (level-0 edge, ``--element-size`` on level 0): nodes, blocks,
assembly and preconditioner time, the time and CG iterations of ``--solves`` solves with
a random right-hand side, and the client's peak RSS (``VmHWM``). With ``--regularize K``
the solves are of ``M + λ R``, Tikhonov over ``K`` element sizes (its setup, the
multigrid V-cycle's included, counted in the solve time); ``--no-multigrid`` keeps
block-Jacobi there. The default, 2048 with
ell 16, is the mesh of a level-0 run of the scale benchmark (128³ nodes).

``--mesh-data blocks`` puts the stencil in node blocks (docs/distributed.md, "Mesh data
beyond one process"): in files under the scratch read by the embedded scheduler, the
solver's vectors in the process, or with ``--workers N`` persisted with the vectors on a
``LocalCluster`` of N single-threaded worker processes; ``--memory-target`` lets the plan's rule choose
(``auto``). The peak of every process is printed: the client's, and each worker's
(``VmHWM`` read on the worker), with the bytes the workers sent each other, and a line
``cg: {...}`` (JSON) of the solves alone: seconds, bytes sent between workers and tasks run
per CG iteration (``bench_cg_scaling.py`` reads it); ``--node-block-elements`` forces the
node blocks' edge. ``--compare``
also solves the same systems in memory in a second process and prints the relative
difference of the solutions.

Usage::

    python validation/scale/bench_client_memory.py --sizes 1024 2048
"""

from __future__ import annotations

import argparse
import json
import math
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _hwm_mib() -> float:
    return _status_mib("VmHWM")


def _status_mib(field: str) -> float:
    with open("/proc/self/status") as fh:
        return int(re.search(field + r":\s+(\d+)\s+kB", fh.read()).group(1)) / 1024


class _Steps:
    """Peak and resident memory of each step of the client (``--steps``).

    The peak of one step is ``VmHWM`` after it with the high-water mark reset before it
    (``/proc/self/clear_refs``, Linux); the process's peak is the largest of them.
    """

    def __init__(self, show: bool):
        self.show, self.rows, self.peak = show, [], _hwm_mib()

    def run(self, name: str, fn):
        before = _status_mib("VmRSS")
        try:
            with open("/proc/self/clear_refs", "w") as fh:
                fh.write("5")
        except OSError:  # not Linux: the peaks are the process's so far
            pass
        out = fn()
        peak = _hwm_mib()
        self.peak = max(self.peak, peak)
        self.rows.append((name, before, peak, _status_mib("VmRSS")))
        return out

    def print(self) -> None:
        if not self.show:
            return
        print(f"  {'step':<34} {'RSS before':>10} {'peak':>8} {'RSS after':>10}  MiB")
        for name, before, peak, after in self.rows:
            print(f"  {name:<34} {before:>10.0f} {peak:>8.0f} {after:>10.0f}")


class _StandInRunner:
    """Runs no task: returns each block's stencil from a random block of the same shape."""

    local = True

    def __init__(self, seed: int = 0, client=None):
        import numpy as np

        self._rng = np.random.default_rng(seed)
        self._cache: dict = {}
        self.client = client  # a LocalCluster's: the node blocks go to its workers

    def map_unordered(self, fn, args):
        if fn.__name__ == "b_task":
            yield from self._b_pass(args)
            return
        from chunkdic.kernels.m import m_block

        for inputs, job, _u in args:
            # as engine.tasks.m_task: the level's brightness model and cells (their Schur
            # complement, kept by the client)
            key = tuple(job.shape) + (inputs.grey, inputs.grey_cell)
            if key not in self._cache:
                f = self._rng.normal(100.0, 20.0, tuple(n + 2 for n in job.shape)).astype("float32")
                self._cache[key] = m_block(f, (1, 1, 1), (1, 1, 1), job.ell, grey=inputs.grey, center=100.0,
                                           with_lags=True, cell=inputs.grey_cell)
            stencil, fmin, fmax, lags, *cells = self._cache[key]
            yield job.block, stencil, fmin, fmax, lags, None, (cells[0] if cells else None), None  # no crack

    def _b_pass(self, args):
        """A ``b`` pass: each block's partials reduced by the real ``reduce_block`` from random
        element sums of the block's shape (the same for every block: one draw per shape)."""
        import numpy as np

        from chunkdic.method.brightness import reduce_block
        from chunkdic.kernels.blocks import LAGS, ElementSums

        for inputs, job, _u, _active, probes, _probe_active, _other in args:
            key = ("b", inputs.grey, inputs.grey_cell) + tuple(job.block.n_elements)
            if key not in self._cache:
                n = tuple(job.block.n_elements)
                v = self._rng.normal(size=n + (6, 10))
                v[..., 2, :] = 1.0  # the quantity ``1``: the element's voxel count on the diagonal
                gram = np.einsum("...ik,...jk->...ij", v, v) * job.ell**3 / 10
                B = self._rng.normal(size=n + (6, 8, 3))
                # the level's brightness model and cells, as engine.tasks.b_task reduces them
                self._cache[key] = reduce_block(ElementSums(B, gram, 0, np.zeros((6, LAGS + 1))), inputs.grey,
                                                inputs.grey_cell)
            part = self._cache[key]
            yield job.block, part, [(part.scalars, part.n_excluded) for _ in probes], None  # the start gaps' probes; no crack

    def run_everywhere(self, fn):
        fn()


def _worker_peaks(client) -> list[float]:
    """Each worker's peak resident memory (MiB)."""
    return sorted(client.run(_hwm_mib).values())


def _worker_sent(client) -> int:
    """Bytes the workers have sent each other so far."""
    return sum(client.run(lambda dask_worker: dask_worker.transfer_outgoing_bytes_total).values())


def _worker_tasks(client) -> int:
    """Tasks the workers have run so far."""
    return sum(client.run(lambda dask_worker: dask_worker.state.executed_count).values())


class _SolveCounters:
    """Wall time, CG iterations, bytes the workers sent each other and tasks they ran during
    the solves alone (the penalty's setup and the ``M`` pass left out): what a CG iteration
    costs on a cluster (`bench_cg_scaling.py`)."""

    def __init__(self, client):
        self.client, self.seconds, self.iterations, self.sent, self.tasks = client, 0.0, 0, 0, 0

    def solve(self, solver, b):
        before = (_worker_sent(self.client), _worker_tasks(self.client)) if self.client else (0, 0)
        t0 = time.perf_counter()
        x, it = solver.solve(b)
        self.seconds += time.perf_counter() - t0
        self.iterations += it
        if self.client:
            self.sent += _worker_sent(self.client) - before[0]
            self.tasks += _worker_tasks(self.client) - before[1]
        return x, it

    def line(self, nodes: int, blocks: int, workers: int) -> str:
        """One JSON line, prefixed ``cg:``, per iteration."""
        its = max(self.iterations, 1)
        return "cg: " + json.dumps({"nodes": nodes, "node_blocks": blocks, "workers": workers,
                                    "iterations": self.iterations, "seconds_per_iteration": self.seconds / its,
                                    "bytes_per_iteration": self.sent / its, "tasks_per_iteration": self.tasks / its})


def _child(size: int, ell: int, solves: int, regularize: float = 0.0, multigrid: bool = True,
           show_steps: bool = False, iterations: int = 0, mesh_data: str = "client", workers: int = 0,
           save: str | None = None, node_block_elements: int = 0) -> None:
    import dask.config
    import numpy as np

    from chunkdic.method.length import regularize as penalize
    from chunkdic.passes.level import LevelPasses
    from chunkdic.engine.meshes import plan_meshes
    from chunkdic.method.settings import Settings
    from chunkdic.io.handles import ArrayRef
    from chunkdic.solve.cg import warmup

    steps = _Steps(show_steps)
    if node_block_elements:  # the node blocks' edge forced: a cluster's tasks per iteration at a fixed mesh
        from chunkdic.solve import nodeblocks

        nodeblocks.node_block_elements = lambda *_: node_block_elements
    mesh = plan_meshes((size,) * 3, element_size=ell, level=0, coarsest=0)[0]
    f_ref = ArrayRef("zarr", "/nonexistent", "", (size,) * 3, "uint16")  # never opened
    client = cluster = None
    if workers:
        from distributed import Client, LocalCluster

        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, host="127.0.0.1", dashboard_address=None,
                               memory_limit=0)
        client = Client(cluster)
        client.run(warmup)
    runner = _StandInRunner(client=client)
    steps.run("kernels loaded", warmup)
    sent0 = _worker_sent(client) if client else 0
    with tempfile.TemporaryDirectory() as scratch, dask.config.set({"chunkdic.mesh-data": mesh_data}):
        t0 = time.perf_counter()
        # the start field, as a run's: a resident array (the carried field) that the level
        # (its M's field) and the Gauss-Newton state share
        start = np.full((3,) + mesh.nodes_shape, 0.5)
        settings = Settings(element_size=ell)
        lvl = LevelPasses(0, mesh, f_ref, f_ref, runner, settings, Path(scratch))
        op = steps.run("M pass", lambda: lvl.assemble_m(start))
        t_m = time.perf_counter() - t0
        runner._cache.clear()  # the stand-in's blocks: not the client's
        rng = np.random.default_rng(1)
        counters = _SolveCounters(client)
        times, its, solutions = [], [], []
        if not multigrid:
            op.solver.multigrid = False
        for k in range(solves):
            b = rng.normal(size=mesh.nodes_shape + (3,))
            t0 = time.perf_counter()
            if regularize:
                steps.run(f"regularisation {k + 1}", lambda: penalize(op, settings, 0, ell, regularize * ell))
            x, it = steps.run(f"solve {k + 1}", lambda: counters.solve(op.solver, b))
            times.append(time.perf_counter() - t0)
            its.append(it)
            if save:
                solutions.append(x)
            x = None
        b = None  # not the client's: the engine holds its own right-hand sides
        if iterations:
            _gauss_newton(lvl, op, iterations, steps)
        lvl.release()
    nodes = int(np.prod(mesh.nodes_shape))
    print(f"{size:>6} {ell:>4} {nodes:>10} {len(lvl.jobs):>7} {t_m:>12.1f} {statistics.median(times):>9.2f} "
          f"{statistics.median(its):>6.0f} {steps.peak:>14.0f}  {op.solver.__class__.__name__}", flush=True)
    if mesh_data == "blocks":
        print("  " + counters.line(nodes, math.prod(len(c) for c in op.solver.chunks), workers), flush=True)
    if client is not None:
        sent = _worker_sent(client) - sent0
        print(f"  workers' peaks MiB: {', '.join(f'{p:.0f}' for p in _worker_peaks(client))}; "
              f"sent between workers {sent / 2**20:.1f} MiB, {sent / max(sum(its), 1) / 2**20:.2f} MiB per CG "
              f"iteration; {statistics.median(times) / max(statistics.median(its), 1) * 1e3:.0f} ms per CG iteration",
              flush=True)
        client.close()
        cluster.close()
    if save:
        np.save(save, np.stack(solutions))
    steps.print()


def _gauss_newton(lvl, op, iterations: int, steps: "_Steps") -> None:
    """``iterations`` passes of the engine's own Gauss–Newton loop (``gauss_newton.iterate``:
    the ``b`` pass's sums on the client, the brightness fit, the penalty, the solve, the
    noise step, the state and its best field) on stand-in ``b`` partials, then the nodal
    uncertainty a result reports: what a level-0 run holds on top of ``M`` and its solver."""
    from chunkdic.method.gauss_newton import iterate
    from chunkdic.method.noise import nodal_uncertainty
    from chunkdic.method.stopping import History, State

    state = State(op.built_at)  # the level's start, as a new level's (method.start.fresh_state)
    state = steps.run(f"Gauss-Newton, {iterations} passes",
                      lambda: iterate(lvl, op, state, 0.0, iterations, History(), None)[0])
    steps.run("nodal uncertainty", lambda: nodal_uncertainty(op.solver, 1.0, 1.0))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[2048])
    p.add_argument("--element-size", type=int, default=16)
    p.add_argument("--solves", type=int, default=3)
    p.add_argument("--regularize", type=float, default=0.0, help="Tikhonov length, element sizes (0: none)")
    p.add_argument("--no-multigrid", action="store_true", help="block-Jacobi even where the V-cycle would be used")
    p.add_argument("--steps", action="store_true", help="print each step's peak and resident memory")
    p.add_argument("--iterations", type=int, default=0,
                   help="then this many Gauss-Newton passes of the engine's loop on stand-in b partials")
    p.add_argument("--mesh-data", choices=("client", "blocks"), default="client",
                   help="where the stencil and the solver's vectors live (chunkdic.mesh-data)")
    p.add_argument("--memory-target", help="plan's rule: blocks when the client's mesh data exceed it (e.g. 2GiB)")
    p.add_argument("--workers", type=int, default=0, help="node blocks on a LocalCluster of this many workers")
    p.add_argument("--node-block-elements", type=int, default=0,
                   help="elements per node block side (a multiple of the voxel blocks'; default: the plan's rule)")
    p.add_argument("--compare", action="store_true",
                   help="also solve in memory and print the relative difference of the solutions")
    p.add_argument("--save", help=argparse.SUPPRESS)
    p.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        _child(args.child, args.element_size, args.solves, args.regularize, not args.no_multigrid, args.steps,
               args.iterations, args.mesh_data, args.workers, args.save, args.node_block_elements)
        return
    print("  size  ell      nodes  blocks  M assembly s   solve s  CG it  client peak MiB  solver")
    for size in args.sizes:  # one process per size: each peak is its own
        mesh_data = args.mesh_data
        if args.memory_target:
            mesh_data = _placement(size, args.element_size, args.memory_target)
            print(f"  memory target {args.memory_target}: mesh data in the {mesh_data}")
        runs = [(mesh_data, args.workers)] + ([("client", 0)] if args.compare else [])
        saved = []
        for mode, workers in runs:
            out = tempfile.NamedTemporaryFile(suffix=".npy", delete=False).name if args.compare else None
            subprocess.run([sys.executable, __file__, "--child", str(size), "--element-size", str(args.element_size),
                            "--solves", str(args.solves), "--regularize", str(args.regularize),
                            "--mesh-data", "blocks" if mode == "blocks" else "client", "--workers", str(workers)]
                           + (["--no-multigrid"] if args.no_multigrid else []) + (["--steps"] if args.steps else [])
                           + ["--iterations", str(args.iterations), "--node-block-elements",
                              str(args.node_block_elements)] + (["--save", out] if out else []),
                           check=True)
            saved.append(out)
        if args.compare:
            import numpy as np

            a, b = np.load(saved[0]), np.load(saved[1])
            print(f"  relative difference of the solutions: {np.linalg.norm(a - b) / np.linalg.norm(b):.2e}")
            for path in saved:
                Path(path).unlink()


def _placement(size: int, ell: int, target: str) -> str:
    """``blocks`` or ``client``: the plan's rule (:func:`chunkdic.engine.processmemory.mesh_placement`) for this mesh."""
    import math

    from chunkdic.engine.costs import CLIENT_BYTES_PER_NODE, base_bytes
    from chunkdic.engine.meshes import plan_meshes
    from chunkdic.inputs import parse_memory

    mesh = plan_meshes((size,) * 3, element_size=ell, level=0, coarsest=0)[0]
    need = base_bytes() + CLIENT_BYTES_PER_NODE * math.prod(mesh.nodes_shape)
    return "blocks" if need > parse_memory(target) else "client"


if __name__ == "__main__":
    main()
