"""The regularizer of the C8 field: Tikhonov (the squared norm of the discrete Hessian) and the equilibrium gap.

With small elements the image term alone leaves the nodal values noisy (C8 nodal values
are de-averaged by the inverse of the mass-like matrix ``M``) and nodes that see little
texture ill-determined. The modified Gauss–Newton step then solves

    (M + λ R) δa = b − λ R a

with a penalty ``aᵀ R a`` that damps the short wavelengths of the field and leaves the
long ones to the images (the usual regularised global DVC: pyxel, UFreckles, Correli):

``tikhonov``
    ``R = Σ_axes D2ᵀ D2 + 2 Σ_planes Dmᵀ Dm``, the squared Frobenius norm of the discrete
    Hessian of each component: second differences along every grid line of nodes plus
    twice the squared mixed differences ``u₀₀ − u₁₀ − u₀₁ + u₁₁`` of every 2×2 square of
    nodes in the three grid planes (a discrete curvature, in voxel units scaled away by the
    normalisation). Its plane-wave symbol is ``(Σ_i s_i)²`` with ``s_i = 2 − 2 cos θ_i``,
    ``|θ|⁴`` to leading order: a wave is damped by its wavelength whatever its direction.
    The second differences alone (``Σ s_i²``) would damp a wave along a
    grid diagonal 2–3× less than one along an axis, so at the same resolution along the
    axes the field would keep 1.2× more noise (measured on the star, docs/engine.md). It reaches
    every node, the ROI's edges and corners included, and costs nothing for rigid and
    linear fields: it penalises the curvature of the field, not its gradient (the H¹
    energy ``∫ |∇u|²`` would pull a homogeneous strain towards zero: on a 5³-node mesh of a
    −2 % compression it measured −1.7 %). A fourth-order low-pass.
``equilibrium-gap``
    ``R = Kᵀ P K + μ_s Σ_faces Lᵀ P_s L + μ_e Σ_edges D2ᵀ D2``: ``K`` the stiffness of a
    homogeneous isotropic elastic solid on the C8 mesh (Poisson ratio ``POISSON``), ``P``
    keeps its rows at interior nodes: the equilibrium gap, zero for any field in
    equilibrium (Tomičević, Hild, Roux 2013). On the ROI faces, where ``K u`` is a traction
    the images cannot constrain, ``L`` is the in-plane (Q4) Laplacian of each face, ``P_s``
    keeps the rows inside the face; on the 12 edges of the box, which the face rows leave
    out, ``D2`` is the second difference along the edge. ``μ_s`` and ``μ_e`` make a plane
    wave cost as much per face node and per edge node as per interior node. Each term sets
    the next lower-dimensional part from its boundary (interior from the faces, faces from
    the edges, edges from the corners), so the null space is 24 fields fixed by the 8
    corners, as many as Tikhonov's; without the edge term it held every field set by its
    edge values (3 (12 (n - 2) + 8) of them), left to the few voxels of the edge nodes, and
    Gauss–Newton on CT scans at ℓ = 6 and 4 moved those nodes by up to 88 voxels and ended
    stalled or diverged (docs/engine.md). It couples the components as an
    elastic solid does; a localised band (a local softening) is not in equilibrium for a
    homogeneous material, and the equilibrium gap damps it more than Tikhonov does.

Normalisation (as pyxel does for its weak regularisation): ``λ`` is such that a plane
wave of wavelength ``T`` is penalised ``(ℓ_reg / T)^4`` times its image term
``vᵀ M v``: one length ``ℓ_reg`` (voxels)
sets the weight; features shorter than it are damped, longer ones left to the images.
``λ`` is measured with waves of wavelength ``T_ref = 10 ℓ`` (bounded by the mesh), where
the discrete operators follow the continuous scaling, averaged over the three directions
and polarisations.

Everything is built from the mesh alone (no voxels) and applied matrix-free on the client
by element loops (the kernels of :mod:`chunkdic.solve.penalty`), next to the stencil product of
``M`` in the same CG; the robust reweighting that frees some of its terms is
:mod:`chunkdic.solve.reweighting`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..mesh import node_colours
from .penalty import (
    NO_FREED,
    TERM_KINDS,
    apply_edges,
    apply_faces,
    apply_hessian,
    apply_hessian_freed,
    apply_vector,
    freed_diagonal,
    elastic_element,
    face_laplacian_element,
)

KINDS = ("none", "tikhonov", "equilibrium-gap")
#: order of the low-pass: penalty ∝ (ℓ_reg / T)^ORDER for a plane wave of wavelength T
ORDER = {"tikhonov": 4, "equilibrium-gap": 4}


def _interior(x: np.ndarray) -> np.ndarray:
    """Zero the rows of the boundary nodes (the projection ``P``)."""
    out = np.zeros_like(x)
    out[1:-1, 1:-1, 1:-1] = x[1:-1, 1:-1, 1:-1]
    return out


@dataclass
class Regularizer:
    """The operator ``R`` of one mesh (no weight): :meth:`apply` and :meth:`diagonal_blocks`.

    Parameters
    ----------
    kind : {"tikhonov", "equilibrium-gap"}
    nodes_shape : tuple of 3 int
    ell : float
        Element edge, voxels of the level.
    freed : ndarray, shape (nz, ny, nx, 6), uint8, optional
        Tikhonov only: the terms the robust reweighting left out (weight 0; every other
        term keeps weight 1). Bit ``c`` of ``freed[i, j, k, t]`` frees component ``c`` of the
        term of kind ``TERM_KINDS[t]`` anchored at node ``(i, j, k)`` (a second difference at
        its centre node, a mixed one at its square's first corner): 6 B per node
        (:func:`robust_freed`). The normalisation (:func:`plane_wave_weight`), the probed
        diagonal classes of the preconditioners and the V-cycle's coarse operators are
        those of the plain penalty (docs/engine.md).
    """

    kind: str
    nodes_shape: tuple[int, int, int]
    ell: float
    freed: np.ndarray | None = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        if self.kind not in KINDS[1:]:
            raise ValueError(f"unknown regularisation {self.kind!r}")
        self.nodes_shape = tuple(int(n) for n in self.nodes_shape)
        if self.freed is not None:
            if self.kind != "tikhonov":
                raise ValueError("only the Tikhonov penalty is reweighted term by term")
            self.freed = np.ascontiguousarray(self.freed, np.uint8)
            if self.freed.shape != self.nodes_shape + (len(TERM_KINDS),):
                raise ValueError(f"freed terms of shape {self.freed.shape} on a mesh of {self.nodes_shape} nodes")
            if not self.freed.any():
                self.freed = None
        self._Kf = face_laplacian_element()
        self.surface_weight = self.edge_weight = 0.0
        if self.kind == "tikhonov":
            self._Ke = np.zeros((24, 24))
        else:
            self._Ke = elastic_element(self.ell)
            self.surface_weight, self.edge_weight = self._balance_boundary()

    @property
    def order(self) -> int:
        return ORDER[self.kind]

    def numba_args(self) -> tuple:
        """``(code, Ke, Kf, surface weight, edge weight, freed)`` for :func:`add_weighted`."""
        return ((1 if self.kind == "tikhonov" else 2), self._Ke, self._Kf, float(self.surface_weight),
                float(self.edge_weight), NO_FREED if self.freed is None else self.freed)

    def resized(self, nodes_shape) -> "Regularizer":
        """The same plain operator on a mesh of ``nodes_shape`` nodes, with this one's boundary
        weights (for probing its stencil on a small mesh: the weights balanced on the small
        mesh differ) and no freed term."""
        small = Regularizer(self.kind, nodes_shape, self.ell)
        small.surface_weight, small.edge_weight = self.surface_weight, self.edge_weight
        return small

    def plain(self) -> "Regularizer":
        """This operator with every term at weight 1 (itself when none is freed)."""
        return self if self.freed is None else self.with_freed(None)

    def with_freed(self, freed: np.ndarray | None) -> "Regularizer":
        """The same operator with the terms ``freed`` left out (:attr:`freed`), sharing this
        one's probed diagonal classes and V-cycle operators (those of the plain penalty)."""
        out = Regularizer(self.kind, self.nodes_shape, self.ell, freed)
        out.surface_weight, out.edge_weight = self.surface_weight, self.edge_weight
        for cache in ("_diagonal", "_multigrid"):
            if hasattr(self, cache):
                setattr(out, cache, getattr(self, cache))
        return out

    def sub(self, region: tuple[slice, slice, slice]) -> "Regularizer":
        """The operator on the sub-mesh ``region`` of the nodes (its freed terms with it)."""
        shape = tuple(len(range(*r.indices(n))) for r, n in zip(region, self.nodes_shape))
        return Regularizer(self.kind, shape, self.ell, None if self.freed is None else self.freed[region])

    def _K(self, x: np.ndarray) -> np.ndarray:
        y = np.zeros_like(x)
        apply_vector(self._Ke, x, y)
        return y

    def apply(self, x: np.ndarray) -> np.ndarray:
        """``R x`` for a nodal field ``x`` of shape (nz, ny, nx, 3), float64."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        if self.kind == "tikhonov":
            y = np.zeros_like(x)
            if self.freed is None:
                apply_hessian(x, y, 1.0)
            else:
                apply_hessian_freed(x, y, 1.0, self.freed)
            return y
        y = self._K(_interior(self._K(x)))
        if self.surface_weight:
            apply_faces(self._Kf, x, y, float(self.surface_weight))
        if self.edge_weight:
            apply_edges(x, y, float(self.edge_weight))
        return y

    def _boundary_terms(self, x: np.ndarray) -> tuple[float, float, float]:
        """The three terms of ``xᵀ R x`` (volume; faces and edges with unit weight)."""
        vol = float(np.sum(_interior(self._K(x)) ** 2))
        y = np.zeros_like(x)
        apply_faces(self._Kf, x, y, 1.0)
        z = np.zeros_like(x)
        apply_edges(x, z, 1.0)
        return vol, float(np.sum(x * y)), float(np.sum(x * z))

    def _balance_boundary(self) -> tuple[float, float]:
        """``(μ_s, μ_e)``: plane waves cost the same per face node and per edge node as per interior node."""
        n = [int(k) for k in self.nodes_shape]
        n_int = max(int(np.prod([max(k - 2, 0) for k in n])), 1)
        n_face = max(sum(2 * max(n[(a + 1) % 3] - 2, 0) * max(n[(a + 2) % 3] - 2, 0) for a in range(3)), 1)
        n_edge = max(sum(4 * max(n[a] - 2, 0) for a in range(3)), 1)
        vol = surf = edge = 0.0
        for v in plane_waves(self.nodes_shape, self.ell, reference_wavelength(self.nodes_shape, self.ell)):
            a, b, c = self._boundary_terms(v)
            vol, surf, edge = vol + a, surf + b, edge + c
        if vol <= 0:
            return 0.0, 0.0
        mu_s = (vol / n_int) / (surf / n_face) if surf > 0 else 0.0
        mu_e = (vol / n_int) / (edge / n_edge) if edge > 0 else 0.0
        return mu_s, mu_e

    def diagonal_blocks(self, planes: slice = slice(None)) -> np.ndarray:
        """The 3×3 diagonal blocks of ``R`` on the z planes ``planes`` of the nodes (default:
        all), shape (nz', ny, nx, 3, 3), float64 (for the preconditioner).

        ``R`` is the same at every node farther than its reach (2 nodes for the equilibrium
        gap, 1 for Tikhonov) from the mesh faces: the blocks are probed on a mesh of at
        most ``2 (reach + 1) + 1`` nodes per axis, with unit vectors on a colouring of
        nodes whose supports do not overlap, and mapped back by distance to the faces.
        The probed blocks are kept (a few kB): a slab of planes costs only its own copy,
        so that the client never needs all of them at once (72 B per node). With freed
        terms, their share of the diagonal is taken off (``planes`` a contiguous slice).
        """
        blocks, index = self.diagonal_classes()
        out = blocks[np.ix_(index[0][planes], index[1], index[2])]
        if self.freed is not None:  # Tikhonov's blocks are diagonal: the freed terms' share off
            z = np.arange(self.nodes_shape[0])[planes]
            if z.size:
                less = np.zeros(out.shape[:4])
                freed_diagonal(self.freed, int(z[0]), less)
                out[..., [0, 1, 2], [0, 1, 2]] += less
        return out

    def diagonal_classes(self) -> tuple[np.ndarray, list]:
        """``(blocks, index)``: the diagonal blocks probed on the small mesh (float64) and, per
        axis, each node's position in it (int64 arrays of the mesh's length): block ``(i, j, k)``
        is ``blocks[index[0][i], index[1][j], index[2][k]]`` (block-Jacobi reads them so,
        :func:`chunkdic.solve.stencil.block_solve`). Those of the plain penalty: with freed
        terms, block-Jacobi preconditions with a diagonal a little too large at their
        nodes, which keeps it symmetric positive definite (docs/engine.md)."""
        cached = getattr(self, "_diagonal", None)
        if cached is not None:
            return cached
        reach = 2
        core = reach + 1
        small_shape = tuple(min(n, 2 * core + 1) for n in self.nodes_shape)
        small = self.plain() if small_shape == self.nodes_shape else self.resized(small_shape)
        period = 2 * reach + 1
        blocks = np.zeros(small_shape + (3, 3))
        for sel in node_colours(small_shape, period):
            for j in range(3):
                e = np.zeros(small_shape + (3,))
                e[sel, j] = 1.0
                blocks[sel, :, j] = small.apply(e)[sel]
        index = [np.where(np.arange(n) < core, np.arange(n),
                          np.where(np.arange(n) >= n - core, m - (n - np.arange(n)), core))
                 for n, m in zip(self.nodes_shape, small_shape)]
        self._diagonal = blocks, index
        return self._diagonal


def reference_wavelength(nodes_shape, ell: float) -> float:
    """Wavelength (voxels) of the normalising plane waves: ``10 ℓ``, at most the mesh's smallest extent."""
    extent = (min(nodes_shape) - 1) * ell
    return float(max(min(10.0 * ell, extent), 4.0 * ell))


def plane_waves(nodes_shape, ell: float, wavelength: float):
    """The 9 plane waves (3 directions × 3 polarisations) of ``wavelength`` (voxels) on the nodes.

    Each is ``sin(2π x_d / T + 1)`` in one component, over node positions ``k ell``.
    """
    axes = [np.arange(n) * ell for n in nodes_shape]
    for d in range(3):
        shape = [1, 1, 1]
        shape[d] = -1
        s = np.sin(2 * np.pi * axes[d] / wavelength + 1.0).reshape(shape)
        for c in range(3):
            v = np.zeros(tuple(nodes_shape) + (3,))
            v[..., c] = np.broadcast_to(s, nodes_shape)
            yield v


def plane_wave_weight(reg: Regularizer, matvec, length: float) -> float:
    """``λ`` such that a plane wave of wavelength ``T`` costs ``(length / T)^p`` of its image term.

    ``matvec(x)`` applies ``M``; measured at :func:`reference_wavelength` over the 9 waves:
    ``λ = (length / T)^p · Σ vᵀ M v / Σ vᵀ R v``, i.e. :func:`plane_wave_unit` ``· length^p``.
    """
    return plane_wave_unit(reg, matvec) * float(length) ** reg.order


def plane_wave_unit(reg: Regularizer, matvec) -> float:
    """The ``λ`` of :func:`plane_wave_weight` for a length of one voxel: ``Σ vᵀ M v / Σ vᵀ R v / T^p``.

    Nine products of ``M`` and of ``R`` over the whole mesh (0.6 s at 65³ nodes, 1024³ at
    ℓ = 16): a caller that weighs several lengths against the same ``M`` keeps it
    (:func:`chunkdic.method.length.regularize`).
    """
    T = reference_wavelength(reg.nodes_shape, reg.ell)
    reg = reg.plain()  # one length means one weight, whatever the robust reweighting freed
    m = r = 0.0
    for v in plane_waves(reg.nodes_shape, reg.ell, T):
        m += float(np.sum(v * matvec(v)))
        r += float(np.sum(v * reg.apply(v)))
    if r <= 0:
        return 0.0
    return m / r / T ** reg.order
