"""What a reference scan's texture supports: statistics of sampled boxes, measured in tasks.

Three questions a user asks before choosing an element size ``ℓ``, answered from the
reference alone (docs/engine.md, "Know your texture"):

- **Autocorrelation length** per axis: the lag at which the autocorrelation of the grey
  levels (mean removed) first falls below 1/e, linearly interpolated between lags; the size of
  the texture's features.
- **Weakly textured elements**: an element whose mean squared gradient of the *prepared*
  reference (the engine's Gaussian low-pass, ``smoothing``) carries less than the image noise's
  own (:data:`WEAK_SNR`): there the data hardly set the field and the regularisation fills it
  in. The fraction of such elements falls as ``ℓ`` grows.
- **Predicted noise** ``σ_u`` at the nodes for the engine without regularisation: the
  engine's own model (:func:`chunkdic.method.noise.nodal_uncertainty`,
  ``κ σ_r² [M⁻¹]_ii``) on the ``M`` of sampled sub-meshes (the engine's ``M`` kernel on the
  prepared reference), with ``σ_r²`` the residual of two scans each carrying white noise of
  std ``noise`` through the low-pass, and ``κ`` its correlation factor
  (:func:`chunkdic.method.noise.correlation_factor`).
- The **smallest element size the texture supports** (:func:`smallest_supported`): the
  smallest of :data:`LADDER` from which on every size has at most :data:`WEAK_LIMIT` more
  weakly textured elements than the largest size and a predicted ``σ_u`` of at most
  :data:`SIGMA_LIMIT`. The weak elements alone miss a coarse texture: its elements hold some
  gradient, too little to set their nodes. None is supported when every element of the
  largest size is weakly textured (no texture above the noise: a flat or pure-noise scan),
  or when no size whose ``σ_u`` is measured is within the limit (a size too large for a
  sub-mesh in the boxes is presumed within it only when a smaller one is:
  :meth:`TextureStats.why_unsupported` says which).

The image noise is the user's (std per scan, grey levels) or, by default, estimated from
the reference: the robust spread of its second differences (``1.4826 · median |f_{i-1} -
2 f_i + f_{i+1}| / √6`` over the three axes; exact for white noise, and insensitive to
smooth texture and to the few voxels on edges).

Out of core: at most :data:`BOXES` boxes of at most ``edge`` voxels per side, spread over
the scan (an axis holding two boxes gets them at its quarters), each read and reduced by
one task to mesh-sized sums; the client never holds a voxel. That task computes the ``M``
of the sizes asked for and of the ladder's first only; when that one's ``σ_u`` is above
the limit, a second task per box computes the others' (the costly part of a task, read
only by a coarse texture or an element size it does not support).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..io.handles import ArrayRef
from ..kernels.autocorrelation import autocorrelation_length, lag_sums
from ..kernels.blocks import LAGS
from ..kernels.m import m_block
from ..method.noise import correlation_factor, nodal_uncertainty
from ..solve.cg import StencilSolver
from ..solve.stencil import half_stencil
from .prefilter import gaussian_radius, lowpass

__all__ = ["BOXES", "LADDER", "SIGMA_LIMIT", "WEAK_LIMIT", "WEAK_SNR", "TextureStats", "measure_texture", "sample_boxes",
           "smallest_supported"]

#: element sizes (voxels) among which the smallest supported one is sought
LADDER = (4, 5, 6, 8, 10, 12, 16, 20, 24, 32, 48, 64)
#: an element is weakly textured when its texture's mean squared gradient is below this
#: multiple of the noise's (the prepared reference's: texture and noise, minus the noise)
WEAK_SNR = 1.0
#: the texture supports ``ℓ`` when at most this fraction of its elements is weakly textured
WEAK_LIMIT = 0.1
#: the texture supports ``ℓ`` when the median predicted ``σ_u`` (unregularised, voxels) is at most
#: this: on the concrete specimens at texture scales 1 / 2 / 4 (noise 0.02 per scan) the
#: regularised defaults stop gaining from smaller elements below ℓ = 4 / 6 / 8, whose
#: predicted medians are 0.50 / 0.44 / 0.47 voxel, the next smaller sizes' 1.1 and 0.96
#: (docs/engine.md, "Know your texture")
SIGMA_LIMIT = 0.7
#: boxes sampled at most (2 per axis)
BOXES = 8
#: lags of the autocorrelation examined at most (voxels): an autocorrelation length
#: beyond it is reported as at least this
MAX_LAG = 64
#: elements per side of the sub-meshes whose ``M`` predicts the noise: 8³ nodes, the size
#: :func:`~chunkdic.method.noise.nodal_uncertainty` solves exactly
NOISE_ELEMENTS = 7


@dataclass
class TextureStats:
    """What :func:`measure_texture` found.

    Attributes
    ----------
    acl : tuple of 3 float
        Autocorrelation length per axis (z, y, x), voxels; ``inf`` when the
        autocorrelation stays above 1/e up to the largest lag examined.
    noise : float
        Std of the image noise per scan, grey levels (given or estimated).
    noise_estimated : bool
        Whether ``noise`` was estimated from the reference.
    weak_fraction : dict of int to float
        Per element size of :data:`LADDER` that fits a box: the fraction of weakly
        textured elements.
    smallest : int or None
        The smallest element size the texture supports (None: none of the sizes measured,
        :meth:`why_unsupported`).
    sigma_u : dict of int to (float, float)
        Per requested element size, and per size of the ladder (a sub-mesh of three elements
        in a box) up to the first within :data:`SIGMA_LIMIT`: the median and 90 % quantile
        over the sampled inner nodes of the predicted ``σ_u`` (pooled over the components),
        voxels; NaN when no sub-mesh of that size fits, infinite where it holds no texture.
    kappa : dict of int to float
        The noise correlation factor used for each requested size.
    boxes : int
        Boxes sampled; ``box_edge`` their largest edge, voxels.
    textured : bool
        Whether the reference holds texture above its noise: False when every element of
        the largest size measured is weakly textured (a flat or pure-noise scan), which then
        supports no element size.
    """

    acl: tuple[float, float, float]
    noise: float
    noise_estimated: bool
    weak_fraction: dict[int, float]
    smallest: int | None
    sigma_u: dict[int, tuple[float, float]] = field(default_factory=dict)
    kappa: dict[int, float] = field(default_factory=dict)
    boxes: int = 0
    box_edge: int = 0
    textured: bool = True

    def why_unsupported(self) -> str:
        """Why the texture supports none of the sizes measured, in words ('' when it supports one)."""
        if self.smallest is not None:
            return ""
        if not self.textured:
            return ("no texture above the noise: every element of the largest size measured is weakly "
                    "textured")
        known = {e: s[0] for e, s in self.sigma_u.items() if not math.isnan(s[0])}
        if not known:
            return "no sub-mesh of three elements fits in the sampled boxes: the predicted noise is unknown"
        if min(known.values()) > SIGMA_LIMIT:
            largest = max(known)
            return (f"the predicted σ_u median is above {SIGMA_LIMIT:g} voxel at every size measured, "
                    f"{known[largest]:.2g} voxel at {largest} voxels, the largest that fits three elements per "
                    f"side of the sampled boxes")
        return (f"no size from which on every larger one has at most {100 * WEAK_LIMIT:.0f} % more weakly "
                f"textured elements than the largest and a predicted σ_u median of at most {SIGMA_LIMIT:g} voxel")


def sample_boxes(shape, edge: int, count: int = BOXES, within=None) -> list[tuple[tuple[int, int], ...]]:
    """Boxes of at most ``edge`` voxels per side over a scan of ``shape`` (or over the box
    ``within``, per axis (start, stop)): per axis one centred box, or two centred on the
    axis's quarters when it holds two; at most ``count``."""
    within = [(0, int(n)) for n in shape] if within is None else [(int(a), int(b)) for a, b in within]
    per_axis = []
    for lo, hi in within:
        n = hi - lo
        e = min(int(edge), n)
        centres = (n / 2,) if n < 2 * e else (n / 4, 3 * n / 4)
        per_axis.append([(lo + s, lo + s + e) for s in (max(min(int(round(c - e / 2)), n - e), 0) for c in centres)])
    boxes = [(a, b, c) for a in per_axis[0] for b in per_axis[1] for c in per_axis[2]]
    if len(boxes) == 8 and count < 8:  # every other corner of the 2×2×2 grid first: each axis's two halves seen
        boxes = boxes[0::3][:2] + boxes[5:7] + [b for i, b in enumerate(boxes) if i not in (0, 3, 5, 6)]
    return boxes[:count]


