"""The second copies of the nodes a known crack splits: their coupling, penalty and solve.

With a crack surface given (docs/cracks.md, "Correlating with a known crack"), the nodes
whose support the surface splits (:mod:`chunkdic.passes.crack_cut`) carry a second copy
``u'``: the field of the other side of the surface at the node. The unknowns of a level are
then the nodal field ``u`` (the node's own side; every node) and ``u'`` at the ``K`` split
nodes. The ``M`` pass gives the couplings of copies 0 in ``M``'s stencil and the others as
node-pair entries, which :meth:`CrackCoupling.from_pairs` assembles into two sparse
matrices, ``B`` (``u`` with ``u'``) and ``C`` (``u'`` with ``u'``); each Gauss–Newton step
solves

    [ M + λR   B ] [δu ]   [ b − λ R u ]
    [ Bᵀ       C ] [δu'] = [ b'        ]

by conjugate gradients preconditioned by ``M + λR``'s own preconditioner and an exact
factorisation of ``C`` (:func:`solve_coupled`). The penalty is released across the surface:
every term of the Tikhonov penalty that involves a split node is freed
(:meth:`CrackCoupling.release`), and ``u'`` carries no penalty, so neither side's field is
drawn towards the other's.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..solve.penalty import TERM_KINDS
from ..solve.stencil import pcg

__all__ = ["CrackCoupling", "solve_coupled"]

#: a second copy whose 3×3 block of ``C`` has an eigenvalue below this fraction of the
#: median node's (a sliver of the other side with too little texture) is held, as weak nodes are
WEAK = 1e-3


@dataclasses.dataclass(frozen=True)
class CrackCoupling:
    """The split nodes of a level and the couplings of their second copies.

    Attributes
    ----------
    nodes : ndarray, shape (K, 3), int
        The split nodes (index triples), in raster order.
    edges : ndarray, shape (r, 4), int
        The mesh edges the surface meets (axis, then the first node's index triple): the
        penalty terms across them are released.
    B : scipy.sparse.csr_matrix, shape (3 n, 3 K)
        ``M`` between the nodal field (flattened as (nz, ny, nx, 3)) and the second copies ((K, 3)).
    C : scipy.sparse.csr_matrix, shape (3 K, 3 K)
        ``M`` between the second copies, weak copies held.
    """

    nodes: np.ndarray
    edges: np.ndarray
    B: sp.csr_matrix
    C: sp.csr_matrix

    @classmethod
    def from_pairs(cls, pairs: dict, edges: np.ndarray, nodes_shape, scale: float) -> "CrackCoupling | None":
        """From the ``M`` pass's entries ``{(node a, copy, node b, copy): 3×3}`` (node index
        triples, at least one copy 1) and the mesh edges the surface meets (r, 4); ``scale``:
        the median node's mean eigenvalue of ``M``'s diagonal blocks (the weak-copy hold).
        None when the surface meets no mesh edge."""
        edges = np.unique(np.asarray(edges, int).reshape(-1, 4), axis=0)
        if not len(edges):
            return None
        flat = lambda n: int(np.ravel_multi_index(n, nodes_shape))  # noqa: E731
        split = sorted({flat(a) for (a, ca, _, _) in pairs if ca} | {flat(b) for (_, _, b, cb) in pairs if cb})
        index = {n: k for k, n in enumerate(split)}
        n_nodes, K = int(np.prod(nodes_shape)), len(split)
        rows = {True: [], False: []}
        for (a, ca, b, cb), block in pairs.items():
            if ca and not cb:  # B holds (u, u'), its transpose the (u', u) entries
                continue
            r = 3 * (index[flat(a)] if ca else flat(a))
            c = 3 * index[flat(b)]
            for i in range(3):
                for j in range(3):
                    rows[bool(ca)].append((r + i, c + j, block[i][j]))
        C = _sparse(rows[True], (3 * K, 3 * K))
        C = C + _weak_hold(C, K, scale)
        B = _sparse(rows[False], (3 * n_nodes, 3 * K))
        nodes = np.array(np.unravel_index(np.array(split, int), nodes_shape)).T.reshape(-1, 3)
        return cls(nodes, edges, B, C)

    @property
    def count(self) -> int:
        return len(self.nodes)

    def at_nodes(self, u: np.ndarray) -> np.ndarray:
        """``u`` (3, nz, ny, nx) at the split nodes: (K, 3)."""
        return np.ascontiguousarray(u[(slice(None), *self.nodes.T)].T)

    def other_field(self, u: np.ndarray, other: np.ndarray | None) -> np.ndarray:
        """The field of second copies on the whole grid (3, nz, ny, nx): ``u`` with ``other``
        (K, 3) at the split nodes (what the passes read; None: ``u`` itself)."""
        out = np.array(u, dtype=np.float64, copy=True)
        if other is not None:
            out[(slice(None), *self.nodes.T)] = np.asarray(other).T
        return out

    def release(self, freed: np.ndarray | None, nodes_shape) -> np.ndarray:
        """``freed`` (:attr:`chunkdic.solve.regularizer.Regularizer.freed`, None: none) with
        every Tikhonov term across the surface freed (all three components): a second
        difference whose two mesh edges, a mixed difference whose square's four edges, include
        one the surface meets."""
        out = np.zeros(tuple(nodes_shape) + (len(TERM_KINDS),), np.uint8) if freed is None else freed.copy()
        cut = np.zeros((3,) + tuple(nodes_shape), bool)
        cut[tuple(self.edges.T)] = True
        for t in range(len(TERM_KINDS)):
            crossing, anchor = _crossing(cut, t)
            out[anchor + (t,)] |= np.where(crossing, 7, 0).astype(np.uint8)
        return out


def _crossing(cut: np.ndarray, t: int):
    """Whether each term of kind ``t`` (anchored as :func:`chunkdic.solve.reweighting.robust_freed`
    anchors them) crosses a cut mesh edge (``cut``, (3, nz, ny, nx)), and its anchor slices."""
    shape = cut.shape[1:]
    if t < 3:
        n = shape[t]
        lo, mid = [slice(None)] * 3, [slice(None)] * 3
        lo[t], mid[t] = slice(0, n - 2), slice(1, n - 1)
        return cut[t][tuple(lo)] | cut[t][tuple(mid)], tuple(mid)
    p, q = {3: (0, 1), 4: (0, 2), 5: (1, 2)}[t]

    def corner(dp, dq):
        s = [slice(None)] * 3
        s[p] = slice(dp, shape[p] - 1 + dp)
        s[q] = slice(dq, shape[q] - 1 + dq)
        return tuple(s)

    return (cut[p][corner(0, 0)] | cut[p][corner(0, 1)] | cut[q][corner(0, 0)] | cut[q][corner(1, 0)]), corner(0, 0)


def _sparse(entries: list, shape) -> sp.csr_matrix:
    if not entries:
        return sp.csr_matrix(shape)
    r, c, v = (np.array(x) for x in zip(*entries))
    return sp.coo_matrix((v.astype(np.float64), (r.astype(np.int64), c.astype(np.int64))), shape=shape).tocsr()


def _weak_hold(C: sp.csr_matrix, K: int, scale: float) -> sp.csr_matrix:
    """The diagonal term that holds the second copies of too little texture (:data:`WEAK`)."""
    hold = np.zeros(3 * K)
    for k in range(K):
        block = C[3 * k:3 * k + 3, 3 * k:3 * k + 3].toarray()
        if np.linalg.eigvalsh(0.5 * (block + block.T))[0] < WEAK * scale:
            hold[3 * k:3 * k + 3] = WEAK * scale
    return sp.diags(hold).tocsr()


def solve_coupled(solver, coupling: CrackCoupling, rhs: np.ndarray,
                  rhs_other: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Solve the coupled step (module docstring) by preconditioned CG.

    Parameters
    ----------
    solver : chunkdic.solve.cg.StencilSolver
        ``M + λR`` (its penalty with the crack's terms released).
    coupling : CrackCoupling
    rhs : ndarray, shape (nz, ny, nx, 3), float64
        ``b − λ R u``.
    rhs_other : ndarray, shape (K, 3), float64
        ``b'`` of the second copies.

    Returns
    -------
    delta : ndarray, shape (nz, ny, nx, 3)
    delta_other : ndarray, shape (K, 3)
    iterations : int
    """
    shape = rhs.shape
    n = rhs.size
    b = np.concatenate([rhs.reshape(-1), np.asarray(rhs_other, np.float64).reshape(-1)])
    x = np.zeros_like(b)
    factor = spla.splu(coupling.C.tocsc())
    B, BT, C = coupling.B, coupling.B.T.tocsr(), coupling.C

    def matvec(p, out):
        pu, pw = p[:n], p[n:]
        out[:n] = solver.matvec(pu.reshape(shape)).reshape(-1) + B @ pw
        out[n:] = BT @ pu + C @ pw

    def precondition(r, out):
        out[:n] = solver.precondition(r[:n].reshape(shape)).reshape(-1)
        out[n:] = factor.solve(r[n:])

    # relative to this right-hand side, not to the level's largest (as StencilSolver.solve):
    # the second copies of thin slivers have small entries in both C and b', and a residual
    # measured against the first step's scale left their increments unsolved (one CG
    # iteration per pass, 30 passes without converging on the 64³ test pair); and 1e-3 × the
    # solver's rtol, so that the field does not depend on the float32 round-off of M's block
    # sums (blocks of 2³ elements against one: 6.5e-8 voxel at rtol, 4e-11 at 1e-3 rtol)
    iterations = pcg(matvec, precondition, b, x, solver.rtol * 1e-3, solver.maxiter)
    if iterations < 0:
        iterations = solver.maxiter
    return x[:n].reshape(shape), x[n:].reshape(-1, 3), iterations
