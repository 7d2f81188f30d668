"""Figures of a correlation (paper section 5, Figs. 5-10), with colour bars and units.

Every figure reads only what it shows: the cut planes are computed by worker tasks
(:func:`chunkdic.export.correction.planes`, one element layer per task) and only 2-D planes and
mesh-sized arrays reach the client. Figures are drawn with matplotlib's
object-oriented API on an Agg canvas created inside each function (no ``pyplot``, no
global backend switch, nothing at import). Every figure is written as PNG, PDF or SVG
(``fmt``) at a chosen resolution (``dpi``); axes are in the scan's physical unit when the
result carries a voxel size (:func:`chunkdic.plot.figures.frame`), else in voxels of its level.

- ``cut_x``, ``cut_y``, ``cut_z``: mid-plane cuts of the ROI normal to x, y, z of one result
  (``cuts_from``); top row reference, deformed and corrected (Figs. 6-8, one grey scale),
  bottom row ``f − g`` (before correction) and ``f − corrected`` (one diverging scale);
- ``residual``: the residual ``f - (λ g(X + u(X)) + μ)`` on the three mid-planes (the
  scans low-passed as correlated, the brightness found);
- ``uz_map``, ``uy_map``, ``ux_map``: displacement components on the mid-plane normal to x,
  one panel per result, common extent and colour bar, diverging map centred on 0 (Fig. 9;
  :mod:`chunkdic.plot.maps`);
- ``epszz_map``: ``eps_zz`` on that plane, linearly interpolated between element
  centres (Fig. 10);
- ``epszz_profile`` (and ``epszz_profile.csv``): mean ``eps_zz`` per element layer along z,
  one curve per result, with the truth for a synthetic pair (:mod:`chunkdic.plot.profile`);
- ``gap``: matching gap per iteration, one curve per result and level (section 5.1);
- ``uncertainty_map``: the per-node displacement uncertainty on the mid-plane normal
  to x, one panel per result;
- ``uncertainty.png`` (from :func:`chunkdic.analysis.metrology.uncertainty`): log-log ``sigma_U``
  versus element size with the power-law fit (Fig. 5).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.outputs import Outputs
from ..results.result import Result
from ..results.scans import input_paths, input_scans, interpolation_of, level_refs
from ..results.strain import DEFAULT_MEASURE, MEASURE_SYMBOLS, check_measure
from ..scheduler import open_runner
from ..export import correction
from .figures import (
    AXES,
    as_results,
    check_figure_options,
    common_frame,
    curve_style,
    figure,
    frame,
    mid_planes,
    panel,
    plane_extent,
    resolution_text,
    result_label,
    save,
    shared_colorbar,
    symmetric_limit,
    with_labels,
)
from .maps import plot_epszz_maps, plot_u_maps, plot_uncertainty_map, plot_uz_maps
from .profile import epszz_profile, synthetic_field, true_curve, write_profile_csv

log = logging.getLogger(__name__)

__all__ = ["report", "plot_cuts", "plot_u_maps", "plot_uz_maps", "plot_epszz_maps", "plot_epszz_profile",
           "plot_gap", "gap_figure", "plot_uncertainty", "plot_uncertainty_map", "mid_planes"]


# --------------------------------------------------------------------------- cuts


def plot_cuts(result, out_dir, *, ref=None, deformed=None, interpolation: str | None = None, scheduler=None,
              progress: Callable[[str], None] | None = None, fmt: str = "png",
              dpi: int | None = None) -> dict[str, str]:
    """Mid-plane cuts of reference, deformed and corrected images, and the residual.

    Writes ``cut_z``, ``cut_y``, ``cut_x`` (paper Figs. 6-8: reference, deformed and
    corrected on one grey scale; below, ``f − g`` before correction and ``f − corrected``
    on one diverging scale) and ``residual`` (three panels) into ``out_dir``.

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
        receives the three planes (:func:`chunkdic.export.correction.planes`).
    progress : callable(str), optional
        Called with a message per figure.
    fmt : {"png", "pdf", "svg"}
    dpi : int, optional

    Returns
    -------
    dict of str to str
        Figure name -> path.
    """

    result = as_results(result)[0]
    out_dir = Path(out_dir)
    interpolation = interpolation or interpolation_of(result)
    planes = mid_planes(result)
    fr = frame(result)
    lab = fr.unit
    paths, residuals = {}, {}
    # the runner first: with a cluster, missing levels are then written to scratch by its workers
    with open_runner(scheduler) as runner, level_refs(result, ref, deformed) as (f_ref, g_ref):
        for normal in (2, 1, 0):
            name = AXES[normal]
            idx = planes[name]
            cut = correction.planes(result, f_ref, g_ref, normal, idx, runner, interpolation=interpolation)
            residuals[name] = (cut["prepared"] - cut["corrected"], cut["prepared"])
            paths[f"cut_{name}"] = _cut_figure(result, normal, idx, cut, fr, out_dir / f"cut_{name}.{fmt}", dpi)
            if progress:
                progress(f"wrote {paths[f'cut_{name}']}")
    fig = figure(13, 4.4)
    axs = fig.subplots(1, 3)
    lim = max([np.nanpercentile(np.abs(r), 99.5) for r, _ in residuals.values() if np.isfinite(r).any()] or [1.0])
    for ax, normal in zip(axs, (2, 1, 0)):
        name = AXES[normal]
        r, f = residuals[name]
        extent, row_ax, col_ax = plane_extent(result, normal, fr)
        rng = float(np.nanmax(f) - np.nanmin(f)) or 1.0
        gap = float(np.sqrt(np.nanmean(r**2)) / rng) if np.isfinite(r).any() else float("nan")
        panel(fig, ax, r, extent, f"normal to {name}, {name} = {planes[name]}; gap {100 * gap:.2f} %",
              f"{col_ax} ({lab})", f"{row_ax} ({lab})", "f − corrected (grey level)",
              cmap="RdBu_r", vmin=-lim, vmax=lim)
    fig.suptitle(f"{result_label(result)}: residual f − (λ g(X + u(X)) + μ), scans low-passed as correlated, on the "
                 f"ROI mid-planes; final gap {100 * result.final_gap:.2f} %")
    paths["residual"] = save(fig, out_dir / f"residual.{fmt}", dpi)
    if progress:
        progress(f"wrote {paths['residual']}")
    return paths


def _cut_figure(result: Result, normal: int, idx: int, cut: dict, fr, path, dpi) -> str:
    """One cut figure: f, g, corrected (grey) over f − g and f − corrected (diverging)."""
    name = AXES[normal]
    f, g, c = cut["reference"], cut["deformed"], cut["corrected"]
    finite = np.concatenate([v[np.isfinite(v)] for v in (f, g, c)])
    vmin, vmax = np.percentile(finite, [0.5, 99.5]) if finite.size else (0, 1)
    # before correction the raw scans (what a user sees), after it the residual the engine
    # minimised (low-passed reference as correlated); one scale so the drop is visible
    diffs = (f - g, cut["prepared"] - c)
    lim = symmetric_limit(diffs, 99.5)
    extent, row_ax, col_ax = plane_extent(result, normal, fr)
    xl, yl = f"{col_ax} ({fr.unit})", f"{row_ax} ({fr.unit})"
    fig = figure(13.5, 8.4)
    axs = fig.subplots(2, 3)
    top = [panel(fig, ax, img, extent, title, xl, yl, None, cmap="gray", vmin=vmin, vmax=vmax)
           for ax, img, title in zip(axs[0], (f, g, c), ("(a) reference f", "(b) deformed g",
                                                          "(c) corrected λ g(X + u(X)) + μ"))]
    shared_colorbar(fig, top[0], axs[0], "grey level")
    bottom = [panel(fig, ax, img, extent, title, xl, yl, None, cmap="RdBu_r", vmin=-lim, vmax=lim)
              for ax, img, title in zip(axs[1, :2], diffs, ("(d) f − g, before correction",
                                                            "(e) f − corrected (residual, low-passed f)"))]
    shared_colorbar(fig, bottom[0], axs[1, :2], "difference (grey level)")
    axs[1, 2].set_visible(False)
    fig.suptitle(f"{result_label(result)}: mid-plane cut normal to {name}, {name} = {idx} (voxel of level "
                 f"{result.info.get('level', 0)}); {resolution_text(result)}")
    return save(fig, path, dpi)


# --------------------------------------------------------------------------- gap and ε_zz(z)


def _percent(v, _pos=None) -> str:
    """A tick label in plain percent: ``0.5 %``, ``2 %`` (no ``1e-2`` offsets)."""
    return f"{v:.4g} %"


def gap_figure(results):
    """The matching-gap figure (section 5.1): one curve per result and pyramid level.

    Each level's iterations form one labelled curve ("NAME: level s (ℓ = …)", NAME the
    result's :func:`~chunkdic.plot.figures.result_label`), from the coarsest, each curve in its
    own colour and line style (:func:`~chunkdic.plot.figures.curve_style`); the rigid-translation steps that open a level are drawn as black open squares
    (one legend entry), the Gauss-Newton iterations as filled dots. The y axis is
    logarithmic with plain percent ticks.

    Returns
    -------
    matplotlib.figure.Figure
        Not yet written (:func:`plot_gap` saves it); its legend labels are the curves'.
    """
    from matplotlib.ticker import FuncFormatter, LogLocator

    results = as_results(results)
    fig = figure(7.5, 4.5)
    ax = fig.subplots()
    rigid_done = False
    curve = 0
    for res in results:
        name = result_label(res)
        h = res.history
        gap = 100 * np.asarray(h["gap"], float)
        step = np.arange(len(gap))
        levels = np.asarray(h["level"])
        rigid = np.asarray(h["iteration"]) < 0
        for lev in dict.fromkeys(levels.tolist()):  # order of appearance: coarsest first
            on = levels == lev
            line, = ax.plot(step[on & ~rigid], gap[on & ~rigid], marker="o", ms=4, lw=1.2, **curve_style(curve),
                            label=f"{name}: level {lev} (ℓ = {res.info['element_size']})")
            curve += 1
            if (on & rigid).any():
                ax.plot(step[on & rigid], gap[on & rigid], "s", ms=8, mfc="none", mec="k", mew=1.2,
                        label=None if rigid_done else "rigid translation steps")
                rigid_done = True
                # join the rigid steps to the level's first iteration, thin and in the level's colour
                k = np.nonzero(on)[0]
                ax.plot(step[k], gap[k], "-", lw=0.6, color=line.get_color())
    ax.set_yscale("log")
    ax.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.yaxis.set_minor_locator(LogLocator(base=10, subs=np.arange(1, 10)))
    ax.yaxis.set_major_formatter(FuncFormatter(_percent))
    ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, p: ""))
    ax.set_xlabel("evaluation (rigid steps □, then Gauss–Newton iterations ●, level by level)")
    ax.set_ylabel("matching gap R")
    ax.set_title("Matching gap per iteration")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def plot_gap(results, path, *, dpi: int | None = None) -> str:
    """Write :func:`gap_figure` to ``path`` (``.png``, ``.pdf`` or ``.svg``); returns ``path``."""
    return save(gap_figure(results), path, dpi)


def plot_epszz_profile(results, path, *, ref=None, deformed=None, dpi: int | None = None,
                       strain: str = DEFAULT_MEASURE) -> dict[str, str]:
    """ε_zz(z): mean zz strain per element layer along z, one curve per result, and the truth
    when the pair is synthetic (:mod:`chunkdic.plot.profile`); the numbers go to a CSV next to
    the figure (same name, ``.csv``; columns :data:`chunkdic.plot.profile.PROFILE_COLUMNS`).

    Parameters
    ----------
    results : Result, path or sequence of them
    path : path
        Figure file (``.png``, ``.pdf`` or ``.svg``).
    ref, deformed : path, optional
        The scans, when not at the paths recorded in the results (where the synthetic
        truth is looked for).
    dpi : int, optional
    strain : {"green-lagrange", "small"}
        Strain measure of the curves and the truth (default Green–Lagrange).

    Returns
    -------
    dict
        ``{"epszz_profile": figure path, "epszz_profile_csv": CSV path}``.
    """

    results = as_results(results)
    frames = common_frame(results)
    rows, truth = [], None
    for res, fr in zip(results, frames):
        fld = synthetic_field(res, ref, deformed)
        rows.append((res, epszz_profile(res, fld, check_measure(strain)), fr))
        if fld is not None and truth is None:
            zt, et = true_curve(res, fld, strain=strain)
            truth = (fr.position(0, zt), et)
    fig = figure(6.0, 5.2)
    ax = fig.subplots()
    if truth is not None:
        ax.plot(truth[1], truth[0], "-", color="0.3", lw=1, label="truth (plane mean)")
    for i, (res, prof, fr) in enumerate(rows):
        name = result_label(res)
        line, = ax.plot(prof.eps_zz, fr.position(0, prof.z), marker="o", ms=5, **curve_style(i),
                        label=f"{name}: {resolution_text(res)} (level {res.info.get('level', 0)})")
        if prof.eps_zz_true is not None:
            ax.plot(prof.eps_zz_true, fr.position(0, prof.z), "x", ms=7, color=line.get_color(),
                    label=f"{name}: truth per layer")
    ax.axvline(0.0, color="k", lw=0.5)
    ax.xaxis.get_major_formatter().set_useOffset(False)
    ax.set_xlabel(f"mean {MEASURE_SYMBOLS[strain]}_zz per element layer (–), {strain} strain")
    ax.set_ylabel(f"z ({frames[0].unit})")
    ax.set_title(f"{MEASURE_SYMBOLS[strain]}_zz(z) profile")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    out = {"epszz_profile": save(fig, path, dpi)}
    out["epszz_profile_csv"] = write_profile_csv(rows, Path(path).with_suffix(".csv"))
    return out


def plot_uncertainty(report, path, *, dpi: int | None = None) -> str:
    """Log-log ``sigma_U`` versus element size with the power-law fit (paper Fig. 5).

    Parameters
    ----------
    report : chunkdic.analysis.metrology.UncertaintyReport
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
    return save(fig, path, dpi)


