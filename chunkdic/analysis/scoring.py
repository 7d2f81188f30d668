"""One scoring rule for displacement fields measured by any DVC tool against a known truth.

A field measured by chunkdic (at its C8 nodes) or by another code (at its own grid points)
is scored the same way, so that the numbers of different tools compare:

- **Region.** Only points at least ``ell`` voxels from the volume's faces count. The faces
  are the outer faces of the outer voxels: voxel ``i`` has its centre at ``i``
  (shared/DESIGN.md), so along an axis of ``n`` voxels they sit at ``-0.5`` and
  ``n - 0.5``, and a point ``p`` is scored when ``p + 0.5 >= ell`` and
  ``n - 0.5 - p >= ell`` on all three axes. Local (subset) codes place no point nearer to
  the border than about half a subset, and C8 boundary nodes are 2–4× noisier than inner
  ones, so scoring the same region is what makes tools comparable.
- **Failures.** Inside that region, points whose displacement is not finite, or that the
  tool itself flags as failed (``valid=False``: not converged, rejected and replaced by
  interpolation, ...), are left out of the statistics and counted in ``n_failed``. They
  are never dropped without a count.
- **Statistics** of the error ``e = u - u_true`` over the remaining ``n`` points:
  per-component bias (mean of ``e``) and standard deviation (population, ``ddof=0``, as in
  :func:`chunkdic.analysis.metrology.uncertainty`); ``sigma`` pooled over the three components
  ``= sqrt(mean of the three variances)``; ``rms = sqrt(mean over points of |e|²)``
  (bias included); ``max_error = max |e|``.

``sigma`` measures the scatter (the a-priori uncertainty of the paper's section 4.2, where
the truth is a uniform translation); ``rms`` measures the whole error against a
non-uniform truth such as a compression band, bias and model error included.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from ..errors import InputError

__all__ = ["Score", "score_between_nodes", "score_displacement", "scored_region"]


@dataclass(frozen=True)
class Score:
    """Scores of one displacement field (all lengths in voxels of the reference).

    Attributes
    ----------
    n_points : int
        Points that entered the statistics (inside the region, finite, valid).
    n_failed : int
        Points inside the region left out because ``u`` was not finite or the tool
        flagged them (``valid=False``).
    n_outside : int
        Points nearer than ``ell`` to the volume's faces (not scored).
    bias : tuple of 3 float
        Mean error per component ``(z, y, x)``.
    std : tuple of 3 float
        Standard deviation of the error per component ``(z, y, x)`` (``ddof=0``).
    sigma : float
        ``sqrt(mean(std**2))``: the three components pooled.
    rms : float
        ``sqrt(mean |u - u_true|²)`` over the points (vector error, bias included).
    max_error : float
        Largest ``|u - u_true|`` (vector norm).
    """

    n_points: int
    n_failed: int
    n_outside: int
    bias: tuple[float, float, float]
    std: tuple[float, float, float]
    sigma: float
    rms: float
    max_error: float

    def as_dict(self) -> dict:
        """The scores as a JSON-serialisable dict (NaN stays NaN)."""
        d = asdict(self)
        d["bias"], d["std"] = list(self.bias), list(self.std)
        return d


def _as_points(a, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim < 1 or a.shape[0] != 3:
        raise InputError(f"{name} must have the component axis first, shape (3, ...), got {a.shape}")
    return a.reshape(3, -1)


def scored_region(points, volume_shape, ell: float) -> np.ndarray:
    """Which points lie at least ``ell`` voxels inside the volume's faces.

    Parameters
    ----------
    points : array_like, shape (3, N) or (3, nz, ny, nx), float, voxels
        Positions ``(z, y, x)`` in the reference scan (voxel ``i`` centred at ``i``).
    volume_shape : tuple of 3 int
        ``(nz, ny, nx)`` of the reference scan.
    ell : float, voxels
        Required distance to the faces at ``-0.5`` and ``n - 0.5``.

    Returns
    -------
    ndarray, shape (N,), bool
    """
    p = _as_points(points, "points")
    shape = np.asarray(volume_shape, dtype=np.float64).reshape(-1)
    if shape.size != 3 or np.any(shape < 1):
        raise InputError(f"volume_shape must be 3 positive integers (z, y, x), got {volume_shape!r}")
    if not np.isfinite(ell) or ell < 0:
        raise InputError(f"ell must be a non-negative number of voxels, got {ell!r}")
    tol = 1e-9  # a node exactly ell from the face counts, whatever the round-off
    lo = p + 0.5 >= ell - tol
    hi = (shape[:, None] - 0.5) - p >= ell - tol
    return np.all(lo & hi & np.isfinite(p), axis=0)


def score_displacement(points, u, u_true, volume_shape, ell: float, *, valid=None) -> Score:
    """Score a measured displacement field against the truth (module docstring: the rule).

    Parameters
    ----------
    points : array_like, shape (3, N) or (3, nz, ny, nx), float, voxels
        Positions ``(z, y, x)`` of the measurement points in the reference scan.
    u : array_like, same shape as ``points``, float, voxels
        Measured displacement ``(Uz, Uy, Ux)`` with ``f(X) = g(X + u(X))``.
    u_true : array_like, shape like ``u`` or (3,), float, voxels
        True displacement at the same points (``(3,)``: a uniform translation).
    volume_shape : tuple of 3 int
        ``(nz, ny, nx)`` of the reference scan.
    ell : float, voxels
        Only points at least ``ell`` from the volume's faces are scored (use the element
        size / node spacing of the comparison).
    valid : array_like of bool, shape (N,) or ``points.shape[1:]``, optional
        ``False`` where the tool reports a failure; such points are counted in
        ``n_failed``, not scored. Default: all valid.

    Returns
    -------
    Score
        With ``n_points == 0`` the statistics are NaN.

    Examples
    --------
    >>> pts = np.array([[20.0, 40.0], [20.0, 40.0], [20.0, 40.0]])
    >>> s = score_displacement(pts, [[0.6, 0.4], [0.5, 0.5], [0.5, 0.5]], (0.5, 0.5, 0.5), (64, 64, 64), 16)
    >>> round(s.rms, 3), s.n_points
    (0.1, 2)
    """
    p = _as_points(points, "points")
    uu = _as_points(u, "u")
    if uu.shape != p.shape:
        raise InputError(f"u has {uu.shape[1]} points, points has {p.shape[1]}")
    t = np.asarray(u_true, dtype=np.float64)
    t = np.broadcast_to(t.reshape(3, 1), p.shape) if t.shape == (3,) else _as_points(t, "u_true")
    if t.shape != p.shape:
        raise InputError(f"u_true has {t.shape[1]} points, points has {p.shape[1]}")
    ok = np.ones(p.shape[1], dtype=bool)
    if valid is not None:
        ok = np.asarray(valid, dtype=bool).reshape(-1)
        if ok.size != p.shape[1]:
            raise InputError(f"valid has {ok.size} entries, points has {p.shape[1]}")
    inside = scored_region(p, volume_shape, ell)
    good = inside & ok & np.all(np.isfinite(uu), axis=0) & np.all(np.isfinite(t), axis=0)
    n = int(good.sum())
    n_failed = int((inside & ~good).sum())
    n_outside = int((~inside).sum())
    if n == 0:
        nan3 = (float("nan"),) * 3
        return Score(0, n_failed, n_outside, nan3, nan3, float("nan"), float("nan"), float("nan"))
    e = uu[:, good] - t[:, good]
    bias, std = e.mean(axis=1), e.std(axis=1)
    norm2 = (e * e).sum(axis=0)
    return Score(
        n_points=n,
        n_failed=n_failed,
        n_outside=n_outside,
        bias=tuple(float(v) for v in bias),
        std=tuple(float(v) for v in std),
        sigma=float(np.sqrt((std ** 2).mean())),
        rms=float(np.sqrt(norm2.mean())),
        max_error=float(np.sqrt(norm2.max())),
    )


def _grid_interpolate(axes, u: np.ndarray, positions) -> np.ndarray:
    """Trilinear interpolation of a nodal field on the grid ``axes`` at the grid ``positions``
    (both sequences of 3 increasing 1-D arrays), one axis at a time; NaN nodes spread to the
    cells that touch them."""
    out = np.asarray(u, np.float64)
    for axis in (2, 1, 0):
        a, p = np.asarray(axes[axis], np.float64), np.asarray(positions[axis], np.float64)
        if a.size == 1:
            out = np.take(out, np.zeros(p.size, np.int64), axis=axis + 1)
            continue
        k = np.clip(np.searchsorted(a, p, side="right") - 1, 0, a.size - 2)
        w = ((p - a[k]) / (a[k + 1] - a[k])).reshape([-1 if i == axis + 1 else 1 for i in range(4)])
        out = np.take(out, k, axis=axis + 1) * (1.0 - w) + np.take(out, k + 1, axis=axis + 1) * w
    return out


def _points_interpolate(axes, u: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Trilinear interpolation of a nodal field on the grid ``axes`` at scattered points
    ``pts`` (3, N) inside its hull: (3, N). NaN nodes spread to the cells that touch them,
    as in :func:`_grid_interpolate`."""
    k, w = [], []
    for a, p in zip(axes, pts):
        a = np.asarray(a, np.float64)
        if a.size == 1:
            k.append(np.zeros(p.size, np.int64)); w.append(np.zeros(p.size)); continue
        i = np.clip(np.searchsorted(a, p, side="right") - 1, 0, a.size - 2)
        k.append(i); w.append((p - a[i]) / (a[i + 1] - a[i]))
    out = np.zeros((3, pts.shape[1]))
    for c in np.ndindex(2, 2, 2):
        idx = [np.minimum(ki + ci, ax.size - 1) for ki, ci, ax in zip(k, c, axes)]
        wt = np.prod([wi if ci else 1.0 - wi for wi, ci in zip(w, c)], axis=0)
        out += u[:, idx[0], idx[1], idx[2]] * wt
    return out


