"""The solver of ``M + λR`` on node blocks: the stencil CG when the mesh does not fit one process.

:class:`PartitionedSolver` is a drop-in for :class:`~chunkdic.solve.cg.StencilSolver`
(the method sees the same operations: ``solve``, ``matvec``, ``data_matvec``,
``stencil_product``, ``regularize``, ``penalty_gradient``, ``local_variances``, the weak
nodes, ``rigid_matrix``), with ``M``'s half stencil and the brightness cells' couplings
held in node blocks (:mod:`chunkdic.solve.nodeblocks`) instead of the client:

- on the workers of a cluster, with every CG vector: each block's haloed stencil is
  persisted once, a product is one task per block over the block and its vector's halo
  (one node for ``M``, two for ``R``; the cells' couplings summed over the block's cells
  and folded onto the next block's first planes), block-Jacobi is node by node, CG's dot
  products are sums of the blocks' partial sums gathered by the client, two passes per
  iteration;
- with the embedded scheduler, in files (:mod:`chunkdic.solve.haloedfiles`), the vectors in
  the process: CG is the in-memory :func:`~chunkdic.solve.stencil.pcg` whose product reads
  each block's haloed stencil once, the penalty and block-Jacobi on the whole vectors.

The same kernels as the in-memory solver run on each block, so the two give the same
iterates to the round-off of the stencil's float32 sums and the dot products' order
(tested at 1e-10).

Preconditioner: block-Jacobi, whatever the length. The V-cycle's coarse levels are not
partitioned; at the lengths where the in-memory solver takes the V-cycle
(:data:`~chunkdic.solve.cg.MULTIGRID_FROM`) block-Jacobi needs several times more
iterations (docs/distributed.md).
"""

from __future__ import annotations

import logging
import math

import dask.array as da
import numpy as np

from ..errors import InputError
from ..warn import warn_user
from .cg import relative_tolerance
from .haloedfiles import HaloedFiles
from .nodeblocks import core_slices, extended_chunks, fold_faces, from_client, haloed
from .penalty import NO_FREED, add_weighted, freed_diagonal
from .regularizer import Regularizer
from .stencil import _subtract_cells, block_solve, half_matvec, no_diagonal, pcg

log = logging.getLogger(__name__)

#: halo of the penalty's product: ``R`` reaches two nodes (second differences, ``Kᵀ P K``)
PENALTY_DEPTH = 2


class BlockStencil:
    """The half stencil of ``M`` in node blocks, as the method's code reads ``solver.matrix``:
    its shape, dtype, and any region as an in-memory array (computed block by block)."""

    def __init__(self, blocks: da.Array, holder):
        self.blocks, self.holder = blocks, holder

    @property
    def shape(self) -> tuple:
        return self.blocks.shape

    @property
    def dtype(self):
        return self.blocks.dtype

    def __getitem__(self, key) -> np.ndarray:
        return np.asarray(self.holder.values(self.blocks[key])[0])