# --------------------------------------------------------------------------- all


def _cuts_result(results: list[Result], cuts_from) -> Result:
    """The result whose field the cuts use: ``cuts_from`` (a Result among ``results``, or the
    path of one), default the first."""
    if cuts_from is None:
        return results[0]
    if isinstance(cuts_from, Result):
        for res in results:
            if res is cuts_from:
                return res
    else:
        want = os.path.realpath(os.fspath(cuts_from))
        for res in results:
            if res.path is not None and os.path.realpath(res.path) == want:
                return res
    given = cuts_from.path if isinstance(cuts_from, Result) else cuts_from
    raise InputError(f"--cuts-from {given}: not one of the results given "
                     f"({', '.join(str(r.path) for r in results)})")


def report(results, out_dir, *, ref=None, deformed=None, interpolation: str | None = None, scheduler=None,
           overwrite: bool = False, progress: Callable[[str], None] | None = None, cuts_from=None,
           fmt: str = "png", dpi: int | None = None, labels=None, strain: str = DEFAULT_MEASURE,
           shown: Callable[[Result], Result] | None = None,
           extra: dict[str, Callable] | None = None) -> dict[str, str]:
    """All figures of one or several results into ``out_dir``.

    Cuts and residual come from one result (``cuts_from``, default the first; they need the
    scans: recorded paths, or ``ref``/``deformed``); the maps, the ε_zz(z) profile and the
    gap plot show every result (one panel or curve each, e.g. one per element size as in
    paper Figs. 9-10).

    Parameters
    ----------
    results : Result, path or sequence of them
    out_dir : path
        Created if missing; an existing folder must be empty, or a figures folder that
        chunkdic wrote with ``overwrite`` (see :mod:`chunkdic.io.outputs`).
    ref, deformed : path, optional
    interpolation : {"cubic", "linear"}, optional
    scheduler
        Where the cut planes are computed (:func:`plot_cuts`).
    overwrite : bool
        Replace the figures of an earlier report in ``out_dir``.
    progress : callable(str), optional
        One message per figure written (or skipped, with the reason).
    cuts_from : Result or path, optional
        The result whose field the cuts use; must be one of ``results``.
    fmt : {"png", "pdf", "svg"}
        File format of every figure.
    dpi : int, optional
        Resolution of every figure, dots per inch (default
        :data:`chunkdic.plot.figures.DEFAULT_DPI`; a PNG's pixel size scales with it).
    labels : sequence of str, optional
        The name of each result in every legend and panel title (default: its file stem;
        ``--label`` on the command line).
    strain : {"green-lagrange", "small"}
        Strain measure of the ε_zz map and profile (default Green–Lagrange: a rigid rotation
        shows no strain; ``"small"``: the paper's).
    shown : callable(Result) -> Result, optional
        The field the maps and profiles show (e.g. without its rigid motion,
        :func:`chunkdic.analysis.rigid.remove_rigid`); the cuts keep the measured field, which
        the corrected image needs.
    extra : dict of str to callable(path, dpi) -> str, optional
        More figures, by name (the file is ``NAME.{fmt}``), written with the others (a
        profile along a line: ``chunkdic report --profile``).

    Returns
    -------
    dict of str to str
        Figure name -> path (and ``epszz_profile_csv`` -> the profile's numbers).
    """

    results = as_results(results)
    for res in results:
        res.check_displacement()
    if interpolation not in (None, "cubic", "linear"):
        raise InputError(f"interpolation must be cubic or linear, got {interpolation!r}")
    check_figure_options(fmt, dpi)
    check_measure(strain)
    cut_res = _cuts_result(results, cuts_from)
    at = next(i for i, r in enumerate(results) if r is cut_res)
    results = with_labels(results, labels)
    cut_res = results[at]
    say = progress or (lambda msg: None)
    skip = None
    try:
        input_scans(cut_res, ref, deformed)  # checked before anything is written
    except InputError as exc:
        recorded = [p for p in (cut_res.info.get("inputs") or {}).values()
                    if isinstance(p, str) and not p.startswith("<in-memory") and Path(p).exists()]
        if ref is not None or deformed is not None or len(recorded) == 2:
            raise  # scans given, or on disk but unusable (damaged, another shape): refused
        skip = exc  # scans not on disk (in-memory inputs, moved): the cuts are skipped
    inputs = [p for r in results for p in input_paths(r, ref, deformed)]
    plan = Outputs(inputs=inputs, overwrite=overwrite)
    out_dir = plan.add(out_dir, "figures").final
    paths = {}

    def done(name, path):
        paths[name] = path
        say(f"wrote {path}")

    fields = results if shown is None else [shown(r) for r in results]
    with plan:  # a failure removes the figures this run wrote, never older files
        for comp in "zyx":
            done(f"u{comp}_map", plot_u_maps(fields, out_dir / f"u{comp}_map.{fmt}", comp, dpi=dpi))
        done("epszz_map", plot_epszz_maps(fields, out_dir / f"epszz_map.{fmt}", dpi=dpi, strain=strain))
        for name, fn in (("gap", plot_gap), ("uncertainty_map", plot_uncertainty_map)):
            done(name, fn(fields, out_dir / f"{name}.{fmt}", dpi=dpi))
        for name, path in plot_epszz_profile(fields, out_dir / f"epszz_profile.{fmt}", ref=ref,
                                             deformed=deformed, dpi=dpi, strain=strain).items():
            done(name, path)
        for name, make in (extra or {}).items():
            done(name, make(out_dir / f"{name}.{fmt}", dpi))
        if skip is None:
            paths.update(plot_cuts(cut_res, out_dir, ref=ref, deformed=deformed,
                                   interpolation=interpolation or interpolation_of(cut_res), scheduler=scheduler,
                                   progress=say, fmt=fmt, dpi=dpi))
        else:
            say(f"skipped the cuts and residual: {skip}")
    return paths
