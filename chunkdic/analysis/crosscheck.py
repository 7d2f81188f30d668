"""The paper's independent check of a result: 2-D Q4-DIC on mid-plane cuts (section 5.3).

"A two-dimensional image correlation analysis (Q4-DIC) was run on the three (a)-(c)
pairs": the mid-plane cuts of the reference (a) against the corrected deformed volume (c)
(normal to z, y and x), with the element size of the 3-D run. Had the 3-D field been
exact, the 2-D field would be zero; the paper found it below 0.02 pixel on every cut and
"similar to white noise". A wrong 3-D field shows instead as a larger 2-D field that
varies smoothly in space.

The cuts come from worker tasks (:func:`chunkdic.export.correction.planes`, one element layer
per task: the client never reads a slab of a scan). Each pair is the reference *as the
engine saw it* (low-passed) and the corrected image ``λ g̃(X + u(X)) + μ`` (the engine's
warp kernel and the brightness it found), so that the check sees the 3-D field's error and
not a difference of image preparation. The 2-D correlation (:mod:`chunkdic.analysis.q4`) runs on the
ROI cut with :func:`chunkdic.analysis.q4.correlate2d`'s default ROI (a margin of ``max(2, ell // 4)``
pixels, then whole elements, as the engine's default ROI: on the bare cut, border pixels
whose ``X + u`` steps in and out of the image by a hundredth of a pixel made the
iterations stall), the result's element size in pixels of its level, no further low-pass.

Per cut: the mean (length of the mean vector), the standard deviation (pooled over the two
components) and the maximum length of the nodal 2-D displacement, pixels of the result's
level, and its spatial correlation length: the lag where the autocorrelation of the nodal
field (mean removed, averaged over the two components and the two grid directions) first
falls below 1/e, linearly interpolated, in pixels. White noise on the nodes gives less than
one node spacing (``ell``); a smooth error field gives several.

The paper's "less than 0.02 pixel" is read as the level of the field: its mean and standard
deviation (``Cut.passed``). On a noisy pair that bound lies below what the 2-D correlation
itself can resolve on one slice, so the bound is ``max(0.02, K_NOISE × floor)`` where the
*noise floor* is the 2-D correlation's own predicted standard uncertainty on that cut
(:func:`noise_floor`): the a-priori estimate ``κ σ_r² M⁻¹`` of global DIC with the 2-D
``M`` of the cut and the residual noise ``σ_r`` and correlation factor ``κ`` the 3-D run
measured (``Result.info["noise"]``). A result is then "consistent with noise" when its std is
within ``K_NOISE`` floors, its mean within ``K_MEAN`` predicted uncertainties of the mean
(each bound at least 0.02 pixel) and the correlation length is below one element. Results without a noise estimate keep the paper's 0.02 pixel.

Masked results: pixels where the corrected image is not defined (outside the specimen
mask, NaN) are left out of the 2-D correlation (the reference cut is set to NaN there),
and the figures of merit run over the 2-D nodes of Q4 elements at least half defined. The maximum over the nodes is reported too; on a converged
synthetic 64³ result at ``ell = 8`` it is 3–4 standard deviations, 0.03–0.04 pixel
(docs/analysis.md, "Cut check"). Every node of the 2-D mesh counts, the border ones too.
An error of the 3-D field *in* the plane of a cut comes back as the opposite 2-D field,
smooth (long correlation length); an error *across* the plane moves the cut onto other
material, and comes back as a larger but noise-like 2-D field.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from ..io.outputs import Outputs
from ..results.result import Result, open_result
from ..results.scans import input_paths, input_scans, interpolation_of, level_refs
from ..scheduler import check_scheduler, open_runner
from ..export import correction
from ..plot.figures import (
    AXES,
    check_figure_options,
    figure,
    level_label,
    mid_planes,
    result_label,
    save,
)
from .q4 import Q4Result, _Level, correlate2d
from .q4mesh import plan2d

__all__ = ["Cut", "cutcheck", "correlation_length", "plot_cutcheck", "noise_floor", "measured_nodes"]

#: the paper's bound on the cut-check displacement, pixels (section 5.3)
THRESHOLD = 0.02
#: a cut is consistent with noise when its std is within this many noise floors
K_NOISE = 2.0
#: ... and its mean within this many predicted uncertainties of the mean
K_MEAN = 3.0
#: random draws of the noise-floor estimate
_FLOOR_DRAWS = 16


@dataclass
class Cut:
    """The 2-D check of one mid-plane cut.

    Attributes
    ----------
    axis : str
        Normal of the cut, ``"z"``, ``"y"`` or ``"x"``.
    index : int
        Plane index along ``axis``, voxels of the result's level.
    mean, std, max : float
        Length of the mean 2-D displacement, its standard deviation (pooled over the two
        components) and its largest nodal length, pixels of the result's level.
    correlation_length : float
        Lag (pixels) where the nodal autocorrelation falls below 1/e; a lower bound equal to
        the largest lag examined when it never does.
    status : str
        The 2-D correlation's status (``converged`` expected).
    gap : float
        Its final matching gap.
    components : tuple of str
        The in-plane axes ``(rows, columns)`` of the 2-D field, e.g. ``("y", "x")``.
    passed : bool
        The paper's criterion as chunkdic reads it: the 2-D correlation converged, its
        mean and standard deviation are below ``bound`` and its correlation length
        is below one element (no spatial correlation beyond neighbouring nodes).
    floor : float
        The 2-D correlation's predicted standard uncertainty on this cut from the scans'
        noise (:func:`noise_floor`), pixels; NaN when not estimated.
    bound : float
        ``max(THRESHOLD, K_NOISE * floor)``, pixels.
    nodes : int
        2-D nodes the figures run over (those of Q4 elements at least half defined).
    floor_mean : float
        Predicted standard uncertainty of the mean vector (:func:`noise_floor`), pixels.
    bound_mean : float
        ``max(THRESHOLD, K_MEAN * floor_mean)``: the bound on ``mean``, pixels.
    """

    axis: str
    index: int
    mean: float
    std: float
    max: float
    correlation_length: float
    status: str
    gap: float
    components: tuple[str, str]
    passed: bool
    floor: float = math.nan
    bound: float = THRESHOLD
    nodes: int = 0
    floor_mean: float = math.nan
    bound_mean: float = THRESHOLD

    def as_dict(self) -> dict:
        d = asdict(self)
        d["components"] = list(self.components)
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}


def correlation_length(u: np.ndarray, spacing: float) -> float:
    """Lag where the autocorrelation of a nodal field first falls below 1/e.

    Parameters
    ----------
    u : ndarray, shape (k, ny, nx)
        Nodal field (``k`` components), on a regular grid.
    spacing : float
        Node spacing, pixels.

    Returns
    -------
    float, pixels
        The lag, linearly interpolated between grid lags, of the autocorrelation averaged
        over the components (autocovariances added, mean removed per component) and over the
        two grid directions (biased estimator, zero-padded FFT). The largest lag examined
        (half the grid) when it stays above 1/e; 0 for a constant field.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> correlation_length(rng.standard_normal((2, 40, 40)), 8.0) < 8.0
    True
    """
    v = np.asarray(u, np.float64) - np.mean(u, axis=(1, 2), keepdims=True)
    ny, nx = v.shape[1:]
    spec = np.fft.rfft2(v, s=(2 * ny, 2 * nx))
    acov = np.fft.irfft2((spec * spec.conj()).real.sum(axis=0), s=(2 * ny, 2 * nx))
    if acov[0, 0] <= 0:
        return 0.0
    n = min(ny, nx) // 2 + 1
    rho = 0.5 * (acov[:n, 0] + acov[0, :n]) / acov[0, 0]
    below = np.nonzero(rho < 1 / math.e)[0]
    if below.size == 0:
        return float((n - 1) * spacing)
    k = int(below[0])
    frac = (rho[k - 1] - 1 / math.e) / (rho[k - 1] - rho[k])
    return float((k - 1 + frac) * spacing)


def _stats(res: Q4Result, nodes: np.ndarray | None = None) -> tuple[float, float, float]:
    u = res.displacement.reshape(2, -1)
    if nodes is not None:
        u = u[:, nodes.ravel()]
    mean = float(np.linalg.norm(u.mean(axis=1)))
    std = float(np.sqrt(u.var(axis=1).mean()))
    return mean, std, float(np.sqrt((u**2).sum(axis=0)).max())


def measured_nodes(defined: np.ndarray, mesh) -> np.ndarray:
    """2-D nodes touching a Q4 element whose pixels are at least half ``defined`` (bool, nodes shape)."""
    ell = mesh.element_size
    box = defined[mesh.roi].astype(np.float64)
    ny, nx = mesh.shape
    frac = box.reshape(ny, ell, nx, ell).mean(axis=(1, 3))
    a = np.pad(frac >= 0.5, 1)
    return a[:-1, :-1] | a[1:, :-1] | a[:-1, 1:] | a[1:, 1:]


def noise_floor(prepared: np.ndarray, corrected: np.ndarray, element_size: int, sigma_r: float, kappa: float,
                nodes: np.ndarray | None = None, seed: int = 0) -> float:
    """The 2-D correlation's predicted standard uncertainty on a cut, pixels.

    The a-priori estimate of global DIC, ``Cov(u) = κ σ_r² M⁻¹`` (paper 4.2; the 3-D engine's
    per-node uncertainty, :func:`chunkdic.method.noise.nodal_uncertainty`), applied to the
    2-D correlation of the cut: ``M`` is its level-0 Q4 matrix on this pair (as
    :mod:`chunkdic.analysis.q4` builds it, pixels outside a mask left out), ``σ_r`` the
    residual noise the 3-D run measured, and the noise correlation factor ``κ`` of the 3-D
    run (a cube of the per-axis factor, :mod:`chunkdic.method.noise`) taken to the power 2/3
    for two axes.

    Parameters
    ----------
    prepared, corrected : ndarray, shape (a, b), float
        The cut pair as :func:`check_cut` correlates it (NaN pixels left out).
    element_size : int
        Q4 element edge, pixels.
    sigma_r, kappa : float
        ``Result.info["noise"]``: the 3-D residual's noise standard deviation (grey
        levels of the result's level) and its correlation factor.
    nodes : ndarray of bool, optional
        The 2-D nodes to pool over (default all).

    Returns
    -------
    floor : float
        ``sqrt(mean of κ^(2/3) σ_r² diag(M⁻¹))`` over ``nodes`` and both components
        (exact diagonal up to 4000 unknowns, else a 32-probe Hutchinson estimate): the
        standard deviation a field of noise alone has.
    floor_mean : float
        The predicted standard uncertainty of the mean 2-D vector over ``nodes`` (both
        components, ``κ^(2/3) σ_r² 1ᵀ M⁻¹ 1 / n²``): far below ``floor``, it is what makes an
        error with a mean (an offset, a bump) visible through the noise.
    """

    if not (math.isfinite(sigma_r) and math.isfinite(kappa)):
        return math.nan, math.nan
    f = np.asarray(prepared, np.float64)
    g = np.asarray(corrected, np.float64)
    f = np.where(np.isfinite(g), f, np.nan)
    mesh = plan2d(f.shape, int(element_size), None, 0)[0]
    lvl = _Level(f, g, mesh, "linear")
    n = lvl.phi.shape[1]
    pick = np.ones(2 * n, bool) if nodes is None else np.concatenate([nodes.ravel()] * 2)
    if 2 * n <= 4000:
        diag = np.diag(np.linalg.inv(lvl.M.toarray() + 1e-9 * float(lvl.M.diagonal().mean()) * np.eye(2 * n)))
        mean_var = float(diag[pick].mean())
    else:
        rng = np.random.default_rng(seed)
        z = np.where(pick[:, None], rng.choice([-1.0, 1.0], size=(2 * n, 32)), 0.0)
        mean_var = float(np.mean([zi @ lvl.solve(zi) for zi in z.T])) / pick.sum()
    k2 = kappa ** (2.0 / 3.0) * sigma_r**2
    # the mean over the nodes, per component: Var = k2 1ᵀ M⁻¹ 1 / |P|² (one solve each)
    var_mean = 0.0
    for c in range(2):
        one = np.zeros(2 * n)
        one[c * n:(c + 1) * n] = pick[c * n:(c + 1) * n]
        var_mean += float(one @ lvl.solve(one)) / max(float(one.sum()), 1.0) ** 2
    return float(math.sqrt(k2 * mean_var)), float(math.sqrt(k2 * var_mean))


def check_cut(prepared: np.ndarray, corrected: np.ndarray, element_size: int, normal: int, index: int,
              noise: tuple[float, float] | None = None) -> tuple[Cut, Q4Result]:
    """The 2-D Q4 correlation of one cut pair and its figures of merit.

    Parameters
    ----------
    prepared, corrected : ndarray, shape (a, b), float32
        The reference as the engine saw it and the corrected deformed image over the ROI
        cut (NaN where the corrected image is not defined).
    element_size : int
        Element edge of the 3-D result, pixels of its level.
    normal, index : int
        Axis normal to the cut and its index (for the report).
    noise : tuple (sigma_r, kappa), optional
        The 3-D run's residual noise and correlation factor (``Result.info["noise"]``,
        :func:`noise_floor`); without it the bound is the paper's :data:`THRESHOLD`.
    """
    prepared = np.asarray(prepared, np.float64)
    corrected = np.asarray(corrected, np.float64)
    defined = np.isfinite(corrected) & np.isfinite(prepared)
    prepared = np.where(defined, prepared, np.nan)  # outside a specimen mask: left out
    floor = floor_mean = math.nan
    if noise is not None:
        mesh = plan2d(prepared.shape, int(element_size), None, 0)[0]
        floor, floor_mean = noise_floor(prepared, corrected, element_size, *noise,
                                        nodes=measured_nodes(defined, mesh))
    bound = max(THRESHOLD, K_NOISE * floor) if math.isfinite(floor) else THRESHOLD
    bound_mean = max(THRESHOLD, K_MEAN * floor_mean) if math.isfinite(floor_mean) else THRESHOLD
    # solved to 5 % of the bound that judges it (the default 1e-3 pixel when the bound is the paper's)
    res = correlate2d(prepared, corrected, element_size=element_size, tolerance=max(1e-3, 0.05 * bound))
    nodes = measured_nodes(defined, res.mesh)
    mean, std, mx = _stats(res, nodes)
    comps = tuple(AXES[a] for a in range(3) if a != normal)
    u = res.displacement - (res.displacement[:, nodes].mean(axis=1)[:, None, None] if nodes.any() else 0.0)
    length = correlation_length(np.where(nodes[None], u, 0.0), element_size)
    passed = res.converged and mean < bound_mean and std < bound and length < element_size
    cut = Cut(AXES[normal], int(index), mean, std, mx, length, res.status, float(res.gap), comps, bool(passed),
              floor, bound, int(nodes.sum()), floor_mean, bound_mean)
    res.measured = nodes  # for the figure
    return cut, res


def cutcheck(result, output=None, *, ref=None, deformed=None, scheduler=None, overwrite: bool = False,
             progress: Callable[[str], None] | None = None, fmt: str = "png",
             dpi: int | None = None) -> list[Cut]:
    """Run the paper's cut check (section 5.3) on a correlation result.

    Parameters
    ----------
    result : Result or path
        A result of :func:`chunkdic.correlate` whose scans are on disk.
    output : path, optional
        Folder for ``cutcheck.png`` (``.pdf``, ``.svg`` with ``fmt``; one panel per cut: the
        length of the 2-D displacement at the nodes) and ``cutcheck.json`` (the numbers); written through
        :class:`chunkdic.io.outputs.Outputs` (kind ``cutcheck``). None: nothing is written.
    ref, deformed : path, optional
        The scans (default: the paths recorded in the result).
    scheduler
        Where the cut planes are computed, as in :func:`chunkdic.correlate`.
    overwrite : bool
        Replace the files of an earlier cut check in ``output``.
    progress : callable(str), optional
        One message per cut.
    fmt : {"png", "pdf", "svg"}, keyword-only
        File format of the figure.
    dpi : int, keyword-only, optional
        Its resolution, dots per inch (default :data:`chunkdic.plot.figures.DEFAULT_DPI`).

    Returns
    -------
    list of Cut
        Normal to z, y, x, in that order.

    References
    ----------
    Roux, Hild, Viot, Bernard, section 5.3 ("Check of correction from mid-plane cuts").
    """

    res = result if isinstance(result, Result) else open_result(result)
    res.check_displacement()
    scans = input_scans(res, ref, deformed)  # every input checked before anything is written
    check_scheduler(scheduler)
    check_figure_options(fmt, dpi)
    plan = Outputs(inputs=input_paths(res, ref, deformed), overwrite=overwrite)
    out = plan.add(output, "cutcheck").final if output is not None else None
    say = progress or (lambda msg: None)
    ell = int(res.info["element_size"])
    est = res.info.get("noise") or {}
    noise = (float(est.get("sigma_r") or math.nan), float(est.get("kappa") or math.nan))
    planes = mid_planes(res)
    with plan:  # a failure removes what this run wrote
        cuts, fields = [], []
        # the runner first: a level missing from the scans is then built by its workers
        with open_runner(scheduler) as runner, level_refs(res, scans=scans) as (f_ref, g_ref):
            for normal in range(3):
                idx = planes[AXES[normal]]
                cut = correction.planes(res, f_ref, g_ref, normal, idx, runner, interpolation=interpolation_of(res))
                c, q = check_cut(cut["prepared"], cut["corrected"], ell, normal, idx, noise)
                cuts.append(c)
                fields.append(q)
                say(f"cut normal to {c.axis} at {c.axis} = {idx}: mean {c.mean:.4f}, std {c.std:.4f}, "
                    f"max {c.max:.4f} pixel, correlation length {c.correlation_length:.1f} pixel, noise floor "
                    f"{c.floor:.4f} pixel (of the mean {c.floor_mean:.4f}) ({c.status})")
        if out is not None:
            figure_path = plot_cutcheck(res, cuts, fields, out / f"cutcheck.{fmt}", dpi=dpi)
            (out / "cutcheck.json").write_text(json.dumps([c.as_dict() for c in cuts], indent=2) + "\n")
            say(f"wrote {figure_path}, {out / 'cutcheck.json'}")
    return cuts


def plot_cutcheck(result: Result, cuts: list[Cut], fields: list[Q4Result], path, *, dpi: int | None = None) -> str:
    """One panel per cut: the length of the 2-D displacement at the nodes (common colour
    scale) with arrows showing its direction (auto-scaled per panel).

    Axes in voxels of the result's level, in the scan's frame; the title of each panel gives
    the cut's figures. Written by :func:`chunkdic.plot.figures.save` (format from the extension
    of ``path``, resolution ``dpi``).
    """

    roi = result.mesh.roi
    lengths = [np.sqrt((q.displacement**2).sum(axis=0)) for q in fields]
    lengths = [np.where(getattr(q, "measured", True), m, np.nan) for q, m in zip(fields, lengths)]
    vmax = max(max(float(np.nanmax(m)) if np.isfinite(m).any() else 0.0 for m in lengths), THRESHOLD)
    fig = figure(5.0 * len(cuts), 4.6)
    axs = np.atleast_1d(fig.subplots(1, len(cuts)))
    lab = level_label(result)
    for ax, c, q, m in zip(axs, cuts, fields, lengths):
        rows, cols = (AXES.index(a) for a in c.components)
        # the cut's pixel (0, 0) is the ROI's first voxel: node positions in the scan's frame
        ys, xs = (axis + roi[a].start for axis, a in zip(q.mesh.node_axes(), (rows, cols)))
        h = q.mesh.element_size / 2
        extent = [xs[0] - h, xs[-1] + h, ys[0] - h, ys[-1] + h]
        measured = getattr(q, "measured", None)
        if measured is not None:
            m = np.where(measured, m, np.nan)
        im = ax.imshow(m, origin="lower", extent=extent, cmap="magma", vmin=0.0, vmax=vmax, interpolation="nearest")
        ax.quiver(*np.meshgrid(xs, ys), q.displacement[1], q.displacement[0], color="c", angles="xy")
        ax.set_title(f"normal to {c.axis}, {c.axis} = {c.index}\nmean {c.mean:.4f}, std {c.std:.4f}, max {c.max:.4f} px;"
                     f" corr. length {c.correlation_length:.1f} px\nbounds: std {c.bound:.4f}, mean {c.bound_mean:.4f} px "
                     f"(noise floor {c.floor:.4f} px)",
                     fontsize=9)
        ax.set_xlabel(f"{c.components[1]} ({lab})")
        ax.set_ylabel(f"{c.components[0]} ({lab})")
        fig.colorbar(im, ax=ax, shrink=0.8, label="|u| of the 2-D Q4 field (pixel)")
    fig.suptitle(f"Cut check (paper 5.3) of {result_label(result)}: Q4-DIC of reference vs corrected cuts, "
                 f"ℓ = {result.info['element_size']}; a converged 3-D field stays within max({THRESHOLD} px, "
                 f"{K_NOISE:g} × noise floor), white-noise-like")
    return save(fig, path, dpi)
