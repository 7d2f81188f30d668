"""Robust reweighting of the Tikhonov penalty: the terms a field's kinks free.

One round of iteratively reweighted least squares with a hard threshold: the terms of the
Hessian penalty (:data:`~chunkdic.solve.penalty.TERM_KINDS`) whose value lies beyond
:data:`ROBUST_THRESHOLD` robust standard deviations of their kind and component get weight
0 (:attr:`chunkdic.solve.regularizer.Regularizer.freed`). docs/engine.md, "The band and the
slip at ℓ = 8".
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import find_objects, label

from .penalty import TERM_KINDS

#: the robust reweighting frees a term beyond this many robust standard deviations of its kind and
#: component (:func:`robust_freed`; docs/engine.md, "The band and the slip at ℓ = 8")
ROBUST_THRESHOLD = 6.0
#: terms beyond the threshold are freed only as a connected set (same kind and component, 26
#: neighbours) that spans at least this fraction of the mesh's nodes along :data:`SPANNING_AXES`
#: axes: a kink (a band's edge, a slip, a crack) is a surface across the field, outliers of
#: the noise (weakly textured nodes) compact clusters or streaks along one of the texture's
#: features (:func:`robust_freed`; the engine asks for it where the texture's features
#: outgrow the elements, :func:`chunkdic.method.length.choose_regularization`)
SPANNING_FRACTION = 0.5
SPANNING_AXES = 2
#: where only sheets are freed, a component keeps them only if its sheets of second differences
#: along one axis bend the field one way, or its slope along that axis has one sign, to this
#: degree (:func:`_one_sided`): the feature's component read 0.87–1.00 on the slips, cracks and
#: bands measured, the imaging's mismatch at most 0.67 (docs/engine.md, "The regularisation
#: length on a coarse texture")
ONE_SIDED = 0.75
#: the robust standard deviation of a normal sample from its median absolute value
MAD_TO_SIGMA = 1.4826


def robust_freed(x: np.ndarray, threshold: float = ROBUST_THRESHOLD, spanning: float = SPANNING_FRACTION) -> np.ndarray:
    """The Tikhonov terms of the field ``x`` to free: one robust reweighting (IRLS with a
    hard threshold) of the Hessian penalty.

    Each term (a second difference along a grid line, a mixed difference of a 2×2 square,
    per component) whose value exceeds ``threshold`` robust standard deviations of its kind
    and component (:data:`MAD_TO_SIGMA` × the median of their absolute values over the
    mesh) gets weight 0, with ``spanning`` only in a connected set of such terms (same kind
    and component) whose extent reaches ``spanning`` of the mesh along
    :data:`SPANNING_AXES` axes, a sheet (0: every such term): the kinks of a band, a slip or
    a crack, where the field truly bends along a surface, while the noise and smooth fields
    (a wave's differences are the wave itself, their robust σ its amplitude) keep every
    term. Weakly textured nodes (elements small against the texture's features) have
    heavy-tailed noise correlated over a few nodes: without the span they freed clusters of
    up to ~13 terms on waves (extent ≤ 5 nodes of 25), and with a span along one axis a
    streak of 14 terms on a 24-voxel wave, and the length chosen for the freed penalty went
    long (docs/engine.md, "The regularisation length on a coarse texture", and "The band and
    the slip at ℓ = 8"). With ``spanning``, a component keeps its sheets only if its sheets
    of second differences along one axis are one-sided (:func:`_one_sided`): there the
    imaging's mismatch at a kink bends the components the feature does not move as sharply,
    both ways along the sheet, and freed they follow it (a slip at ℓ = 8 on 24-voxel grains:
    0.150 voxel with ``u_z``'s sheets freed, 0.112 with ``u_x``'s only).

    Parameters
    ----------
    x : ndarray, shape (nz, ny, nx, 3), float
        The nodal field (voxels of the level), e.g. the regularised solution at the chosen length.
    threshold : float
        In robust standard deviations.
    spanning : float
        The fraction of the mesh's nodes a freed set must reach along :data:`SPANNING_AXES`
        axes; 0 frees every term beyond the threshold.

    Returns
    -------
    freed : ndarray, shape (nz, ny, nx, 6), uint8
        :attr:`Regularizer.freed`. Built one kind and component at a time: the client holds
        at most two float64 difference arrays of the mesh's size at once (16 B per node).
    """
    x = np.asarray(x)
    shape = x.shape[:3]
    freed = np.zeros(shape + (len(TERM_KINDS),), np.uint8)
    for c in range(3):
        u = x[..., c]
        one_sided = spanning <= 0  # every component keeps its terms
        for t in range(len(TERM_KINDS)):
            d, anchor = _term_values(u, t)
            if d.size == 0:
                continue
            a = np.abs(d)
            sigma = MAD_TO_SIGMA * float(np.median(a))
            if not sigma > 0:
                continue
            beyond = a > threshold * sigma
            del a
            sheets = _spanning(beyond, shape, spanning)
            if not one_sided and t < 3 and sheets.any():
                one_sided = _one_sided(u, t, d, sheets)
            del d
            freed[anchor + (t,)] |= (sheets.astype(np.uint8) << c)
        if not one_sided:
            freed &= np.uint8(0xFF ^ (1 << c))
    return freed


def _one_sided(u: np.ndarray, t: int, d: np.ndarray, terms: np.ndarray) -> bool:
    """Whether the second differences ``d`` of ``u`` (nz, ny, nx) along axis ``t`` marked in
    ``terms`` (bool, anchored as :func:`_term_values`) bend the field one way along their sheet,
    or the field's slope along ``t`` there (a central difference, less its median over the
    mesh: a uniform strain is no kink's) has one sign: :func:`_one_signed` of either at least
    :data:`ONE_SIDED`. A band's edge or a hinge bends one way; a slip or a crack (both
    flanks, bent opposite ways) carries one jump."""
    if _one_signed(d[terms]) >= ONE_SIDED:
        return True
    lo, _, hi = _three_nodes(u.shape, t)
    g = u[hi] - u[lo]
    return _one_signed(g[terms] - np.median(g)) >= ONE_SIDED


def _one_signed(v: np.ndarray) -> float:
    """``|Σ v| / Σ |v|`` in [0, 1]: 1 when every value has one sign."""
    total = float(np.abs(v).sum())
    return abs(float(v.sum())) / total if total > 0 else 0.0


def _spanning(beyond: np.ndarray, shape, fraction: float) -> np.ndarray:
    """The terms of ``beyond`` (bool, one kind and component) in connected sets (26 neighbours)
    whose extent reaches ``fraction`` of the mesh's ``shape`` (nodes) along :data:`SPANNING_AXES` axes."""
    if fraction <= 0 or not beyond.any():
        return beyond
    labels, _ = label(beyond, np.ones((3, 3, 3), bool))
    keep = np.zeros(int(labels.max()) + 1, bool)
    for k, box in enumerate(find_objects(labels), start=1):
        keep[k] = sum(b.stop - b.start >= fraction * n for b, n in zip(box, shape)) >= SPANNING_AXES
    return keep[labels]


def _three_nodes(shape, t: int) -> tuple[tuple, tuple, tuple]:
    """Slices of the nodes ``shape`` (nz, ny, nx) before, at and after each inner node along
    axis ``t``: a second or a central difference there."""
    n = shape[t]
    lo, mid, hi = ([slice(None)] * 3 for _ in range(3))
    lo[t], mid[t], hi[t] = slice(0, n - 2), slice(1, n - 1), slice(2, n)
    return tuple(lo), tuple(mid), tuple(hi)


def _term_values(u: np.ndarray, t: int) -> tuple[np.ndarray, tuple]:
    """The terms of kind ``TERM_KINDS[t]`` of a scalar nodal field ``u`` (nz, ny, nx) and where
    they are anchored (a tuple of slices into the nodes): the unweighted difference."""
    if t < 3:
        lo, mid, hi = _three_nodes(u.shape, t)
        return u[lo] - 2.0 * u[mid] + u[hi], mid
    p, q = {3: (0, 1), 4: (0, 2), 5: (1, 2)}[t]

    def corner(dp, dq):
        s = [slice(None)] * 3
        s[p] = slice(dp, u.shape[p] - 1 + dp)
        s[q] = slice(dq, u.shape[q] - 1 + dq)
        return tuple(s)

    return u[corner(0, 0)] - u[corner(1, 0)] - u[corner(0, 1)] + u[corner(1, 1)], corner(0, 0)
