"""The start of a level: the field its iterations begin from.

On finer levels the coarser level's field carried to the finer nodes (DESIGN.md: the
half-voxel offset, × 2). On the coarsest level of a new run the start of lowest gap among
(:func:`best_start`, docs/engine.md, "The start"):

- the mean rigid translation (paper section 5.1): the integer translation of phase
  correlation (:meth:`~chunkdic.method.protocol.Passes.translation`), refined by
  Gauss–Newton with the rigid restriction of ``M`` (:func:`chunkdic.method.gauss_newton.rigid_step`),
  then an affine field (:func:`affine_step`);
- no motion (the zero field);
- with ``init``, an earlier result's field evaluated at the new nodes (:func:`init_field`).

The affine step: a rigid translation cannot start a C8 mesh on a large homogeneous strain
or rotation: at 10–20 % compression or 10° of rotation the far elements are several voxels
(beyond the texture's capture range) from where a translation puts them, and their
Gauss–Newton steps go astray. Gauss–Newton restricted to affine fields
``u(X) = t + A (X - c)`` uses every voxel of the level for 12 unknowns, linearised where the
field is right (near ``c``) and pulled outwards pass by pass; the C8 iterations then start
within a fraction of a voxel of any field that is affine to first order. The C8 basis holds
affine fields exactly (trilinear shape functions reproduce linear functions), so the affine
field is a nodal field ``a = P p`` with ``P`` the ``(3N, 12)`` table of node coordinates, and
the restricted system is ``Pᵀ M P δp = Pᵀ b``: the nodal ``b`` of an ordinary pass summed
with weights, and ``M`` applied to the 12 columns of ``P`` on the client (mesh-sized work, no
extra pass over the voxels; paper section 5.1 does the same for the rigid translation). A
regularisation term would vanish on affine fields (curvature Tikhonov) or nearly
(equilibrium gap), so the step leaves it out.

An earlier result's field (``correlate(init=…)``): evaluated with its own shape functions at
the new mesh's nodes, positions and values converted between levels with the half-voxel
offset, by :func:`chunkdic.mesh.carry_field`; outside the earlier ROI it takes the linear
extension of the nearest element up to one element beyond the earlier mesh, and beyond
that the value at that limit (``clamp=True``); nodes the earlier run did not measure (NaN)
take the mean of the measured nodes, per component (docs/analysis.md, "Starting from an
earlier result").
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..mesh import Mesh, carry_field, transfer
from ..solve.stencil import stencil_matvec
from .events import Affine, Init, StartChoice, emit
from .gauss_newton import rigid_step
from .operator import Operator
from .protocol import Passes
from .stopping import History, State

#: Gauss-Newton passes of the rigid step (a uniform translation: three unknowns)
RIGID_ITERATIONS = 10
#: a chosen start farther than this (voxels of the level) from the field M was built at rebuilds M
MOVED_START = 0.5

#: passes of the affine step at most
MAX_PASSES = 20


def affine_table(mesh) -> tuple[np.ndarray, np.ndarray]:
    """The nodal fields of the 12 affine parameters over ``mesh``.

    Returns
    -------
    P : ndarray, shape (12, nz, ny, nx, 3), float64
        Column ``k`` is the nodal field of parameter ``k``: ``k < 3`` the translation along
        component ``k``; ``k = 3 + 3 i + j`` the gradient ``dU_i/dX_j`` times the ROI's half
        extent along ``j`` (so that all columns move the nodes by O(1) voxel, which keeps
        ``Pᵀ M P`` well conditioned).
    centre : ndarray, shape (3,), float64
        ``c``, the ROI's centre, voxels of the level.
    """
    axes = mesh.node_axes()
    centre = np.array([(a[0] + a[-1]) / 2 for a in axes])
    half = np.array([max((a[-1] - a[0]) / 2, 1.0) for a in axes])
    grid = np.meshgrid(*[(a - c) / h for a, c, h in zip(axes, centre, half)], indexing="ij")
    P = np.zeros((12,) + mesh.nodes_shape + (3,))
    for i in range(3):
        P[i, ..., i] = 1.0
        for j in range(3):
            P[3 + 3 * i + j, ..., i] = grid[j]
    return P, centre


def affine_field(P: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The nodal field ``P p``, shape (3, nz, ny, nx) (the engine's layout)."""
    return np.moveaxis(np.tensordot(p, P, axes=1), -1, 0)


def gradient(p: np.ndarray, mesh) -> np.ndarray:
    """``dU_i/dX_j`` (3, 3) of the affine parameters ``p`` (:func:`affine_table`)."""
    half = np.array([max((a[-1] - a[0]) / 2, 1.0) for a in mesh.node_axes()])
    return p[3:].reshape(3, 3) / half[None, :]


