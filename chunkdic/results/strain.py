"""Small strains of a C8 displacement field: per element, mean over the ROI, principal values.

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
    "displacement_gradient",
    "element_strain",
    "principal_strains",
    "mean_strain",
    "StrainSummary",
    "strain_summary",
]


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


def element_strain(u: np.ndarray, element_size: float) -> np.ndarray:
    """Small-strain tensor per element, at the element centres (paper section 5.4).

    Parameters
    ----------
    u : ndarray, shape (3, nz, ny, nx), float64, voxels
        Nodal displacement.
    element_size : float
        Element edge ``ell``, voxels.

    Returns
    -------
    eps : ndarray, shape (3, 3, nz-1, ny-1, nx-1), float64, dimensionless
        ``eps[i, j] = (dU_i/dX_j + dU_j/dX_i) / 2``, axes ``(z, y, x)``.
    """
    H = displacement_gradient(u, element_size)
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
        Eigenvalues in decreasing order.
    """
    eps = np.asarray(eps, dtype=np.float64)
    if eps.shape[:2] != (3, 3):
        raise InputError(f"strain tensors must have shape (3, 3, ...), got {eps.shape}")
    moved = np.moveaxis(eps, (0, 1), (-2, -1))
    vals = np.linalg.eigvalsh(0.5 * (moved + np.swapaxes(moved, -1, -2)))[..., ::-1]
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

    def as_dict(self) -> dict:
        """JSON-friendly dict (arrays as nested lists)."""
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in asdict(self).items()}


def mean_strain(u: np.ndarray, element_size: float, *, exclude_outer: bool = True,
                elements: np.ndarray | None = None) -> StrainSummary:
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
    H_all = _element_mean(H, use)
    H_in = _element_mean(H[(slice(None), slice(None)) + inner], use[inner])
    factor = np.array([1.0 - 2.0 * ell / (k * ell) if e else 1.0 for k, e in zip(n, excluded)])
    mean, mean_all, corrected = _sym(H_in), _sym(H_all), _sym(H_in * factor[None, :])
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
    )


def strain_summary(result, *, exclude_outer: bool = True) -> StrainSummary:
    """:func:`mean_strain` of a :class:`chunkdic.Result` (element size from its info; the
    active elements of its mask, if any): what every mean strain of a result uses, so that
    elements a mask excludes never count."""
    active = None if result.active is None else result.active > 0
    return mean_strain(result.displacement, result.info["element_size"], exclude_outer=exclude_outer,
                       elements=active)
