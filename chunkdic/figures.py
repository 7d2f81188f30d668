"""Plotting helpers: what the figures of :mod:`chunkdic.report` and :mod:`chunkdic.crosscheck` share.

One idea: the pieces every figure is made of, without drawing any figure itself: an Agg
canvas created per figure with matplotlib's object-oriented API (no ``pyplot``, no global
backend switch, nothing at import), one image panel with its colour bar, the mid-planes of
a result's ROI and the axes and extent of a plane, the label of a result's voxel unit, and
results opened from paths.
"""

from __future__ import annotations

from pathlib import Path

from .errors import InputError
from .result import Result, open_result

__all__ = ["AXES", "figure", "panel", "as_results", "level_label", "mid_planes", "plane_extent"]

AXES = "zyx"


def figure(width: float, height: float):
    """A matplotlib ``Figure`` of ``width`` x ``height`` inches on its own Agg canvas (110 dpi)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def as_results(results) -> list[Result]:
    """One or several results (objects or paths) as a non-empty list of :class:`Result`."""
    if isinstance(results, (Result, str, Path)):
        results = [results]
    out = [r if isinstance(r, Result) else open_result(r) for r in results]
    if not out:
        raise InputError("no result given")
    return out


def level_label(result: Result) -> str:
    """Axis label of the result's voxel unit: ``"voxel, level S"``."""
    return f"voxel, level {int(result.info.get('level', 0))}"


def mid_planes(result: Result) -> dict[str, int]:
    """Index (level voxels) of the ROI mid-plane normal to each axis: ``{"z": .., "y": .., "x": ..}``."""
    return {AXES[a]: (r.start + r.stop) // 2 for a, r in enumerate(result.mesh.roi)}


def plane_extent(result: Result, normal: int):
    """imshow extent (columns axis, rows axis) of a plane; rows = first remaining axis."""
    roi = result.mesh.roi
    a, b = [k for k in range(3) if k != normal]
    return [roi[b].start - 0.5, roi[b].stop - 0.5, roi[a].start - 0.5, roi[a].stop - 0.5], AXES[a], AXES[b]


def panel(fig, ax, img, extent, title, xlabel, ylabel, cbar, **kw):
    """``img`` on ``ax`` (origin lower, nearest), with title, axis labels and a colour bar ``cbar``."""
    im = ax.imshow(img, origin="lower", extent=extent, interpolation="nearest", **kw)
    ax.set_title(title, fontsize=10)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    fig.colorbar(im, ax=ax, shrink=0.8, label=cbar)
    return im
