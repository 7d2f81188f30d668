"""The client's block-Jacobi CG on two cores: each product split between two threads.

Between the passes over the voxels the client solves alone and the machine's other cores
wait: at 1024³ (ℓ = 16, 65³ nodes) 8.4 s of a level 0 of ~120 s were single-threaded CG,
77 ms per iteration, of which the data stencil's product takes 30 ms, the brightness
cells' complement 19, the reweighted Tikhonov penalty 10 and block-Jacobi 16. Every kernel
is ``nogil``: here the calling thread applies the stencil while one more thread applies
the cells and the penalty into a vector of its own (the two halves balance within 10 %),
and block-Jacobi, node by node, is split by halves of the z planes. The same arithmetic as
:func:`~chunkdic.solve.stencil.pcg_block_jacobi` in another order of summation; one
mesh-sized float64 vector more (24 B per node, counted by :mod:`chunkdic.engine.costs`).
"""

from __future__ import annotations

import concurrent.futures
import os
import threading

import numpy as np

from .. import config
from .penalty import add_weighted
from .stencil import _subtract_cells, axpy, block_solve, half_matvec, pcg

#: the two lanes pay from this many nodes (below, the threads' hand-over, ~50 µs per
#: product, outweighs half of a product that takes a millisecond)
LANES_FROM = 8192

_lock = threading.Lock()
_executor: tuple[int, concurrent.futures.ThreadPoolExecutor] | None = None  # (pid, executor)


def second_lane() -> concurrent.futures.ThreadPoolExecutor | None:
    """The one extra thread of the client's CG, or None when the run has a single core
    (``num-threads`` of chunkdic's configuration, else the machine's cores). A forked
    process gets its own: the parent's thread does not exist in it."""
    global _executor
    if int(config.get("num-threads") or os.cpu_count() or 1) < 2:
        return None
    with _lock:
        if _executor is None or _executor[0] != os.getpid():
            _executor = (os.getpid(), concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="chunkdic-cg"))
    return _executor[1]


def pays(nodes_shape, has_second_term: bool) -> bool:
    """Whether :func:`pcg_two_lanes` should replace the serial CG: a second term to hand over
    (cells or a penalty), a mesh of at least :data:`LANES_FROM` nodes and two cores."""
    return has_second_term and int(np.prod(nodes_shape)) >= LANES_FROM and second_lane() is not None


def pcg_two_lanes(H, diag_args, b, x, rtol, maxiter, reg_args, lam, cells, cell, overwrite_b=False) -> int:
    """:func:`~chunkdic.solve.stencil.pcg_block_jacobi` (same arguments, grouped) on two threads.

    ``reg_args``: ``(code, Ke, Kf, sw, ew, freed)`` of :func:`add_weighted` (code 0: no
    penalty). Returns the iterations, -1 if not converged; ``x`` updated in place.
    """
    lane = second_lane()
    code = reg_args[0]
    spare = np.empty_like(b)
    spare_f = spare.reshape(-1)
    half = max(1, H.shape[0] // 2)
    Rd, iz, iy, ix = diag_args

    def second_terms(p):
        spare[:] = 0.0
        if cells.shape[0]:
            _subtract_cells(cells, cell, p, spare)
        if code != 0:
            add_weighted(*reg_args, lam, p, spare)

    def matvec(p, q):
        job = lane.submit(second_terms, p)
        try:
            half_matvec(H, p, q)
        finally:
            job.result()
        axpy(1.0, spare_f, q.reshape(-1))

    def precondition(r, z):
        job = lane.submit(block_solve, H[half:], Rd, iz[half:], iy, ix, lam, r[half:], z[half:])
        try:
            block_solve(H[:half], Rd, iz[:half], iy, ix, lam, r[:half], z[:half])
        finally:
            job.result()

    return pcg(matvec, precondition, b, x, rtol, maxiter, overwrite_b)
