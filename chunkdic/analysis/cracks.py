"""Cracks: displacement discontinuities found in a result, their surfaces, openings and slidings.

A jump ``δ`` across a surface of normal ``n`` cannot be followed by the continuous C8 field: the
correlation spreads it over the element the surface cuts (and, with a regularisation, over its
length), whose gradient becomes nearly rank one, ``H ≈ δ nᵀ / w``. :func:`find_cracks`:

1. **Jump per element.** ``ΔH = H − H̄``, ``H̄`` the element-wise median of ``H`` over the
   :data:`BACKGROUND` ³ elements around (the smooth strain, which a surface a few elements
   across does not move); its largest singular value times ``ℓ`` is the element's jump
   ``J`` (voxels), its right singular vector the normal ``n``, its left the jump's direction.
2. **Significance.** ``z = J / σ_J``, ``σ_J`` the standard uncertainty of ``ℓ aᵀ ΔH n`` from
   the solve's covariance (:mod:`chunkdic.analysis.covariance`; without a per-node uncertainty,
   the robust spread of ``J`` over the mesh, at least :data:`FLOOR`); kept when ``z ≥`` :data:`MIN_Z`.
3. **Localisation.** ``J ≥`` :data:`LOCALISED` times the median jump of the :data:`BACKGROUND` ³
   elements around: a surface, not a smoothly varying strain.
4. **Thin surface.** ``J`` at least that of the two neighbours along ``n`` (non-maximum
   suppression, as edge detectors do): one element across.
5. **Cracks.** 26-connected groups of at least :data:`MIN_ELEMENTS` such elements.

The **residual** (:mod:`chunkdic.analysis.residuals`, when the scans are at hand) is reported
per crack as the ratio of its elements' RMS residual to the median element's: a jump leaves a
misfit that a smooth strain localised over an element does not (ratios above 1.5 on synthetic
cracks of 0.3 voxel and more); below about 0.2 voxel the ratio stays near 1 and the field alone
speaks.

**Opening and sliding** of each crack element: ``δ = u(c + L n) − u(c − L n) − 2 L H̄ n``
(``c`` the element's centre, ``L = ℓ (1 + Σ|n_i|) / 2``, just beyond the elements the surface
cuts), split into the opening ``δ · n`` (``n`` oriented so that it is ≥ 0 where the surface
opens) and the sliding ``|δ − (δ · n) n|``; their standard uncertainties from the covariance.
Each crack's mean opening and sliding come with the uncertainty of the mean. A regularisation
longer than ``ℓ`` spreads the jump beyond ``L``: the opening is then a lower bound
(docs/cracks.md has the measured table).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..mesh import LOCAL_NODES
from ..results.strain import displacement_gradient
from .covariance import NodalCovariance, element_gradient_weights, point_stencil

__all__ = ["Crack", "CrackMap", "find_cracks", "MIN_Z", "LOCALISED", "MIN_ELEMENTS", "BACKGROUND"]

#: significance of an element's jump against its noise
MIN_Z = 5.0
#: an element's jump against the median jump around it
LOCALISED = 2.0
#: elements per side of the neighbourhood of the background strain and the median jump
BACKGROUND = 5
#: the fewest elements of a crack
MIN_ELEMENTS = 3
#: the noise of a jump (voxels) at least, when the result holds no per-node uncertainty
FLOOR = 1e-3
#: nodes apart (per axis) of the two points of a jump: ``2 L ≤ (1 + √3) ℓ`` plus their elements
JUMP_RADIUS = 4


@dataclass
class Crack:
    """One crack: its elements and its mean opening and sliding (voxels of the result's level).

    ``normal`` is the mean unit normal ``(z, y, x)``; ``residual_ratio`` its elements' mean RMS
    residual over the median element's (NaN without the scans).
    """

    label: int
    elements: int
    centre: list
    normal: list
    opening: float
    sigma_opening: float
    sliding: float
    sigma_sliding: float
    jump: float
    residual_ratio: float = math.nan


@dataclass
class CrackMap:
    """Outcome of :func:`find_cracks`: per-element arrays over the mesh and the cracks.

    Attributes
    ----------
    labels : ndarray, shape (ez, ey, ex), int32
        Crack number of each element (0: none).
    jump, z, opening, sliding, sigma_opening, sigma_sliding, residual_ratio : ndarray, shape (ez, ey, ex)
        Per element (opening, sliding and their σ only on crack elements, NaN elsewhere).
    normal : ndarray, shape (3, ez, ey, ex)
        Unit normal per element ``(z, y, x)``.
    cracks : list of Crack
    """

    labels: np.ndarray
    jump: np.ndarray
    z: np.ndarray
    normal: np.ndarray
    opening: np.ndarray
    sliding: np.ndarray
    sigma_opening: np.ndarray
    sigma_sliding: np.ndarray
    residual_ratio: np.ndarray
    cracks: list = field(default_factory=list)
    element_size: float = 1.0
    level: int = 0

    def as_dict(self) -> dict:
        from dataclasses import asdict

        return {"element_size": self.element_size, "level": self.level,
                "cracks": [{k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                            for k, v in asdict(c).items()} for c in self.cracks]}

    def text(self, source: str = "") -> str:
        lines = [f"{source}: {len(self.cracks)} crack(s) (openings and slidings in voxels of level {self.level}, "
                 "± one standard uncertainty; residual: the elements' RMS over the median element's)"]
        for c in self.cracks:
            lines.append(f"  crack {c.label}: {c.elements} elements around ({', '.join(f'{v:.1f}' for v in c.centre)}), "
                         f"normal ({', '.join(f'{v:+.2f}' for v in c.normal)}); opening {c.opening:+.4f} ± "
                         f"{c.sigma_opening:.4f}, sliding {c.sliding:.4f} ± {c.sigma_sliding:.4f}; "
                         f"residual ratio {c.residual_ratio:.2f}")
        return "\n".join(lines)


def _median_filter(a: np.ndarray, size: int) -> np.ndarray:
    from scipy import ndimage

    return ndimage.median_filter(a, size=size, mode="nearest")


def _background(H: np.ndarray) -> np.ndarray:
    """The element-wise median of ``H`` (3, 3, ez, ey, ex) over ``BACKGROUND``³ elements (NaN left as 0)."""
    Hn = np.nan_to_num(H)
    return np.stack([np.stack([_median_filter(Hn[i, j], BACKGROUND) for j in range(3)]) for i in range(3)])


def _element_centres(result) -> np.ndarray:
    return np.stack(np.meshgrid(*result.mesh.element_axes(), indexing="ij"))


def _jump_sigma(cov: NodalCovariance | None, ell: float, e, a, n) -> float:
    """σ of ``ℓ aᵀ H_e n`` (the jump of element ``e`` along its singular directions)."""
    if cov is None:
        return math.nan
    w = element_gradient_weights(ell * np.outer(a, n), ell)
    return math.sqrt(max(cov.local_variance_at(np.asarray(e) + LOCAL_NODES, w), 0.0))


def _candidates(result, cov, ell: float):
    """Per element: jump, direction, normal, z; and the background gradient."""
    H = displacement_gradient(result.displacement, ell)
    Hbg = _background(H)
    D = np.moveaxis(np.nan_to_num(H - Hbg), (0, 1), (-2, -1))
    U, S, Vt = np.linalg.svd(D)
    jump = S[..., 0] * ell
    jump = np.where(np.isfinite(H).all(axis=(0, 1)), jump, 0.0)
    a, n = np.moveaxis(U[..., :, 0], -1, 0), np.moveaxis(Vt[..., 0, :], -1, 0)
    local = _median_filter(jump, BACKGROUND)
    z = np.zeros_like(jump)
    # without a per-node uncertainty: the robust spread of the jumps over the mesh (at least
    # FLOOR voxel, so that round-off on a noise-free field is no crack)
    spread = max(1.4826 * float(np.median(np.abs(jump - np.median(jump)))), FLOOR)
    for e in np.argwhere(jump >= LOCALISED * local):  # σ only where it can matter
        e = tuple(int(v) for v in e)
        sigma = spread if cov is None else _jump_sigma(cov, ell, e, a[(slice(None),) + e], n[(slice(None),) + e])
        z[e] = jump[e] / sigma if sigma > 0 else 0.0
    keep = (z >= MIN_Z) & (jump >= LOCALISED * local)
    return jump, z, keep, a, n, Hbg


def _thin(jump: np.ndarray, keep: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Non-maximum suppression along each element's normal (one element across)."""
    out = keep.copy()
    shape = np.array(jump.shape)
    for e in np.argwhere(keep):
        step = np.rint(n[:, e[0], e[1], e[2]] / np.abs(n[:, e[0], e[1], e[2]]).max()).astype(int)
        for s in (step, -step):
            f = e + s
            if np.all(f >= 0) and np.all(f < shape) and jump[tuple(f)] > jump[tuple(e)]:
                out[tuple(e)] = False
    return out


def find_cracks(result, *, residual: np.ndarray | None = None, covariance: NodalCovariance | None = None) -> CrackMap:
    """Find the displacement discontinuities of a result (module docstring).

    Parameters
    ----------
    result : Result
    residual : ndarray, shape (ez, ey, ex), optional
        RMS residual per element (:func:`chunkdic.analysis.residuals.element_residuals`).
    covariance : NodalCovariance, optional
        The field's covariance (default: built here; without a per-node uncertainty the noise of
        a jump is the robust spread of the jumps, and the openings' uncertainties are NaN).

    Returns
    -------
    CrackMap
    """
    from scipy import ndimage

    result.check_displacement()
    ell = float(result.info["element_size"])
    cov = covariance
    if cov is None:
        try:
            cov = NodalCovariance.of_result(result)
        except InputError:
            cov = None
    if min(result.mesh.shape) < 3:
        raise InputError(f"result {result.path}: crack detection needs at least 3 elements per axis")
    jump, z, keep, a, n, Hbg = _candidates(result, cov, ell)
    thin = _thin(jump, keep, n)
    labels, count = ndimage.label(thin, structure=np.ones((3, 3, 3), bool))
    sizes = ndimage.sum_labels(thin, labels, index=np.arange(1, count + 1)) if count else []
    small = [k + 1 for k, s in enumerate(sizes) if s < MIN_ELEMENTS]
    labels[np.isin(labels, small)] = 0
    labels = _renumber(labels)
    ratio = np.full(jump.shape, np.nan) if residual is None else residual / np.nanmedian(residual)
    cmap = CrackMap(labels.astype(np.int32), jump, z, n, *(np.full(jump.shape, np.nan) for _ in range(4)), ratio,
                    element_size=ell, level=result.level)
    _measure(result, cmap, Hbg, cov)
    return cmap


def _renumber(labels: np.ndarray) -> np.ndarray:
    out = np.zeros_like(labels)
    for k, v in enumerate([v for v in np.unique(labels) if v], 1):
        out[labels == v] = k
    return out


def _jump(result, c, n, L, Hbg_e) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``δ`` across one element, and the nodes (16, 3) and signs (16,) of its two points' weights."""
    mesh = result.mesh
    pa, pb = c - L * n, c + L * n
    ua, ub = (mesh.evaluate(result.displacement, p.reshape(3, 1))[:, 0] for p in (pa, pb))
    (na, wa), (nb, wb) = point_stencil(mesh, pa), point_stencil(mesh, pb)
    return ub - ua - Hbg_e @ (2 * L * n), np.concatenate([nb, na]), np.concatenate([wb, -wa])


def _measure(result, cmap: CrackMap, Hbg: np.ndarray, cov) -> None:
    """Opening and sliding per crack element and per crack, with their uncertainties."""
    ell = cmap.element_size
    centres = _element_centres(result)
    for label in range(1, int(cmap.labels.max()) + 1):
        at = [tuple(int(v) for v in e) for e in np.argwhere(cmap.labels == label)]
        normals = np.stack([cmap.normal[(slice(None),) + e] for e in at])
        mean_n = np.sum([v if v @ normals[0] >= 0 else -v for v in normals], axis=0)  # normals oriented alike
        mean_n /= np.linalg.norm(mean_n)
        w_open = np.zeros((3,) + result.mesh.nodes_shape)
        w_slide = np.zeros_like(w_open)
        for e in at:
            nv = cmap.normal[(slice(None),) + e]
            nv = nv if nv @ mean_n >= 0 else -nv
            cmap.normal[(slice(None),) + e] = nv
            L = ell * (1 + np.abs(nv).sum()) / 2
            # δ · n does not depend on the normal's sense (both flip): > 0 opens, < 0 interpenetrates
            delta, nodes, signs = _jump(result, centres[(slice(None),) + e], nv, L, Hbg[(slice(None), slice(None)) + e])
            t = delta - (delta @ nv) * nv
            t_hat = t / np.linalg.norm(t) if np.linalg.norm(t) > 0 else np.zeros(3)
            cmap.opening[e], cmap.sliding[e] = float(delta @ nv), float(np.linalg.norm(t))
            for target, direction, sig in ((w_open, nv, cmap.sigma_opening), (w_slide, t_hat, cmap.sigma_sliding)):
                w = signs[:, None] * direction[None, :]
                np.add.at(target, (slice(None),) + tuple(nodes.T), w.T / len(at))
                if cov is not None:
                    sig[e] = math.sqrt(max(cov.local_variance_at(nodes, w, JUMP_RADIUS), 0.0))
        sig = [math.nan, math.nan] if cov is None else [math.sqrt(max(v, 0.0)) for v in
                                                         np.diag(cov.covariance([w_open, w_slide]))]
        sel = cmap.labels == label
        ratio = cmap.residual_ratio[sel]
        cmap.cracks.append(Crack(
            label, len(at), centres[:, sel].mean(axis=1).tolist(), mean_n.tolist(),
            float(np.mean(cmap.opening[sel])), sig[0], float(np.mean(cmap.sliding[sel])), sig[1],
            float(cmap.jump[sel].mean()), float(np.nanmean(ratio)) if np.isfinite(ratio).any() else math.nan))
