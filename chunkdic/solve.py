"""Client-side solve of ``M δa = b`` (paper section 3) on the nodal 27-point stencil.

``M`` is a weighted mass matrix: conjugate gradients with a 3×3 nodal block-Jacobi
preconditioner converge in about a hundred iterations whatever the mesh size, where a
direct factorisation costs seconds to minutes (shared/DESIGN.md). The stencil is used
as is for the matrix-vector product, so ``M`` is never converted to CSR.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass

import numba
import numpy as np

log = logging.getLogger(__name__)

CENTRE = 13


class PoorTextureWarning(UserWarning):
    """Some nodes see too little image gradient to be measured reliably."""


@numba.njit(nogil=True, cache=True)
def _stencil_matvec(S, x, y):
    nz, ny, nx = x.shape[:3]
    for z in range(nz):
        for yy in range(ny):
            for xx in range(nx):
                a0 = 0.0
                a1 = 0.0
                a2 = 0.0
                for k in range(27):
                    z2 = z + k // 9 - 1
                    y2 = yy + (k // 3) % 3 - 1
                    x2 = xx + k % 3 - 1
                    if z2 < 0 or z2 >= nz or y2 < 0 or y2 >= ny or x2 < 0 or x2 >= nx:
                        continue
                    v0 = x[z2, y2, x2, 0]
                    v1 = x[z2, y2, x2, 1]
                    v2 = x[z2, y2, x2, 2]
                    s = S[z, yy, xx, k]
                    a0 += s[0, 0] * v0 + s[0, 1] * v1 + s[0, 2] * v2
                    a1 += s[1, 0] * v0 + s[1, 1] * v1 + s[1, 2] * v2
                    a2 += s[2, 0] * v0 + s[2, 1] * v1 + s[2, 2] * v2
                y[z, yy, xx, 0] = a0
                y[z, yy, xx, 1] = a1
                y[z, yy, xx, 2] = a2


def stencil_matvec(S: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``y = M x`` for the stencil ``S`` (nz, ny, nx, 27, 3, 3) and ``x`` (nz, ny, nx, 3)."""
    y = np.empty_like(x)
    _stencil_matvec(S, np.ascontiguousarray(x), y)
    return y


@dataclass
class StencilSolver:
    """Preconditioned CG on a nodal stencil; the preconditioner is built once per level.

    Parameters
    ----------
    stencil : ndarray, shape (nz, ny, nx, 27, 3, 3), float32 or float64
        Assembled ``M`` (see docs/architecture.md for the layout); used in place.
    weak_threshold : float
        A node is *poorly textured* when the smallest eigenvalue of its 3×3 diagonal
        block is below ``weak_threshold`` times the median over nodes of the mean
        eigenvalue. Such nodes get a small Tikhonov term (``weak_threshold`` × that
        median) so the system stays solvable, and a warning names them.
    rtol : float
        Relative residual tolerance of CG.
    """

    stencil: np.ndarray
    weak_threshold: float = 1e-3
    rtol: float = 1e-7
    maxiter: int = 2000

    def __post_init__(self):
        S = self.stencil
        self.nodes_shape = S.shape[:3]
        diag = S[..., CENTRE, :, :].reshape(-1, 3, 3).astype(np.float64)
        eig = np.linalg.eigvalsh(diag)  # ascending
        scale = float(np.median(eig.mean(axis=1)))
        if not np.isfinite(scale) or scale <= 0:
            raise ValueError("the reference image has no gradient in the ROI: nothing to correlate")
        weak = eig[:, 0] < self.weak_threshold * scale
        self.weak_nodes = np.argwhere(weak.reshape(self.nodes_shape))
        if weak.any():
            # Regularise in place: a Tikhonov term on the weak nodes' own block.
            diag[weak] += self.weak_threshold * scale * np.eye(3)
            S[..., CENTRE, :, :] = diag.reshape(S.shape[:3] + (3, 3))
        self.block_inverse = np.linalg.inv(diag)
        self.scale = scale
        # float32 for the matrix-vector product: CG is bound by memory traffic through the
        # stencil, and M only steers the modified Gauss-Newton steps (the converged field
        # solves b = 0 whatever M), so its round-off at 6e-8 changes nothing measurable.
        self.matrix = S.astype(np.float32, copy=False)
        self.stencil = None  # only the float32 matrix is kept

    def solve(self, b: np.ndarray) -> tuple[np.ndarray, int]:
        """Solve ``M δa = b``; ``b`` and the result have shape (nz, ny, nx, 3).

        Returns the solution and the number of CG iterations.
        """
        b = np.ascontiguousarray(b, dtype=np.float64)
        x = np.zeros_like(b)
        iterations = _pcg(self.matrix, self.block_inverse.reshape(self.nodes_shape + (3, 3)), b, x,
                          self.rtol, self.maxiter)
        if iterations < 0:
            warnings.warn(f"CG did not reach rtol={self.rtol} in {self.maxiter} iterations", RuntimeWarning,
                          stacklevel=2)
            iterations = self.maxiter
        return x, iterations


@numba.njit(nogil=True, cache=True)
def _block_jacobi(Binv, r, z):
    nz, ny, nx = r.shape[:3]
    for i in range(nz):
        for j in range(ny):
            for k in range(nx):
                for a in range(3):
                    z[i, j, k, a] = (Binv[i, j, k, a, 0] * r[i, j, k, 0] + Binv[i, j, k, a, 1] * r[i, j, k, 1]
                                     + Binv[i, j, k, a, 2] * r[i, j, k, 2])


@numba.njit(nogil=True, cache=True)
def _pcg(S, Binv, b, x, rtol, maxiter):
    """Preconditioned conjugate gradients, x updated in place; -1 if not converged.

    Written out (rather than scipy's ``cg``) so that its vector operations are plain
    loops: on a busy machine, multithreaded BLAS calls on these small vectors cost more
    than the whole stencil product.
    """
    r = b.copy()  # x starts at zero
    z = np.empty_like(b)
    q = np.empty_like(b)
    _block_jacobi(Binv, r, z)
    p = z.copy()
    rz = np.sum(r * z)
    bnorm = np.sqrt(np.sum(b * b))
    if bnorm == 0.0:
        return 0
    for it in range(1, maxiter + 1):
        _stencil_matvec(S, p, q)
        alpha = rz / np.sum(p * q)
        x += alpha * p
        r -= alpha * q
        if np.sqrt(np.sum(r * r)) <= rtol * bnorm:
            return it
        _block_jacobi(Binv, r, z)
        rz_new = np.sum(r * z)
        p *= rz_new / rz
        p += z
        rz = rz_new
    return -1
