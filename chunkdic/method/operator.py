"""The Gauss–Newton operator of a level: ``M``, its rigid restriction and solver, as the ``M`` pass left them.

``M_ij = Σ_voxels (∇f·N_i)(∇f·N_j)`` (paper section 3) is summed once per level from the
reference by a pass over the voxels (:meth:`chunkdic.method.protocol.Passes.assemble_m`),
which returns it as an :class:`Assembled` (the half stencil, the noise-correlation sums
of the sensitivities, a mask's element activity, the reference's range, the brightness
cells' couplings). :func:`build_operator` turns it into the frozen :class:`Operator` the
method iterates with: the solver of ``M + λR`` (:class:`chunkdic.solve.cg.StencilSolver`),
the rigid 3×3 restriction of ``M``, the element activity and the centring and range of
the grey levels the ``b`` passes use.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ..solve.cg import PoorTextureWarning, StencilSolver
from ..solve.regularizer import Regularizer, plane_wave_unit
from ..warn import warn_user
from .crack import CrackCoupling

log = logging.getLogger(__name__)

__all__ = ["Assembled", "Operator", "build_operator", "warn_weak_nodes"]


@dataclasses.dataclass
class Assembled:
    """What the ``M`` pass of a level gives (:meth:`chunkdic.method.protocol.Passes.assemble_m`).

    Attributes
    ----------
    stencil : ndarray, shape (nz, ny, nx, 14, 3, 3), float32
        The half stencil of ``M`` (:data:`chunkdic.solve.stencil.HALF_OFFSETS`).
    lags : ndarray, shape (3, LAGS + 1), float64
        The pass's sensitivity lag sums (:mod:`chunkdic.method.noise`).
    active : ndarray, shape (ez, ey, ex), bool, optional
        Element activity of a specimen mask (None: every element).
    fmin, fmax : float
        Range of the prepared reference over the ROI.
    cells : ndarray, shape (cz, cy, cx, k+1, k+1, k+1, 3, 4), float32, optional
        The brightness cells' Schur complement (:func:`chunkdic.kernels.m.cell_couplings` over
        the mesh), None without cells.
    """

    stencil: np.ndarray
    lags: np.ndarray
    active: np.ndarray | None
    fmin: float
    fmax: float
    cells: np.ndarray | None = None
    crack: tuple | None = None


@dataclasses.dataclass(frozen=True)
class Operator:
    """``M`` of one level and what the passes need of it; its fields never change.

    Attributes
    ----------
    solver : StencilSolver
        CG on ``M`` (plus the penalty ``λ R`` that :func:`chunkdic.method.length.regularize`
        sets), with the poorly textured nodes held.
    rigid_matrix : ndarray, shape (3, 3), float64
        ``M`` restricted to uniform translations (``Σ_ij M_ij``, since ``Σ_a N_a = 1``),
        less the brightness cells' share.
    active : ndarray, shape (ez, ey, ex), bool, optional
        Elements with enough material of a specimen mask (None: every element).
    dynamic_range : float
        ``max f - min f`` over the ROI (the gap's normalisation, paper section 5.1).
    center : float
        The mid grey level, the centring constant of the ``b`` passes' brightness sums.
    sensitivity_lags : ndarray, shape (3, LAGS + 1), float64
        The ``M`` pass's sensitivity lag sums (:func:`chunkdic.method.noise.correlation_factor`).
    built_at : ndarray, shape (3, nz, ny, nx), float64
        The field ``M`` was summed at (voxels it maps outside ``g`` are left out), voxels of
        the level: a checkpoint keeps it, so that a resumed level rebuilds the very same ``M``.
    reused : bool
        Read from the output where an interrupted run kept it, not summed by a pass.
    crack : CrackCoupling, optional
        The nodes a known crack splits and their second copies' couplings (None: no crack,
        or one that splits no node).
    """

    solver: StencilSolver
    rigid_matrix: np.ndarray
    active: np.ndarray | None
    dynamic_range: float
    center: float
    sensitivity_lags: np.ndarray
    built_at: np.ndarray
    reused: bool = False
    crack: CrackCoupling | None = None
    # λ of a unit regularisation length per penalty kind: nine products with M each, once
    # (the correlated level weighs up to three lengths against the same M)
    _unit_weights: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)

    @property
    def nodes_shape(self) -> tuple[int, int, int]:
        return tuple(self.solver.nodes_shape)

    def masked_nodes(self) -> np.ndarray:
        """Nodes with no active element around them (bool, nodes shape); all False without a mask."""
        n = self.nodes_shape
        if self.active is None:
            return np.zeros(n, bool)
        a = np.pad(self.active, 1)
        around = sum(a[dz:dz + n[0], dy:dy + n[1], dx:dx + n[2]] for dz in (0, 1) for dy in (0, 1) for dx in (0, 1))
        return around == 0

    def weak_nodes(self) -> np.ndarray:
        """Poorly textured nodes (index triples, shape (n, 3)), those outside a specimen mask left out."""
        weak = self.solver.weak_nodes
        if self.active is not None and len(weak):
            weak = weak[~self.masked_nodes()[tuple(weak.T)]]
        return weak

    def unit_weight(self, kind: str, element_size: float) -> float:
        """``λ`` of a unit regularisation length for the penalty ``kind`` on this ``M``
        (:func:`chunkdic.solve.regularizer.plane_wave_unit`), computed once per operator and kind."""
        if kind not in self._unit_weights:
            reg = Regularizer(kind, self.nodes_shape, element_size)
            self._unit_weights[kind] = plane_wave_unit(reg, self.solver.stencil_product)
        return self._unit_weights[kind]


def build_operator(m: Assembled, built_at: np.ndarray, *, cell: int = 1, reused: bool = False,
                   make_solver=StencilSolver) -> Operator:
    """The :class:`Operator` of an assembled ``M`` (its stencil is the solver's from now on).

    ``make_solver(stencil, cells=, cell=)`` makes the solver: the in-memory
    :class:`~chunkdic.solve.cg.StencilSolver`, or one of the same operations whose stencil
    lives in node blocks (:class:`~chunkdic.solve.partitioned.PartitionedSolver`, which the
    passes give for a mesh that does not fit the client).

    Raises
    ------
    InputError
        ``M`` has no gradient at all (:class:`~chunkdic.solve.cg.StencilSolver`).
    """
    lags, active, fmin, fmax = m.lags, m.active, float(m.fmin), float(m.fmax)
    S, cells, crack, m = m.stencil, m.cells, m.crack, None
    # the rigid-body restriction of M: since Σ_a N_a = 1, Σ_voxels ∇f ∇fᵀ = Σ_ij M_ij (the solver's)
    solver = make_solver(S, cells=cells, cell=cell)
    crack = None if crack is None else CrackCoupling.from_pairs(*crack, solver.nodes_shape, solver.scale)
    return Operator(solver, solver.rigid_matrix, active, fmax - fmin, 0.5 * (fmin + fmax), lags, built_at, reused,
                    crack)


def warn_weak_nodes(op: Operator, mesh, level: int, correlated: int) -> None:
    """Warn of the correlated level's poorly textured nodes (coarser levels: logged only).

    A coarser level only gives the next one its start, and its nodes are regularised
    anyway (:func:`chunkdic.method.length.regularize`): a warning about them, printed by every
    run on scans whose corners lose texture to the sums, told users nothing they could act on.
    """
    weak = op.weak_nodes()
    if len(weak) == 0:
        return
    if level != correlated:
        log.info("level %d: %d of %d nodes see little texture (regularised; only a start for level %d)",
                 level, len(weak), int(np.prod(mesh.nodes_shape)), level - 1)
        return
    coords = mesh.node_coords()
    where = ", ".join(
        "node (%d, %d, %d) at voxel (%.1f, %.1f, %.1f)" % (*n, *coords[(slice(None), *n)]) for n in weak[:5]
    )
    more = f" and {len(weak) - 5} more" if len(weak) > 5 else ""
    warn_user(f"level {level}: {len(weak)} of {np.prod(mesh.nodes_shape)} nodes see too little texture "
              f"to be measured ({where}{more}); they are regularised and their values are unreliable",
              PoorTextureWarning)