def box_task(ref: ArrayRef, box, sigma: float, ladder, noise_sizes, max_lag: int) -> dict:
    """Task: one box of the reference reduced to sums (no voxel leaves the task).

    Parameters
    ----------
    ref : ArrayRef
        The reference (level-0 or the level of the element sizes).
    box : tuple of 3 (start, stop)
        The box, voxels.
    sigma : float
        The engine's low-pass (``smoothing``), voxels.
    ladder : sequence of int
        Element sizes whose per-element mean squared gradient is wanted.
    noise_sizes : sequence of int
        Element sizes whose ``M`` over a central sub-mesh of :data:`NOISE_ELEMENTS`
        elements per side is wanted.
    max_lag : int

    Returns
    -------
    dict
        ``box`` as given; ``lags`` (3, 4, max_lag + 1) float64: per axis and lag ``k``, ``Σ f f_k``,
        ``Σ f``, ``Σ f_k``, pair count; ``d2`` the median of the absolute second differences;
        ``energy`` ℓ → (ez, ey, ex) float64 mean ``|∇f|²`` of the prepared reference per
        element; ``half`` ℓ → half stencil (float32), ``slags`` ℓ → (3, LAGS + 1).
    """
    f, prepared, inner = _read_box(ref, box, sigma)
    out = {"box": box, "lags": lag_sums(f, max_lag) if max_lag else None, "d2": _second_difference_median(f)}
    energy = sum(g[inner].astype(np.float64) ** 2 for g in np.gradient(prepared))
    out["energy"] = {ell: _element_means(energy, ell) for ell in ladder if min(energy.shape) >= ell}
    return {**out, **_stencils(prepared, inner, noise_sizes)}