def affine_step(passes: Passes, op: Operator, t: np.ndarray, tolerance: float, history: History, progress=None, *,
                max_passes: int = MAX_PASSES) -> np.ndarray:
    """Gauss–Newton restricted to affine fields from the translation ``t``.

    Parameters
    ----------
    passes : Passes
        The coarsest level's passes.
    op : Operator
        Its ``M``.
    t : ndarray, shape (3,), float64, voxels of the level
        The rigid translation (:func:`chunkdic.method.gauss_newton.rigid_step`).
    tolerance : float
        Stop when the step moves no node by more than this (voxels of the level).
    history : History
        Passes are recorded with negative iteration numbers after the rigid step's.
    progress : callable, optional

    Returns
    -------
    ndarray, shape (3, nz, ny, nx), float64, voxels of the level
        The affine field of lowest gap met (the translation's if no affine field was better).
    """
    mesh, level = passes.mesh, passes.level
    P, _ = affine_table(mesh)
    flat = P.reshape(12, -1)
    K = np.stack([stencil_matvec(op.solver.matrix, P[k]).reshape(-1) for k in range(12)]) @ flat.T
    K = 0.5 * (K + K.T)
    p = np.zeros(12)
    p[:3] = t
    first = -1 - int(np.count_nonzero(np.asarray(history.rows["iteration"]) < 0) if history.rows["iteration"] else 0)
    best_gap, best_p = np.inf, p.copy()
    for it in range(max_passes):
        u = affine_field(P, p)
        ps = passes.assemble_b(u, op)
        if not np.isfinite(ps.gap):
            break
        if ps.gap < best_gap:
            best_gap, best_p = ps.gap, p.copy()
        elif ps.gap > 2.0 * best_gap:  # going astray: keep the best
            history.add(level, first - it, ps.gap, np.nan, ps.n_excluded)
            break
        rhs = flat @ ps.b.reshape(-1)
        try:
            dp = np.linalg.solve(K, rhs)
        except np.linalg.LinAlgError:
            break
        move = float(np.abs(affine_field(P, dp)).max())
        history.add(level, first - it, ps.gap, move, ps.n_excluded)
        emit(progress, Affine(level=level, iteration=it, gap=ps.gap, max_delta=move, gradient=gradient(p, mesh).tolist()))
        p = p + dp
        if move < tolerance:
            best_p = p  # converged: the last step is below the tolerance
            break
    return affine_field(P, best_p)


def uniform(t, mesh: Mesh) -> np.ndarray:
    """A uniform nodal field ``t`` (3,) over ``mesh``: shape (3, nz, ny, nx)."""
    return np.asarray(t, dtype=np.float64)[:, None, None, None] * np.ones((3,) + mesh.nodes_shape)


def filled(u: np.ndarray) -> np.ndarray:
    """``u`` (3, nz, ny, nx) with NaN nodes replaced by the mean of the measured ones."""
    bad = ~np.isfinite(u).all(axis=0)
    if not bad.any():
        return u
    out = np.array(u, dtype=np.float64)
    for c in range(3):
        out[c][bad] = np.mean(u[c][~bad])
    return out


def init_field(earlier, mesh: Mesh, level: int) -> np.ndarray:
    """An earlier result's field at the nodes of ``mesh`` (level ``level``), voxels of that level.

    Parameters
    ----------
    earlier : Result
        The earlier result (its ``displacement`` in voxels of its ``level``, its ``mesh``).
    mesh : Mesh
        The new mesh on the level the run starts on.
    level : int
        That level.

    Returns
    -------
    ndarray, shape (3, nz, ny, nx), float64, voxels of ``level``
    """
    return carry_field(filled(earlier.displacement), earlier.mesh, earlier.level, mesh.node_coords(), level,
                       clamp=True)


def level_start(passes: Passes, meshes: dict, coarsest: int, coarser_u: np.ndarray | None, *, earlier=None,
                progress=None) -> tuple[np.ndarray, np.ndarray | None]:
    """The field a new level starts from, shape (3, nz, ny, nx), voxels of the level, and
    the integer translation the rigid step refines (coarsest level only, else ``None``).

    Coarsest level: an ``earlier`` result evaluated at the nodes (:func:`init_field`), or
    the phase-correlation translation. Finer levels: the coarser level's field ``coarser_u``
    carried to the finer nodes (DESIGN.md, half-voxel offset, × 2).
    """
    s, mesh = passes.level, passes.mesh
    if s == coarsest and earlier is not None:
        start = init_field(earlier, mesh, s)
        emit(progress, Init(level=s, path=earlier.path, mean=[float(v) for v in start.mean(axis=(1, 2, 3))]))
        return start, None
    if s == coarsest:
        t_int = passes.translation()
        return uniform(t_int, mesh), t_int
    return transfer(coarser_u, meshes[s + 1], s + 1, mesh, s), None


