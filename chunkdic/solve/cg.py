"""Client-side solve of ``(M + λR) δa = b − λ R a`` (paper section 3) on the nodal stencil.

``M`` is a weighted mass matrix: conjugate gradients with a 3×3 nodal block-Jacobi
preconditioner converge in about a hundred iterations whatever the mesh size, where a
direct factorisation costs seconds to minutes (shared/DESIGN.md). The stencil is used
as is for the matrix-vector product, never converted to CSR, and only its symmetric half
is kept (:data:`~chunkdic.solve.stencil.HALF_OFFSETS`): at 128³ nodes the float32 half stencil is 1 GB instead
of 2. The regularisation ``R`` (:mod:`chunkdic.solve.regularizer`) is applied matrix-free
in the same CG. A long Tikhonov length makes ``M + λ R`` a fourth-order operator whose
smooth modes block-Jacobi cannot reach (hundreds to thousands of iterations): there a
multigrid V-cycle (:mod:`chunkdic.solve.multigrid`) preconditions the same CG instead.
"""

from __future__ import annotations

import logging

import numpy as np

from ..errors import InputError
from ..warn import warn_user
from . import lanes
from .galerkin import matrix_hierarchy, regularizer_stencil
from .multigrid import VCycle
from .penalty import NO_FREED, add_weighted
from .regularizer import Regularizer
from .stencil import (
    half_matvec,
    no_diagonal,
    pcg,
    pcg_block_jacobi,
    rigid_restriction,
    stencil_matvec,
    subtract_cells,
)

log = logging.getLogger(__name__)

#: multigrid replaces block-Jacobi from ``λ tr R_ii ≥ MULTIGRID_FROM tr M_ii`` (medians
#: over nodes): from about 7ℓ with Tikhonov, where block-Jacobi CG needs ~100 iterations and
#: the V-cycle 9 (docs/engine.md, "Solve"); about 9ℓ with the equilibrium gap, whose
#: diagonal is smaller at equal length. Without its edge term the equilibrium gap's null
#: space would hold every field set by the box's edges, which defeats the V-cycle (1 012
#: iterations at 16ℓ); with it the null space has 24 fields, like Tikhonov's, and the V-cycle
#: needs 27-74 iterations from 8ℓ to 32ℓ where block-Jacobi needs 214-1 861.
MULTIGRID_FROM = 100.0
#: nodes per slab of planes of the client's node-by-node work (:func:`z_slabs`): the
#: float64 temporaries of a slab (a few of 72 B per node) stay under ~20 MB
SLAB_NODES = 65536


class PoorTextureWarning(UserWarning):
    """Some nodes see too little image gradient to be measured reliably."""


