"""Grey-level (brightness and contrast) correction between the two scans.

Real X-ray sources drift: the deformed scan is often brighter or of another contrast than
the reference, by a global factor and by a slow drift across the specimen. The residual is
therefore taken as ``r = f(X) - (λ g(X + u(X)) + μ)`` with a brightness model ``(λ, μ)``:

``none``
    ``λ = 1, μ = 0``: the paper's plain residual.
``global``
    one gain and one offset for the whole ROI.
``offset``
    one gain for the ROI and one offset per element: follows a smooth brightness drift
    (any drift is close to constant over one element).
``element``
    a gain and an offset per element (``λ`` kept within [0.5, 2]; an element too flat to
    fix a gain gets an offset only).

The brightness unknowns are eliminated exactly at every pass (variable projection):
for the current field, ``(λ, μ)`` minimise ``Σ r²``, and ``b = Σ N ∇f r`` is evaluated with
them, all from one pass over the voxels (:class:`chunkdic.kernels.ElementSums`): each
block task reduces its element sums with :func:`reduce_block` (the per-element models in
full) and the client finishes the global parts with :func:`combine`. The Gauss–Newton
matrix of the per-element models is ``M`` minus the Schur complement of their unknowns,
built in the ``M`` pass (:func:`chunkdic.kernels.m_block`). With ``α = λ - 1`` and
``g' = g(X+u) - c`` the residual reads ``r = d - α g' - μ'`` (``d = f - g(X+u)``); the
returned gain and offset are in the usual form ``f ≈ gain · g(X + u) + offset``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .blocks import ElementSums
from .kernels import element_to_nodes

MODELS = ("none", "global", "offset", "element")
#: bounds of a per-element gain (``element`` model)
GAIN_RANGE = (0.5, 2.0)
#: an element whose ``Σ (g' - mean)²`` is below this fraction of ``Σ g'²`` fixes no gain
FLAT = 1e-12


@dataclass
class Partials:
    """One block's share of a ``b`` pass, reduced for a brightness model; partials add up.

    Attributes
    ----------
    nodal : ndarray, shape (K, nz, ny, nx, 3), float64
        Nodal arrays over the block's nodes (``K`` depends on the model).
    scalars : ndarray, shape (m,), float64
        Sums over the block's valid voxels (first: their number).
    elements : ndarray, shape (p, ez, ey, ex), float64
        Per-element fields (first: valid voxels per element).
    n_excluded : int
        Voxels whose ``X + u(X)`` leaves ``g``.
    """

    nodal: np.ndarray
    scalars: np.ndarray
    elements: np.ndarray
    n_excluded: int


@dataclass
class Fit:
    """A pass's outcome for the whole ROI.

    Attributes
    ----------
    b : ndarray, shape (nz, ny, nx, 3), float64
        Right-hand side with the optimal brightness, grey levels² / voxel.
    ssr : float
        ``Σ w r²`` over the valid voxels (weights ``w``, :class:`chunkdic.blocks.ElementSums`), grey levels².
    weight : float
        ``Σ w``: the number of valid voxels, the ones at the edge of the usable part of ``g`` in part.
    gain, offset : ndarray, shape (ez, ey, ex), float64
        Brightness per element: ``f ≈ gain · g(X + u) + offset`` (grey levels).
    valid_per_element : ndarray, shape (ez, ey, ex), float64
        ``Σ w`` per element.
    """

    b: np.ndarray
    ssr: float
    weight: float
    gain: np.ndarray
    offset: np.ndarray
    valid_per_element: np.ndarray


def _means(mom: np.ndarray):
    n = mom[..., 0]
    safe = np.where(n > 0, n, 1.0)
    return n, mom[..., 1] / safe, mom[..., 2] / safe


def reduce_block(sums: ElementSums, model: str) -> Partials:
    """Reduce a block's element sums for ``model`` (task side)."""
    B, mom = sums.B, sums.moments
    n_e, md, mg = _means(mom)
    Bd, Bg, B1 = B[..., 0, :, :], B[..., 1, :, :], B[..., 2, :, :]
    n = float(n_e.sum())
    if model == "none":
        return Partials(element_to_nodes(Bd)[None], np.array([n, mom[..., 3].sum()]), n_e[None], sums.n_excluded)
    if model == "global":
        nodal = np.stack([element_to_nodes(Bd), element_to_nodes(Bg), element_to_nodes(B1)])
        return Partials(nodal, np.concatenate([[n], mom[..., 1:].sum(axis=(0, 1, 2))]), n_e[None], sums.n_excluded)
    # within-element (centred) sums
    cdd = mom[..., 3] - n_e * md * md
    cdg = mom[..., 4] - n_e * md * mg
    cgg = mom[..., 5] - n_e * mg * mg
    if model == "offset":
        P = element_to_nodes(Bd - md[..., None, None] * B1)
        Q = element_to_nodes(Bg - mg[..., None, None] * B1)
        scalars = np.array([n, cdd.sum(), cdg.sum(), cgg.sum()])
        return Partials(np.stack([P, Q]), scalars, np.stack([n_e, md, mg]), sums.n_excluded)
    if model == "element":
        ok = (n_e > 0) & (cgg > FLAT * mom[..., 5])
        alpha = np.where(ok, cdg / np.where(ok, cgg, 1.0), 0.0)
        alpha = np.clip(alpha, GAIN_RANGE[0] - 1.0, GAIN_RANGE[1] - 1.0)
        mu = md - alpha * mg
        b = element_to_nodes(Bd - alpha[..., None, None] * Bg - mu[..., None, None] * B1)
        ssr = cdd - 2 * alpha * cdg + alpha * alpha * cgg
        return Partials(b[None], np.array([n, ssr.sum()]), np.stack([n_e, alpha, mu]), sums.n_excluded)
    raise ValueError(f"unknown brightness model {model!r}")