@dataclasses.dataclass(frozen=True)
class Start:
    """The start chosen on the coarsest level (:func:`best_start`).

    Attributes
    ----------
    u : ndarray, shape (3, nz, ny, nx), float64, voxels of the level
        The field.
    op : Operator
        ``M`` the level iterates with: the one given, or built again around ``u``.
    rigid_t : ndarray, shape (3,), float64, voxels of the level
        The start's translation: the refined rigid translation, or the chosen field's mean.
    """

    u: np.ndarray
    op: Operator
    rigid_t: np.ndarray


def best_start(passes: Passes, op: Operator, start: np.ndarray, t_int, tolerance: float, history: History,
               progress=None) -> Start:
    """The start of lowest gap on the coarsest level.

    Candidates: no motion (the zero field), the rigid translation refined by Gauss–Newton
    then an affine field (paper section 5.1), and with ``init`` the earlier result's field
    (``start``; ``t_int`` is then ``None`` and the phase-correlation translation is found
    here). Without ``init``, no motion is a candidate only when the part of ``g`` prepared
    for the rigid field covers it (a motion within about an element): a larger translation
    found by phase correlation is trusted as before, without a second prefilter of ``g``
    for a field that cannot win. Each is measured by :meth:`Passes.gap` and the lowest wins:
    an earlier result is a good start only when the motion goes on as before, and between
    two identical scans of a loading series the previous increment started the iterations
    at 13 % instead of 0.001 % and stalled them (docs/engine.md, "The start"). With ``init`` the rigid and
    affine passes run only when the translation alone already beats the other candidates,
    so a good earlier field costs three gap passes and one small task, not ten passes.

    ``M`` is summed only over the voxels its field maps inside ``g``: built around a
    discarded start 5 voxels off, three corner nodes lost their texture and the iterations
    from the chosen start diverged after the regularisation length was chosen. So a chosen
    start farther than :data:`MOVED_START` from the field ``op`` was built at gets its own ``M``.
    """
    mesh = passes.mesh
    zero = np.zeros((3,) + mesh.nodes_shape)
    gaps, fields = {}, {}
    rigid_t = None

    def measure(name: str, u: np.ndarray) -> None:
        passes.prepare(u)
        gaps[name], fields[name] = passes.gap(u, op), u

    if t_int is not None:  # a new run: the rigid step as before, then compared with no motion
        rigid_t, fields["rigid"] = rigid_and_affine(passes, op, t_int, tolerance, history, progress)
        measure("rigid", fields["rigid"])
        if passes.covers(zero):  # a motion within the prepared window's margin (≥ 8 voxels)
            measure("zero", zero)
    else:  # from an earlier result: that field, no motion, the translation alone
        measure("init", start)
        measure("zero", zero)
        t_int = passes.translation()
        measure("translation", uniform(t_int, mesh))
        if min(gaps, key=gaps.get) == "translation":
            rigid_t, affine = rigid_and_affine(passes, op, t_int, tolerance, history, progress)
            measure("rigid", affine)
    chosen = min(gaps, key=gaps.get)  # ties: the first measured (the rigid step, or the earlier field)
    emit(progress, StartChoice(level=passes.level, chosen=chosen, gaps=dict(gaps)))
    if chosen != "rigid":
        rigid_t = fields[chosen].mean(axis=(1, 2, 3))
    # M was built around the earlier field (init) or the translation: again around another
    # start that moves some node by more than MOVED_START voxels (voxels mapped out of g differ)
    built_at = "init" if "init" in gaps else "rigid"
    if chosen != built_at and float(np.abs(fields[chosen] - op.built_at).max()) > MOVED_START:
        op = passes.assemble_m(fields[chosen])
    return Start(fields[chosen], op, rigid_t)


def rigid_and_affine(passes: Passes, op: Operator, t_int, tolerance: float, history: History,
                     progress=None) -> tuple[np.ndarray, np.ndarray]:
    """The rigid translation from ``t_int`` refined by Gauss–Newton, then the affine field
    from it: a uniform translation cannot start 10-20 % strain or a 10° rotation (12
    unknowns, ``M`` restricted to affine fields: no extra voxel pass; docs/engine.md).
    Returns ``(rigid translation (3,), affine field (3, nz, ny, nx))``, voxels of the level."""
    passes.prepare(uniform(t_int, passes.mesh))
    rigid_t = rigid_step(passes, op, t_int, tolerance, RIGID_ITERATIONS, history, progress)
    return rigid_t, affine_step(passes, op, rigid_t, tolerance, history, progress)


def fresh_state(start: np.ndarray, op: Operator) -> State:
    """The Gauss–Newton state of a new level at ``start``, recording the field ``op`` was built at."""
    return State(start, m_start=op.built_at)
