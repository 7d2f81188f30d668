"""Global 2-D DIC on bilinear Q4 elements: the engine's 2-D sibling (paper section 5.3).

The paper checks a 3-D result by running a *two-dimensional* global correlation (Q4-DIC)
on mid-plane cuts of the reference and of the corrected deformed volume (see
:mod:`chunkdic.cutcheck`). This module is that 2-D code, usable on its own on two images.
It keeps every convention of the C8 engine (shared/DESIGN.md, docs/architecture.md), with
one axis less:

- arrays indexed ``(y, x)``; vector fields ``(2, ny, nx)``, components ``(y, x)``;
- pixel ``i`` has its centre at ``i``; a pixel of pyramid level ``s`` (sum of ``2^s × 2^s``
  pixels) has its centre at level-0 coordinate ``2^s j + (2^s - 1) / 2``;
- ``f(X) = g(X + u(X))``, residual ``r = f(X) - g(X + u(X))``, gap
  ``R = rms(r) / (max f - min f)`` over the ROI;
- element ``k`` along an axis covers pixels ``o + k ell … o + (k+1) ell - 1``, node ``k`` sits
  at ``o + k ell - 0.5``, so every pixel belongs to one element and ``M``, ``b`` are exact
  sums over pixels; local node ``a = 2 dy + dx``;
- coarse-to-fine pyramid of 2×2 sums (up to 3 levels above the correlated one while the
  ROI spans 24 pixels, the same element edge on every level), a rigid translation on the
  coarsest level (phase correlation, then the rigid restriction of ``M``), then modified
  Gauss–Newton per level: ``M`` built once from the reference gradient (centred
  differences), ``b`` re-assembled each iteration, the engine's stopping rule
  (:mod:`chunkdic.method.gauss_newton`: converged, stalled, diverged, max-iterations);
- cubic B-spline interpolation of ``g`` (``linear`` by option); pixels whose ``X + u(X)``
  leaves ``0 … n-1`` (or meets a NaN of ``g``) are dropped from ``b`` and counted.

Not out of core, on purpose: a 2-D image is small (2048² float32 is 16 MB), so the whole
image sits in memory, ``scipy.ndimage`` does the B-spline, and ``M`` (sparse, a few
hundred thousand unknowns at most) is factorised once per level by SuperLU and reused.
No brightness model and no regularisation: the paper's Q4 check compares images that the
3-D engine has already low-passed and corrected for brightness.

The Q4 mesh of each level, the image pyramid and the image reader are in
:mod:`chunkdic.analysis.q4mesh`; this module is the solver and its driver.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..passes.translation import phase_correlation
from ..method.stopping import (  # the engine's stopping rule, shared on purpose
    State,
    decide,
    noise_step_of,
)
from ..errors import InputError
from ..inputs import number
from ..mesh import level_to_level
from .q4mesh import Mesh2D, plan2d, pyramid2d

__all__ = ["Q4Result", "correlate2d"]


@dataclass
class Q4Result:
    """Outcome of :func:`correlate2d`.

    Attributes
    ----------
    displacement : ndarray, shape (2, ny, nx), float64, pixels
        Nodal displacement, components ``(y, x)`` (``Uy, Ux``), in pixels of the input
        images (level 0).
    node_coords : ndarray, shape (2, ny, nx), float64, pixels
        Node positions.
    mesh : Mesh2D
        The mesh of level 0.
    status : str
        ``converged``, ``stalled``, ``diverged`` or ``max-iterations`` (the engine's rule).
    gap, initial_gap : float
        Matching gap of the returned field and of ``u = 0`` on level 0 (dimensionless).
    excluded : int
        Level-0 ROI pixels left out of the last pass (``X + u`` outside ``g`` or on a NaN).
    history : list of dict
        One row per pass: ``level``, ``iteration`` (negative: rigid steps), ``gap``,
        ``max_delta`` (NaN for the final evaluation), ``excluded``.
    levels : list of int
        Pyramid levels correlated, coarsest first.
    seconds : float
    """

    displacement: np.ndarray
    node_coords: np.ndarray
    mesh: Mesh2D
    status: str
    gap: float
    initial_gap: float
    excluded: int
    history: list[dict] = field(default_factory=list)
    levels: list[int] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def converged(self) -> bool:
        return self.status == "converged"

    def summary(self) -> dict:
        """JSON-ready summary (means and spread of each component, pixels)."""
        u = self.displacement.reshape(2, -1)
        return {"status": self.status, "element_size": self.mesh.element_size,
                "nodes": list(self.mesh.nodes_shape),
                "roi": [[r.start, r.stop] for r in self.mesh.roi], "levels": self.levels,
                "mean": {c: float(np.mean(v)) for c, v in zip("yx", u)},
                "std": {c: float(np.std(v)) for c, v in zip("yx", u)},
                "gap": self.gap, "initial_gap": self.initial_gap, "excluded_pixels": self.excluded,
                "iterations": sum(1 for h in self.history if h["iteration"] >= 0), "seconds": self.seconds}


# --------------------------------------------------------------------------- one level


@dataclass
class _Pass:
    b: np.ndarray
    gap: float
    n_excluded: int
    n_valid: int


class _Level:
    """One pyramid level: ``M`` factorised once, ``b`` and the gap of any nodal field."""

    def __init__(self, f: np.ndarray, g: np.ndarray, mesh: Mesh2D, interpolation: str):
        self.mesh = mesh
        self.order = 3 if interpolation == "cubic" else 1
        roi = mesh.roi
        # gradient of f: centred differences, one-sided at the image border (as the engine)
        grads = np.gradient(np.nan_to_num(f), edge_order=1)
        self.f = f[roi].ravel()
        f_bad = ~np.isfinite(self.f)
        self.f = np.where(f_bad, 0.0, self.f)
        fy, fx = (np.where(f_bad, 0.0, gr[roi].ravel()) for gr in grads)
        self.f_ok = ~f_bad
        finite = self.f[self.f_ok]
        self.range = float(finite.max() - finite.min()) if finite.size else 0.0
        # g: NaN pixels (outside a 3-D ROI, say) masked with the interpolation stencil's reach
        g_bad = ~np.isfinite(g)
        self.g_bad = ndi.binary_dilation(g_bad, iterations=2) if g_bad.any() else None
        g = np.where(g_bad, np.nanmean(g) if (~g_bad).any() else 0.0, g)
        self.g_shape = g.shape
        # B-spline coefficients once per level (in memory: a 2-D image is small)
        self.g = ndi.spline_filter(g, order=3, mode="mirror") if self.order == 3 else g
        phi = mesh.shape_matrix()
        self.phi = phi
        self.L = sp.hstack([sp.diags(fy) @ phi, sp.diags(fx) @ phi], format="csr")
        M = (self.L.T @ self.L).tocsc()
        # a small ridge keeps a node without texture (M nearly singular) finite; a node with
        # almost no pixels (< 1 % of the mean diagonal: a corner of a specimen mask's cut) is
        # held where it is, so that it cannot keep the iterations from converging
        mean_diag = max(float(M.diagonal().mean()), 1e-30)
        ridge = 1e-9 * mean_diag + np.where(M.diagonal() < 0.01 * mean_diag, mean_diag, 0.0)
        self.M = M
        self.solve = spla.factorized((M + sp.diags(ridge)).tocsc())
        n = phi.shape[1]
        blocks = [[M[i * n:(i + 1) * n, j * n:(j + 1) * n].sum() for j in range(2)] for i in range(2)]
        self.rigid = np.array(blocks)  # Σ_a N_a = 1: the rigid 2×2 system is the sum of M's blocks
        Y, X = np.meshgrid(*(np.arange(r.start, r.stop, dtype=np.float64) for r in roi), indexing="ij")
        self.X = (Y.ravel(), X.ravel())

    def assemble(self, u: np.ndarray) -> _Pass:
        """``b`` (2 n nodes), gap and pixel counts of the nodal field ``u`` (2, ny, nx)."""
        pos = [x + self.phi @ c.ravel() for x, c in zip(self.X, u)]
        valid = self.f_ok.copy()
        for p, n in zip(pos, self.g_shape):
            valid &= (p >= 0) & (p <= n - 1)
        if self.g_bad is not None:
            near = [np.clip(np.rint(p), 0, n - 1).astype(np.int64) for p, n in zip(pos, self.g_shape)]
            valid &= ~self.g_bad[near[0], near[1]]
        gv = ndi.map_coordinates(self.g, pos, order=self.order, mode="mirror", prefilter=False)
        r = np.where(valid, self.f - gv, 0.0)
        n_valid = int(valid.sum())
        gap = math.sqrt(float(r @ r) / n_valid) / self.range if n_valid and self.range > 0 else math.inf
        return _Pass(self.L.T @ r, gap, int(valid.size - n_valid), n_valid)


def _iterate(lvl: _Level, u: np.ndarray, tolerance: float, max_iterations: int, s: int,
             history: list[dict]) -> State:
    """Modified Gauss–Newton on one level with the engine's stopping rule."""
    state = State(u=u)
    n = lvl.phi.shape[1]
    diag = lvl.M.diagonal()
    measured = diag > 0
    while state.status is None:
        p = lvl.assemble(state.u)
        if math.isfinite(p.gap):
            state.record(p, None)
        decide(state, p.gap, tolerance, max_iterations)
        row = dict(level=s, iteration=state.iteration, gap=p.gap, max_delta=math.nan, excluded=p.n_excluded)
        if state.status is None:
            delta = lvl.solve(p.b)
            # the increment in units of the field's own uncertainty, sigma_u^2 ~ sigma_r^2 / M_ii (the
            # diagonal bound the 3-D engine uses): the stopping rule ends a level whose increments
            # stay at the noise level as converged (chunkdic.method.stopping)
            sigma_r2 = (p.gap * lvl.range) ** 2
            if sigma_r2 > 0 and measured.any():
                q, unsettled = noise_step_of(delta[measured][:, None], (sigma_r2 / diag[measured])[:, None], tolerance)
                state.note_noise_step(q, fraction=float(unsettled.mean()))
            state.step(np.stack([delta[:n], delta[n:]], axis=-1).reshape(*lvl.mesh.nodes_shape, 2))
            row["max_delta"] = state.last_delta
        history.append(row)
    return state


def _rigid(lvl: _Level, t: np.ndarray, tolerance: float, max_iterations: int, s: int,
           history: list[dict]) -> np.ndarray:
    """Sub-pixel refinement of a uniform translation with the rigid restriction of ``M``."""
    n = lvl.phi.shape[1]
    ones = np.ones((2,) + lvl.mesh.nodes_shape)
    for it in range(max_iterations):
        p = lvl.assemble(t[:, None, None] * ones)
        delta = np.linalg.solve(lvl.rigid, [p.b[:n].sum(), p.b[n:].sum()])
        history.append(dict(level=s, iteration=-1 - it, gap=p.gap, max_delta=float(np.abs(delta).max()),
                            excluded=p.n_excluded))
        t = t + delta
        if np.abs(delta).max() < tolerance:
            break
    return t


# --------------------------------------------------------------------------- driver


def _image(a, name: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 2 or min(a.shape) < 2:
        raise InputError(f"{name} must be a 2-D image, got shape {a.shape}")
    if a.dtype == bool:
        raise InputError(f"{name} is a two-level (bool) image: it has no sub-pixel information; correlate the "
                         "grey-level image it was segmented from")
    if a.dtype.kind not in "uif":
        raise InputError(f"{name} has dtype {a.dtype}: expected numbers")
    return a.astype(np.float64)

def correlate2d(ref, deformed, *, element_size: int, roi=None, coarsest: int | None = None,
                interpolation: str = "cubic", smoothing: float = 0.0, tolerance: float = 1e-3,
                coarse_tolerance: float = 1e-2, max_iterations: int = 30) -> Q4Result:
    """Measure the displacement field between two images by multiscale Q4-DIC.

    Parameters
    ----------
    ref, deformed : array_like, shape (ny, nx) and (my, mx)
        Reference ``f`` and deformed ``g`` images (any numeric dtype; NaN pixels of ``g``
        are never used, NaN pixels of ``f`` are left out). ``f(X) = g(X + u(X))``.
    element_size : int
        Element edge ``ell``, pixels (>= 2).
    roi : str or sequence, optional
        ``"y0:y1,x0:x1"`` or two ``(start, stop)`` pairs, pixels; default: the image with
        a margin of ``max(2, ell // 4)`` pixels. Trimmed, centred, to whole elements.
    coarsest : int, optional
        Coarsest pyramid level (default: up to 3 while the ROI spans 24 pixels).
    interpolation : {"cubic", "linear"}
        Interpolation of ``g``: cubic B-spline (default) or bilinear.
    smoothing : float
        Standard deviation (pixels of each level) of a Gaussian low-pass of both images
        (default 0: the images as given, as in the paper's cut check).
    tolerance, coarse_tolerance : float
        Convergence when ``max |δa|`` falls below it on level 0 / coarser levels, pixels.
    max_iterations : int
        Iteration cap per level.

    Returns
    -------
    Q4Result

    References
    ----------
    Roux, Hild, Viot, Bernard, sections 3 (global DIC, multiscale) and 5.3 (Q4 check).

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> f = np.fft.ifft2(np.fft.fft2(rng.random((64, 64))) * np.exp(-20 * np.add.outer(
    ...     np.fft.fftfreq(64)**2, np.fft.fftfreq(64)**2))).real
    >>> res = correlate2d(f, np.roll(f, 2, axis=1), element_size=16)
    >>> res.status, np.round(res.displacement.mean(axis=(1, 2)), 3).tolist()
    ('converged', [0.0, 2.0])
    """

    t_start = time.perf_counter()
    f0, g0 = _image(ref, "the reference"), _image(deformed, "the deformed image")
    ell = int(number(element_size, "element size", minimum=2, integer=True))
    number(smoothing, "smoothing", minimum=0)
    number(tolerance, "tolerance", minimum=0)
    number(coarse_tolerance, "coarse tolerance", minimum=0)
    max_iterations = int(number(max_iterations, "max iterations", minimum=1, integer=True))
    if interpolation not in ("cubic", "linear"):
        raise InputError(f"interpolation must be cubic or linear, got {interpolation!r}")
    if coarsest is not None:
        coarsest = int(number(coarsest, "coarsest level", minimum=0, integer=True))
    meshes = plan2d(f0.shape, ell, roi, coarsest)
    top = max(meshes)
    fs, gs = pyramid2d(f0, top), pyramid2d(g0, top)
    history: list[dict] = []
    u = None
    for s in range(top, -1, -1):
        f, g = fs[s], gs[s]
        if smoothing:
            f, g = (ndi.gaussian_filter(a, smoothing, mode="mirror") for a in (f, g))
        lvl = _Level(f, g, meshes[s], interpolation)
        if lvl.range <= 0:
            raise InputError("the reference is constant over the ROI: nothing to correlate")
        if u is None:  # coarsest level: mean rigid translation first (engine, paper 5.1)
            box = meshes[s].roi
            gbox = np.nan_to_num(g[tuple(slice(r.start, min(r.stop, n)) for r, n in zip(box, g.shape))])
            fbox = np.nan_to_num(f[box])[: gbox.shape[0], : gbox.shape[1]]
            t = phase_correlation(fbox[None], gbox[None])[1:] if min(gbox.shape) > 1 else np.zeros(2)
            t = _rigid(lvl, t, coarse_tolerance if s else tolerance, max_iterations, s, history)
            u = t[:, None, None] * np.ones((2,) + meshes[s].nodes_shape)
        else:  # carry the coarse field to this level's nodes (half-pixel offset, times 2)
            at = level_to_level(meshes[s].node_coords(), s, s + 1)
            u = meshes[s + 1].evaluate(u, at) * 2.0
        if s == 0:
            initial = lvl.assemble(np.zeros((2,) + meshes[0].nodes_shape)).gap
        state = _iterate(lvl, u, coarse_tolerance if s else tolerance, max_iterations, s, history)
        u = state.u
    return Q4Result(displacement=u, node_coords=meshes[0].node_coords(), mesh=meshes[0], status=state.status,
                    gap=state.gap, initial_gap=initial, excluded=state.excluded, history=history,
                    levels=sorted(meshes, reverse=True), seconds=time.perf_counter() - t_start)