def combine(model: str, nodal: np.ndarray, scalars: np.ndarray, elements: np.ndarray, center: float) -> Fit:
    """Finish a pass on the client from the summed partials of every block.

    ``center`` is the centring constant ``c`` the tasks used (grey levels).
    """
    n_e = elements[0]
    n = scalars[0]
    ones = np.ones_like(n_e)
    if model == "none":
        return Fit(nodal[0], float(scalars[1]), float(n), ones, 0 * ones, n_e)
    if model == "global":
        sd, sg, sdd, sdg, sgg = scalars[1:]
        A = np.array([[sgg, sg], [sg, n]])
        alpha, mu = np.linalg.solve(A, [sdg, sd]) if np.linalg.det(A) > FLAT * sgg * n else (0.0, sd / max(n, 1))
        b = nodal[0] - alpha * nodal[1] - mu * nodal[2]
        ssr = sdd - 2 * alpha * sdg - 2 * mu * sd + alpha**2 * sgg + 2 * alpha * mu * sg + mu**2 * n
        return Fit(b, float(max(ssr, 0.0)), float(n), (1 + alpha) * ones, (mu - alpha * center) * ones, n_e)
    if model == "offset":
        cdd, cdg, cgg = scalars[1:]
        alpha = cdg / cgg if cgg > 0 else 0.0
        b = nodal[0] - alpha * nodal[1]
        ssr = cdd - 2 * alpha * cdg + alpha**2 * cgg
        mu = elements[1] - alpha * elements[2]
        return Fit(b, float(max(ssr, 0.0)), float(n), (1 + alpha) * ones, mu - alpha * center, n_e)
    if model == "element":
        alpha, mu = elements[1], elements[2]
        return Fit(nodal[0], float(scalars[1]), float(n), 1 + alpha, mu - alpha * center, n_e)
    raise ValueError(f"unknown brightness model {model!r}")
