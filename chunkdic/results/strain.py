"""Strains of a C8 displacement field: per element, mean over the ROI, principal values, rotation.

The C8 field is trilinear in each element, so its gradient is bilinear there; at the
element centre it is the average of the four edge differences along each axis
(``du/dz = mean over the 4 z-edges of (u[k+1] - u[k]) / ell``). That centre value is also
the element's *average* gradient (the gradient is linear in the other coordinates), which
is the paper's "strain constant per element" (section 5.4, C8P1).

Layout of strain arrays (one choice, everywhere in chunkdic):

- displacement gradient ``H[i, j] = dU_i / dX_j``, shape ``(3, 3, ez, ey, ex)``, axes
  ``(z, y, x)`` for both ``i`` and ``j``;
- small-strain tensor ``eps = (H + H^T) / 2``, same shape (the full symmetric tensor, not
  6 components, so that ``eps[0, 0]`` is ``eps_zz`` and ``eps[2, 1]`` is ``eps_xy``).

Strains are dimensionless: displacements and element size are in voxels of the same level.

Measures (:data:`MEASURES`): ``"small"``, the paper's ``(H + Hᵀ) / 2``, which a rigid
rotation by ``θ`` turns into a false strain of about ``-θ²/2`` (−0.0038 at 5°); and
``"green-lagrange"``, ``E = (H + Hᵀ + HᵀH) / 2 = (FᵀF − I) / 2`` with ``F = I + H``, zero for
any rigid rotation, equal to the small strain to first order. :data:`DEFAULT_MEASURE` is
Green–Lagrange, so that a rotated specimen shows no strain (what DVC users expect of
VIC-3D or spam); ``"small"`` stays one option away. The rotation of an element is that of
the polar decomposition ``F = R U`` (:func:`rotation_angle`); above
:data:`ROTATION_WARNING` degrees the small strain is no longer trustworthy and the
commands say so.

References
----------
Roux, Hild, Viot, Bernard, sections 5.2 (mean strain over the ROI without the outermost
elements, strain uncertainty) and 5.4 (element strains, first-order correction
``(1 - 2 ell / L)`` of the mean strain).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..errors import InputError

__all__ = [
    "MEASURES",
    "DEFAULT_MEASURE",
    "MEASURE_SYMBOLS",
    "ROTATION_WARNING",
    "green_lagrange",
    "rotation_angle",
    "displacement_gradient",
    "element_strain",
    "principal_strains",
    "mean_strain",
    "StrainSummary",
    "strain_summary",
]


#: strain measures, by name
MEASURES = ("small", "green-lagrange")
#: the measure of every command and of :func:`strain_summary` unless told otherwise
DEFAULT_MEASURE = "green-lagrange"
#: the symbol of each measure in figures and tables (E: Green–Lagrange, ε: small strain)
MEASURE_SYMBOLS = {"small": "ε", "green-lagrange": "E"}
#: rotation (degrees) above which small strain is not trustworthy
ROTATION_WARNING = 1.0


def check_measure(measure: str) -> str:
    if measure not in MEASURES:
        raise InputError(f"strain measure must be one of {', '.join(MEASURES)}, got {measure!r}")
    return measure


def green_lagrange(H: np.ndarray) -> np.ndarray:
    """Green–Lagrange strain ``E = (H + Hᵀ + HᵀH) / 2`` of displacement gradients.

    Parameters
    ----------
    H : ndarray, shape (3, 3, ...), float64
        ``H[i, j] = dU_i / dX_j`` (:func:`displacement_gradient`).

    Returns
    -------
    ndarray, shape (3, 3, ...), float64, dimensionless

    Examples
    --------
    >>> t = np.radians(10.0)
    >>> R = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    >>> float(np.abs(green_lagrange(R - np.eye(3))).max()) < 1e-15
    True
    """
    H = np.asarray(H, np.float64)
    HtH = np.einsum("ki...,kj...->ij...", H, H)
    return 0.5 * (H + H.swapaxes(0, 1) + HtH)


def rotation_angle(H: np.ndarray) -> np.ndarray:
    """Rotation angle of the polar decomposition ``F = R U`` (``F = I + H``), degrees.

    Parameters
    ----------
    H : ndarray, shape (3, 3, ...), float64

    Returns
    -------
    ndarray, shape (...), float64, degrees in [0, 180]; NaN where ``H`` has a NaN.
    """
    H = np.asarray(H, np.float64)
    F = np.moveaxis(H, (0, 1), (-2, -1)) + np.eye(3)
    finite = np.isfinite(F).all(axis=(-2, -1))
    W, _, Vt = np.linalg.svd(np.where(finite[..., None, None], F, np.eye(3)))
    R = W @ Vt
    det = np.linalg.det(R)
    W[..., :, 2] *= np.sign(det)[..., None]  # a proper rotation
    R = W @ Vt
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.where(finite, np.degrees(np.arccos(cos)), np.nan)


def _check_nodal(u: np.ndarray) -> np.ndarray:
    u = np.asarray(u, dtype=np.float64)
    if u.ndim != 4 or u.shape[0] != 3 or min(u.shape[1:]) < 2:
        raise InputError(f"nodal displacement must have shape (3, nz, ny, nx) with >= 2 nodes per axis, got {u.shape}")
    return u


def displacement_gradient(u: np.ndarray, element_size: float) -> np.ndarray:
    """Gradient of a C8 nodal field at the element centres.

    Parameters
    ----------
    u : ndarray, shape (3, nz, ny, nx), float64, voxels
        Nodal displacement, components ``(z, y, x)``.
    element_size : float
        Element edge ``ell``, voxels of the same level as ``u``.

    Returns
    -------
    H : ndarray, shape (3, 3, nz-1, ny-1, nx-1), float64, dimensionless
        ``H[i, j] = dU_i / dX_j`` at each element centre (= the element average).

    Examples
    --------
    >>> import numpy as np
    >>> z, y, x = np.meshgrid(*[np.arange(3.0) * 8] * 3, indexing="ij")
    >>> H = displacement_gradient(np.stack([0.01 * z, 0 * y, 0.02 * y]), 8)
    >>> round(float(H[0, 0, 0, 0, 0]), 12), round(float(H[2, 1, 1, 1, 1]), 12)
    (0.01, 0.02)
    """
    u = _check_nodal(u)
    ell = float(element_size)
    if not ell > 0:
        raise InputError(f"element size must be positive, got {element_size!r}")
    H = np.empty((3, 3) + tuple(n - 1 for n in u.shape[1:]))
    for j in range(3):  # derivative axis (node axes are 1, 2, 3 of u)
        d = np.diff(u, axis=j + 1) / ell
        for other in range(3):
            if other != j:  # average the 4 parallel edges: mean of neighbours on the other axes
                lo = [slice(None)] * 4
                hi = [slice(None)] * 4
                lo[other + 1] = slice(None, -1)
                hi[other + 1] = slice(1, None)
                d = 0.5 * (d[tuple(lo)] + d[tuple(hi)])
        H[:, j] = d
    return H


def element_strain(u: np.ndarray, element_size: float, measure: str = "small") -> np.ndarray:
    """Strain tensor per element, at the element centres (paper section 5.4).

    Parameters
    ----------
    u : ndarray, shape (3, nz, ny, nx), float64, voxels
        Nodal displacement.
    element_size : float
        Element edge ``ell``, voxels.
    measure : {"small", "green-lagrange"}
        Small strain (the paper's, default of this low-level function) or Green–Lagrange.

    Returns
    -------
    eps : ndarray, shape (3, 3, nz-1, ny-1, nx-1), float64, dimensionless
        ``eps[i, j] = (dU_i/dX_j + dU_j/dX_i) / 2`` (small), axes ``(z, y, x)``.
    """
    H = displacement_gradient(u, element_size)
    if check_measure(measure) == "green-lagrange":
        return green_lagrange(H)
    return 0.5 * (H + H.swapaxes(0, 1))


def principal_strains(eps: np.ndarray) -> np.ndarray:
    """Principal values of symmetric tensors, largest first.

    Parameters
    ----------
    eps : ndarray, shape (3, 3, ...), float64
        Symmetric tensors (e.g. :func:`element_strain`, or one mean tensor ``(3, 3)``).

    Returns
    -------
    ndarray, shape (3, ...), float64
        Eigenvalues in decreasing order; NaN for a tensor with a NaN entry.
    """
    eps = np.asarray(eps, dtype=np.float64)
    if eps.shape[:2] != (3, 3):
        raise InputError(f"strain tensors must have shape (3, 3, ...), got {eps.shape}")
    moved = np.moveaxis(eps, (0, 1), (-2, -1))
    finite = np.isfinite(moved).all(axis=(-2, -1))  # NaN tensors (elements not measured) give NaN
    sym = 0.5 * (moved + np.swapaxes(moved, -1, -2))
    vals = np.linalg.eigvalsh(np.where(finite[..., None, None], sym, 0.0))[..., ::-1]
    vals = np.where(finite[..., None], vals, np.nan)
    return np.moveaxis(vals, -1, 0)


def _sym(H: np.ndarray) -> np.ndarray:
    return 0.5 * (H + H.T)


def _element_mean(H: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Mean of ``H`` (3, 3, ez, ey, ex) over the elements ``use``; NaN where there is none
    (without the warning of ``nanmean``, which the CLI would print)."""
    count = int(use.sum())
    if count == 0:
        return np.full((3, 3), np.nan)
    return np.where(use, H, 0.0).sum(axis=(2, 3, 4)) / count


@dataclass(frozen=True)
class StrainSummary:
    """Mean strain of a C8 field over its ROI (paper sections 5.2 and 5.4).

    Attributes
    ----------
    mean : ndarray, shape (3, 3)
        Mean strain over the elements left when the outermost layer is removed
        (on axes with fewer than 3 elements nothing is removed, see ``excluded``).
    mean_all : ndarray, shape (3, 3)
        Mean strain over every element.
    corrected : ndarray, shape (3, 3)
        ``mean`` with the first-order correction of section 5.4: assuming no strain in the
        removed elements, the mean over the whole ROI of edge ``L_j = n_j ell`` is the inner
        mean of ``dU_i/dX_j`` times ``(1 - 2 ell / L_j)`` (then symmetrised).
    factor : ndarray, shape (3,)
        ``1 - 2 ell / L_j`` per axis ``(z, y, x)`` (1 where nothing was removed).
    volume_change, volume_change_corrected : float
        ``tr(mean)``, ``tr(corrected)``.
    eps_zz, eps_zz_corrected : float
        ``mean[0, 0]``, ``corrected[0, 0]`` (z is the compression axis).
    principal : ndarray, shape (3,)
        Principal values of ``mean``, largest first.
    delta_eps : float
        ``max |principal|``: the strain uncertainty of section 4.2 when the field is a
        rigid translation.
    elements : tuple of 3 int
        Elements per axis that entered ``mean``.
    excluded : tuple of 3 bool
        Whether the outer layer was removed along ``(z, y, x)``.
    measure : str
        ``"small"`` or ``"green-lagrange"``.
    max_rotation : float
        Largest element rotation (polar decomposition) over the averaged elements, degrees.
    correction_applies : bool
        Whether the ``(1 - 2 ell / L)`` correction's assumption holds: the removed outer layer
        carries little strain (its mean strain below half the inner mean's, norms of the
        symmetric gradients), as around a localised band. False for a uniform strain, where
        ``mean`` is already right and ``corrected`` is too small by ``factor``. Judged per
        derivative axis ``j``: column ``j`` of the mean gradient over the two outer layers
        normal to ``j`` against that of the inner elements.
    correction_axes : tuple of 3 bool
        The same judged per axis ``(z, y, x)``: a band normal to z spans the whole width
        along y and x, so its outer layers normal to y and x are strained and only ``z``
        qualifies; then ``eps_zz_corrected`` still estimates the mean over the whole ROI.
    outer : ndarray, shape (3, 3)
        Column ``j``: the mean ``dU_i/dX_j`` over the two outer layers normal to ``j`` (NaN
        where nothing was removed).
    """

    mean: np.ndarray
    mean_all: np.ndarray
    corrected: np.ndarray
    factor: np.ndarray
    volume_change: float
    volume_change_corrected: float
    eps_zz: float
    eps_zz_corrected: float
    principal: np.ndarray
    delta_eps: float
    elements: tuple[int, int, int]
    excluded: tuple[bool, bool, bool]
    measure: str = "small"
    max_rotation: float = 0.0
    correction_applies: bool = True
    correction_axes: tuple[bool, bool, bool] = (True, True, True)
    outer: np.ndarray | None = None

    def as_dict(self) -> dict:
        """JSON-friendly dict (arrays as nested lists)."""
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in asdict(self).items()}