class PartitionedSolver:
    """Preconditioned CG on ``M + λ R`` with ``M`` and the vectors in node blocks.

    Parameters
    ----------
    stencil : dask.array.Array, shape (nz, ny, nx, 14, 3, 3), float32
        The half stencil of ``M`` in node blocks (:func:`~chunkdic.solve.nodeblocks.node_chunks`),
        held by ``holder``.
    holder : WorkerHolder or DiskHolder
        Where the blocks live.
    cells : dask.array.Array, shape (cz, cy, cx, k+1, k+1, k+1, 3, 4), float32, optional
        The brightness cells' couplings, chunked by the cells of each node block (blocks
        hold whole cells).
    cell : int
        ``k``, elements per side of a cell.
    weak_threshold, rtol, maxiter
        As :class:`~chunkdic.solve.cg.StencilSolver`.
    """

    def __init__(self, stencil: da.Array, holder, *, cells: da.Array | None = None, cell: int = 1,
                 files: HaloedFiles | None = None, weak_threshold: float = 1e-3, rtol: float = 1e-5,
                 maxiter: int = 2000):
        self.holder, self.rtol, self.maxiter = holder, rtol, maxiter
        self.cells, self.cell = cells, int(cell)
        self.nodes_shape = tuple(int(n) for n in stencil.shape[:3])
        self.chunks = stencil.chunks[:3]
        self.largest_rhs = 0.0
        self.multigrid = False
        #: with the blocks on disk, the vectors stay in the process (:meth:`_in_process`) and the
        #: products read the stencil's haloed blocks from their files
        self._files = None
        if holder.where == "disk":
            self._files = files if files is not None else HaloedFiles.from_array(
                _flat(stencil), None if cells is None else _flat(cells), self.cell, holder.directory / "haloed",
                holder.threads)
        #: ``M`` restricted to uniform translations, less the brightness cells' share (3, 3),
        #: taken before the weak nodes are held (as the in-memory solver's)
        self.rigid_matrix = self._rigid(stencil)
        # one sweep over the blocks: the float64 mean and smallest eigenvalue of every node
        # (16 B per node in the client), the weak nodes against the means' median
        eig = holder.gather(stencil.map_blocks(_eigenvalues, chunks=self.chunks + ((2,),), drop_axis=[4, 5],
                                               dtype=np.float64))
        scale = float(np.median(eig[..., 0]))
        if not np.isfinite(scale) or scale <= 0:
            raise InputError("the reference image has no gradient in the ROI: nothing to correlate")
        self.weak_nodes = np.argwhere(eig[..., 1] < weak_threshold * scale)
        del eig
        self.scale = scale
        held = np.zeros((0, 3, 3))
        #: the weak nodes' held diagonal blocks less their own (float64, as the float32 stencil
        #: holds them): what the products from the files (which keep the own) add
        self._weak_delta = held
        if len(self.weak_nodes):
            (blocks,) = holder.values(stencil.vindex[tuple(self.weak_nodes.T)][:, 0])
            held = blocks.astype(np.float64) + weak_threshold * scale * np.eye(3)
            self._weak_delta = held.astype(np.float32).astype(np.float64) - blocks.astype(np.float64)
        self._weak_blocks = held
        self.matrix_blocks = stencil
        if len(held):
            self.matrix_blocks = stencil.map_blocks(_hold_weak, nodes=self.weak_nodes, blocks=held.astype(np.float32),
                                                    dtype=stencil.dtype)
        self._Hh = None
        if self._files is None:
            # on the workers: each block's haloed stencil held once, the blocks' own nodes read
            # from it, so that a product moves only its vector's halo
            self._Hh = holder.hold(haloed(_flat(self.matrix_blocks), 1), "haloed")
            self.matrix_blocks = self._Hh.map_blocks(_own_nodes, grid=self._Hh.numblocks, new_axis=[4, 5],
                                                     chunks=self.chunks + ((14,), (3,), (3,)), dtype=stencil.dtype)
        self.matrix = BlockStencil(self.matrix_blocks, holder)
        # the node axes and one axis of each node's entries: every block function's arrays
        # are 4-D, aligned block by block (map_blocks aligns trailing axes otherwise)
        self._H = _flat(self.matrix_blocks)
        self._W = None if cells is None else _flat(cells)
        # with the vectors in the process, block-Jacobi's diagonal blocks of M (weak nodes held)
        # in files of their own beside the stencil's, read block by block (36 B per node)
        if self._files is not None:
            self._files.save_diagonal(self.matrix_blocks[..., :1, :, :])
        self.regularizer: Regularizer | None = None
        self.weight = 0.0
        self._reg_args = (0, np.zeros((24, 24)), np.zeros((4, 4)), 0.0, 0.0, NO_FREED)
        self._freed = None
        self._diag_args = no_diagonal(self.nodes_shape)

    # --- products -------------------------------------------------------------------

    def _vector(self, x: np.ndarray, name: str) -> da.Array:
        return from_client(np.ascontiguousarray(x, dtype=np.float64), self.chunks, self.holder, name)

    def _product(self, x: da.Array, data: bool = True, penalty: bool = True, cells: bool = True) -> da.Array:
        """``(M - cells + λ R) x`` on the blocks (each term when asked), a lazy node-block array."""
        reg = penalty and self.regularizer is not None
        depth = PENALTY_DEPTH if reg else 1
        numblocks = x.numblocks
        args = [haloed(x, depth)]
        if data:
            args.append(self._Hh)
        if reg and self._freed is not None:
            args.append(haloed(self._freed, depth))
        y = _map(_product_block, *args, data=data, reg_args=self._reg_args if reg else None,
                          weight=self.weight, depth=depth, grid=numblocks, freed=reg and self._freed is not None,
                          chunks=x.chunks, dtype=np.float64)
        if data and cells and self.cells is not None:
            y = y - self._cells_product(x)
        return y

    def _cells_product(self, x: da.Array) -> da.Array:
        """``Σ_c W_c W_cᵀ x`` over each block's cells, folded onto the node blocks."""
        ext = extended_chunks(self.chunks)
        numblocks = x.numblocks
        part = _map(_cells_block, haloed(x, 1), self._W, k=self.cell, grid=numblocks,
                             chunks=ext + ((3,),), dtype=np.float64)
        return fold_faces(part)

    def _precondition(self, r: da.Array) -> da.Array:
        """Block-Jacobi ``D⁻¹ r`` node by node (the diagonal blocks formed on the fly)."""
        Rd, iz, iy, ix = self._diag_args
        # from the haloed stencil's block itself, not its own nodes' copy (self._H, made by a task
        # of its own): a task needing the stencil's block runs where it is, and r's block moves
        # (24 B per node) if it is elsewhere, not the copy (504 B per node)
        return _map(_jacobi_block, self._Hh, r, Rd=Rd, index=(iz, iy, ix), lam=self.weight, grid=self._Hh.numblocks,
                    chunks=r.chunks, dtype=np.float64)

    def _in_process(self, x: np.ndarray, out: np.ndarray | None, penalty: bool = True,
                    cells: bool = True) -> np.ndarray:
        """``(M - cells + λ R) x`` with ``x`` and the product in the process: the stencil's
        blocks read from their files, the penalty (matrix-free) on the whole vector."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        out = np.empty(x.shape) if out is None else out
        self._files.product(x, out, cells=cells)
        if len(self.weak_nodes):
            nodes = tuple(self.weak_nodes.T)
            out[nodes] += np.einsum("wij,wj->wi", self._weak_delta, x[nodes])
        if penalty and self.regularizer is not None:
            add_weighted(*self._reg_args, self.weight, x, out)
        return out

    def matvec(self, x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``(M + λ R) x`` (nz, ny, nx, 3), float64, in the client."""
        if self._files is not None:
            return self._in_process(x, out)
        return self.holder.gather(self._product(self._vector(x, "in")), out)

    def data_matvec(self, x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``M x`` minus the brightness cells' complement."""
        if self._files is not None:
            return self._in_process(x, out, penalty=False)
        return self.holder.gather(self._product(self._vector(x, "in"), penalty=False), out)

    def stencil_product(self, x: np.ndarray) -> np.ndarray:
        """``M x`` alone (no cells, no penalty)."""
        if self._files is not None:
            return self._in_process(x, None, penalty=False, cells=False)
        return self.holder.gather(self._product(self._vector(x, "in"), penalty=False, cells=False))

    def penalty_gradient(self, a: np.ndarray) -> np.ndarray:
        """``λ R a`` for the total nodal field ``a`` (nz, ny, nx, 3): in the client, as
        :meth:`~chunkdic.solve.cg.StencilSolver.penalty_gradient` (mesh vectors only)."""
        if self.regularizer is None:
            return np.zeros(a.shape)
        y = self.regularizer.apply(a)
        y *= self.weight
        return y

    def _rigid(self, H: da.Array) -> np.ndarray:
        """``Σ_ij M_ij`` (3, 3) less the brightness cells' share (the operator's rigid restriction)."""
        centre, off = self.holder.values(H[..., 0, :, :].sum(axis=(0, 1, 2), dtype=np.float64),
                                         H[..., 1:, :, :].sum(axis=(0, 1, 2, 3), dtype=np.float64))
        rigid = centre + off + off.T
        if self.cells is not None:
            (shares,) = self.holder.values(self.cells.sum(axis=(3, 4, 5), dtype=np.float64))
            shares = shares.reshape(-1, 3, 4)
            rigid = rigid - np.einsum("cip,cjp->ij", shares, shares)
        return rigid

    # --- regularisation and diagonals ------------------------------------------------

    def regularize(self, regularizer: Regularizer | None, weight: float) -> None:
        """Solve ``(M + weight R)`` from now on (``None`` or 0: plain ``M``)."""
        self.regularizer = regularizer if weight > 0 else None
        self.weight = float(weight) if self.regularizer is not None else 0.0
        self._diag_args = no_diagonal(self.nodes_shape)
        self._freed = None
        if self.regularizer is not None:
            self._reg_args = self.regularizer.numba_args()
            blocks, index = self.regularizer.diagonal_classes()
            self._diag_args = (np.ascontiguousarray(blocks, np.float64),
                               *(np.ascontiguousarray(i, np.int64) for i in index))
            if self.regularizer.freed is not None:
                self._freed = from_client(self.regularizer.freed, self.chunks, self.holder, "freed")

    def diagonal_blocks(self, planes: slice = slice(None)) -> np.ndarray:
        """The 3×3 diagonal blocks of ``M`` on the z planes ``planes``, weak nodes held, float64."""
        out = self.matrix[planes, :, :, 0, :, :].astype(np.float64)
        if len(self._weak_blocks):
            z = np.arange(self.nodes_shape[0])[planes]
            inside = np.isin(self.weak_nodes[:, 0], z)
            nodes = self.weak_nodes[inside]
            out[(np.searchsorted(z, nodes[:, 0]), nodes[:, 1], nodes[:, 2])] = self._weak_blocks[inside]
        return out

    def local_variances(self) -> np.ndarray:
        """``diag(A_ii⁻¹ M_ii A_ii⁻¹)`` of every node (nz, ny, nx, 3), float64, block by block."""
        Rd, iz, iy, ix = self._diag_args
        args = [self._H] + ([] if self._freed is None else [haloed(self._freed, PENALTY_DEPTH)])
        y = _map(_variance_block, *args, Rd=Rd, index=(iz, iy, ix), lam=self.weight, grid=self._H.numblocks,
                 weak=(self.weak_nodes, self._weak_blocks), chunks=self.chunks + ((3,),), dtype=np.float64)
        return self.holder.gather(y)

    # --- the solve --------------------------------------------------------------------

    def solve(self, b: np.ndarray, *, overwrite_b: bool = False,
              reference: float | None = None, rtol: float | None = None) -> tuple[np.ndarray, int]:
        """Solve ``(M + λR) x = b`` (nz, ny, nx, 3): :meth:`~chunkdic.solve.cg.StencilSolver.solve`'s
        CG (block-Jacobi). With the blocks on disk its vectors are in the process
        (:func:`~chunkdic.solve.stencil.pcg`, the products block by block from the stencil's
        files; ``overwrite_b`` as in memory); on workers they are node blocks there (``b``
        copied into them); ``reference`` and ``rtol`` as there. Returns the solution (in the
        client) and the number of CG iterations."""
        rtol = relative_tolerance(self, b, reference, rtol)
        if self._files is not None:
            b = np.array(b, dtype=np.float64, order="C", copy=None if overwrite_b else True)
            x = np.zeros_like(b)
            Rd, iz, iy, ix = self._diag_args
            iterations = pcg(self.matvec, lambda r, z: self._files.precondition(r, z, Rd, (iz, iy, ix), self.weight),
                             b, x, rtol, self.maxiter, overwrite_b=True)
            return x, self._iterations(iterations)
        r = self._vector(b, "r")
        x, iterations = self._pcg(r, rtol)
        return self.holder.gather(x), self._iterations(iterations)

    def _iterations(self, iterations: int) -> int:
        if iterations < 0:
            warn_user(f"CG did not reach rtol={self.rtol} in {self.maxiter} iterations", RuntimeWarning)
            return self.maxiter
        return iterations

    def _pcg(self, r: da.Array, rtol: float) -> tuple[da.Array, int]:
        """:func:`~chunkdic.solve.stencil.pcg_block_jacobi` on node blocks from ``x = 0``: two
        passes over the blocks per iteration, each holding its vectors and gathering its dot
        products in the same pass (the new ``p``, ``q = A p`` and ``p·q``; ``x``, ``r``,
        ``r·r`` and ``r·D⁻¹r``)."""
        step, precondition = self.holder.step, self._precondition
        x = da.zeros(r.shape, chunks=r.chunks)
        _, (bb, rz) = step({}, lambda _: [_dot(r, r), _dot(r, precondition(r))])
        bnorm = math.sqrt(bb)
        if bnorm == 0.0:
            return x, 0
        p = precondition(r)
        for it in range(1, self.maxiter + 1):
            held, (pq,) = step({"p": p, "q": self._product(p)}, lambda d: [_dot(d["p"], d["q"])])
            p = held["p"]
            alpha = rz / pq
            held, (rr, rz_new) = step({"x": x + alpha * p, "r": r - alpha * held["q"]},
                                      lambda d: [_dot(d["r"], d["r"]), _dot(d["r"], precondition(d["r"]))])
            x, r = held["x"], held["r"]
            if math.sqrt(rr) <= rtol * bnorm:
                return x, it
            p = precondition(r) + (rz_new / rz) * p
            rz = rz_new
        return x, -1


def _flat(x: da.Array) -> da.Array:
    """``x`` (nodes first) with its trailing axes as one (a single chunk along it)."""
    return x.reshape(x.shape[:3] + (int(np.prod(x.shape[3:])),))


def _map(fn, *arrays, **kwargs) -> da.Array:
    """``fn`` on the same block of every 4-D node-block array (their last axes differ: map_blocks
    pairs blocks by index, it does not align chunks)."""
    return da.map_blocks(fn, *arrays, **kwargs)


def _dot(a: da.Array, b: da.Array):
    """``a · b`` as the sum of the blocks' sums (gathered by the client)."""
    return da.map_blocks(lambda u, v: np.array([[[np.dot(u.reshape(-1), v.reshape(-1))]]]), a, b,
                         chunks=tuple((1,) * n for n in a.numblocks[:3]), drop_axis=3, dtype=np.float64).sum()


# --- block functions (each one task) ----------------------------------------------------

def _own_nodes(Hh, grid, block_info=None):
    """The block's own nodes of its haloed stencil (…, 126) as (…, 14, 3, 3)."""
    own = Hh[core_slices(block_info[0]["chunk-location"], grid, 1, Hh.shape)]
    return own.reshape(own.shape[:3] + (14, 3, 3))


def _eigenvalues(H):
    """The mean and the smallest eigenvalue of each node's diagonal block (…, 2), float64."""
    w = np.linalg.eigvalsh(H[..., 0, :, :].astype(np.float64))
    return np.stack([w.mean(axis=-1), w[..., 0]], axis=-1)


def _block_origin(block_info) -> tuple[int, int, int]:
    return tuple(lo for lo, _ in block_info[None]["array-location"][:3])


def _hold_weak(H, nodes=None, blocks=None, block_info=None):
    """The weak nodes' diagonal blocks of this block replaced by their held values."""
    origin = np.array(_block_origin(block_info))
    local = nodes - origin
    inside = np.all((local >= 0) & (local < np.array(H.shape[:3])), axis=1)
    if not inside.any():
        return H
    H = H.copy()
    H[(*local[inside].T, 0)] = blocks[inside]
    return H


def _product_block(x, *rest, data, reg_args, weight, depth, grid, freed, block_info=None):
    """One block of ``(M + λ R) x``: the kernels of the in-memory solver on the haloed block."""
    block_id = block_info[0]["chunk-location"]
    core = core_slices(block_id, grid, depth, x.shape)
    x = np.ascontiguousarray(x)
    y = np.zeros(x.shape)
    if data:
        H = rest[0].reshape(rest[0].shape[:3] + (14, 3, 3))
        inner = core_slices(block_id, grid, depth - 1, x.shape) if depth > 1 else (slice(None),) * 3
        yh = np.zeros(H.shape[:3] + (3,))
        half_matvec(np.ascontiguousarray(H), np.ascontiguousarray(x[inner]), yh)
        y[inner] += yh
    if reg_args is not None:
        code, Ke, Kf, sw, ew, free = reg_args
        if freed:
            free = np.ascontiguousarray(rest[-1])
        add_weighted(code, Ke, Kf, sw, ew, free, weight, x, y)
    return y[core]


def _cells_block(x, W, k, grid, block_info=None):
    """``-Σ_c W_c W_cᵀ x`` of the block's cells over its extended nodes (x haloed by one)."""
    block_id = block_info[0]["chunk-location"]
    lo = [1 if i > 0 else 0 for i in block_id[:3]]
    ext = tuple(slice(a, None) for a in lo)
    x = np.ascontiguousarray(x[ext])
    y = np.zeros(x.shape)
    W = W.reshape(W.shape[:3] + (k + 1,) * 3 + (3, 4))
    _subtract_cells(np.ascontiguousarray(W), int(k), x, y)
    return -y[tuple(slice(0, n) for n in block_info[None]["chunk-shape"][:3])]


def _class_index(index, block_info):
    origin = _block_origin(block_info)
    shape = block_info[None]["chunk-shape"][:3]
    return tuple(np.ascontiguousarray(i[o:o + n]) for i, o, n in zip(index, origin, shape))


def _jacobi_block(Hh, r, Rd, index, lam, grid, block_info=None):
    """``D⁻¹ r`` on one block, ``D`` from its haloed stencil's own nodes."""
    H = _own_nodes(Hh, grid, block_info)
    z = np.empty(r.shape)
    block_solve(np.ascontiguousarray(H), Rd, *_class_index(index, block_info), lam, np.ascontiguousarray(r), z)
    return z


def _variance_block(H, *freed, Rd, index, lam, grid, weak, block_info=None):
    """``diag(A_ii⁻¹ M_ii A_ii⁻¹)`` of the block's nodes (the in-memory solver's expression);
    ``freed``: the block's freed terms haloed by :data:`PENALTY_DEPTH`, whose share of ``R``'s
    diagonal is taken off as :meth:`~chunkdic.solve.regularizer.Regularizer.diagonal_blocks` does."""
    iz, iy, ix = _class_index(index, block_info)
    H = H.reshape(H.shape[:3] + (14, 3, 3))
    diag = H[..., 0, :, :].astype(np.float64)
    nodes, held = weak
    if len(nodes):
        local = nodes - np.array(_block_origin(block_info))
        inside = np.all((local >= 0) & (local < np.array(H.shape[:3])), axis=1)
        diag[tuple(local[inside].T)] = held[inside]
    A = diag
    if lam:
        R = Rd[np.ix_(iz, iy, ix)]
        if freed:
            f = np.ascontiguousarray(freed[0])
            less = np.zeros(f.shape[:3] + (3,))
            freed_diagonal(f, 0, less)
            R[..., [0, 1, 2], [0, 1, 2]] += less[core_slices(block_info[0]["chunk-location"], grid, PENALTY_DEPTH,
                                                             f.shape)]
        A = diag + lam * R
    inv = np.linalg.inv(A)
    return np.einsum("...ij,...jk,...ki->...i", inv, diag, inv)
