"""Geometric multigrid V-cycle: the preconditioner of the client's CG on ``M + λ R``.

Block-Jacobi CG (:mod:`chunkdic.solve.cg`) needs few iterations on ``M`` alone, but the
regularisation ``λ R`` of a long length is a fourth-order operator whose smooth modes
block-Jacobi cannot reach: 600–1 300 iterations at 25³ nodes (docs/engine.md, "Solve").
One V-cycle of this module takes their place as the preconditioner: 7 to 16 iterations
from ℓ to 32ℓ there, the same counts at 16³ to 48³ nodes. :class:`~chunkdic.solve.cg.StencilSolver`
uses it at long lengths, for both kinds. The equilibrium gap needs its edge
term for that: without it, its null space holds every field set by the box's edges, out of
reach of a point smoother and of the coarse grid alike (measured: 627 iterations instead
of 2 000 at 32ℓ, but no faster); with 24 null fields, as Tikhonov's, 27–74 iterations
from 8ℓ to 32ℓ on 24³ nodes, where block-Jacobi needs 214–1 861.

Smoother: Chebyshev polynomial of degree :data:`DEGREE` in the block-Jacobi-preconditioned
operator, over ``[λ_max / 30, 1.1 λ_max]`` (``λ_max`` of ``D⁻¹A`` from 10 Lanczos steps of
block-Jacobi CG): only matrix-vector products, so the fine level keeps its half stencil
and matrix-free ``R``. Degree 1, i.e. block-Jacobi damped by ``1 / θ`` (``θ`` the middle
of the interval), is the default: degree 2 saved no iteration at long lengths (11 and 14
at 16ℓ and 32ℓ on 24³ nodes, both) for twice the fine-level products. The same smoother
before and after the coarse correction makes the V-cycle symmetric and, the smoother
being convergent, positive definite: plain PCG stays valid. The coarsest level (at most
:data:`COARSEST` nodes) is solved by a dense Cholesky factorisation.
The coarse operators come from :mod:`chunkdic.solve.galerkin`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from .galerkin import (
    ClassStencil,
    assemble_dense,
    identity_transfer,
    node_stencil,
    regularizer_hierarchy,
    transfer,
)
from .regularizer import Regularizer
from .penalty import add_weighted
from .stencil import axpy, block_jacobi, block_jacobi_step, block_solve, block_solve_step, dot, half_matvec

DEGREE = 1
#: the smoothing interval is ``[λ_max / SMOOTH_RANGE, 1.1 λ_max]`` of ``D⁻¹A``
SMOOTH_RANGE = 30.0
#: Lanczos steps estimating ``λ_max``
LANCZOS_STEPS = 10
#: the coarsest level has at most this many nodes (dense Cholesky of 3× as many unknowns)

@numba.njit(nogil=True, cache=True)
def _cholesky(A):
    """Lower Cholesky factor of the dense SPD ``A`` in place (its upper triangle left as is); False if not SPD.

    Written out rather than LAPACK's: on the busy 2-core machine scipy's threaded
    ``cho_factor`` took 0.3 s for 192 unknowns (as the solver's CG once did, :func:`chunkdic.solve.stencil.pcg_block_jacobi`).
    """
    n = A.shape[0]
    for j in range(n):
        d = A[j, j]
        for k in range(j):
            d -= A[j, k] * A[j, k]
        if not d > 0.0:
            return False
        d = np.sqrt(d)
        A[j, j] = d
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= A[i, k] * A[j, k]
            A[i, j] = s / d
    return True


@numba.njit(nogil=True, cache=True)
def _cholesky_solve(L, b, x):
    """``x = (L Lᵀ)⁻¹ b`` with the lower factor of :func:`_cholesky` (flat vectors)."""
    n = L.shape[0]
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]


# --- the hierarchy -------------------------------------------------------------------

@dataclass
class _Level:
    shape: tuple
    M: np.ndarray                 # half stencil (nz, ny, nx, 14, 3, 3), float32
    R: ClassStencil | None        # None on the fine level (R applied matrix-free there)
    transfers: tuple | None = None  # per-axis axis_transfer (None: axis kept) to the next coarser level
    Binv: np.ndarray | None = None  # block-Jacobi of M + λR (coarse levels; the fine one solves its blocks)
    diag: tuple | None = None  # the fine level: (Rd, iz, iy, ix, λ) of stencil.block_solve
    lmax: float = 0.0

    def __post_init__(self):
        if self.transfers is not None:  # (fine_index, fine_weight) of each axis, as :func:`transfer` takes them
            self.tables = tuple(a for t, n in zip(self.transfers, self.shape)
                                for a in (t if t is not None else identity_transfer(n))[:2])


class VCycle:
    """The symmetric V-cycle preconditioner of ``M + λ R``.

    Parameters
    ----------
    matrices : list
        :func:`matrix_hierarchy` of the fine half stencil (reusable for every ``λ``).
    fine_diagonal : tuple
        ``(Rd, iz, iy, ix)``: the class blocks of ``R_ii`` and each node's class per axis, from
        which block-Jacobi forms the fine level's diagonal blocks of ``M + λ R`` as it goes
        (:func:`~chunkdic.solve.stencil.block_solve`: no stored inverse on the fine level).
    regularizer : Regularizer
    weight : float
        ``λ``.
    """

    def __init__(self, matrices, fine_diagonal: tuple, regularizer: Regularizer, weight: float):
        self.weight = float(weight)
        self._reg_args = regularizer.numba_args()
        coarse_R = regularizer_hierarchy(regularizer)
        if len(coarse_R) != len(matrices):
            raise ValueError("the hierarchies of M and R do not match")
        self.levels = []
        for k, (shape, M, tr) in enumerate(matrices):
            R = None if k == 0 else coarse_R[k]
            lev = _Level(shape, M, R, tr)
            if k == 0:
                lev.diag = (*fine_diagonal, self.weight)
            else:
                diag = M[..., 0, :, :].astype(np.float64) + self.weight * R.diagonal_blocks()
                lev.Binv = np.linalg.inv(diag)
            self.levels.append(lev)
        for k, lev in enumerate(self.levels[:-1]):
            lev.lmax = 1.1 * self._lambda_max(k)
        last = self.levels[-1]
        n = int(np.prod(last.shape))
        A = np.zeros((3 * n, 3 * n))
        assemble_dense(last.M.astype(np.float64), *node_stencil(last.M).classes, 1, 1.0, A)
        R = coarse_R[len(self.levels) - 1]
        assemble_dense(R.S, *R.classes, R.reach, self.weight, A)
        if not _cholesky(A):
            raise np.linalg.LinAlgError("the coarsest multigrid level is not positive definite")
        self._coarse = A

    def apply(self, k: int, x: np.ndarray, y: np.ndarray) -> None:
        """``y = A_k x`` on level ``k``."""
        lev = self.levels[k]
        half_matvec(lev.M, x, y)
        if k == 0:
            add_weighted(*self._reg_args, self.weight, x, y)
        else:
            lev.R.matvec_add(self.weight, x, y)

    def _precondition(self, k: int, r: np.ndarray, z: np.ndarray) -> None:
        """``z = D_k⁻¹ r``, block-Jacobi of level ``k``."""
        lev = self.levels[k]
        if lev.diag is not None:
            block_solve(lev.M, *lev.diag, r, z)
        else:
            block_jacobi(lev.Binv, r, z)

    def _precondition_step(self, k: int, r: np.ndarray, x: np.ndarray, theta: float) -> None:
        """``x += D_k⁻¹ r / θ`` (the damped block-Jacobi step, fused)."""
        lev = self.levels[k]
        if lev.diag is not None:
            block_solve_step(lev.M, *lev.diag, r, x, theta)
        else:
            block_jacobi_step(lev.Binv, r, x, theta)

    def _lambda_max(self, k: int) -> float:
        """Largest eigenvalue of ``D⁻¹A`` on level ``k`` (10 Lanczos steps of block-Jacobi CG from a fixed random start)."""
        lev = self.levels[k]
        rng = np.random.default_rng(0)
        r = rng.standard_normal(lev.shape + (3,))  # the right-hand side, then the residual of
        # CG from x = 0 (only its coefficients are used)
        z, q = np.empty_like(r), np.empty_like(r)
        self._precondition(k, r, z)
        p = z.copy()
        rz = dot(r.reshape(-1), z.reshape(-1))
        alphas, betas = [], []
        for _ in range(min(LANCZOS_STEPS, 3 * int(np.prod(lev.shape)))):
            self.apply(k, p, q)
            pq = dot(p.reshape(-1), q.reshape(-1))
            if pq <= 0 or rz <= 0:
                break
            alpha = rz / pq
            axpy(-alpha, q.reshape(-1), r.reshape(-1))
            self._precondition(k, r, z)
            rz_new = dot(r.reshape(-1), z.reshape(-1))
            beta = rz_new / rz
            alphas.append(alpha)
            betas.append(beta)
            p *= beta
            p += z
            rz = rz_new
        m = len(alphas)
        if m == 0:
            return 1.0
        T = np.zeros((m, m))
        for i in range(m):
            T[i, i] = 1.0 / alphas[i] + (betas[i - 1] / alphas[i - 1] if i > 0 else 0.0)
            if i + 1 < m:
                T[i, i + 1] = T[i + 1, i] = np.sqrt(betas[i]) / alphas[i]
        return float(np.linalg.eigvalsh(T)[-1])

    def _smooth(self, k: int, b: np.ndarray, x: np.ndarray, zero_start: bool, r: np.ndarray) -> None:
        """Chebyshev smoothing of ``A_k x = b`` in place (degree :data:`DEGREE`); ``r``: a work
        vector of ``b``'s shape (the cycle's own residual, reused: no vector per call)."""
        lev = self.levels[k]
        hi = lev.lmax
        lo = hi / SMOOTH_RANGE
        theta, delta = 0.5 * (hi + lo), 0.5 * (hi - lo)
        sigma = theta / delta
        rho = 1.0 / sigma
        if zero_start and DEGREE == 1:
            self._precondition_step(k, b, x, theta)  # x = 0: the residual is b itself
            return
        if zero_start:
            np.copyto(r, b)
        else:
            self.apply(k, x, r)
            np.subtract(b, r, out=r)
        if DEGREE == 1:  # damped block-Jacobi: x += D⁻¹ r / θ, fused (no vector for the step)
            self._precondition_step(k, r, x, theta)
            return
        d, t = np.empty_like(b), np.empty_like(b)
        self._precondition(k, r, d)
        d /= theta
        for step in range(DEGREE):
            x += d
            if step == DEGREE - 1:
                break
            self.apply(k, d, t)
            r -= t
            rho_new = 1.0 / (2.0 * sigma - rho)
            self._precondition(k, r, t)
            d *= rho_new * rho
            d += (2.0 * rho_new / delta) * t
            rho = rho_new

    def cycle(self, b: np.ndarray, k: int = 0, out: np.ndarray | None = None) -> np.ndarray:
        """One V-cycle from level ``k``: an approximation of ``A_k⁻¹ b`` (a symmetric positive
        definite map), into ``out`` when given.

        A level holds one work vector during its cycle (the residual, which the smoother
        shares) besides ``b`` and the result: a solve is the client's peak (docs/distributed.md).
        """
        x = np.empty_like(b) if out is None else out
        if k == len(self.levels) - 1:
            _cholesky_solve(self._coarse, b.reshape(-1), x.reshape(-1))
            return x
        lev = self.levels[k]
        x.fill(0.0)
        r = np.empty_like(b)
        self._smooth(k, b, x, True, r)
        self.apply(k, x, r)
        np.subtract(b, r, out=r)
        coarse_shape = self.levels[k + 1].shape
        rc = np.empty(coarse_shape + (3,))
        transfer(r, *lev.tables, rc, True)
        xc = self.cycle(rc, k + 1)
        del rc
        transfer(x, *lev.tables, xc, False)
        del xc
        self._smooth(k, b, x, False, r)
        return x
