"""Statistics of a result over a region: means with honest confidence intervals, profiles.

For each displacement component (``Uz, Uy, Ux`` at the region's nodes) and each strain
component (``E_zz … E_xy``, Green–Lagrange by default, or the small strain ``eps_*``, at the
region's element centres): the mean, the population standard deviation, and the confidence
interval of the mean, ``mean ± z σ_mean`` (``z = 1.96`` at 95 %), with ``σ_mean² = wᵀ C w``:
``w`` the weights that make the mean from the nodal field (for a strain, through the C8
gradient, linearised about the measured field for Green–Lagrange) and ``C`` the solve's
nodal covariance (:mod:`chunkdic.analysis.covariance`; docs/statistics.md says why this and
not the field's spatial autocorrelation). ``std/√n``, the interval of independent samples,
is given beside it: nodes are correlated, so it is not the uncertainty of the mean (5–12× too
small on a regularised field, 1.4–2× too large without regularisation, where neighbouring
nodes are anticorrelated; docs/statistics.md).

A line gives a **profile**: at each sample point the C8 displacement (trilinear, exact for
the field) and the strain of the element holding it, with their standard uncertainties from
the nodes around the point (:meth:`~chunkdic.analysis.covariance.NodalCovariance.local_variance`).

``remove_rigid``: the statistics of the field without its rigid motion
(:mod:`chunkdic.analysis.rigid`); the intervals count that the motion was fitted on the same
nodes. ``truth``: a known field (a synthetic pair's ``field.json``) adds the DVC Challenge 2.0
bias, noise floor and ``u_rms`` of the error (:mod:`chunkdic.analysis.challenge`).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import asdict, dataclass, field
from statistics import NormalDist

import numpy as np

from ..errors import InputError
from ..mesh import LOCAL_NODES, Mesh, level0_position
from ..results.result import FLAG_MASKED, FLAG_NO_DATA
from ..results.strain import DEFAULT_MEASURE, check_measure, displacement_gradient, element_strain
from .covariance import NodalCovariance, element_gradient_weights, gradient_adjoint, point_stencil
from .regions import Region, region_of

__all__ = ["Row", "RegionStats", "Profile", "region_stats", "profile", "stats", "strain_names", "read_truth"]

#: strain components reported, in order: normal, then shear
STRAIN_PAIRS = ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1))


def strain_names(measure: str) -> list[str]:
    """``E_zz … E_xy`` (Green–Lagrange) or ``eps_zz … eps_xy`` (small strain)."""
    prefix = "E" if measure == "green-lagrange" else "eps"
    return [f"{prefix}_{'zyx'[i]}{'zyx'[j]}" for i, j in STRAIN_PAIRS]


@dataclass
class Row:
    """One quantity over a region (units: ``unit``; strains are dimensionless).

    ``sigma_mean``: standard uncertainty of the mean (the solve's covariance), ``low``/``high``
    its confidence interval, ``naive_sigma_mean`` = ``std/√n``. With a truth: ``bias``,
    ``noise_floor``, ``u_rms`` of the error (DVC Challenge 2.0).
    """

    quantity: str
    unit: str
    n: int
    mean: float
    std: float
    sigma_mean: float
    low: float
    high: float
    naive_sigma_mean: float
    bias: float | None = None
    noise_floor: float | None = None
    u_rms: float | None = None


COLUMNS = ("quantity", "unit", "n", "mean", "std", "sigma_mean", "low", "high", "naive_sigma_mean",
           "bias", "noise_floor", "u_rms")


@dataclass
class RegionStats:
    """Outcome of :func:`region_stats`: one :class:`Row` per quantity and what they were taken over."""

    result: str | None
    region: str
    measure: str
    confidence: float
    rows: list[Row]
    voxel_length: list | None = None
    unit: str | None = None
    rigid: dict | None = None
    truth: dict | None = None
    method: str = "solve"
    info: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        d = asdict(self)
        d["rows"] = [asdict(r) for r in self.rows]
        return _finite(d)

    def row(self, quantity: str) -> Row:
        return next(r for r in self.rows if r.quantity == quantity)

    def csv(self) -> str:
        """One line per quantity under one header line (``region`` first)."""
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(("region",) + COLUMNS)
        for r in self.rows:
            w.writerow([self.region] + ["" if getattr(r, k) is None else getattr(r, k) for k in COLUMNS])
        return buf.getvalue()

    def text(self) -> str:
        pct = f"{100 * self.confidence:g} %"
        lines = [f"{self.result}: {self.region}; {self.measure} strain; {pct} interval of the mean from the solve's "
                 "nodal covariance (docs/statistics.md); std/sqrt(n) beside it for comparison"]
        if self.voxel_length:
            lines.append(f"(a voxel of the level is {' x '.join(f'{v:g}' for v in dict.fromkeys(self.voxel_length))} "
                         f"{self.unit}; strains are dimensionless)")
        if self.rigid:
            lines.append("(rigid motion removed first)")
        head = f"{'quantity':<8} {'unit':<12} {'n':>6} {'mean':>12} {'std':>11} {pct + ' interval of the mean':>30}"
        head += f"  {'±1.96 std/√n':>12}"
        if self.truth:
            head += f"  {'bias':>10} {'noise floor':>11} {'u_rms':>10}"
        lines.append(head)
        for r in self.rows:
            line = (f"{r.quantity:<8} {r.unit:<12} {r.n:>6} {r.mean:>+12.5g} {r.std:>11.4g} "
                    f"{'[' + format(r.low, '+.5g') + ', ' + format(r.high, '+.5g') + ']':>30}  "
                    f"{1.959963984540054 * r.naive_sigma_mean:>12.3g}")
            if self.truth and r.bias is not None:
                line += f"  {r.bias:>+10.3g} {r.noise_floor:>11.3g} {r.u_rms:>10.3g}"
            lines.append(line)
        return "\n".join(lines)


@dataclass
class Profile:
    """Outcome of :func:`profile`: values and standard uncertainties along a line.

    Attributes
    ----------
    distance : ndarray, shape (n,), level-0 voxels from the line's start
    points : ndarray, shape (n, 3), level-0 voxels ``(z, y, x)``
    names : list of str
        ``Uz, Uy, Ux`` (voxels of the level) and the strain components.
    values, sigma : ndarray, shape (len(names), n), float64
    """

    result: str | None
    region: str
    measure: str
    distance: np.ndarray
    points: np.ndarray
    names: list
    values: np.ndarray
    sigma: np.ndarray
    unit: str = "voxel"
    rigid: dict | None = None

    def as_dict(self) -> dict:
        return _finite({"result": self.result, "region": self.region, "measure": self.measure, "unit": self.unit,
                        "distance": self.distance.tolist(), "points": self.points.tolist(),
                        "values": {n: v.tolist() for n, v in zip(self.names, self.values)},
                        "sigma": {n: v.tolist() for n, v in zip(self.names, self.sigma)}, "rigid": self.rigid})

    def csv(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["distance", "z", "y", "x"] + [c for n in self.names for c in (n, f"sigma_{n}")])
        for k in range(self.distance.size):
            w.writerow([f"{self.distance[k]:.6g}"] + [f"{v:.6g}" for v in self.points[k]]
                       + [f"{v:.8g}" for n in range(len(self.names)) for v in (self.values[n, k], self.sigma[n, k])])
        return buf.getvalue()

    def text(self) -> str:
        lines = [f"{self.result}: profile along the {self.region} ({self.distance.size} points; {self.measure} "
                 "strain; ± one standard uncertainty)"]
        lines.append(f"{'distance':>9}  " + "  ".join(f"{n:>20}" for n in self.names))
        for k in range(self.distance.size):
            cells = [f"{self.values[n, k]:+.4e} ±{self.sigma[n, k]:.1e}" for n in range(len(self.names))]
            lines.append(f"{self.distance[k]:>9.2f}  " + "  ".join(f"{c:>20}" for c in cells))
        return "\n".join(lines)


def _finite(obj):
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    if isinstance(obj, (float, np.floating)) and not math.isfinite(obj):
        return None
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def read_truth(truth):
    """A known field: a :class:`chunkdic.synth.fields.Field`, its JSON dict, or a synthetic pair
    (its folder, ``field.json`` or a scan of it; :func:`chunkdic.synth.synthetic.load_field`)."""
    from ..synth.fields import Field
    from ..synth.synthetic import load_field

    if truth is None or isinstance(truth, Field):
        return truth
    if isinstance(truth, dict):
        return Field.from_json(truth)
    field_ = load_field(truth)
    if field_ is None:
        raise InputError(f"truth {truth}: the pair was written without a field (no motion): nothing to compare")
    return field_


def _true_nodes(result, field_) -> np.ndarray:
    """The known field at the result's nodes, voxels of its level (3, nz, ny, nx)."""
    X0 = level0_position(result.node_coords, result.scale)
    return field_.displacement(*X0) / result.scale


def strain_coefficients(H: np.ndarray, i: int, j: int, measure: str) -> np.ndarray:
    """``∂E_ij / ∂H`` (3, 3, ...) at the gradients ``H`` (3, 3, ...): the strain linearised.

    Small strain: ``(e_i e_jᵀ + e_j e_iᵀ) / 2``; Green–Lagrange adds
    ``δ(HᵀH)_ij / 2 = (H_ki δH_kj + H_kj δH_ki) / 2``.
    """
    Hn = np.nan_to_num(np.asarray(H, np.float64))
    G = np.zeros_like(Hn)
    G[i, j] += 0.5
    G[j, i] += 0.5
    if measure == "green-lagrange":
        G[:, j] += 0.5 * Hn[:, i]
        G[:, i] += 0.5 * Hn[:, j]
    return G


def _strain_weights(H: np.ndarray, use: np.ndarray, i: int, j: int, measure: str, ell: float) -> np.ndarray:
    """Nodal weights of the mean of strain ``(i, j)`` over the elements ``use`` (linearised about ``H``)."""
    G = strain_coefficients(H, i, j, measure) * (use / max(int(use.sum()), 1))
    return gradient_adjoint(G, ell)


def _z(confidence: float) -> float:
    if not 0 < confidence < 1:
        raise InputError(f"confidence must lie between 0 and 1, got {confidence!r}")
    return NormalDist().inv_cdf(0.5 + confidence / 2)


def _prepared(result, remove_rigid: bool, covariance):
    """The result shown (rigid motion removed or not), the covariance, the weight map and the motion."""
    from .rigid import effective_weights, fit_rigid, remove_rigid as remove

    result.check_displacement()
    cov = covariance
    if cov is None:
        try:
            cov = NodalCovariance.of_result(result)
        except InputError:
            cov = None  # no per-node uncertainty: means and std, no interval
    if not remove_rigid:
        return result, cov, (lambda w: w), None
    motion = fit_rigid(result, covariance=cov)
    return remove(result, motion), cov, (lambda w: effective_weights(result, motion, w)), motion


def region_stats(result, region: Region | None = None, *, measure: str = DEFAULT_MEASURE,
                 remove_rigid: bool = False, truth=None, confidence: float = 0.95, covariance=None) -> RegionStats:
    """Mean, std and confidence interval of the mean of each component over a region (module docstring).

    Parameters
    ----------
    result : Result
    region : Region, optional
        :mod:`chunkdic.analysis.regions` (default: the whole ROI). Not a line (see :func:`profile`).
    measure : {"green-lagrange", "small"}, keyword-only
    remove_rigid : bool, keyword-only
        Statistics of the field without its least-squares rigid motion.
    truth : Field, dict or path, optional
        A known displacement field: adds bias, noise floor and ``u_rms`` of the error.
    confidence : float
        Of the interval (default 0.95).
    covariance : NodalCovariance, optional
        Reuse one built before (default: built here).

    Returns
    -------
    RegionStats
        Intervals are NaN when the result holds no per-node uncertainty.
    """
    from .regions import roi_region

    check_measure(measure)
    z = _z(confidence)
    region = roi_region(result) if region is None else region
    if region.kind == "line":
        raise InputError("a line gives a profile, not region statistics: use profile()")
    truth_field = read_truth(truth)
    if truth_field is not None and remove_rigid:
        raise InputError("--truth compares the measured field with the known one: leave out --remove-rigid")
    shown, cov, weights_of, motion = _prepared(result, remove_rigid, covariance)
    u = shown.displacement
    level = result.level
    unit = f"voxel (level {level})" if level else "voxel"
    nodes = region.nodes & np.isfinite(u).all(axis=0)
    if shown.flags is not None:
        nodes &= (shown.flags & (FLAG_NO_DATA | FLAG_MASKED)) == 0
    ell = float(result.info["element_size"])
    H = displacement_gradient(u, ell)
    E = element_strain(u, ell, measure)
    elements = region.elements & np.isfinite(H).all(axis=(0, 1))
    if shown.active is not None:
        elements &= shown.active > 0
    if not nodes.any():
        raise InputError(f"{region.text}: no measured node in it")
    u_err = e_err = None
    if truth_field is not None:
        ut = _true_nodes(result, truth_field)
        u_err, e_err = u - ut, E - element_strain(ut, ell, measure)
    rows = []
    weights = []
    for c, name in enumerate(("Uz", "Uy", "Ux")):
        w = np.zeros_like(u)
        w[c][nodes] = 1.0 / nodes.sum()
        weights.append(weights_of(w))
        rows.append(_row(name, unit, u[c][nodes], u_err[c][nodes] if u_err is not None else None))
    if elements.any():
        for (i, j), name in zip(STRAIN_PAIRS, strain_names(measure)):
            weights.append(weights_of(_strain_weights(H, elements, i, j, measure, ell)))
            rows.append(_row(name, "1", E[i, j][elements], e_err[i, j][elements] if e_err is not None else None))
    sig = _sigmas(cov, weights)
    for r, s in zip(rows, sig):
        r.sigma_mean, r.low, r.high = s, r.mean - z * s, r.mean + z * s
    info = {"nodes": int(nodes.sum()), "elements": int(elements.sum())}
    length = result.voxel_length()
    return RegionStats(result.path, region.text, measure, confidence, rows,
                       None if length is None else length.tolist(), result.unit,
                       None if motion is None else motion.as_dict(),
                       None if truth_field is None else truth_field.to_json(),
                       "solve" if cov is not None else "none (no per-node uncertainty)", info)


def _sigmas(cov, weights) -> list[float]:
    if cov is None:
        return [math.nan] * len(weights)
    return [math.sqrt(max(cov.variance(w), 0.0)) for w in weights]


def _row(name: str, unit: str, values: np.ndarray, error: np.ndarray | None) -> Row:
    n = int(values.size)
    row = Row(name, unit, n, float(values.mean()), float(values.std()), math.nan, math.nan, math.nan,
              float(values.std() / math.sqrt(n)))
    if error is not None:  # the DVC Challenge 2.0 numbers (chunkdic.analysis.challenge)
        row.bias, row.noise_floor = float(error.mean()), float(error.std())
        row.u_rms = math.hypot(row.bias, row.noise_floor)
    return row


def profile(result, region: Region, *, measure: str = DEFAULT_MEASURE, remove_rigid: bool = False,
            covariance=None) -> Profile:
    """Displacement and strain along a line, with standard uncertainties (module docstring).

    Parameters
    ----------
    result : Result
    region : Region
        A line (:func:`chunkdic.analysis.regions.line_region`).
    measure, remove_rigid, covariance
        As in :func:`region_stats`. With ``remove_rigid`` the uncertainties are the nodes'
        own (the rigid fit's is not added: it is small against one point's).
    """
    check_measure(measure)
    if region.kind != "line":
        raise InputError(f"a profile needs a line, not a {region.kind}")
    shown, cov, _, motion = _prepared(result, remove_rigid, covariance)
    u = shown.displacement
    mesh: Mesh = result.mesh
    ell = float(result.info["element_size"])
    H = displacement_gradient(u, ell)
    E = element_strain(u, ell, measure)
    pts = region.points
    n = pts.shape[0]
    names = ["Uz", "Uy", "Ux"] + strain_names(measure)
    values = np.full((len(names), n), np.nan)
    sigma = np.full((len(names), n), np.nan)
    values[:3] = mesh.evaluate(u, pts.T)
    for k, p in enumerate(pts):
        e = tuple(int(mesh.element_index(a, np.asarray(p[a]))[0]) for a in range(3))
        for q, (i, j) in enumerate(STRAIN_PAIRS):
            values[3 + q, k] = E[(i, j) + e]
        if cov is None:
            continue
        nodes, pw = point_stencil(mesh, p)
        for c in range(3):
            w = np.zeros((8, 3))
            w[:, c] = pw
            sigma[c, k] = math.sqrt(max(cov.local_variance_at(nodes, w), 0.0))
        corners = np.asarray(e) + LOCAL_NODES
        for q, (i, j) in enumerate(STRAIN_PAIRS):
            G = strain_coefficients(H[(slice(None), slice(None)) + e], i, j, measure)
            sigma[3 + q, k] = math.sqrt(max(cov.local_variance_at(corners, element_gradient_weights(G, ell)), 0.0))
    level = result.level
    return Profile(result.path, region.text, measure, region.distance,
                   level0_position(pts, result.scale), names, values, sigma,
                   f"voxel (level {level})" if level else "voxel", None if motion is None else motion.as_dict())


def stats(result, *, box=None, slab=None, mask=None, label=None, line=None, step=None, measure: str = DEFAULT_MEASURE,
          remove_rigid: bool = False, truth=None, confidence: float = 0.95, scheduler=None):
    """Region statistics or a profile of a result: what ``chunkdic stats`` prints.

    One region at most: ``box="z0:z1,y0:y1,x0:x1"``, ``slab="z=a:b"``, ``mask=PATH`` (``label=N``)
    or ``line="z,y,x:z,y,x"`` (``step``), all in level-0 voxels; none: the ROI.

    Returns
    -------
    RegionStats, or Profile for a line

    Examples
    --------
    >>> s = chunkdic.stats("result.zarr", box="8:40,8:40,8:40")  # doctest: +SKIP
    >>> s.row("E_zz").mean, (s.row("E_zz").low, s.row("E_zz").high)  # doctest: +SKIP
    """
    from ..results.scans import as_result

    result = as_result(result)
    region = region_of(result, box=box, slab=slab, mask=mask, label=label, line=line, step=step, scheduler=scheduler)
    if region.kind == "line":
        if truth is not None:
            raise InputError("--truth applies to region statistics, not to a profile")
        return profile(result, region, measure=measure, remove_rigid=remove_rigid)
    return region_stats(result, region, measure=measure, remove_rigid=remove_rigid, truth=truth,
                        confidence=confidence)
