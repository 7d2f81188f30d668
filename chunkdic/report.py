"""Figures of a correlation (paper section 5, Figs. 5-10): PNG files with colour bars and units.

Every figure reads only what it shows: the cut planes are computed by worker tasks
(:func:`chunkdic.correction.planes`, one element layer per task) and only 2-D planes and
mesh-sized arrays reach the client. Figures are drawn with matplotlib's
object-oriented API on an Agg canvas created inside each function (no ``pyplot``, no
global backend switch, nothing at import).

- ``cut_x.png``, ``cut_y.png``, ``cut_z.png``: mid-plane cuts of the ROI normal to x, y, z;
  reference, deformed and corrected side by side (Figs. 6-8);
- ``residual.png``: the residual ``f - (λ g(X + u(X)) + μ)`` on the three mid-planes (the
  scans low-passed as correlated, the brightness found);
- ``uz_map.png``: ``Uz`` on the mid-plane normal to x, one panel per result (Fig. 9);
- ``epszz_map.png``: ``eps_zz`` on that plane, linearly interpolated between element
  centres (Fig. 10);
- ``gap.png``: matching gap per iteration (section 5.1);
- ``uncertainty_map.png``: the per-node displacement uncertainty on the mid-plane normal
  to x, one panel per result;
- ``uncertainty.png`` (from :func:`chunkdic.metrology.uncertainty`): log-log ``sigma_U``
  versus element size with the power-law fit (Fig. 5).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from . import correction
from .errors import InputError
from .figures import AXES, as_results, figure, level_label, mid_planes, panel, plane_extent
from .result import Result

log = logging.getLogger(__name__)

__all__ = ["report", "plot_cuts", "plot_uz_maps", "plot_epszz_maps", "plot_gap", "plot_uncertainty",
           "plot_uncertainty_map",
           "mid_planes"]


# --------------------------------------------------------------------------- cuts


def plot_cuts(result, out_dir, *, ref=None, deformed=None, interpolation: str | None = None, scheduler=None,
              progress: Callable[[str], None] | None = None) -> dict[str, str]:
    """Mid-plane cuts of reference, deformed and corrected images, and the residual.

    Writes ``cut_z.png``, ``cut_y.png``, ``cut_x.png`` (three panels each, shared grey scale,
    paper Figs. 6-8) and ``residual.png`` (three panels) into ``out_dir``.

    Parameters
    ----------
    result : Result or path
    out_dir : path
    ref, deformed : path, optional
        The scans (default: the paths recorded in the result).
    interpolation : {"cubic", "linear"}, optional
        Default: the result's.
    scheduler
        Where the plane tasks run, as in :func:`chunkdic.correlate`. The client only
        receives the three planes (:func:`chunkdic.correction.planes`).
    progress : callable(str), optional
        Called with a message per figure.

    Returns
    -------
    dict of str to str
        Figure name -> path.
    """
    from .resultscans import interpolation_of, level_refs
    from .scheduler import open_runner

    result = as_results(result)[0]
    out_dir = Path(out_dir)
    interpolation = interpolation or interpolation_of(result)
    planes = mid_planes(result)
    lab = level_label(result)
    paths, residuals = {}, {}
    # the runner first: with a cluster, missing levels are then written to scratch by its workers
    with open_runner(scheduler) as runner, level_refs(result, ref, deformed) as (f_ref, g_ref):
        for normal in (2, 1, 0):
            name = AXES[normal]
            idx = planes[name]
            cut = correction.planes(result, f_ref, g_ref, normal, idx, runner, interpolation=interpolation)
            f, g, c = cut["reference"], cut["deformed"], cut["corrected"]
            residuals[name] = (cut["prepared"] - c, cut["prepared"])
            finite = np.concatenate([v[np.isfinite(v)] for v in (f, g, c)])
            vmin, vmax = np.percentile(finite, [0.5, 99.5]) if finite.size else (0, 1)
            extent, row_ax, col_ax = plane_extent(result, normal)
            fig = figure(13, 4.4)
            axs = fig.subplots(1, 3)
            for ax, img, title in zip(axs, (f, g, c), ("(a) reference f", "(b) deformed g",
                                                       "(c) corrected λ g(X + u(X)) + μ")):
                panel(fig, ax, img, extent, title, f"{col_ax} ({lab})", f"{row_ax} ({lab})",
                      "grey level", cmap="gray", vmin=vmin, vmax=vmax)
            fig.suptitle(f"Mid-plane cut normal to {name}, {name} = {idx} ({lab}); ℓ = {result.info['element_size']}")
            path = out_dir / f"cut_{name}.png"
            fig.savefig(path)
            paths[f"cut_{name}"] = str(path)
            if progress:
                progress(f"wrote {path}")
    fig = figure(13, 4.4)
    axs = fig.subplots(1, 3)
    lim = max([np.nanpercentile(np.abs(r), 99.5) for r, _ in residuals.values() if np.isfinite(r).any()] or [1.0])
    for ax, normal in zip(axs, (2, 1, 0)):
        name = AXES[normal]
        r, f = residuals[name]
        extent, row_ax, col_ax = plane_extent(result, normal)
        rng = float(np.nanmax(f) - np.nanmin(f)) or 1.0
        gap = float(np.sqrt(np.nanmean(r**2)) / rng) if np.isfinite(r).any() else float("nan")
        panel(fig, ax, r, extent, f"normal to {name}, {name} = {planes[name]}; gap {100 * gap:.2f} %",
              f"{col_ax} ({lab})", f"{row_ax} ({lab})", "f − corrected (grey level)",
              cmap="RdBu_r", vmin=-lim, vmax=lim)
    fig.suptitle(f"Residual f − (λ g(X + u(X)) + μ), scans low-passed as correlated, on the ROI mid-planes; final gap {100 * result.final_gap:.2f} %")
    path = out_dir / "residual.png"
    fig.savefig(path)
    paths["residual"] = str(path)
    if progress:
        progress(f"wrote {path}")
    return paths


# --------------------------------------------------------------------------- maps


def _grid(n: int):
    cols = min(n, 2 if n == 4 else 3)
    return (n + cols - 1) // cols, cols


def _x_plane(results: list[Result]) -> int:
    """Mid-plane normal to x of the first result (the paper's x = 100 voxels)."""
    return mid_planes(results[0])["x"]


def _x_plane_map(res: Result, nodal: np.ndarray, x: int) -> np.ndarray:
    """A nodal field (k, nz, ny, nx) on the ROI plane normal to x, C8-interpolated: (k, Lz, Ly)."""
    roi = res.mesh.roi
    zz, yy = np.meshgrid(np.arange(roi[0].start, roi[0].stop, dtype=float),
                         np.arange(roi[1].start, roi[1].stop, dtype=float), indexing="ij")
    return res.mesh.evaluate(nodal, np.stack([zz, yy, np.full_like(zz, x)]))


def plot_uncertainty_map(results, path, *, x: int | None = None) -> str:
    """Per-node standard uncertainty ``σ_U`` (pooled over the three components) on the plane
    normal to x, one panel per result (``Result.uncertainty``; docs/engine.md).

    Returns ``path``; results without an uncertainty are shown as empty panels.
    """
    results = as_results(results)
    x = _x_plane(results) if x is None else int(x)
    maps = []
    for res in results:
        if res.uncertainty is None:
            maps.append(None)
            continue
        pooled = np.sqrt(np.mean(res.uncertainty**2, axis=0))[None]
        maps.append(_x_plane_map(res, pooled, x)[0])
    finite = [m[np.isfinite(m)] for m in maps if m is not None]
    vmax = max([float(v.max()) for v in finite if v.size] or [1.0])
    rows, cols = _grid(len(results))
    fig = figure(5.2 * cols, 4.4 * rows)
    axs = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    for ax, res, m in zip(axs, results, maps):
        extent, _, _ = plane_extent(res, 2)
        lab = level_label(res)
        if m is None:
            ax.set_title(f"ℓ = {res.info['element_size']}: no uncertainty in this result", fontsize=10)
            ax.set_axis_off()
            continue
        panel(fig, ax, m, extent, f"ℓ = {res.info['element_size']}", f"y ({lab})", f"z ({lab})",
              f"σ_U ({lab})", cmap="magma", vmin=0.0, vmax=vmax)
    for ax in axs[len(results):]:
        ax.set_visible(False)
    fig.suptitle(f"Per-node displacement uncertainty σ_U on the plane x = {x}")
    fig.savefig(path)
    return str(path)


def plot_uz_maps(results, path, *, x: int | None = None) -> str:
    """``Uz`` on the plane normal to x, one panel per result (paper Fig. 9).

    Parameters
    ----------
    results : Result, path or sequence of them
        Results of the same pair (e.g. several element sizes), same level.
    path : path
        PNG file.
    x : int, optional
        Plane index, voxels of the level (default: mid-plane of the first result's ROI).

    Returns
    -------
    str
        ``path``.
    """
    results = as_results(results)
    x = _x_plane(results) if x is None else int(x)
    maps = [_x_plane_map(res, res.displacement, x)[0] for res in results]
    vmin = min(float(np.nanmin(m)) for m in maps)
    vmax = max(float(np.nanmax(m)) for m in maps)
    rows, cols = _grid(len(results))
    fig = figure(5.2 * cols, 4.4 * rows)
    axs = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    for ax, res, m in zip(axs, results, maps):
        extent, row_ax, col_ax = plane_extent(res, 2)
        lab = level_label(res)
        panel(fig, ax, m, extent, f"ℓ = {res.info['element_size']}", f"y ({lab})", f"z ({lab})",
              f"Uz ({lab})", cmap="viridis", vmin=vmin, vmax=vmax)
    for ax in axs[len(results):]:
        ax.set_visible(False)
    fig.suptitle(f"Uz on the plane x = {x}")
    fig.savefig(path)
    return str(path)


def _epszz_plane(res: Result, x: float):
    """eps_zz on the plane ``x`` at the element centres (linear along x between centre
    layers) and the centre coordinates ``(cz, cy)``."""
    mesh = res.mesh
    eps = res.element_strain()[0, 0]  # (ez, ey, ex)
    ell = mesh.element_size
    centres = [o + ell * (np.arange(n) + 0.5) - 0.5 for o, n in zip(mesh.origin, mesh.shape)]
    cx = centres[2]
    if len(cx) == 1:
        layer = eps[:, :, 0]
    else:
        k = int(np.clip(np.searchsorted(cx, x) - 1, 0, len(cx) - 2))
        w = float(np.clip((x - cx[k]) / ell, 0.0, 1.0))
        layer = (1 - w) * eps[:, :, k] + w * eps[:, :, k + 1]
    return layer, centres[0], centres[1]


def plot_epszz_maps(results, path, *, x: int | None = None, step: float = 0.5) -> str:
    """``eps_zz`` on the plane normal to x, interpolated linearly between element centres
    (paper Fig. 10: "linearly interpolated between element centers where the element strain
    has been imposed"), one panel per result.

    The map covers the hull of the element centres (half an element inside the ROI);
    along x, the two nearest layers of centres are interpolated linearly too.

    Parameters
    ----------
    results : Result, path or sequence of them
    path : path
        PNG file.
    x : int, optional
        Plane index (default: mid-plane of the first result's ROI).
    step : float
        Pixel size of the rendered map, voxels.
    """
    from scipy.interpolate import RegularGridInterpolator

    results = as_results(results)
    x = _x_plane(results) if x is None else int(x)
    maps = []
    for res in results:
        layer, cz, cy = _epszz_plane(res, x)
        if len(cz) < 2 or len(cy) < 2:
            zz, yy = cz, cy
            img = layer
        else:
            zz = np.arange(cz[0], cz[-1] + 1e-9, step)
            yy = np.arange(cy[0], cy[-1] + 1e-9, step)
            interp = RegularGridInterpolator((cz, cy), layer, method="linear")
            img = interp(np.stack(np.meshgrid(zz, yy, indexing="ij"), axis=-1))
        maps.append((img, [yy[0], yy[-1], zz[0], zz[-1]]))
    lim = max(float(np.abs(m).max()) for m, _ in maps) or 1e-6
    rows, cols = _grid(len(results))
    fig = figure(5.2 * cols, 4.4 * rows)
    axs = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    for ax, res, (img, extent) in zip(axs, results, maps):
        lab = level_label(res)
        im = ax.imshow(img, origin="lower", extent=extent, cmap="RdBu_r", vmin=-lim, vmax=lim,
                       interpolation="bilinear")
        ax.set_title(f"ℓ = {res.info['element_size']}", fontsize=10)
        ax.set_xlabel(f"y ({lab})")
        ax.set_ylabel(f"z ({lab})")
        fig.colorbar(im, ax=ax, shrink=0.8, label="ε_zz (–)")
    for ax in axs[len(results):]:
        ax.set_visible(False)
    fig.suptitle(f"ε_zz on the plane x = {x}, linear between element centres")
    fig.savefig(path)
    return str(path)


def plot_gap(results, path) -> str:
    """Matching gap (%) per iteration, every level, one line per result (section 5.1).

    Rigid-translation steps come first (open markers), then Gauss-Newton iterations
    (filled markers), level by level from the coarsest.
    """
    results = as_results(results)
    fig = figure(7.5, 4.5)
    ax = fig.subplots()
    for res in results:
        h = res.history
        gap = 100 * np.asarray(h["gap"], float)
        step = np.arange(len(gap))
        line, = ax.semilogy(step, gap, "-", lw=1, label=f"ℓ = {res.info['element_size']}")
        rigid = np.asarray(h["iteration"]) < 0
        ax.semilogy(step[rigid], gap[rigid], "o", mfc="none", color=line.get_color())
        ax.semilogy(step[~rigid], gap[~rigid], "o", ms=4, color=line.get_color())
        levels = np.asarray(h["level"])
        for k in np.nonzero(np.diff(levels))[0]:
            ax.axvline(k + 0.5, color=line.get_color(), lw=0.5, ls=":")
    ax.set_xlabel("evaluation (rigid steps ○, then Gauss–Newton iterations ●; dotted: next level)")
    ax.set_ylabel("matching gap R (%)")
    ax.set_title("Matching gap per iteration")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.savefig(path)
    return str(path)


def plot_uncertainty(report, path) -> str:
    """Log-log ``sigma_U`` versus element size with the power-law fit (paper Fig. 5).

    Parameters
    ----------
    report : chunkdic.metrology.UncertaintyReport
    path : path
        PNG file.
    """
    rows = report.rows
    ell = np.array([r["element_size"] for r in rows], float)
    fig = figure(6.5, 4.8)
    ax = fig.subplots()
    for key, mark, lab in (("std_z", "v", "σ(Uz)"), ("std_y", "^", "σ(Uy)"), ("std_x", "s", "σ(Ux)")):
        ax.loglog(ell, [max(r[key], 1e-12) for r in rows], mark, ms=4, alpha=0.5, label=lab)
    ax.loglog(ell, [max(r["sigma_u"], 1e-12) for r in rows], "o", mfc="none", ms=9, mew=1.5, color="k",
              label="σ(U) (RMS of components)")
    if report.fit is not None:
        xs = np.geomspace(ell.min() * 0.9, ell.max() * 1.1, 50)
        ax.loglog(xs, report.fit(xs), "-", color="k",
                  label=f"fit A^(α+1) ℓ^(−α): A = {report.fit.A:.3g} vox., α = {report.fit.alpha:.3g}")
    t = ", ".join(f"{v:g}" for v in report.shift)
    ax.set_xticks(sorted(set(ell)), [f"{v:g}" for v in sorted(set(ell))])
    ax.set_xticks([], minor=True)
    ax.set_xlabel("element size ℓ (voxel)")
    ax.set_ylabel("displacement uncertainty σ(U) (voxel)")
    ax.set_title(f"A-priori uncertainty, Fourier shift ({t}) voxel")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path)
    return str(path)


