"""Grey-level (brightness and contrast) correction between the two scans.

Real X-ray sources drift: the deformed scan is often brighter or of another contrast than
the reference, by a global factor and by a slow drift across the specimen. The residual is
therefore taken as ``r = f(X) - (λ g(X + u(X)) + μ(X))`` with a brightness model:

``none``
    ``λ = 1, μ = 0``: the paper's plain residual.
``global``
    one gain and one offset for the whole ROI.
``drift`` (default)
    one gain, a linear drift of the offset across the ROI and one offset per element on
    top: follows any smooth brightness change (a drift is linear inside each element and
    nearly constant from one element to the next), and does not read a brightness
    gradient as motion.
``element``
    a gain and an offset per element (``λ`` kept within :data:`GAIN_RANGE`; an element too
    flat to fix a gain gets an offset only).

The brightness unknowns are eliminated exactly at every pass (variable projection): for
the current field they minimise ``Σ w r²``, and ``b = Σ w N ∇f r`` is evaluated with them,
from one pass over the voxels (:class:`chunkdic.kernels.blocks.ElementSums`): each block task
reduces its element sums with :func:`reduce_block` (the per-element unknowns in full) and
the client finishes the global ones with :func:`combine`. The Gauss–Newton matrix of the
per-element models is ``M`` minus the Schur complement of their per-element unknowns,
built in the ``M`` pass (:func:`chunkdic.kernels.m.m_block`; the few global unknowns are left
out of it, as their coupling with the nodal field is weak). With ``α = λ - 1`` and
``g' = g(X+u) - c``, ``r = d - α g' - μ'`` (``d = f - g(X+u)``); the returned gain and offset
are in the usual form ``f ≈ gain · g(X + u) + offset`` (offset at the element centre, plus
``drift · (X - X_e)`` for the ``drift`` model).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..kernels.b import element_to_nodes
from ..kernels.blocks import LAGS, ElementSums

MODELS = ("none", "global", "drift", "element")
#: bounds of a per-element gain (``element`` model)
GAIN_RANGE = (0.5, 2.0)
#: an element whose ``Σ (g' - mean)²`` is below this fraction of ``Σ g'²`` fixes no gain
FLAT = 1e-12
# positions of the quantities in ElementSums (blocks.QUANTITIES)
_D, _G, _ONE, _Z, _Y, _X = range(6)
_THETA = (_G, _Z, _Y, _X)  # global unknowns of the drift model: gain, then the drift per axis


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
        Per-element fields (first: ``Σ w`` per element).
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
    """

    b: np.ndarray
    ssr: float
    weight: float
    gain: np.ndarray
    offset: np.ndarray
    drift: np.ndarray
    valid_per_element: np.ndarray

    def share(self, fields: np.ndarray) -> None:
        """Point gain, offset and valid counts at rows 0-2 of ``fields`` (the same values, as
        :func:`chunkdic.engine.gauss_newton.element_fields` copies them): the pass and the
        state then hold them once (48 MB at 128³ elements)."""
        self.gain, self.offset, self.valid_per_element = fields[0], fields[1], fields[2]


def _nodes(B, coef) -> np.ndarray:
    """Nodal sum of ``Σ_q coef[q] B[:, :, :, q]`` over the elements (``coef``: per element or scalar)."""
    E = sum(np.asarray(c)[..., None, None] * B[..., q, :, :] for q, c in coef.items())
    return element_to_nodes(E)


def reduce_block(sums: ElementSums, model: str) -> Partials:
    """Reduce a block's element sums for ``model`` (task side)."""
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


def combine(model: str, nodal: np.ndarray, scalars: np.ndarray, elements: np.ndarray, center: float,
            element_size: float = 1.0) -> Fit:
    """Finish a pass on the client from the summed partials of every block.

    ``center`` is the centring constant ``c`` the tasks used (grey levels), ``element_size``
    the element edge (voxels; the drift's unit in the sums is one element). The two halves,
    :func:`nodal_rhs` and :func:`element_fit`, let a caller drop ``nodal`` in between
    (:meth:`chunkdic.engine.level.Level.assemble_b`).
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
        S = scalars[1:].reshape(5, 5)
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
    if model == "drift":
        b = np.tensordot(_global_coefficients(model, scalars), nodal[1:], axes=1)
        np.subtract(nodal[0], b, out=b)  # b = nodal[0] - Σ θ_k nodal[k], in the product's array
        return b
    raise ValueError(f"unknown brightness model {model!r}")


def element_fit(model: str, b: np.ndarray, scalars: np.ndarray, elements: np.ndarray, center: float,
                element_size: float = 1.0) -> Fit:
    """The :class:`Fit` of a pass from its ``b`` (:func:`nodal_rhs`), scalars and element rows."""
    # a copy: a view would keep every row of ``elements`` (7 float64 per element with the
    # drift model) alive in the pass the level holds (docs/distributed.md)
    n_e = elements[0].copy()
    n = scalars[0]
    ones = np.ones_like(n_e) if model in ("none", "global") else None  # not held by the other models
    zero3 = np.zeros(3)
    if model == "none":
        return Fit(b, float(scalars[1]), float(n), ones, 0 * ones, zero3, n_e)
    if model == "global":
        sdd, sdg, sd, sgg, sg, _ = scalars[1:]
        alpha, mu = _global_coefficients(model, scalars)
        ssr = sdd - 2 * alpha * sdg - 2 * mu * sd + alpha**2 * sgg + 2 * alpha * mu * sg + mu**2 * n
        return Fit(b, float(max(ssr, 0.0)), float(n), (1 + alpha) * ones, (mu - alpha * center) * ones, zero3, n_e)
    if model == "drift":
        S = scalars[1:].reshape(5, 5)
        A, rhs = S[1:, 1:], S[1:, 0]
        theta = _global_coefficients(model, scalars)
        ssr = S[0, 0] - 2 * theta @ rhs + theta @ A @ theta
        alpha, beta = theta[0], theta[1:]
        mean = elements[1:]  # element means of d, g', 1, z~, y~, x~
        mu = mean[_D] - alpha * mean[_G] - np.tensordot(beta, mean[_Z:_X + 1], axes=1)  # a view: no copy
        # offset at the element centre (q~ = 0): μ_e - α c
        return Fit(b, float(max(ssr, 0.0)), float(n), np.full_like(n_e, 1 + alpha), mu - alpha * center,
                   beta / float(element_size), n_e)
    if model == "element":
        alpha, mu = elements[1], elements[2]
        return Fit(b, float(scalars[1]), float(n), 1 + alpha, mu - alpha * center, zero3, n_e)
    raise ValueError(f"unknown brightness model {model!r}")
