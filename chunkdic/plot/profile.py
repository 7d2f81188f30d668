"""The ε_zz(z) profile of results: mean axial strain per element layer along z, and the
truth when the pair is synthetic.

One idea: a number per element layer that a researcher compares across element sizes
and against the imposed field (a compression band shows as a dip of the width of the
band). For each result, layer ``k`` (element centres at ``z_k = z0 + (k + 1/2) ℓ - 1/2``,
level voxels) gets the mean of ``eps_zz`` over its elements (the element strains of
:mod:`chunkdic.results.strain`; elements outside a specimen mask and NaN elements are left out).

The truth, when both scans of the result carry the synthetic field that made them
(:func:`chunkdic.synth.synthetic.load_metadata`, roles ``reference`` and ``deformed``), is
the mean of ``∂Uz/∂Z`` over the same elements: per element
``(Uz(Z1) - Uz(Z0)) / (Z1 - Z0)`` averaged over the element's ``(y, x)`` face with 2x2
Gauss points, which is exact for the affine and band fields of :mod:`chunkdic.synth.fields`
(``Uz`` linear in ``y, x``, or independent of them). Level-``s`` voxel ``c`` is level-0
voxel ``2^s c + (2^s - 1)/2`` (DESIGN.md), where the field lives.

Only mesh-sized arrays are read; the truth is evaluated one element layer at a time.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..mesh import level0_position
from ..results.result import Result
from ..synth import synthetic
from ..synth.fields import Field

__all__ = ["LayerProfile", "epszz_profile", "synthetic_field", "true_layer_strain", "write_profile_csv",
           "PROFILE_COLUMNS"]

#: columns of ``epszz_profile.csv`` (one row per result and element layer)
PROFILE_COLUMNS = ("result", "element_size", "level", "layer", "z", "z_physical", "unit", "eps_zz",
                   "eps_zz_true", "elements")

_GAUSS = (0.5 - 0.5 / np.sqrt(3.0), 0.5 + 0.5 / np.sqrt(3.0))  # 2-point Gauss on [0, 1]


@dataclass(frozen=True)
class LayerProfile:
    """The ε_zz(z) profile of one result.

    Attributes
    ----------
    z : ndarray, shape (ez,), float64, voxels of the result's level
        Element-layer centres.
    eps_zz : ndarray, shape (ez,), float64
        Mean element ``eps_zz`` per layer (NaN for a layer with no measured element).
    elements : ndarray, shape (ez,), int
        Elements averaged per layer.
    eps_zz_true : ndarray, shape (ez,), float64, or None
        Mean true ``∂Uz/∂Z`` over the same elements (synthetic pairs only).
    """

    z: np.ndarray
    eps_zz: np.ndarray
    elements: np.ndarray
    eps_zz_true: np.ndarray | None


def synthetic_field(result: Result, ref=None, deformed=None) -> Field | None:
    """The field that made the result's pair, when both scans are a synthetic pair's
    reference and deformed scan (their Zarr attributes, :mod:`chunkdic.synth.synthetic`);
    ``None`` otherwise (measured scans, scans not on disk, a pair without a field)."""

    inputs = result.info.get("inputs") or {}
    metas = []
    for given, role in ((ref, "reference"), (deformed, "deformed")):
        src = given if given is not None else inputs.get(role)
        if not isinstance(src, (str, Path)) or str(src).startswith("<in-memory") or not Path(src).is_dir():
            return None
        try:
            meta = synthetic.load_metadata(src)
        except InputError:
            return None
        if meta.get("role") != role:
            return None
        metas.append(meta)
    if metas[0].get("field") is None or metas[0].get("field") != metas[1].get("field"):
        return None
    return Field.from_json(metas[0]["field"])


def _level0(result: Result, c):
    """Level-0 voxel coordinate of level coordinate ``c`` (DESIGN.md voxel centres)."""
    return level0_position(c, result.scale)


def _zz(dU_dZ: np.ndarray, strain: str) -> np.ndarray:
    """The zz strain of the column ``∂U/∂Z`` (3, ...): ``∂Uz/∂Z`` (small), or the Green–Lagrange
    ``E_zz = ∂Uz/∂Z + (Σ_i (∂U_i/∂Z)²) / 2``, which needs that column only."""
    if strain == "small":
        return dU_dZ[0]
    return dU_dZ[0] + 0.5 * (dU_dZ**2).sum(axis=0)


def true_layer_strain(result: Result, field: Field, strain: str = "small") -> np.ndarray:
    """Mean true zz strain of every element of the result's mesh, shape ``(ez, ey, ex)``.

    Per element: ``∂U/∂Z = (U(Z1) - U(Z0)) / (Z1 - Z0)`` on its bottom and top faces, averaged
    over 2x2 Gauss points of the face (exact when ``U`` is at most cubic in ``y`` and ``x`` on
    an element), computed one element layer at a time; then its ``strain`` measure, as the
    measured element strain is that of the element's mean gradient.
    """
    mesh = result.mesh
    ell = mesh.element_size
    (oz, oy, ox), (ez, ey, ex) = mesh.origin, mesh.shape
    g = np.asarray(_GAUSS)
    ys = _level0(result, (oy - 0.5 + ell * (np.arange(ey)[:, None] + g)).ravel())  # (ey*2,)
    xs = _level0(result, (ox - 0.5 + ell * (np.arange(ex)[:, None] + g)).ravel())
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    out = np.empty((ez, ey, ex))
    for k in range(ez):
        z0, z1 = _level0(result, [oz - 0.5 + k * ell, oz - 0.5 + (k + 1) * ell])
        d = (field.displacement(np.full_like(yy, z1), yy, xx)
             - field.displacement(np.full_like(yy, z0), yy, xx)) / (z1 - z0)
        out[k] = _zz(d.reshape(3, ey, 2, ex, 2).mean(axis=(2, 4)), strain)
    return out


def epszz_profile(result: Result, field: Field | None = None, strain: str = "small") -> LayerProfile:
    """Mean ``eps_zz`` per element layer of ``result`` (and the truth of ``field``, if given).

    Parameters
    ----------
    result : Result
    field : Field, optional
        The synthetic field of the pair (:func:`synthetic_field`), level-0 voxels.
    strain : {"small", "green-lagrange"}
        Strain measure of the profile and of its truth.

    Returns
    -------
    LayerProfile
    """
    mesh = result.mesh
    eps = result.element_strain(strain)[0, 0]
    use = np.isfinite(eps)
    if result.active is not None:
        use &= np.asarray(result.active, bool)
    n = use.sum(axis=(1, 2))
    with np.errstate(invalid="ignore"):
        mean = np.where(use, eps, 0.0).sum(axis=(1, 2)) / np.where(n > 0, n, np.nan)
        true = None
        if field is not None:
            t = true_layer_strain(result, field, strain)
            true = np.where(use, t, 0.0).sum(axis=(1, 2)) / np.where(n > 0, n, np.nan)
    z = mesh.element_axes()[0]
    return LayerProfile(z, mean, n.astype(int), true)


def true_curve(result: Result, field: Field, n: int = 400, lateral: int = 12, strain: str = "small"):
    """The truth as a continuous curve: ``(z, mean zz strain over the ROI plane at z)``, z in
    level voxels over the ROI, the plane sampled on ``lateral x lateral`` points."""
    roi = result.mesh.roi
    z = np.linspace(roi[0].start - 0.5, roi[0].stop - 0.5, n)
    ys = _level0(result, np.linspace(roi[1].start - 0.5, roi[1].stop - 0.5, lateral))
    xs = _level0(result, np.linspace(roi[2].start - 0.5, roi[2].stop - 0.5, lateral))
    Z = _level0(result, z)[:, None, None]
    h = 0.25
    yy, xx = np.broadcast_arrays(ys[None, :, None], xs[None, None, :])
    d = (field.displacement(Z + h, yy, xx) - field.displacement(Z - h, yy, xx)) / (2 * h)
    return z, _zz(d, strain).mean(axis=(1, 2))


def write_profile_csv(rows: list[tuple[Result, LayerProfile, object]], path) -> str:
    """Write ``epszz_profile.csv``: one line per result and element layer, columns
    :data:`PROFILE_COLUMNS` (``z`` in voxels of the result's level, ``z_physical`` in
    ``unit`` or empty, ``eps_zz_true`` empty without a synthetic truth).

    ``rows``: ``(result, profile, frame)`` with the result's :class:`chunkdic.plot.figures.Frame`.
    """
    def num(v):
        return "" if v is None or not np.isfinite(v) else repr(float(v))

    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(PROFILE_COLUMNS)
        for i, (res, prof, fr) in enumerate(rows):
            name = res.path or f"result {i}"
            for k in range(len(prof.z)):
                zp = fr.position(0, prof.z[k]) if fr.physical else None
                w.writerow([name, res.info["element_size"], res.level, k, num(prof.z[k]),
                            num(zp), fr.unit if fr.physical else "", num(prof.eps_zz[k]),
                            num(None if prof.eps_zz_true is None else prof.eps_zz_true[k]), int(prof.elements[k])])
    return str(path)
