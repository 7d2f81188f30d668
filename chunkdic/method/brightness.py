"""Grey-level (brightness and contrast) correction between the two scans.

Real X-ray sources drift: the deformed scan is often brighter or of another contrast than
the reference, by a global factor and by a slow drift across the specimen. The residual is
therefore taken as ``r = f(X) - (λ g(X + u(X)) + μ(X))`` with a brightness model:

``none``
    ``λ = 1, μ = 0``: the paper's plain residual.
``global``
    one gain and one offset for the whole ROI.
``drift`` (default)
    one gain and an affine offset ``a_c + b_c·(X - X_c)`` per *cell* of ``k³`` elements
    (:func:`offset_cell`: cells of about :data:`OFFSET_CELL_VOXELS` voxels): follows any
    brightness change that is close to linear over a cell, one that bends across the
    specimen included, and does not read a brightness gradient as motion. With ``k = 1``
    (large elements, or ``grey_cell`` 0) the earlier form: one gain, one linear drift across
    the ROI and one offset per element. Cells rather than elements because every offset
    takes from the field the information of the texture's mean gradient over its support:
    one per element cost about 10 % of noise at ℓ = 8 (docs/engine.md, "Brightness").
``element``
    a gain and an offset per element (``λ`` kept within :data:`GAIN_RANGE`; an element too
    flat to fix a gain gets an offset only).

The brightness unknowns are eliminated exactly at every pass (variable projection): for
the current field they minimise ``Σ w r²``, and ``b = Σ w N ∇f r`` is evaluated with them,
from one pass over the voxels (:class:`chunkdic.kernels.blocks.ElementSums`): each block task
reduces its element sums with :func:`reduce_block` (the per-element unknowns in full) and
the client finishes the global ones with :func:`combine`. The Gauss–Newton matrix of the
per-element models is ``M`` minus the Schur complement of their per-element unknowns,
built in the ``M`` pass (:func:`chunkdic.kernels.m.m_block`); the affine offsets of cells of
several elements reach across the cell, beyond ``M``'s stencil: their Schur complement is
kept apart, per cell, and subtracted in the client's solve
(:func:`chunkdic.kernels.m.cell_couplings`; left out, it slows Gauss–Newton
×3-5 per pass). The one global gain stays out of the step's matrix (rank one over the ROI).
A cell never straddles two blocks: blocks hold whole cells (:func:`aligned_block_elements`),
so a task eliminates its cells' offsets exactly, as it did its elements'. With ``α = λ - 1`` and
``g' = g(X+u) - c``, ``r = d - α g' - μ'`` (``d = f - g(X+u)``); the returned gain and offset
are in the usual form ``f ≈ gain · g(X + u) + offset`` (offset at the element centre, plus
``drift · (X - X_e)`` for the ``drift`` model; with cells, each cell has its own slope, which
:func:`chunkdic.export.correction.cell_slopes` reads back from the offsets, and the drift
reported is the plane through the offsets, :func:`offset_plane_slope`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..kernels.b import element_to_nodes
from ..kernels.blocks import LAGS, ElementSums
from .mismatch import FLAT, local_residual
from .settings import DEFAULT_GREY_CELL_VOXELS

MODELS = ("none", "global", "drift", "element")
#: bounds of a per-element gain (``element`` model)
GAIN_RANGE = (0.5, 2.0)
# positions of the quantities in ElementSums (blocks.QUANTITIES)
_D, _G, _ONE, _Z, _Y, _X = range(6)
_THETA = (_G, _Z, _Y, _X)  # global unknowns of the drift model: gain, then the drift per axis
_COORDS = (_Z, _Y, _X)
#: edge (voxels of the level) of the cells sharing one offset in the ``drift`` model (the default
#: setting, :data:`chunkdic.method.settings.DEFAULT_GREY_CELL_VOXELS`)
OFFSET_CELL_VOXELS = DEFAULT_GREY_CELL_VOXELS


def offset_cell(model: str, element_size: int, cell_voxels: float = OFFSET_CELL_VOXELS) -> int:
    """Elements per side of a cell sharing one brightness offset: ``round(cell_voxels / ℓ)``
    (at least 1) for the ``drift`` model, 1 for the others (``element`` fits per element,
    ``none`` and ``global`` have no local offset).

    >>> offset_cell("drift", 8), offset_cell("drift", 12), offset_cell("drift", 48), offset_cell("global", 8)
    (4, 3, 1, 1)
    """
    if model != "drift" or cell_voxels <= 0:
        return 1
    return max(1, int(round(float(cell_voxels) / int(element_size))))


def aligned_block_elements(elements_per_block: int, cell: int) -> int:
    """Elements per block side rounded down to whole cells (one cell at least), so that no cell
    straddles two blocks (blocks start at multiples of it from the mesh's first element).

    Down, not up: a block then stays within the edge asked for (``chunkdic.block-voxels``, the
    memory plan's), and a level keeps as many blocks to share among the threads. Rounding up
    made the 300³ run's level 1 at ℓ = 12 one block of 12³ elements (one thread) instead of
    8 (docs/engine.md, "Brightness").

    >>> aligned_block_elements(8, 4), aligned_block_elements(3, 4), aligned_block_elements(5, 1)
    (8, 4, 5)
    >>> aligned_block_elements(10, 3), aligned_block_elements(21, 5), aligned_block_elements(16, 4)
    (9, 20, 16)
    """
    k = max(1, int(cell))
    return max(1, int(elements_per_block) // k) * k


@dataclass
class Partials:
    """One block's share of a ``b`` pass, reduced for a brightness model; partials add up.

    Attributes
    ----------
    nodal : ndarray, shape (K, nz, ny, nx, 3), float64
        Nodal arrays over the block's nodes (``K`` depends on the model).
    scalars : ndarray, shape (m,), float64
        Sums over the block's valid voxels (first: ``Σ w``).
    elements : ndarray, shape (p, ez, ey, ex), float64
        Per-element fields (first: ``Σ w`` per element; last: the :data:`RESIDUAL_ROWS`
        rows of :func:`residual_rows`).
    n_excluded : int
        Voxels whose ``X + u(X)`` leaves ``g``.
    lags : ndarray, shape (6, LAGS + 1)
        The residual's autocorrelation sums (:class:`chunkdic.kernels.blocks.ElementSums`).
    """

    nodal: np.ndarray
    scalars: np.ndarray
    elements: np.ndarray
    n_excluded: int
    lags: np.ndarray


@dataclass
class Fit:
    """A pass's outcome for the whole ROI.

    Attributes
    ----------
    b : ndarray, shape (nz, ny, nx, 3), float64
        Right-hand side with the optimal brightness, grey levels² / voxel.
    ssr : float
        ``Σ w r²`` over the valid voxels, grey levels².
    weight : float
        ``Σ w``: the number of valid voxels, the ones at the edge of the usable part of ``g`` in part.
    gain, offset : ndarray, shape (ez, ey, ex), float64
        Brightness per element: ``f ≈ gain · g(X + u) + offset`` at the element centre
        (grey levels).
    drift : ndarray, shape (3,), float64
        Offset gradient (grey levels per voxel, z, y, x) of the ``drift`` model, else 0.
    valid_per_element : ndarray, shape (ez, ey, ex), float64
        ``Σ w`` per element.
    residual : ndarray, shape (2, ez, ey, ex), float64, optional
        Per element, the residual left by the element's own best gain and offset and the
        reference's own variation (:func:`residual_rows`), grey levels²: what tells a residual
        that is noise from one that is not (:mod:`chunkdic.method.mismatch`).
    """

    b: np.ndarray
    ssr: float
    weight: float
    gain: np.ndarray
    offset: np.ndarray
    drift: np.ndarray
    valid_per_element: np.ndarray
    residual: np.ndarray | None = None
    #: the element fields parked out of memory (:meth:`share`), holding gain, offset, valid counts
    #: and residual rows in place of the arrays above (then None)
    parked: object = None

    def share(self, fields) -> None:
        """Point gain, offset, valid counts and the residual rows at rows 0-2 and 6-7 of
        ``fields`` (the same values, as :func:`chunkdic.method.gauss_newton.element_fields`
        copies them): the pass and the state then hold them once (40 B per element, 80 MB
        at 128³ elements). ``fields`` parked out of memory
        (:meth:`~chunkdic.method.protocol.Passes.park`, not an ndarray): the pass holds none
        of those arrays, only ``fields`` (:attr:`parked`)."""
        if not isinstance(fields, np.ndarray):
            self.gain = self.offset = self.valid_per_element = self.residual = None
            self.parked = fields
            return
        self.gain, self.offset, self.valid_per_element = fields[0], fields[1], fields[2]
        if self.residual is not None:
            self.residual = fields[6:]

    def median_gain(self) -> float:
        """The median of the per-element gain (row 0 of the parked fields when the fit holds none)."""
        return float(np.median(self.gain if self.gain is not None else self.parked[0]))


def _nodes(B, coef) -> np.ndarray:
    """Nodal sum of ``Σ_q coef[q] B[:, :, :, q]`` over the elements (``coef``: per element or scalar)."""
    E = sum(np.asarray(c)[..., None, None] * B[..., q, :, :] for q, c in coef.items())
    return element_to_nodes(E)


def _cell_sum(a: np.ndarray, k: int) -> np.ndarray:
    """Sums of ``a`` (leading axes: elements) over cells of ``k³`` elements (the last ones partial)."""
    for ax in range(3):
        a = np.add.reduceat(a, np.arange(0, a.shape[ax], k), axis=ax)
    return a


def _cell_to_elements(c: np.ndarray, k: int, shape) -> np.ndarray:
    """Each element's copy of its cell's value (inverse of :func:`_cell_sum`'s grouping)."""
    for ax in range(3):
        c = np.take(np.repeat(c, k, axis=ax), np.arange(shape[ax]), axis=ax)
    return c


def _offsets_from_cell_centres(shape, k: int) -> np.ndarray:
    """(ez, ey, ex, 3): each element's centre minus its cell's centre, in elements."""
    out = np.zeros(tuple(shape) + (3,))
    for ax, n in enumerate(shape):
        i = np.arange(n)
        first = (i // k) * k
        count = np.minimum(k, n - first)
        o = (i - first) - (count - 1) / 2.0
        out[..., ax] = o.reshape([-1 if a == ax else 1 for a in range(3)])
    return out


def _cell_centred(sums: ElementSums, k: int):
    """``(B, G, offsets)`` with the coordinate quantities centred on each element's cell
    instead of on the element: ``q~ + o`` for an element whose centre is ``o`` elements from
    its cell's (``o`` returned, shape (ez, ey, ex, 3))."""
    B, G = sums.B, sums.gram
    o = _offsets_from_cell_centres(G.shape[:3], k)
    T = np.broadcast_to(np.eye(6), G.shape).copy()
    for j, q in enumerate(_COORDS):
        T[..., q, _ONE] = o[..., j]
    Gc = np.einsum("...ij,...jk,...lk->...il", T, G, T)
    Bc = B.copy()
    for j, q in enumerate(_COORDS):
        Bc[..., q, :, :] += o[..., j, None, None] * B[..., _ONE, :, :]
    return Bc, Gc, o


#: rows at the end of every model's element fields (:func:`residual_rows`)
RESIDUAL_ROWS = 2


def residual_rows(gram: np.ndarray) -> np.ndarray:
    """:func:`chunkdic.method.mismatch.local_residual` of each element from its element sums
    (``f - c = d + g'``): shape (2, ez, ey, ex), grey levels²."""
    return local_residual(gram[..., _ONE, _ONE], gram[..., _D, _ONE], gram[..., _G, _ONE], gram[..., _D, _D],
                          gram[..., _D, _G], gram[..., _G, _G])


def reduce_block(sums: ElementSums, model: str, cell: int = 1) -> Partials:
    """Reduce a block's element sums for ``model`` (task side).

    ``cell``: elements per side of the cells sharing one offset (``drift``; the block holds
    whole cells from its first element, :func:`aligned_block_elements`; 1: per element).
    Every model's element rows end with the :func:`residual_rows`.
    """
    part = _reduce_model(sums, model, cell)
    part.elements = np.concatenate([part.elements, residual_rows(sums.gram)])
    return part


def _reduce_model(sums: ElementSums, model: str, cell: int) -> Partials:
    """:func:`reduce_block` without the residual rows."""
    B, G = sums.B, sums.gram
    lags = sums.lags if sums.lags is not None else np.zeros((6, LAGS + 1))
    n_e = G[..., _ONE, _ONE]
    n = float(n_e.sum())
    if model == "none":
        return Partials(_nodes(B, {_D: 1.0})[None], np.array([n, G[..., _D, _D].sum()]), n_e[None],
                        sums.n_excluded, lags)
    if model == "global":
        nodal = np.stack([_nodes(B, {q: 1.0}) for q in (_D, _G, _ONE)])
        S = G[..., [_D, _G, _ONE], :][..., [_D, _G, _ONE]].sum(axis=(0, 1, 2))
        return Partials(nodal, np.concatenate([[n], S[np.triu_indices(3)]]), n_e[None], sums.n_excluded, lags)
    if model == "drift" and cell > 1:
        return _reduce_cells(sums, int(cell), lags)
    # per-element offsets: centre every quantity on its element mean (weights w)
    safe = np.where(n_e > 0, n_e, 1.0)
    mean = G[..., _ONE, :] / safe[..., None]  # (ez, ey, ex, 6)
    W = G - n_e[..., None, None] * mean[..., :, None] * mean[..., None, :]  # within-element covariances
    if model == "drift":
        nodal = np.stack([_nodes(B, {q: 1.0, _ONE: -mean[..., q]}) for q in (_D,) + _THETA])
        S = W[..., [_D, *_THETA], :][..., [_D, *_THETA]].sum(axis=(0, 1, 2))
        return Partials(nodal, np.concatenate([[n], S.ravel()]), np.concatenate([n_e[None], np.moveaxis(mean, -1, 0)]),
                        sums.n_excluded, lags)
    if model == "element":
        cgg, cdg, cdd = W[..., _G, _G], W[..., _D, _G], W[..., _D, _D]
        ok = (n_e > 0) & (cgg > FLAT * G[..., _G, _G])
        alpha = np.where(ok, cdg / np.where(ok, cgg, 1.0), 0.0)
        alpha = np.clip(alpha, GAIN_RANGE[0] - 1.0, GAIN_RANGE[1] - 1.0)
        mu = mean[..., _D] - alpha * mean[..., _G]
        b = _nodes(B, {_D: 1.0, _G: -alpha, _ONE: -mu})
        ssr = cdd - 2 * alpha * cdg + alpha * alpha * cgg
        return Partials(b[None], np.array([n, ssr.sum()]), np.stack([n_e, alpha, mu]), sums.n_excluded, lags)
    raise ValueError(f"unknown brightness model {model!r}")


def _reduce_cells(sums: ElementSums, k: int, lags: np.ndarray) -> Partials:
    """The ``drift`` model with an affine offset per cell of ``k³`` elements: ``a_c + b_c·(X - X_c)``,
    eliminated per cell (every quantity's least-squares projection on the cell's ``1, z, y, x``
    removed, the coordinates centred on the cell's centre); the gain is then the one global
    unknown. Four unknowns per cell instead of one per element: at ``k = 4`` a sixteenth as
    many, and a brightness that bends across the specimen is followed by the cells' slopes,
    as well as the element offsets with one global drift followed it (docs/engine.md).

    The partials keep the leading rows of the per-element ``drift`` model's, so that
    :func:`nodal_rhs` and :func:`element_fit` read both: the scalars' layout in full, whose
    drift rows and columns are zero (no global drift to fit), then six more scalars, the cells'
    slopes summed with their weights (their presence marks the cells' partials; the drift
    reported is not their mean but the plane through the element offsets,
    :func:`offset_plane_slope`: a steadier reading); the nodal rows of ``d`` and ``g'`` only
    (those of the drift, zero, left out: 72 B per node fewer in the client's sums), and the
    element rows ``Σ w`` and each element's offsets ``a + b·(X_e - X_c)`` of ``d`` and ``g'``
    (so that the fitted offset at the element's centre is ``d-row - α g-row``; the constant
    rows of ``1`` and the coordinates left out, 32 B per element)."""
    B, G, o = _cell_centred(sums, k)
    n_e = G[..., _ONE, _ONE]
    G_c = _cell_sum(G, k)
    lin, fitted = [_ONE, *_COORDS], [_D, _G]
    GLL = G_c[..., lin, :][..., lin]
    GLQ = G_c[..., lin, :][..., fitted]
    # per cell, the offset's coefficients for d and g'; pinv: a cell with too few voxels to fix
    # its slopes (a thin cell at a mask's edge) gets the minimum-norm ones
    coef = np.linalg.pinv(GLL, rcond=1e-12, hermitian=True) @ GLQ  # (cz, cy, cx, 4, 2)
    W = G_c[..., fitted, :][..., fitted] - np.swapaxes(GLQ, -1, -2) @ coef  # within-cell, 2 x 2
    S = np.zeros((5, 5))
    S[:2, :2] = W.sum(axis=(0, 1, 2))
    n_c = G_c[..., _ONE, _ONE]
    slopes = np.einsum("abc,abcjq->qj", n_c, coef[..., 1:, :])  # Σ n_c b_c for d, g' (per element length)
    coef_e = _cell_to_elements(coef, k, n_e.shape)
    nodal = np.zeros((len(fitted),) + tuple(n + 1 for n in n_e.shape) + (3,))
    for j, q in enumerate(fitted):
        nodal[j] = _nodes(B, {q: 1.0, **{c: -coef_e[..., i, j] for i, c in enumerate(lin)}})
    rows = np.zeros((len(fitted),) + n_e.shape)
    for j, q in enumerate(fitted):
        rows[q] = coef_e[..., 0, j] + np.einsum("...i,...i->...", coef_e[..., 1:, j], o)
    return Partials(nodal, np.concatenate([[float(n_e.sum())], S.ravel(), slopes.ravel()]),
                    np.concatenate([n_e[None], rows]), sums.n_excluded, lags)


def offset_plane_slope(offset: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Slope (per element length, z, y, x) of the weighted least-squares plane through the
    offsets at the element centres: the drift the ``drift`` model reports with affine offsets
    per cell.

    Each cell has its own slope, fitted on its ~32³ voxels; their weighted mean was a noisy
    reading of a uniform drift (the 96³ grey-level pairs of ``tests/engine/test_real_ct.py``:
    −8.94 / 11.88 grey levels per voxel for a truth of −9.41 / 11.50), while the plane through
    every element's offset across the ROI reads it over the whole specimen's length (−9.32 /
    11.41, as the single global drift of one offset per element, −9.27 / 11.52). With a
    drift that bends, it is the best straight drift.

    Parameters
    ----------
    offset : ndarray, shape (ez, ey, ex), grey levels
        Offset at each element's centre.
    weight : ndarray, shape (ez, ey, ex)
        Valid voxels per element (elements without any are left out).

    >>> z = np.arange(4.0)[:, None, None] * np.ones((4, 3, 2))
    >>> np.round(offset_plane_slope(5.0 - 2.0 * z, np.ones((4, 3, 2))), 12) + 0.0
    array([-2.,  0.,  0.])
    """
    offset = np.asarray(offset, np.float64)
    finite = np.isfinite(offset)
    w = np.where(finite & (np.asarray(weight) > 0), np.asarray(weight, np.float64), 0.0)
    y = np.where(finite, offset, 0.0)
    axes = [np.arange(n, dtype=np.float64) for n in offset.shape]
    one = [np.ones(n) for n in offset.shape]
    # normal equations of the plane a + s·i over the element indices i, from separable sums
    # (einsum with one vector per axis: no (elements, 4) design matrix on the client)
    basis = [tuple(axes[a] if a == k else one[a] for a in range(3)) for k in range(3)] + [tuple(one)]
    G = np.array([[np.einsum("zyx,z,y,x->", w, *(p * q for p, q in zip(bp, bq))) for bq in basis] for bp in basis])
    r = np.array([np.einsum("zyx,zyx,z,y,x->", w, y, *bp) for bp in basis])
    spread = np.array([np.count_nonzero(w.sum(axis=tuple(b for b in range(3) if b != a))) > 1 for a in range(3)])
    if G[3, 3] <= 0:
        return np.zeros(3)
    keep = np.flatnonzero(np.append(spread, True))  # one element (or one with data) along an axis: no slope
    coef = np.zeros(4)
    coef[keep] = np.linalg.lstsq(G[np.ix_(keep, keep)], r[keep], rcond=None)[0]
    return coef[:3]


def combine(model: str, nodal: np.ndarray, scalars: np.ndarray, elements: np.ndarray, center: float,
            element_size: float = 1.0) -> Fit:
    """Finish a pass on the client from the summed partials of every block.

    ``center`` is the centring constant ``c`` the tasks used (grey levels), ``element_size``
    the element edge (voxels; the drift's unit in the sums is one element). The two halves,
    :func:`nodal_rhs` and :func:`element_fit`, let a caller drop ``nodal`` in between
    (:meth:`chunkdic.passes.level.LevelPasses.assemble_b`).
    """
    return element_fit(model, nodal_rhs(model, nodal, scalars), scalars, elements, center, element_size)


def _global_coefficients(model: str, scalars: np.ndarray):
    """The models' global unknowns from the summed scalars: ``(α, μ)`` of ``global``, ``θ`` of
    ``drift`` (gain, then the drift per axis), None for the others."""
    n = scalars[0]
    if model == "global":
        sdd, sdg, sd, sgg, sg, _ = scalars[1:]
        A = np.array([[sgg, sg], [sg, n]])
        return np.linalg.solve(A, [sdg, sd]) if np.linalg.det(A) > FLAT * sgg * n else (0.0, sd / max(n, 1))
    if model == "drift":
        S = scalars[1:26].reshape(5, 5)  # then, with affine offsets per cell, their slopes (marking them)
        A, rhs = S[1:, 1:], S[1:, 0]
        return np.linalg.lstsq(A, rhs, rcond=None)[0] if np.trace(A) > 0 else np.zeros(4)
    return None


def nodal_rhs(model: str, nodal: np.ndarray, scalars: np.ndarray) -> np.ndarray:
    """``b`` (nz, ny, nx, 3) with the optimal global brightness, from the summed nodal rows."""
    if model in ("none", "element"):
        return nodal[0]
    if model == "global":
        alpha, mu = _global_coefficients(model, scalars)
        return nodal[0] - alpha * nodal[1] - mu * nodal[2]
    if model == "drift":  # the cells' partials (_reduce_cells) hold no drift rows: their θ is zero there
        b = np.tensordot(_global_coefficients(model, scalars)[:len(nodal) - 1], nodal[1:], axes=1)
        np.subtract(nodal[0], b, out=b)  # b = nodal[0] - Σ θ_k nodal[k], in the product's array
        return b
    raise ValueError(f"unknown brightness model {model!r}")


def misfit(model: str, scalars: np.ndarray) -> tuple[float, float]:
    """``(Σ w r², Σ w)`` of a pass with the model's optimal brightness, from its summed
    scalars alone (the ``ssr`` and ``weight`` of :func:`element_fit`; what a gap needs)."""
    n = float(scalars[0])
    if model in ("none", "element"):
        return float(scalars[1]), n
    if model == "global":
        sdd, sdg, sd, sgg, sg, _ = scalars[1:]
        alpha, mu = _global_coefficients(model, scalars)
        ssr = sdd - 2 * alpha * sdg - 2 * mu * sd + alpha**2 * sgg + 2 * alpha * mu * sg + mu**2 * n
        return float(max(ssr, 0.0)), n
    if model == "drift":
        S = scalars[1:26].reshape(5, 5)
        A, rhs = S[1:, 1:], S[1:, 0]
        theta = _global_coefficients(model, scalars)
        return float(max(S[0, 0] - 2 * theta @ rhs + theta @ A @ theta, 0.0)), n
    raise ValueError(f"unknown brightness model {model!r}")


def element_fit(model: str, b: np.ndarray, scalars: np.ndarray, elements: np.ndarray, center: float,
                element_size: float = 1.0) -> Fit:
    """The :class:`Fit` of a pass from its ``b`` (:func:`nodal_rhs`), scalars and element rows."""
    # a copy: a view would keep every row of ``elements`` (7 float64 per element with the
    # drift model) alive in the pass the level holds (docs/distributed.md)
    n_e = elements[0].copy()
    residual = elements[-RESIDUAL_ROWS:].copy()
    elements = elements[:-RESIDUAL_ROWS]
    n = scalars[0]
    ones = np.ones_like(n_e) if model in ("none", "global") else None  # not held by the other models
    zero3 = np.zeros(3)
    if model == "none":
        return Fit(b, float(scalars[1]), float(n), ones, 0 * ones, zero3, n_e, residual)
    if model == "global":
        alpha, mu = _global_coefficients(model, scalars)
        ssr, _ = misfit(model, scalars)
        return Fit(b, ssr, float(n), (1 + alpha) * ones, (mu - alpha * center) * ones, zero3, n_e, residual)
    if model == "drift":
        theta = _global_coefficients(model, scalars)
        ssr, _ = misfit(model, scalars)
        alpha, beta = theta[0], theta[1:]
        mean = elements[1:]  # element means of d, g', 1, z~, y~, x~ (the cells' partials: d, g' only)
        mu = mean[_D] - alpha * mean[_G]
        if len(scalars) > 26:  # affine offsets per cell (_reduce_cells): the plane through the offsets
            beta = offset_plane_slope(mu, n_e)
        else:
            mu -= np.tensordot(beta, mean[_Z:_X + 1], axes=1)
        # offset at the element centre (q~ = 0): μ_e - α c
        return Fit(b, ssr, float(n), np.full_like(n_e, 1 + alpha), mu - alpha * center,
                   beta / float(element_size), n_e, residual)
    if model == "element":
        alpha, mu = elements[1], elements[2]
        return Fit(b, float(scalars[1]), float(n), 1 + alpha, mu - alpha * center, zero3, n_e, residual)
    raise ValueError(f"unknown brightness model {model!r}")
