"""Virtual extensometers: the elongation and strain between two points or two planes.

**Points** ``A``, ``B`` (level-0 voxels): the C8 field at each (trilinear, exact for the
field), the deformed gauge ``d = B − A + u(B) − u(A)`` and its elongation
``ΔL = |d| − |B − A|``, strain ``ΔL / |B − A|`` (engineering strain of the gauge), lengths in
the scan's unit when it has a voxel size. **Planes** normal to an axis (``z=a``, ``z=b``): the
mean displacement of each plane over the ROI's cross-section (the field at every node column,
on the plane), ``ΔL = ⟨u_z⟩(b) − ⟨u_z⟩(a)``, strain ``ΔL / (b − a)``: a clip-on extensometer
whose knives are planes.

Uncertainty: ``ΔL`` is linear in the nodal field to first order (``δΔL = d̂ · (δu(B) − δu(A))``,
``d̂`` the deformed gauge's direction), so its standard uncertainty is ``√(wᵀ C w)`` with the
solve's covariance (:mod:`chunkdic.analysis.covariance`): the two ends of a short gauge share
their noise, those of a long one under a long regularisation too. Over a loading series
(:func:`chunkdic.open_series`) the gauge reads every step's field from the reference
(cumulative, or composed, which holds no uncertainty: its interval is not given).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import asdict, dataclass, field
from statistics import NormalDist

import numpy as np

from ..errors import InputError
from ..mesh import level0_position, level_to_level
from .covariance import NodalCovariance, point_weights
from .regions import parse_point

__all__ = ["GaugeReading", "GaugeCurve", "gauge", "parse_plane"]


@dataclass
class GaugeReading:
    """One reading: ``length`` and ``elongation`` in ``unit``; ``strain`` dimensionless."""

    step: int
    length: float
    elongation: float
    sigma_elongation: float
    strain: float
    sigma_strain: float
    low: float
    high: float
    status: str = ""


@dataclass
class GaugeCurve:
    """Readings of one gauge over one result (one reading) or a loading series (one per step)."""

    source: str
    gauge: str
    unit: str
    confidence: float
    readings: list = field(default_factory=list)

    def as_dict(self) -> dict:
        d = asdict(self)
        d["readings"] = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()}
                         for r in d["readings"]]
        return d

    def csv(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf)
        names = list(GaugeReading.__dataclass_fields__)
        w.writerow(names)
        for r in self.readings:
            w.writerow([getattr(r, k) for k in names])
        return buf.getvalue()

    def text(self) -> str:
        pct = f"{100 * self.confidence:g} %"
        lines = [f"{self.source}: gauge {self.gauge} (lengths in {self.unit}; {pct} interval of the strain from "
                 "the solve's nodal covariance)",
                 f"{'step':>4}  {'length':>10}  {'elongation':>12}  {'σ':>9}  {'strain':>11}  "
                 f"{pct + ' interval':>26}  status"]
        for r in self.readings:
            lines.append(f"{r.step:>4}  {r.length:>10.4g}  {r.elongation:>+12.5g}  {r.sigma_elongation:>9.2g}  "
                         f"{r.strain:>+11.5f}  [{r.low:+.5f}, {r.high:+.5f}]  {r.status}")
        return "\n".join(lines)


def parse_plane(text: str) -> tuple[int, float]:
    """``"z=12.5"`` (also ``y=``, ``x=``; level-0 voxels) as ``(axis, position)``."""
    axis, _, at = str(text).replace(" ", "").partition("=")
    try:
        value = float(at)
    except ValueError:
        value = math.nan
    if axis not in ("z", "y", "x") or not math.isfinite(value):
        raise InputError(f"plane {text!r}: expected AXIS=POSITION with AXIS one of z, y, x (level-0 voxels)")
    return "zyx".index(axis), value


def _metric(result) -> tuple[np.ndarray, str]:
    """Length of a level-0 voxel per axis and its unit (1, "voxel" without a voxel size)."""
    if result.voxel_size is None:
        return np.ones(3), "level-0 voxels"
    return np.asarray(result.voxel_size, np.float64), result.unit or "unit"


def _node_box(result) -> tuple[np.ndarray, np.ndarray]:
    axes = [level0_position(a, result.scale) for a in result.mesh.node_axes()]
    return np.array([a[0] for a in axes]), np.array([a[-1] for a in axes])


def _check_inside(result, point, what: str) -> None:
    lo, hi = _node_box(result)
    p = np.asarray(point, np.float64)
    if np.any(p < lo - 1e-9) or np.any(p > hi + 1e-9):
        raise InputError(f"{what} ({', '.join(f'{v:g}' for v in p)}) lies outside the ROI (its nodes span "
                         f"({', '.join(f'{v:g}' for v in lo)}) to ({', '.join(f'{v:g}' for v in hi)}), level-0 voxels)")


def _points_gauge(result, a, b):
    """``(length, elongation, weights)`` of the gauge between level-0 points ``a``, ``b``."""
    metric, _ = _metric(result)
    mesh, s = result.mesh, result.scale
    pa, pb = (level_to_level(np.asarray(p, np.float64), 0, result.level) for p in (a, b))
    ua, ub = (mesh.evaluate(result.displacement, p.reshape(3, 1))[:, 0] * s for p in (pa, pb))  # level-0 voxels
    d0 = (np.asarray(b) - np.asarray(a)) * metric
    d = d0 + (ub - ua) * metric
    length = float(np.linalg.norm(d0))
    direction = d / np.linalg.norm(d)
    w = (point_weights(mesh, pb) - point_weights(mesh, pa))[None] * (s * metric * direction)[:, None, None, None]
    return length, float(np.linalg.norm(d)) - length, w


def _planes_gauge(result, axis: int, a: float, b: float):
    """``(length, elongation, weights)`` between the mean planes ``axis = a`` and ``axis = b``."""
    metric, _ = _metric(result)
    mesh, s, u = result.mesh, result.scale, result.displacement
    columns = [ax for k, ax in enumerate(mesh.node_axes()) if k != axis]
    grid = np.meshgrid(*columns, indexing="ij")
    means, weights = [], []
    for at in (a, b):
        p = np.empty((3,) + grid[0].shape)
        p[axis] = level_to_level(np.asarray(at, np.float64), 0, result.level)
        others = [k for k in range(3) if k != axis]
        p[others[0]], p[others[1]] = grid
        values = mesh.evaluate(u, p)[axis]
        ok = np.isfinite(values)
        if not ok.any():
            raise InputError(f"plane {'zyx'[axis]}={at:g} crosses no measured node")
        means.append(float(values[ok].mean()))
        w = np.zeros(mesh.nodes_shape)
        for q in np.argwhere(ok):
            w += point_weights(mesh, p[(slice(None),) + tuple(q)]) / ok.sum()
        weights.append(w)
    wfull = np.zeros((3,) + mesh.nodes_shape)
    wfull[axis] = (weights[1] - weights[0]) * s * metric[axis]
    return abs(b - a) * metric[axis], (means[1] - means[0]) * s * metric[axis] * np.sign(b - a), \
        wfull * np.sign(b - a)


def _reading(result, step: int, spec, z: float) -> GaugeReading:
    result.check_displacement()
    kind, args = spec
    if kind == "points":
        length, elongation, w = _points_gauge(result, *args)
    else:
        length, elongation, w = _planes_gauge(result, *args)
    sigma = math.nan
    if result.uncertainty is not None:
        try:
            sigma = math.sqrt(max(NodalCovariance.of_result(result).variance(w), 0.0))
        except InputError:
            pass
    strain, sig_strain = elongation / length, sigma / length
    return GaugeReading(step, length, elongation, sigma, strain, sig_strain, strain - z * sig_strain,
                        strain + z * sig_strain, str(result.info.get("status", "")))


def _spec(result, points, planes):
    if (points is None) == (planes is None):
        raise InputError("give the gauge as two --points or two --planes")
    if points is not None:
        pts = [parse_point(p) if isinstance(p, str) else tuple(float(v) for v in p) for p in points]
        if len(pts) != 2:
            raise InputError(f"a gauge has two points, got {len(pts)}")
        if np.allclose(pts[0], pts[1]):
            raise InputError("the gauge's two points coincide")
        for p, name in zip(pts, ("first point", "second point")):
            _check_inside(result, p, name)
        text = " to ".join("(" + ", ".join(f"{v:g}" for v in p) + ")" for p in pts)
        return ("points", tuple(pts)), text
    pl = [parse_plane(p) if isinstance(p, str) else (int(p[0]), float(p[1])) for p in planes]
    if len(pl) != 2:
        raise InputError(f"a plane gauge has two planes, got {len(pl)}")
    if pl[0][0] != pl[1][0]:
        raise InputError("the gauge's two planes must be normal to the same axis")
    axis = pl[0][0]
    if pl[0][1] == pl[1][1]:
        raise InputError("the gauge's two planes coincide")
    lo, hi = _node_box(result)
    for _, at in pl:
        if not lo[axis] - 1e-9 <= at <= hi[axis] + 1e-9:
            raise InputError(f"plane {'zyx'[axis]}={at:g} lies outside the ROI (its nodes span {lo[axis]:g} to "
                             f"{hi[axis]:g} along {'zyx'[axis]}, level-0 voxels)")
    return ("planes", (axis, pl[0][1], pl[1][1])), f"planes {'zyx'[axis]}={pl[0][1]:g} and {'zyx'[axis]}={pl[1][1]:g}"


def gauge(source, *, points=None, planes=None, confidence: float = 0.95) -> GaugeCurve:
    """Read a virtual extensometer on a result or over a loading series (module docstring).

    Parameters
    ----------
    source : Result, path of a result, or path of a loading series (``chunkdic series``)
    points : two points ``(z, y, x)`` or strings ``"z,y,x"``, level-0 voxels, keyword-only
    planes : two planes ``(axis, position)`` or strings ``"z=a"``, level-0 voxels, keyword-only
    confidence : float
        Of the strain's interval (default 0.95).

    Returns
    -------
    GaugeCurve
        One reading per step (step 0, the reference, reads 0 for a series).

    Raises
    ------
    InputError
        Points or planes outside the ROI, a series without steps, not two points or planes.

    Examples
    --------
    >>> chunkdic.gauge("result.zarr", points=["10,24,24", "38,24,24"]).readings[0].strain  # doctest: +SKIP
    """
    if not 0 < confidence < 1:
        raise InputError(f"confidence must lie between 0 and 1, got {confidence!r}")
    z = NormalDist().inv_cdf(0.5 + confidence / 2)
    steps, series = _steps(source)
    first = steps[0][1]
    spec, text = _spec(first, points, planes)
    metric, unit = _metric(first)
    curve = GaugeCurve(str(source.path if hasattr(source, "path") else source), text, unit, confidence)
    if series:  # the reference: the gauge's own length, no motion
        kind, args = spec
        length = (float(np.linalg.norm((np.asarray(args[1]) - np.asarray(args[0])) * metric)) if kind == "points"
                  else abs(args[2] - args[1]) * metric[args[0]])
        curve.readings.append(GaugeReading(0, length, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, "reference"))
    for k, res in steps:
        curve.readings.append(_reading(res, k, spec, z))
    return curve


def _steps(source) -> tuple[list, bool]:
    """``([(step, Result)], is a series)``: one result (step 1), or a series' fields from the reference."""
    from pathlib import Path

    from ..io.kinds import kind_of
    from ..results.scans import as_result

    if isinstance(source, (str, Path)) and kind_of(Path(source))[0] == "series":
        from .loadseries import open_series

        series = open_series(source)
        if not series.cumulative:
            raise InputError(f"series {source} has no step: nothing to read")
        return sorted(series.cumulative.items()), True
    return [(1, as_result(source))], False
