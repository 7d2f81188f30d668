"""Figures of the mechanics readings: a gauge's curve over a series, a profile along a line.

Both take the plain dicts of the analyses (``GaugeCurve.as_dict()``, ``Profile.as_dict()`` of
:mod:`chunkdic.analysis`), so that this layer stays below the analyses that compute them.
"""

from __future__ import annotations

import numpy as np

from .figures import figure, save

__all__ = ["plot_gauge", "plot_profile"]


def _array(values) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], np.float64)


def plot_gauge(curve: dict, path, *, dpi: int | None = None) -> str:
    """Strain of a gauge per step with its confidence interval (error bars); returns the path.

    Parameters
    ----------
    curve : dict
        :meth:`chunkdic.analysis.gauge.GaugeCurve.as_dict`.
    path : path
        The figure (PNG, PDF or SVG by its suffix).
    """
    r = curve["readings"]
    step = _array([x["step"] for x in r])
    strain = _array([x["strain"] for x in r])
    low, high = _array([x["low"] for x in r]), _array([x["high"] for x in r])
    fig = figure(5.5, 3.6)
    ax = fig.add_subplot(1, 1, 1)
    err = np.vstack([strain - low, high - strain])
    ax.errorbar(step, strain, yerr=np.where(np.isfinite(err), err, 0.0), fmt="o-", capsize=3,
                label=f"strain ({100 * curve['confidence']:g} % interval)")
    ax.axhline(0.0, color="0.6", lw=0.8)
    ax.set_xlabel("step")
    ax.set_ylabel("strain of the gauge (ΔL / L)")
    ax.set_title(f"gauge {curve['gauge']}", fontsize=9)
    ax.legend(fontsize=8)
    if step.size <= 12:
        ax.set_xticks(step)
    return save(fig, path, dpi)


def plot_profile(profiles: list[dict], path, *, names=("Uz", "Uy", "Ux"), labels=None, dpi: int | None = None) -> str:
    """Displacement and strain along a line with ± one standard uncertainty bands; returns the path.

    Parameters
    ----------
    profiles : list of dict
        :meth:`chunkdic.analysis.stats.Profile.as_dict` of one or several results (the same line).
    path : path
    names : sequence of str
        The displacement components of the first panel; the second shows the normal strains.
    labels : sequence of str, optional
        One name per profile for the legend.
    """
    fig = figure(6.5, 5.5)
    top, bottom = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2, sharex=None)
    colours = ("C0", "C1", "C2", "C3", "C4", "C5")
    for k, prof in enumerate(profiles):
        d = _array(prof["distance"])
        tag = "" if labels is None else f"{labels[k]}: "
        strains = [n for n in prof["values"] if n not in ("Uz", "Uy", "Ux")][:3]
        for ax, which in ((top, names), (bottom, strains)):
            for c, name in enumerate(which):
                v, s = _array(prof["values"][name]), _array(prof["sigma"][name])
                style = "-" if k == 0 else "--"
                ax.plot(d, v, style, color=colours[c % 6], label=f"{tag}{name}")
                ax.fill_between(d, v - s, v + s, color=colours[c % 6], alpha=0.2, lw=0)
    unit = profiles[0].get("unit", "voxel")
    top.set_ylabel(f"displacement ({unit})")
    bottom.set_ylabel(f"strain ({profiles[0]['measure']})")
    bottom.set_xlabel("distance along the line (level-0 voxels)")
    top.set_title(f"profile along the {profiles[0]['region']} (bands: ± one standard uncertainty)", fontsize=9)
    for ax in (top, bottom):
        ax.legend(fontsize=7, ncol=3)
        ax.grid(alpha=0.3)
    return save(fig, path, dpi)
