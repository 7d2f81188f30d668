"""The rigid motion of a result's nodes: fitted, reported with its uncertainty, removed.

A specimen that turns by 2° in the machine shows a small strain of ``cos 2° − 1 ≈ −6e-4``
(small strain) and a displacement field dominated by the turn. :func:`fit_rigid` finds the
least-squares rigid motion ``x = R (X − c) + c + t`` of the measured nodes (``X`` the node,
``x = X + u(X)``; nodes not measured, masked or flagged weak are left out) by the Kabsch
(Umeyama without scale) solution: with ``p_i = X_i − c`` and ``q_i = x_i − c − t`` centred on
the two centroids, ``R = V diag(1, 1, det(V Uᵀ)) Uᵀ`` from the SVD ``Σ p_i q_iᵀ = U S Vᵀ``. The
rotation is finite, not linearised: 10° is found to 1e-3°. The fit runs in physical
coordinates when the scan has a voxel size (a rotation is not one in voxels that are not
cubes).

:func:`remove_rigid` gives the field without it, ``u'(X) = Rᵀ (X + u(X) − c − t) + c − X``:
``F' = Rᵀ F``, so the Green–Lagrange strain is unchanged and the small strain loses the
rotation's ``cos θ − 1``.

Uncertainty: the motion is linearised about the fit, ``δt = mean δu`` and
``δω = I⁻¹ Σ q_i × δu_i`` (``I = Σ |q_i|² 1 − q_i q_iᵀ``), so ``(t, ω)`` are weighted sums of
the nodal field, whose 6×6 covariance comes from the solve
(:class:`chunkdic.analysis.covariance.NodalCovariance`); the angle and axis follow by the
Jacobian of ``ω ↦ (angle, axis)`` of ``exp([ω]×) R``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..results.result import FLAG_MASKED, FLAG_NO_DATA, FLAG_WEAK, Result

__all__ = ["RigidMotion", "fit_rigid", "remove_rigid", "kabsch", "axis_angle", "rotation_matrix"]


def rotation_matrix(axis, angle_degrees: float) -> np.ndarray:
    """Rotation about ``axis`` (any length) by ``angle`` degrees (Rodrigues), right-handed in
    the order of ``axis``'s components."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    t = math.radians(angle_degrees)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K