def mean_strain(u: np.ndarray, element_size: float, *, exclude_outer: bool = True,
                elements: np.ndarray | None = None, measure: str = "small") -> StrainSummary:
    """Mean strain of a C8 nodal field, with and without its outermost layer of elements.

    The mean of element strains equals the volume average of the strain, which only
    depends on boundary nodes; those are the least constrained, so by default the
    outermost layer of elements is left out (paper section 5.2) and the first-order
    correction ``(1 - 2 ell / L)`` of section 5.4 is also given.

    Parameters
    ----------
    u : ndarray, shape (3, nz, ny, nx), float64, voxels
        Nodal displacement.
    element_size : float
        Element edge ``ell``, voxels.
    exclude_outer : bool, keyword-only
        Leave out the outermost layer (on axes with at least 3 elements).
    elements : ndarray of bool, shape (nz-1, ny-1, nx-1), keyword-only, optional
        The elements to average (a specimen mask's active elements); elements with a NaN
        node (not measured) are always left out.
    measure : {"small", "green-lagrange"}, keyword-only
        Strain measure: small strain (the paper's; the mean of the element gradients,
        symmetrised) or the mean of the element Green–Lagrange tensors. The ``(1 - 2 ell /
        L)`` correction is a small-strain one: with Green–Lagrange ``corrected`` is NaN.

    Returns
    -------
    StrainSummary
        ``mean`` (and what derives from it) is NaN when no averaged element is left once
        the outer layer is removed.

    Raises
    ------
    InputError
        No element to average (every one masked out or with a NaN node).

    Examples
    --------
    >>> import numpy as np
    >>> z = np.arange(6.0)[:, None, None] * 10 + np.zeros((6, 6, 6))
    >>> s = mean_strain(np.stack([-0.02 * z, 0 * z, 0 * z]), 10)
    >>> round(s.eps_zz, 12), round(s.eps_zz_corrected, 12)
    (-0.02, -0.012)
    """
    H = displacement_gradient(u, element_size)
    ell = float(element_size)
    n = H.shape[2:]
    excluded = tuple(bool(exclude_outer and k >= 3) for k in n)
    inner = tuple(slice(1, k - 1) if e else slice(None) for k, e in zip(n, excluded))
    use = np.isfinite(H).all(axis=(0, 1))
    if elements is not None:
        use &= np.asarray(elements, dtype=bool)
    if not use.any():
        raise InputError("no element to average the strain over: every element is masked out or has an "
                         "unmeasured (NaN) node")
    factor = np.array([1.0 - 2.0 * ell / (k * ell) if e else 1.0 for k, e in zip(n, excluded)])
    H_in = _element_mean(H[(slice(None), slice(None)) + inner], use[inner])
    # the correction's assumption, per derivative axis j: the two outer layers normal to j
    # carry little of dU/dX_j (column j of H) compared with the inner elements
    H_out = np.full((3, 3), np.nan)
    finite = bool(any(excluded) and np.isfinite(H_in).all())
    big = max(float(np.linalg.norm(H_in[:, j])) for j in range(3)) if finite else 0.0
    holds = [False] * 3
    for j in range(3):
        if not excluded[j]:
            continue
        layers = np.zeros(n, bool)
        layers[tuple(slice(None) if a != j else [0, n[j] - 1] for a in range(3))] = True
        H_out[:, j] = _element_mean(H, use & layers)[:, j]
        inner_j = float(np.linalg.norm(H_in[:, j]))
        holds[j] = finite and (inner_j <= 0.1 * big or float(np.linalg.norm(H_out[:, j])) < 0.5 * inner_j)
    applies = finite and all(h for h, e in zip(holds, excluded) if e)
    angles = rotation_angle(np.where(use, H, 0.0))
    max_rotation = float(angles[use].max())
    if check_measure(measure) == "green-lagrange":
        E = green_lagrange(H)
        mean, mean_all = _element_mean(E[(slice(None), slice(None)) + inner], use[inner]), _element_mean(E, use)
        corrected = np.full((3, 3), np.nan)
    else:
        mean, mean_all, corrected = _sym(H_in), _sym(_element_mean(H, use)), _sym(H_in * factor[None, :])
    principal = principal_strains(mean) if np.isfinite(mean).all() else np.full(3, np.nan)
    return StrainSummary(
        mean=mean,
        mean_all=mean_all,
        corrected=corrected,
        factor=factor,
        volume_change=float(np.trace(mean)),
        volume_change_corrected=float(np.trace(corrected)),
        eps_zz=float(mean[0, 0]),
        eps_zz_corrected=float(corrected[0, 0]),
        principal=principal,
        delta_eps=float(np.abs(principal).max()),
        elements=tuple(int(k - 2) if e else int(k) for k, e in zip(n, excluded)),
        excluded=excluded,
        measure=measure,
        max_rotation=max_rotation,
        correction_applies=applies and any(excluded) and measure == "small",
        correction_axes=tuple(bool(h and measure == "small") for h in holds),
        outer=H_out,
    )


def strain_summary(result, *, exclude_outer: bool = True, measure: str = DEFAULT_MEASURE) -> StrainSummary:
    """:func:`mean_strain` of a :class:`chunkdic.Result` (element size from its info; the
    active elements of its mask, if any): what every mean strain of a result uses, so that
    elements a mask excludes never count. ``measure``: Green–Lagrange by default
    (:data:`DEFAULT_MEASURE`), ``"small"`` for the paper's small strain."""
    active = None if result.active is None else result.active > 0
    return mean_strain(result.displacement, result.info["element_size"], exclude_outer=exclude_outer,
                       elements=active, measure=measure)