def stencil_task(ref: ArrayRef, box, sigma: float, noise_sizes) -> dict:
    """Task: the ``half`` and ``slags`` of :func:`box_task` alone, for sizes its round left out."""
    _, prepared, inner = _read_box(ref, box, sigma)
    return {"box": box, **_stencils(prepared, inner, noise_sizes)}


def _read_box(ref: ArrayRef, box, sigma: float) -> tuple[np.ndarray, np.ndarray, tuple[slice, ...]]:
    """The box's voxels (float64), the reference prepared over it and a halo (the engine's
    low-pass, float32), and the box's slices in the latter."""
    halo = gaussian_radius(sigma) + 1
    outer = tuple(slice(max(a - halo, 0), min(b + halo, n)) for (a, b), n in zip(box, ref.shape))
    raw = ref.read(outer).astype(np.float64)
    inner = tuple(slice(a - o.start, b - o.start) for (a, b), o in zip(box, outer))
    return raw[inner], lowpass(raw, sigma), inner  # float32, as the engine's


def _stencils(prepared: np.ndarray, inner, noise_sizes) -> dict:
    """``half`` ℓ → half stencil of ``M`` (float32) on a central sub-mesh of the box ``inner``
    of ``prepared``, ``slags`` ℓ → its sensitivities' lag sums (3, LAGS + 1), per size that
    fits three elements."""
    out = {"half": {}, "slags": {}}
    shape = [s.stop - s.start for s in inner]
    for ell in noise_sizes:
        n_el = min(NOISE_ELEMENTS, *(s // ell for s in shape))
        if n_el < 3:  # no inner node to predict for
            continue
        # a central sub-mesh with its one-voxel halo inside the prepared window
        start = [o.start + (s - n_el * ell) // 2 for o, s in zip(inner, shape)]
        lo = tuple(1 if s > 0 else 0 for s in start)
        hi = tuple(1 if s + n_el * ell < p else 0 for s, p in zip(start, prepared.shape))
        region = tuple(slice(s - a, s + n_el * ell + b) for s, a, b in zip(start, lo, hi))
        S, _, _, slags = m_block(prepared[region], lo, hi, ell, with_lags=True)
        out["half"][ell] = np.ascontiguousarray(half_stencil(S), dtype=np.float32)
        out["slags"][ell] = slags
    return out


def _in_order(regions, results) -> list[dict]:
    """The tasks' results (each with its ``box``) in the order of ``regions``, whichever
    finished first: the sums, and the noise factor solved on the first box's sub-mesh, are
    then the same every run."""
    by_box = {r["box"]: r for r in results}
    return [by_box[b] for b in regions]


def _second_difference_median(f: np.ndarray) -> float:
    """Median of ``|f[i-1] - 2 f[i] + f[i+1]|`` over the three axes, on every other line of
    every other plane (a median needs no more)."""
    parts = []
    for ax in range(3):
        if f.shape[ax] > 2:
            lines = f[tuple(slice(None) if a == ax else slice(None, None, 2) for a in range(3))]
            parts.append(np.abs(np.diff(lines, n=2, axis=ax)).ravel())
    return float(np.median(np.concatenate(parts))) if parts else math.nan


def _element_means(v: np.ndarray, ell: int) -> np.ndarray:
    """Means of ``v`` over the whole elements of edge ``ell`` that fit, from its first voxel."""
    n = [s // ell for s in v.shape]
    v = v[:n[0] * ell, :n[1] * ell, :n[2] * ell]
    return v.reshape(n[0], ell, n[1], ell, n[2], ell).mean(axis=(1, 3, 5))


def smoothed_noise(sigma: float) -> tuple[float, float, np.ndarray]:
    """White noise of unit variance through the engine's low-pass ``sigma``: its variance,
    the mean squared gradient (centred differences) and its correlation along an axis at
    lags 0 … LAGS."""
    radius = gaussian_radius(sigma) + LAGS + 2
    impulse = np.zeros((2 * radius + 1,) * 3)
    impulse[(radius,) * 3] = 1.0
    h = lowpass(impulse, sigma).astype(np.float64)  # the low-pass's impulse response
    variance = float(np.sum(h * h))
    grad = float(sum(np.sum(g * g) for g in np.gradient(h)))
    rho = np.array([float(np.sum(h * np.roll(h, k, axis=2))) for k in range(LAGS + 1)]) / variance
    return variance, grad, rho


def noise_of_pair(noise: float, sigma: float, slags: np.ndarray) -> tuple[float, float]:
    """``σ_r²`` and ``κ`` of the residual of two scans each with white noise of std ``noise``,
    prepared with the low-pass ``sigma``, for sensitivities whose lag sums are ``slags``
    (:func:`chunkdic.method.noise.correlation_factor`)."""
    variance, _, rho = smoothed_noise(sigma)
    s2 = 2.0 * noise * noise * variance
    r = np.zeros((6, LAGS + 1))
    r[1] = 1.0
    r[0, 0] = s2
    r[0, 1:] = 2.0 * s2 * (1.0 - rho[1:])  # the variogram's squared differences
    return s2, correlation_factor(r, slags, noise_variance=s2)


def measure_texture(ref: ArrayRef, map_tasks, *, element_sizes=(), noise: float | None = None,
                    smoothing: float = 1.0, edge: int = 128, boxes: int = BOXES,
                    ladder=LADDER, max_lag: int = MAX_LAG, within=None) -> TextureStats:
    """The texture statistics of the reference ``ref`` from sampled boxes (module docstring).

    Parameters
    ----------
    ref : ArrayRef
        The reference scan (the level the element sizes are in).
    map_tasks : callable
        ``map_tasks(fn, args)``: results of ``fn(*a)`` for each ``a`` (a runner's ``map_unordered``).
    element_sizes : sequence of int
        Sizes (voxels) whose noise is predicted (:attr:`TextureStats.sigma_u`).
    noise : float, optional
        Std of the image noise per scan, grey levels; default estimated from the reference.
    smoothing : float
        The engine's low-pass, voxels (:class:`~chunkdic.method.settings.Settings` ``smoothing``).
    edge : int
        Box edge, voxels (raised to hold :data:`NOISE_ELEMENTS` elements of the largest
        requested size; clipped to the scan).
    boxes : int
        Boxes at most.
    ladder : sequence of int
        Sizes among which the smallest supported one is sought.
    max_lag : int
        Largest lag of the autocorrelation, voxels (0: none; :attr:`TextureStats.acl` NaN).
    within : sequence of 3 (start, stop), optional
        Sample inside this box only (a correlation's ROI); default the whole scan.
    """
    sizes = sorted({int(e) for e in element_sizes})
    edge = max(int(edge), *(NOISE_ELEMENTS * e + 2 for e in sizes)) if sizes else int(edge)
    regions = sample_boxes(ref.shape, edge, boxes, within)
    fits = min(min(b - a for a, b in box) for box in regions) // 3  # a sub-mesh of 3 elements
    predicted = sorted({*sizes, *(e for e in ladder if e <= fits)})
    # the stencils surely read: the sizes asked for and the ladder's first; the others only
    # when that one is above the limit (a second round of tasks, below)
    done = {*sizes, *predicted[:1]}
    results = _in_order(regions, map_tasks(box_task, [(ref, b, float(smoothing), tuple(ladder), tuple(sorted(done)),
                                                        int(max_lag)) for b in regions]))
    acl = autocorrelation_length(sum(r["lags"] for r in results)) if max_lag else (math.nan,) * 3
    estimated = noise is None
    if estimated:
        noise = 1.4826 * float(np.median([r["d2"] for r in results])) / math.sqrt(6.0)
    _, grad_gain, _ = smoothed_noise(smoothing)
    floor = (1.0 + WEAK_SNR) * grad_gain * float(noise) ** 2  # texture's energy = noise's × WEAK_SNR
    weak = {}
    for ell in ladder:
        e = [r["energy"][ell].ravel() for r in results if ell in r["energy"]]
        if e:
            e = np.concatenate(e)
            weak[ell] = float(np.mean(e <= floor))  # ≤: a flat element is weak under no noise too
    stats = TextureStats(acl, float(noise), estimated, weak, None, boxes=len(regions),
                         box_edge=max(b - a for box in regions for a, b in box))
    for ell in sizes:
        stats.sigma_u[ell], stats.kappa[ell] = _predicted_noise(results, ell, float(noise), smoothing)
    for ell in predicted:  # the ladder's up to the first within the limit (σ_u falls as ℓ grows)
        if ell not in done:
            rest = [e for e in predicted if e not in done]
            _add_stencils(results, map_tasks, ref, float(smoothing), rest)
            done.update(rest)
        if ell not in stats.sigma_u:
            stats.sigma_u[ell], stats.kappa[ell] = _predicted_noise(results, ell, float(noise), smoothing)
        if ell not in sizes and stats.sigma_u[ell][0] <= SIGMA_LIMIT:
            break
    stats.smallest = smallest_supported(weak, {e: s[0] for e, s in stats.sigma_u.items()})
    stats.textured = textured(weak)
    return stats


def textured(weak: dict[int, float]) -> bool:
    """Whether the reference holds texture above its noise: some element of the largest size
    measured is not weakly textured (``weak``: element size → fraction of weak elements)."""
    return bool(weak) and weak[max(weak)] < 1.0


def smallest_supported(weak: dict[int, float], sigma: dict[int, float] | None = None) -> int | None:
    """The smallest size from which on every size has at most :data:`WEAK_LIMIT` more weakly
    textured elements than the largest size measured (what is weak at every size, air around a
    specimen or a pore larger than any element, is the scan's, not the element size's) and a
    median predicted ``σ_u`` of at most :data:`SIGMA_LIMIT` voxel; None when every element of
    the largest size is weak (no texture above the noise). A size whose ``σ_u`` is not known
    is within the limit when a smaller one is (``σ_u`` falls as ℓ grows), not otherwise.

    Parameters
    ----------
    weak : dict of int to float
        Element size (voxels) → fraction of weakly textured elements.
    sigma : dict of int to float, optional
        Element size (voxels) → median predicted ``σ_u``, voxels (NaN or absent: not known;
        None: the weak elements alone judge).

    Examples
    --------
    >>> smallest_supported({4: 0.08, 8: 0.04, 16: 0.01}, {4: 2.5, 8: 0.47, 16: 0.11})
    8
    >>> smallest_supported({4: 0.30, 8: 0.04, 16: 0.01})
    8
    >>> smallest_supported({4: 0.0, 8: 0.0, 16: 0.0}, {4: 2.5, 8: 0.9})  # 16: unknown, 8 above the limit
    >>> smallest_supported({4: 1.0, 8: 1.0, 16: 1.0})  # no texture above the noise
    """
    if not textured(weak):
        return None
    base = weak[max(weak)]
    known = None if sigma is None else {e: s for e, s in sigma.items() if not math.isnan(s)}

    def quiet(ell):  # the predicted noise within the limit, or presumed so from a smaller size's
        if known is None:
            return True
        if ell in known:
            return known[ell] <= SIGMA_LIMIT
        return any(s <= SIGMA_LIMIT for e, s in known.items() if e < ell)

    def holds(ell):
        return weak[ell] <= base + WEAK_LIMIT and quiet(ell)

    supported = [ell for ell in weak if all(holds(m) for m in weak if m >= ell)]
    return min(supported) if supported else None


def _add_stencils(results: list[dict], map_tasks, ref: ArrayRef, sigma: float, sizes) -> None:
    """Each box's ``half`` and ``slags`` of ``sizes`` (a second round of tasks) added to its
    :func:`box_task` result, in place."""
    more = _in_order([r["box"] for r in results],
                     map_tasks(stencil_task, [(ref, r["box"], sigma, tuple(sizes)) for r in results]))
    for r, m in zip(results, more):
        r["half"].update(m["half"])
        r["slags"].update(m["slags"])


def _predicted_noise(results, ell: int, noise: float, smoothing: float) -> tuple[tuple[float, float], float]:
    """Median and 90 % quantile of the predicted ``σ_u`` over the inner nodes of the sampled
    sub-meshes of size ``ell``, and ``κ``."""
    halves = [r["half"][ell] for r in results if ell in r["half"]]
    if not halves:
        return (math.nan, math.nan), math.nan
    s2, kappa = noise_of_pair(noise, smoothing, sum(r["slags"][ell] for r in results if ell in r["slags"]))
    sigma, c = [], None
    inner = (slice(1, -1),) * 3
    for half in halves:
        if not np.median(np.trace(half[..., 0, :, :], axis1=-2, axis2=-1)) > 0:  # no texture: nothing set
            sigma.append(np.full(int(np.prod([n - 2 for n in half.shape[:3]])), np.inf))
            continue
        solver = StencilSolver(half.copy(), multigrid=False)
        local = np.moveaxis(solver.local_variances(), -1, 0)  # diag(M_ii⁻¹), (3, nz, ny, nx)
        if c is None:  # the neighbours' share, solved exactly on the first sub-mesh (as the engine does)
            var = nodal_uncertainty(solver, s2, kappa) ** 2
            c = float(np.median(var[(slice(None), *inner)] / (kappa * s2 * local[(slice(None), *inner)])))
        var = kappa * s2 * c * local
        sigma.append(np.sqrt(var[(slice(None), *inner)].mean(axis=0)).ravel())
    sigma = np.concatenate(sigma)
    # the sample's own value, not interpolated: a flat sub-mesh's nodes are infinite
    return (float(np.median(sigma)), float(np.quantile(sigma, 0.9, method="higher"))), float(kappa)