def axis_angle(R: np.ndarray) -> tuple[np.ndarray, float]:
    """Unit axis and angle (degrees, in [0, 180]) of a rotation matrix, right-handed in the
    order of its rows; axis ``(0, 0, 1)`` for the identity."""
    R = np.asarray(R, np.float64)
    angle = math.degrees(math.acos(float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if np.linalg.norm(v) > 1e-12:
        return v / np.linalg.norm(v), angle
    if angle < 90:
        return np.array([0.0, 0.0, 1.0]), angle
    w, vecs = np.linalg.eigh(0.5 * (R + R.T))  # 180°: the axis is the eigenvector of eigenvalue 1
    return vecs[:, int(np.argmax(w))], angle


def kabsch(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """The rotation ``R`` minimising ``Σ |R p_i − q_i|²`` of centred point sets (N, 3)."""
    U, _, Vt = np.linalg.svd(P.T @ Q)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


#: the order (z, y, x) -> (x, y, z): rotations reported in the right-handed frame of ParaView
_XYZ = np.array([[0, 0, 1], [0, 1, 0], [1, 0, 0]], np.float64)


@dataclass(frozen=True)
class RigidMotion:
    """A fitted rigid motion ``x = R (X − c) + c + t`` and its uncertainty.

    Attributes
    ----------
    rotation : ndarray, shape (3, 3)
        ``R`` acting on ``(z, y, x)`` vectors (physical, or level voxels without a voxel size).
    translation : ndarray, shape (3,)
        ``t``, the displacement of the centroid ``c``, voxels of the result's level ``(z, y, x)``.
    centre : ndarray, shape (3,)
        ``c``, the centroid of the fitted nodes, voxels of the result's level.
    angle : float
        Rotation angle, degrees.
    axis_xyz : ndarray, shape (3,)
        Unit axis ``(x, y, z)``: the rotation is right-handed about it in the frame of
        ParaView and the VTK export.
    translation_sigma : ndarray, shape (3,)
        Standard uncertainty of ``t``, voxels of the level (NaN without a per-node uncertainty).
    angle_sigma, axis_sigma : float
        Standard uncertainty of the angle and the axis's direction, degrees.
    nodes : int
        Nodes in the fit.
    metric : ndarray, shape (3,)
        Length of a level voxel along ``(z, y, x)`` in the fit's coordinates (the voxel size
        in ``unit``, or 1).
    unit : str or None
    """

    rotation: np.ndarray
    translation: np.ndarray
    centre: np.ndarray
    angle: float
    axis_xyz: np.ndarray
    translation_sigma: np.ndarray
    angle_sigma: float
    axis_sigma: float
    nodes: int
    metric: np.ndarray
    unit: str | None = None

    def displacement(self, X: np.ndarray) -> np.ndarray:
        """The rigid motion's displacement at positions ``X`` (3, ...), voxels of the level."""
        m = self.metric.reshape((3,) + (1,) * (X.ndim - 1))
        c = (self.centre * self.metric).reshape(m.shape)
        t = (self.translation * self.metric).reshape(m.shape)
        p = X * m - c
        return (np.einsum("ij,j...->i...", self.rotation, p) + c + t) / m - X

    def as_dict(self) -> dict:
        """JSON-friendly dict (arrays as lists)."""
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in dataclasses.asdict(self).items()}

    def text(self) -> str:
        """Two lines for people: the translation and the rotation with their uncertainties."""
        t = ", ".join(f"{v:+.4f} ± {s:.4f}" for v, s in zip(self.translation, self.translation_sigma))
        a = ", ".join(f"{v:+.4f}" for v in self.axis_xyz)
        axis = f"about the axis (x, y, z) ({a}) ± {self.axis_sigma:.3f} deg"
        if self.angle < 2 * self.angle_sigma:  # the axis of a rotation lost in its noise means nothing
            axis = "(no axis: the angle is within twice its uncertainty)"
        return (f"rigid motion of {self.nodes} nodes (least squares, Kabsch; ± one standard uncertainty):\n"
                f"  translation (Uz, Uy, Ux) of the centroid ({', '.join(f'{v:.1f}' for v in self.centre)}): "
                f"({t}) voxels of the level\n"
                f"  rotation {self.angle:.4f} ± {self.angle_sigma:.4f} deg {axis}")


def fitted_nodes(result: Result) -> np.ndarray:
    """The nodes a rigid fit uses: measured (finite) and not flagged; shape (nz, ny, nx), bool."""
    use = np.isfinite(result.displacement).all(axis=0)
    if result.flags is not None:
        use &= (result.flags & (FLAG_NO_DATA | FLAG_MASKED | FLAG_WEAK)) == 0
    return use


def _metric(result: Result) -> tuple[np.ndarray, str | None]:
    length = result.voxel_length()
    return (np.ones(3), None) if length is None else (np.asarray(length, np.float64), result.unit)


def fit_rigid(result: Result, *, covariance=None) -> RigidMotion:
    """Least-squares rigid motion of the measured nodes (module docstring).

    Parameters
    ----------
    result : Result
    covariance : NodalCovariance, optional
        The field's covariance (default: :meth:`NodalCovariance.of_result`; without a per-node
        uncertainty the uncertainties are NaN).

    Raises
    ------
    InputError
        Fewer than 3 nodes that are not on one line.
    """
    from .covariance import NodalCovariance

    use = fitted_nodes(result)
    metric, unit = _metric(result)
    m = metric[:, None]
    X = result.node_coords[:, use] * m
    x = X + result.displacement[:, use] * m
    if X.shape[1] < 3 or np.linalg.matrix_rank(X.T - X.mean(axis=1)) < 2:
        raise InputError(f"result {result.path}: the rigid motion needs at least 3 measured nodes not on a line")
    c, cx = X.mean(axis=1), x.mean(axis=1)
    R = kabsch((X.T - c), (x.T - cx))
    axis, angle = axis_angle(_XYZ @ R @ _XYZ)
    motion = RigidMotion(R, (cx - c) / metric, c / metric, angle, axis, np.full(3, np.nan), math.nan, math.nan,
                         int(use.sum()), metric, unit)
    if covariance is None and result.uncertainty is not None:
        try:
            covariance = NodalCovariance.of_result(result)
        except InputError:
            covariance = None
    if covariance is None:
        return motion
    cov = covariance.covariance(fit_weights(result, motion))
    ts = np.sqrt(np.diag(cov)[:3]) / metric
    angle_sigma, axis_sigma = _angle_axis_sigma(R, cov[3:, 3:])
    return dataclasses.replace(motion, translation_sigma=ts, angle_sigma=angle_sigma, axis_sigma=axis_sigma)


def _levers(result: Result, motion: RigidMotion, use: np.ndarray) -> np.ndarray:
    """``q_i = R (X_i − c)`` of the fitted nodes, (N, 3), fit coordinates."""
    m = motion.metric[:, None]
    return (motion.rotation @ (result.node_coords[:, use] * m - (motion.centre * motion.metric)[:, None])).T


def fit_weights(result: Result, motion: RigidMotion) -> list[np.ndarray]:
    """The weight fields (3, nz, ny, nx) of ``(t_z, t_y, t_x, ω_z, ω_y, ω_x)`` on the nodal field:
    ``t`` in fit units (voxel size × level voxels), ``ω`` in radians (the linearised fit)."""
    use = fitted_nodes(result)
    q = _levers(result, motion, use)
    inertia = (q * q).sum() * np.eye(3) - q.T @ q
    g = np.linalg.inv(inertia)
    out = []
    for k in range(3):
        w = np.zeros((3,) + use.shape)
        w[k][use] = motion.metric[k] / use.sum()
        out.append(w)
    for k in range(3):
        w = np.zeros((3,) + use.shape)
        w[:, use] = (np.cross(g[k][None, :], q) * motion.metric[None, :]).T  # g_k × q_i, on δu in level voxels
        out.append(w)
    return out


def _angle_axis_sigma(R: np.ndarray, cov_w: np.ndarray) -> tuple[float, float]:
    """Standard uncertainty (degrees) of the angle and the axis direction of ``exp([ω]×) R``."""
    axis0, angle0 = axis_angle(_XYZ @ R @ _XYZ)
    h = 1e-6
    J = np.zeros((4, 3))
    for k in range(3):
        w = np.zeros(3)
        w[k] = h
        K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        axis, angle = axis_angle(_XYZ @ ((np.eye(3) + K + K @ K / 2) @ R) @ _XYZ)
        J[0, k] = math.radians(angle - angle0) / h
        J[1:, k] = (axis - axis0) / h
    c = J @ cov_w @ J.T
    return math.degrees(math.sqrt(max(c[0, 0], 0.0))), math.degrees(math.sqrt(max(np.trace(c[1:, 1:]), 0.0)))


def remove_rigid(result: Result, motion: RigidMotion | None = None) -> Result:
    """The result with the rigid motion removed: ``u'(X) = Rᵀ (X + u(X) − c − t) + c − X``.

    Returns
    -------
    Result
        A copy (same path, mesh and per-node uncertainty) whose ``info["rigid_removed"]``
        holds the motion (:meth:`RigidMotion.as_dict`); its element strains are recomputed
        on demand. Nodes not measured stay NaN.
    """
    motion = fit_rigid(result) if motion is None else motion
    m = motion.metric[:, None, None, None]
    X = result.node_coords * m
    x = X + result.displacement * m
    c = (motion.centre * motion.metric)[:, None, None, None]
    t = (motion.translation * motion.metric)[:, None, None, None]
    u = (np.einsum("ji,j...->i...", motion.rotation, x - c - t) + c - X) / m
    info = {**result.info, "rigid_removed": motion.as_dict()}
    return dataclasses.replace(result, displacement=u, info=info, strain=None)


def effective_weights(result: Result, motion: RigidMotion, w: np.ndarray) -> np.ndarray:
    """Weights on the measured field of the functional ``Σ w · u'`` of the rigid-free field ``u'``.

    Linearised: ``δu'_i = Rᵀ (δu_i − δt − δω × q_i)`` (fit coordinates, ``q_i = x_i − c − t``)
    with ``(δt, δω)`` themselves weighted sums of ``δu`` (:func:`fit_weights`), so the
    uncertainty of a statistic of ``u'`` counts that the rigid motion was estimated from the
    same nodes.
    """
    mm = motion.metric[:, None, None, None]
    v = np.einsum("ij,j...->i...", motion.rotation, w / mm)  # on δu' in fit coordinates -> on δ(u - rigid)
    c = (motion.centre * motion.metric + motion.translation * motion.metric)[:, None, None, None]
    q = result.node_coords * mm + np.nan_to_num(result.displacement) * mm - c
    modes = [float(np.sum(v[k])) for k in range(3)]
    modes += [float(np.sum(v * np.cross(np.eye(3)[k][:, None, None, None], q, axis=0))) for k in range(3)]
    out = v * mm
    for coef, lw in zip(modes, fit_weights(result, motion)):
        out = out - coef * lw
    return out