def score_between_nodes(node_axes, u, u_true, volume_shape, ell: float, *,
                        slab_voxels: int = 2**21, sample: int | None = None, seed: int = 0) -> Score:
    """Score a nodal field *between* its nodes: trilinear on the node grid (as a viewer shows
    it, and as the C8 basis defines it) at every voxel centre at least ``ell`` from the faces.

    The rule for every tool alike: nodal-only scores flatter a C8 field on short
    waves (its L2 fit overshoots at the nodes) and hide what a user sees between them.
    Voxels outside the node grid's hull are not scored (``n_outside``); voxels in a cell with
    a NaN node count as failed.

    Parameters
    ----------
    node_axes : sequence of 3 1-D arrays, float, voxels
        Node positions along ``z, y, x`` (a regular grid: chunkdic's ``Mesh.node_axes()``
        converted to level 0, or a local code's grid), increasing.
    u : array_like, shape (3, nz, ny, nx), float, voxels
        Nodal displacement ``(Uz, Uy, Ux)``.
    u_true : callable or Field
        ``u_true(z, y, x)`` (or ``u_true.displacement``) on broadcast 1-D axes, returning
        shape ``(3, gz, gy, gx)``.
    volume_shape : tuple of 3 int
    ell : float, voxels
        Voxels nearer than ``ell`` to a face are not scored.
    slab_voxels : int, optional
        Voxels evaluated at once (z slabs of whole planes; at least one plane): memory
        ~120 B per voxel, whatever the region's size. The score does not depend on it.
    sample : int, optional
        Score ``sample`` voxel centres drawn uniformly (with replacement, generator ``seed``)
        from the scored voxels instead of all of them, when there are more: a 1024³ region
        is 10⁹ voxels, ~10 min of NumPy per score. The same ``sample``, ``seed`` and region
        draw the same voxels for every tool. ``n_outside`` still counts every voxel.

    Returns
    -------
    Score
        Over the scored voxels (``n_points`` voxels, not nodes).
    """
    shape = tuple(int(n) for n in volume_shape)
    axes = [np.asarray(a, np.float64).reshape(-1) for a in node_axes]
    uu = np.asarray(u, np.float64)
    if uu.shape != (3,) + tuple(a.size for a in axes):
        raise InputError(f"u has shape {uu.shape}, the node axes need {(3,) + tuple(a.size for a in axes)}")
    tol = 1e-9
    vox, region = [], []
    for a, n in zip(axes, shape):
        i = np.arange(n, dtype=np.float64)
        near = (i + 0.5 >= ell - tol) & ((n - 0.5) - i >= ell - tol)
        region.append(int(near.sum()))
        vox.append(i[near & (i >= a[0] - tol) & (i <= a[-1] + tol)])
    outside = int(np.prod(region)) - int(np.prod([v.size for v in vox]))
    if min(v.size for v in vox) == 0:
        nan3 = (float("nan"),) * 3
        return Score(0, 0, outside, nan3, nan3, float("nan"), float("nan"), float("nan"))
    fn = u_true.displacement if hasattr(u_true, "displacement") else u_true
    if sample is not None and int(sample) < math.prod(v.size for v in vox):
        rng = np.random.default_rng(seed)
        pts = np.stack([v[rng.integers(0, v.size, int(sample))] for v in vox])
        field = _points_interpolate(axes, uu, pts)
        truth = np.asarray(fn(*pts), np.float64)
        return replace(score_displacement(pts, field, truth, shape, ell), n_outside=outside)
    # z slabs of at most ``slab_voxels`` voxels: a 1024³ region is 10⁹ voxels, tens of GB of
    # float64 points, field and truth if scored at once
    plane = vox[1].size * vox[2].size
    step = max(1, int(slab_voxels) // plane)
    scores = []
    for z0 in range(0, vox[0].size, step):
        sv = [vox[0][z0:z0 + step], vox[1], vox[2]]
        field = _grid_interpolate(axes, uu, sv)
        truth = np.asarray(fn(sv[0][:, None, None], sv[1][None, :, None], sv[2][None, None, :]), np.float64)
        pts = np.stack(np.meshgrid(*sv, indexing="ij"))
        scores.append(score_displacement(pts, field, truth, shape, ell))
    return replace(_pooled(scores), n_outside=outside)


def _pooled(scores: list[Score]) -> Score:
    """One score of the union of disjoint point sets from each set's score (means, variances
    and mean squares combined by their counts; the population variance of the union is the
    counts' mean of each set's variance plus the spread of the sets' means)."""
    done = [s for s in scores if s.n_points > 0]
    failed = sum(s.n_failed for s in scores)
    if not done:
        nan3 = (float("nan"),) * 3
        return Score(0, failed, 0, nan3, nan3, float("nan"), float("nan"), float("nan"))
    n = np.array([s.n_points for s in done], np.float64)
    bias = np.array([s.bias for s in done])
    var = np.array([s.std for s in done]) ** 2
    mean = (n[:, None] * bias).sum(axis=0) / n.sum()
    pooled_var = (n[:, None] * (var + (bias - mean) ** 2)).sum(axis=0) / n.sum()
    std = np.sqrt(pooled_var)
    rms = math.sqrt(float((n * np.array([s.rms for s in done]) ** 2).sum() / n.sum()))
    return Score(n_points=int(n.sum()), n_failed=failed, n_outside=0,
                 bias=tuple(float(b) for b in mean), std=tuple(float(v) for v in std),
                 sigma=float(np.sqrt(pooled_var.mean())), rms=rms,
                 max_error=max(s.max_error for s in done))