# --------------------------------------------------------------------------- all


def report(results, out_dir, *, ref=None, deformed=None, interpolation: str | None = None, scheduler=None,
           overwrite: bool = False, progress: Callable[[str], None] | None = None) -> dict[str, str]:
    """All figures of one or several results into ``out_dir``.

    Cuts and residual come from the first result (they need the scans: recorded paths, or
    ``ref``/``deformed``); ``Uz``, ``eps_zz`` maps and the gap plot show every result
    (one panel or line each, e.g. one per element size as in paper Figs. 9-10).

    Parameters
    ----------
    results : Result, path or sequence of them
    out_dir : path
        Created if missing; an existing folder must be empty, or a figures folder that
        chunkdic wrote with ``overwrite`` (see :mod:`chunkdic.outputs`).
    ref, deformed : path, optional
    interpolation : {"cubic", "linear"}, optional
    scheduler
        Where the cut planes are computed (:func:`plot_cuts`).
    overwrite : bool
        Replace the figures of an earlier report in ``out_dir``.
    progress : callable(str), optional
        One message per figure written (or skipped, with the reason).

    Returns
    -------
    dict of str to str
        Figure name -> PNG path.
    """
    from .resultscans import input_paths, input_scans, interpolation_of
    from .inputs import check_displacement
    from .outputs import Outputs

    results = as_results(results)
    for res in results:
        check_displacement(res.displacement, res.path, res.flags)
    if interpolation not in (None, "cubic", "linear"):
        raise InputError(f"interpolation must be cubic or linear, got {interpolation!r}")
    say = progress or (lambda msg: None)
    skip = None
    try:
        input_scans(results[0], ref, deformed)  # checked before anything is written
    except InputError as exc:
        recorded = [p for p in (results[0].info.get("inputs") or {}).values()
                    if isinstance(p, str) and not p.startswith("<in-memory") and Path(p).exists()]
        if ref is not None or deformed is not None or len(recorded) == 2:
            raise  # scans given, or on disk but unusable (damaged, another shape): refused
        skip = exc  # scans not on disk (in-memory inputs, moved): the cuts are skipped
    inputs = [p for r in results for p in input_paths(r, ref, deformed)]
    plan = Outputs(inputs=inputs, overwrite=overwrite)
    out_dir = plan.add(out_dir, "figures").final
    paths = {}
    with plan:  # a failure removes the figures this run wrote, never older files
        for name, fn in (("uz_map", plot_uz_maps), ("epszz_map", plot_epszz_maps), ("gap", plot_gap),
                         ("uncertainty_map", plot_uncertainty_map)):
            paths[name] = fn(results, out_dir / f"{name}.png")
            say(f"wrote {paths[name]}")
        if skip is None:
            paths.update(plot_cuts(results[0], out_dir, ref=ref, deformed=deformed,
                                   interpolation=interpolation or interpolation_of(results[0]), scheduler=scheduler,
                                   progress=say))
        else:
            say(f"skipped the cuts and residual: {skip}")
    return paths