class StencilSolver:
    """Preconditioned CG on the half stencil of ``M`` (plus an optional ``λ R``).

    Parameters
    ----------
    half : ndarray, shape (nz, ny, nx, 14, 3, 3), float32
        The stored half of ``M`` (:data:`~chunkdic.solve.stencil.HALF_OFFSETS`). The solver keeps it (no copy) and
        adds to its diagonal blocks the small Tikhonov term of poorly textured nodes.
    weak_threshold : float
        A node is *poorly textured* when the smallest eigenvalue of its 3×3 diagonal
        block is below ``weak_threshold`` times the median over nodes of the mean
        eigenvalue. Such nodes get a Tikhonov term of that size on their own block so the
        system stays solvable, and :attr:`weak_nodes` lists them.
    rtol : float
        Relative residual tolerance of CG, relative to the largest right-hand side this
        solver has seen (not only the current one): the Gauss–Newton steps of a level shrink
        to nothing as it converges, and a residual relative to a vanishing right-hand side
        asked ever more CG iterations of an increment nobody uses (measured at 300³ with a
        long regularisation length: 1 281 iterations, 3.1 s, for a step of max 3e-6 voxel).
        The increments then carry an error of at most ``rtol`` times the first step's size:
        with the default 1e-5, 5e-6 voxel after a first step of half a
        voxel, two hundred times below the level-0 tolerance of 1e-3; at 1024³ (ℓ = 16) the
        level-0 solves took 30-40 % fewer iterations (docs/engine.md, "Solve").
    maxiter : int
        CG iterations before giving up with a warning.
    cells : ndarray, shape (cz, cy, cx, k+1, k+1, k+1, 3, 4), float32, optional
        The Schur complement of the brightness cells' offsets, ``Σ_c W_c W_cᵀ``
        (:func:`chunkdic.kernels.m.cell_couplings` for the whole mesh), subtracted from ``M``
        in every product: the Gauss–Newton matrix of the ``drift`` model with cells of ``k³``
        elements. The preconditioners stay ``M``'s (the term is low-rank per cell).
    cell : int
        ``k``, elements per side of a cell (with ``cells``).
    multigrid : bool or None
        Precondition with a multigrid V-cycle (:mod:`chunkdic.solve.multigrid`) instead of
        block-Jacobi: ``None`` (default) when it pays, i.e. with a regularisation whose weight
        makes ``λ R`` dominate ``M`` (:data:`MULTIGRID_FROM`); ``True`` whenever regularised,
        ``False`` never.

    Raises
    ------
    InputError
        If ``M`` has no gradient at all (nothing to correlate).
    """

    def __init__(self, half: np.ndarray, *, weak_threshold: float = 1e-3, rtol: float = 1e-5,
                 maxiter: int = 2000, multigrid: bool | None = None, cells: np.ndarray | None = None,
                 cell: int = 1):
        self.rtol, self.maxiter = rtol, maxiter
        self.cells = np.zeros((0, 0, 0, 2, 2, 2, 3, 4), np.float32) if cells is None else cells
        self.cell = int(cell)
        #: norm of the largest right-hand side solved so far without a caller's ``reference``
        #: (:meth:`solve`)
        self.largest_rhs = 0.0
        self.nodes_shape = half.shape[:3]
        #: ``M`` restricted to uniform translations, less the brightness cells' share (3, 3),
        #: taken before the weak nodes are held
        self.rigid_matrix = rigid_restriction(half)
        if self.cells.shape[0]:  # a cell's W summed over its nodes
            shares = self.cells.sum(axis=(3, 4, 5), dtype=np.float64).reshape(-1, 3, 4)
            self.rigid_matrix = self.rigid_matrix - np.einsum("cip,cjp->ij", shares, shares)
        # the eigenvalues of the diagonal blocks, a slab of planes at a time: the client
        # never holds the float64 blocks of the whole mesh (docs/distributed.md)
        smallest, mean = np.empty(self.nodes_shape), np.empty(self.nodes_shape)
        for planes in z_slabs(self.nodes_shape):
            eig = np.linalg.eigvalsh(half[planes, :, :, 0, :, :].astype(np.float64))  # ascending
            smallest[planes], mean[planes] = eig[..., 0], eig.mean(axis=-1)
        scale = float(np.median(mean))
        del mean
        if not np.isfinite(scale) or scale <= 0:
            raise InputError("the reference image has no gradient in the ROI: nothing to correlate")
        weak = smallest < weak_threshold * scale
        del smallest
        self.weak_nodes = np.argwhere(weak)
        # the held blocks of the weak nodes in float64 (the stencil keeps them in float32)
        self._weak_blocks = half[(*self.weak_nodes.T, 0)].astype(np.float64) + weak_threshold * scale * np.eye(3)
        if len(self._weak_blocks):
            half[(*self.weak_nodes.T, 0)] = self._weak_blocks
        self.scale = scale
        # float32 for the matrix-vector product: CG is bound by memory traffic through the
        # stencil, and M only steers the modified Gauss-Newton steps (the converged field
        # solves b = λ R a whatever M), so its round-off at 6e-8 changes nothing measurable.
        self.matrix = half if half.dtype == np.float32 else half.astype(np.float32)
        self.regularizer: Regularizer | None = None
        self.weight = 0.0
        self._reg_args = (0, np.zeros((24, 24)), np.zeros((4, 4)), 0.0, 0.0, NO_FREED)
        # block-Jacobi solves each node's 3×3 block of M + λ R as it goes (stencil.block_solve):
        # no stored inverse (72 B per node in float64, 150 MB at 128³ nodes)
        self._diag_args = no_diagonal(self.nodes_shape)
        self.multigrid = multigrid
        self._matrices = None  # the Galerkin coarse M (chunkdic.solve.multigrid), built on first use
        self._vcycle = None
        self._jacobi = None  # block-Jacobi's inverse blocks for precondition(), made on first use

    def diagonal_blocks(self, planes: slice = slice(None)) -> np.ndarray:
        """The 3×3 diagonal blocks of ``M`` on the z planes ``planes`` (default: all), weak
        nodes held: shape (nz', ny, nx, 3, 3), float64 (a copy)."""
        out = self.matrix[planes, :, :, 0, :, :].astype(np.float64)
        if len(self._weak_blocks):
            z = np.arange(self.nodes_shape[0])[planes]
            inside = np.isin(self.weak_nodes[:, 0], z)
            if inside.any():
                nodes = self.weak_nodes[inside]
                out[(np.searchsorted(z, nodes[:, 0]), nodes[:, 1], nodes[:, 2])] = self._weak_blocks[inside]
        return out

    def diagonal_inverse(self, planes: slice = slice(None)) -> np.ndarray:
        """The inverse 3×3 diagonal blocks of ``M + λ R`` on the z planes ``planes``, float64
        (nz', ny, nx, 3, 3), weak nodes' blocks as held in float64 (block-Jacobi's, which
        :func:`~chunkdic.solve.stencil.block_solve` forms from the float32 stencil, differ by
        its rounding only)."""
        diag = self.diagonal_blocks(planes)
        if self.regularizer is not None:
            diag += self.weight * self.regularizer.diagonal_blocks(planes)
        return np.linalg.inv(diag)

    def local_variances(self) -> np.ndarray:
        """``diag(A_ii⁻¹ M_ii A_ii⁻¹)`` of every node (nz, ny, nx, 3), float64, ``A = M + λ R``:
        each node's variance per unit noise when its neighbours are held
        (:func:`chunkdic.method.noise.nodal_uncertainty`), computed in float64 a slab of
        planes at a time (whole-mesh temporaries would take 3 × 72 B per node)."""
        out = np.empty(self.nodes_shape + (3,))
        for planes in z_slabs(self.nodes_shape):
            inv = self.diagonal_inverse(planes)
            out[planes] = np.einsum("...ij,...jk,...ki->...i", inv, self.diagonal_blocks(planes), inv)
        return out

    def regularize(self, regularizer: Regularizer | None, weight: float) -> None:
        """Solve ``(M + weight R)`` from now on (``None`` or 0: plain ``M``)."""
        self.regularizer = regularizer if weight > 0 else None
        self.weight = float(weight) if self.regularizer is not None else 0.0
        self._vcycle = None  # its own arrays freed before the new ones are built
        self._jacobi = None
        self._diag_args = no_diagonal(self.nodes_shape)
        if self.regularizer is not None:
            self._reg_args = self.regularizer.numba_args()
            self._regularizer_diagonal, self._matrix_diagonal = self._median_traces()
            blocks, index = self.regularizer.diagonal_classes()
            self._diag_args = (np.ascontiguousarray(blocks, np.float64),
                               *(np.ascontiguousarray(i, np.int64) for i in index))
        if self._use_multigrid():
            if self._matrices is None:
                self._matrices = matrix_hierarchy(self.matrix)
            self._vcycle = VCycle(self._matrices, self._diag_args, self.regularizer, self.weight)

    def _median_traces(self) -> tuple[float, float]:
        """Medians over nodes of ``tr R_ii`` and ``tr M_ii`` (which preconditioner pays, :meth:`_use_multigrid`)."""
        reg, mat = np.empty(self.nodes_shape), np.empty(self.nodes_shape)
        for planes in z_slabs(self.nodes_shape):
            reg[planes] = np.trace(self.regularizer.diagonal_blocks(planes), axis1=-2, axis2=-1)
            mat[planes] = np.trace(self.diagonal_blocks(planes), axis1=-2, axis2=-1)
        return float(np.median(reg)), float(np.median(mat))

    def _use_multigrid(self) -> bool:
        """Whether :meth:`regularize` builds a V-cycle (:data:`MULTIGRID_FROM`)."""
        if self.regularizer is None or self.multigrid is False:
            return False
        if self.multigrid:
            return True
        return self.weight * self._regularizer_diagonal >= MULTIGRID_FROM * self._matrix_diagonal

    def penalty_gradient(self, a: np.ndarray) -> np.ndarray:
        """``λ R a`` for the total nodal field ``a`` (nz, ny, nx, 3); zeros without regularisation."""
        if self.regularizer is None:
            return np.zeros(a.shape)
        y = self.regularizer.apply(a)
        y *= self.weight
        return y

    def data_matvec(self, x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``M x`` (minus the brightness cells' complement), into ``out`` (float64, x's shape,
        contiguous) when given: the data term of the Gauss–Newton matrix."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        if out is None:
            out = np.empty(x.shape)
        half_matvec(self.matrix, x, out)
        subtract_cells(self.cells, self.cell, x, out)
        return out

    def stencil_product(self, x: np.ndarray) -> np.ndarray:
        """``M x`` alone (no brightness cells, no penalty), (nz, ny, nx, 3) float64."""
        return stencil_matvec(self.matrix, x)

    def matvec(self, x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``(M + λ R) x``, into ``out`` (float64, x's shape, contiguous) when given."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        out = self.data_matvec(x, out)
        if self.regularizer is not None:
            add_weighted(*self._reg_args, self.weight, x, out)
        return out

    def precondition(self, r: np.ndarray) -> np.ndarray:
        """This solver's preconditioner applied to ``r`` (nz, ny, nx, 3): the V-cycle when it
        pays, else block-Jacobi (a caller's own CG on a larger system, :mod:`chunkdic.method.crack`)."""
        r = np.ascontiguousarray(r, dtype=np.float64)
        if self._vcycle is not None:
            return self._vcycle.cycle(r, out=np.empty_like(r))
        if self._jacobi is None:
            self._jacobi = self.diagonal_inverse()
        return np.einsum("...ij,...j->...i", self._jacobi, r)

    def solve(self, b: np.ndarray, *, overwrite_b: bool = False,
              reference: float | None = None, rtol: float | None = None) -> tuple[np.ndarray, int]:
        """Solve ``(M + λR) x = b``; ``b`` and ``x`` have shape (nz, ny, nx, 3).

        ``overwrite_b``: CG may use ``b`` (float64, contiguous) as its residual vector,
        leaving it changed: one mesh-sized vector fewer at the client's peak.
        ``reference``: the caller's CG reference, the largest right-hand-side norm of its
        earlier solves (:func:`rhs_norm`; ``rtol`` is relative to the larger of it and
        ``b``'s): the Gauss–Newton state keeps it, so that a resumed run stops CG where the
        uninterrupted one did. ``None``: the solver's own, :attr:`largest_rhs`, which this
        solve raises. ``rtol``: this solve's tolerance instead of the solver's.
        Returns the solution and the number of CG iterations.
        """
        b = np.ascontiguousarray(b, dtype=np.float64)
        x = np.zeros_like(b)
        code, Ke, Kf, sw, ew, freed = self._reg_args
        rtol = relative_tolerance(self, b, reference, rtol)
        if self._vcycle is not None:
            vcycle = self._vcycle
            iterations = pcg(self.matvec, lambda r, z: vcycle.cycle(r, out=z), b, x, rtol, self.maxiter, overwrite_b)
        elif lanes.pays(self.nodes_shape, self.regularizer is not None or self.cells.shape[0] > 0):
            iterations = self._solve_two_lanes(b, x, rtol, overwrite_b)
        else:
            iterations = pcg_block_jacobi(self.matrix, *self._diag_args, b, x, rtol, self.maxiter,
                                          code if self.regularizer is not None else 0, Ke, Kf, sw, ew, freed,
                                          self.weight, self.cells, self.cell, overwrite_b)
        if iterations < 0:
            warn_user(f"CG did not reach rtol={self.rtol} in {self.maxiter} iterations", RuntimeWarning)
            iterations = self.maxiter
        return x, iterations

    def _solve_two_lanes(self, b: np.ndarray, x: np.ndarray, rtol: float, overwrite_b: bool) -> int:
        """Block-Jacobi CG on two threads (:func:`chunkdic.solve.lanes.pcg_two_lanes`)."""
        code, Ke, Kf, sw, ew, freed = self._reg_args
        reg_args = (code if self.regularizer is not None else 0, Ke, Kf, sw, ew, freed)
        return lanes.pcg_two_lanes(self.matrix, self._diag_args, b, x, rtol, self.maxiter, reg_args, self.weight,
                                   self.cells, self.cell, overwrite_b)


def relative_tolerance(solver, b: np.ndarray, reference: float | None, rtol: float | None = None) -> float:
    """CG's tolerance relative to ``b``'s norm for ``rtol`` (default ``solver.rtol``) relative to
    the larger of ``b``'s norm and ``reference`` (None: ``solver.largest_rhs``, which this raises)."""
    rtol = solver.rtol if rtol is None else rtol
    norm = rhs_norm(b)
    if reference is None:
        solver.largest_rhs = largest = max(solver.largest_rhs, norm)
    else:
        largest = max(float(reference), norm)
    return rtol * largest / norm if norm > 0 else rtol


def rhs_norm(b: np.ndarray) -> float:
    """The Euclidean norm of a right-hand side ``b`` (nz, ny, nx, 3): what CG's tolerance is relative to."""
    return float(np.sqrt(np.sum(b * b)))


def z_slabs(nodes_shape, nodes: int = None):
    """Slices of whole z planes of about ``nodes`` nodes each (default :data:`SLAB_NODES`)
    covering ``nodes_shape``: the unit of the client's node-by-node work on the whole mesh."""
    nodes = SLAB_NODES if nodes is None else nodes
    per_plane = max(int(nodes_shape[1]) * int(nodes_shape[2]), 1)
    step = max(1, nodes // per_plane)
    for z in range(0, int(nodes_shape[0]), step):
        yield slice(z, min(z + step, int(nodes_shape[0])))


def warmup() -> None:
    """Compile the client's solver kernels (CG with and without regularisation, the V-cycle) on tiny systems."""
    half = np.zeros((3, 3, 3, 14, 3, 3), np.float32)
    half[..., 0, :, :] = np.eye(3)
    solver = StencilSolver(half, cells=np.zeros((1, 1, 1, 3, 3, 3, 3, 4), np.float32), cell=2)  # brightness cells
    solver.solve(np.ones((3, 3, 3, 3)))
    solver.data_matvec(np.ones((3, 3, 3, 3)))
    solver.regularize(Regularizer("tikhonov", (3, 3, 3), 2.0), 1.0)
    solver.solve(np.ones((3, 3, 3, 3)))
    if lanes.second_lane() is not None:  # the two-lane CG of large meshes, its kernels called one by one
        freed = np.zeros((3, 3, 3, 6), np.uint8)
        freed[1, 1, 1] = 1
        solver.regularize(Regularizer("tikhonov", (3, 3, 3), 2.0, freed), 1.0)
        solver._solve_two_lanes(np.ones((3, 3, 3, 3)), np.zeros((3, 3, 3, 3)), 1e-5, False)
    half = np.zeros((7, 7, 7, 14, 3, 3), np.float32)  # two multigrid levels
    half[..., 0, :, :] = np.eye(3)
    solver = StencilSolver(half, multigrid=True)
    solver.regularize(Regularizer("tikhonov", (7, 7, 7), 2.0), 1.0)
    solver.solve(np.ones((7, 7, 7, 3)))
    # the V-cycle's coarse penalty product (reached only on larger meshes): compiled here
    # too, so that every kernel of a run is in numba's cache after a first run
    # (chunkdic.kernels.jit.kernels_cached)
    regularizer_stencil(Regularizer("tikhonov", (3, 3, 3), 2.0)).matvec_add(1.0, np.ones((3, 3, 3, 3)),
                                                                           np.zeros((3, 3, 3, 3)))
