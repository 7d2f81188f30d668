"""Plotting helpers: what the figures of :mod:`chunkdic.plot.report` and :mod:`chunkdic.analysis.crosscheck` share.

One idea: the pieces every figure is made of, without drawing any figure itself: an Agg
canvas created per figure with matplotlib's object-oriented API (no ``pyplot``, no global
backend switch, nothing at import), one image panel with its colour bar, the mid-planes of
a result's ROI and the axes and extent of a plane, the label of a result's voxel unit, the
frame that turns level voxels into the scan's physical unit, a colour bar shared by the
panels of a figure, the file formats and the writing of a figure at a chosen resolution,
and results opened from paths.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..mesh import level0_position
from ..results.result import Result, open_result

__all__ = ["AXES", "FORMATS", "DEFAULT_DPI", "Frame", "frame", "figure", "panel", "save", "check_figure_options",
           "shared_colorbar",
           "symmetric_limit", "common_frame", "curve_style", "with_labels", "LINE_STYLES", "as_results", "level_label", "result_label", "mid_planes", "plane_extent"]

AXES = "zyx"
#: file formats of the figures (matplotlib writes each from the file's extension)
FORMATS = ("png", "pdf", "svg")
#: resolution of the figures unless told otherwise (dots per inch)
DEFAULT_DPI = 110
#: short spellings of the OME-NGFF unit names on axes and colour bars
_SHORT_UNITS = {"micrometer": "µm", "millimeter": "mm", "nanometer": "nm", "centimeter": "cm", "meter": "m",
                "angstrom": "Å"}


def figure(width: float, height: float):
    """A matplotlib ``Figure`` of ``width`` x ``height`` inches on its own Agg canvas (110 dpi)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=DEFAULT_DPI, layout="constrained")
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


def result_label(result: Result) -> str:
    """The name of a result in legends and titles: ``info["label"]`` when given (``--label``),
    else its file stem (``m.zarr`` -> ``m``; a series step ``s.zarr/steps/002-cumulative`` ->
    ``s:002-cumulative``), else ``result``."""
    label = (result.info or {}).get("label")
    if label:
        return str(label)
    if not result.path:
        return "result"
    from pathlib import Path

    p = Path(str(result.path))
    stem = p.name[:-5] if p.name.endswith(".zarr") else p.name
    if p.parent.name in ("steps", "composed") and p.parent.parent.name:
        parent = p.parent.parent.name
        return f"{parent[:-5] if parent.endswith('.zarr') else parent}:{stem}"
    return stem


#: the regularisation kinds as figure titles name them
REGULARIZATION_NAMES = {"tikhonov": "Tikhonov", "equilibrium-gap": "equilibrium gap"}


def resolution_text(result: Result) -> str:
    """ℓ and the resolution it buys, for every title that names ℓ:
    ``ℓ = 8 vox, Tikhonov 16 vox, l10 % ≥ 28 vox`` (level-0 voxels, as ``Result.info``
    records them: the element size, the regularisation's kind and length, and the nominal
    l10 % they imply, a lower bound of the spatial resolution that ``chunkdic resolution``
    measures). A result without a regularisation record (older ones) says ``ℓ`` alone."""
    info = result.info or {}
    text = f"ℓ = {info['element_size']} vox"
    reg = info.get("regularization") or {}
    if reg.get("kind") == "none":
        text += ", unregularised"
    elif reg.get("length"):
        text += f", {REGULARIZATION_NAMES.get(reg['kind'], reg['kind'])} {reg['length']:.0f} vox"
    if reg.get("nominal_l10"):
        text += f", l10 % ≥ {reg['nominal_l10']:.0f} vox"
    return text


#: line styles of curves 11-20, 21-30, ... (the first ten: solid, in matplotlib's ten colours)
LINE_STYLES = ("-", "--", ":", "-.")


def curve_style(i: int) -> dict:
    """Colour and line style of curve ``i`` of a figure: the ten ``tab10`` colours, then
    the same colours dashed, dotted, dash-dotted; 40 curves have distinct pairs."""
    from matplotlib import colormaps

    return {"color": colormaps["tab10"](i % 10), "linestyle": LINE_STYLES[(i // 10) % len(LINE_STYLES)]}


def with_labels(results: list[Result], labels=None) -> list[Result]:
    """The results with the names their figures show (``info["label"]``, :func:`result_label`):
    ``labels`` (one per result), else their file stems, made distinct by the parent folder
    when two stems agree. Copies (sharing the arrays); the results given are not changed."""
    import dataclasses

    if labels is not None:
        labels = [str(v) for v in labels]
        if len(labels) != len(results):
            raise InputError(f"{len(labels)} label(s) for {len(results)} result(s): give one --label per result")
    else:
        labels = [result_label(r) for r in results]
        if len(set(labels)) < len(labels):
            labels = [f"{Path(str(r.path)).parent.name}/{lab}" if r.path else lab for r, lab in zip(results, labels)]
    return [dataclasses.replace(r, info={**r.info, "label": lab}) for r, lab in zip(results, labels)]


def level_label(result: Result) -> str:
    """Axis label of the result's voxel unit: ``"voxel, level S"``."""
    return f"voxel, level {int(result.info.get('level', 0))}"


def mid_planes(result: Result) -> dict[str, int]:
    """Index (level voxels) of the ROI mid-plane normal to each axis: ``{"z": .., "y": .., "x": ..}``."""
    return {AXES[a]: (r.start + r.stop) // 2 for a, r in enumerate(result.mesh.roi)}


@dataclass(frozen=True)
class Frame:
    """Where the figures of a result put their axes: level voxels, or the scan's unit.

    A position ``c`` (voxels of the result's level, axis ``a`` in ``(z, y, x)``) is drawn at
    ``offset[a] + step[a] * c``; a displacement ``U`` (level voxels) as ``length[a] * U``.

    Attributes
    ----------
    offset, step, length : tuple of 3 floats
    unit : str
        Axis and colour-bar label: ``"µm"`` or ``"voxel, level S"``.
    physical : bool
    """

    offset: tuple
    step: tuple
    length: tuple
    unit: str
    physical: bool

    def position(self, axis: int, c):
        """Position(s) ``c`` (level voxels) along ``axis`` in this frame."""
        return self.offset[axis] + self.step[axis] * np.asarray(c, dtype=np.float64)


def frame(result: Result, *, physical: bool = True) -> Frame:
    """The :class:`Frame` of a result: the scan's physical unit when the result carries a
    voxel size (level ``s`` voxel ``c`` is level-0 voxel ``2^s c + (2^s - 1) / 2``,
    DESIGN.md voxel centres), else voxels of its level."""
    length = result.voxel_length() if physical else None
    if length is None:
        return Frame((0.0,) * 3, (1.0,) * 3, (1.0,) * 3, level_label(result), False)
    scale = result.scale
    vs = np.asarray(result.info["voxel_size"], dtype=np.float64)
    unit = result.info.get("unit") or "unit"
    return Frame(tuple(level0_position(0.0, scale) * vs), tuple(scale * vs), tuple(length),
                 _SHORT_UNITS.get(unit, unit), True)


def common_frame(results: list[Result]) -> list[Frame]:
    """One frame per result: physical for all when every result has the same unit, else voxels
    for all (a figure never mixes units)."""
    frames = [frame(r) for r in results]
    if len({(f.physical, f.unit) for f in frames}) > 1 or not all(f.physical for f in frames):
        frames = [frame(r, physical=False) for r in results]
    return frames


def plane_extent(result: Result, normal: int, fr: Frame | None = None):
    """imshow extent (columns axis, rows axis) of a plane, in the frame ``fr`` (default level
    voxels); rows = first remaining axis."""
    roi = result.mesh.roi
    fr = fr or frame(result, physical=False)
    a, b = [k for k in range(3) if k != normal]
    ext = [*fr.position(b, [roi[b].start - 0.5, roi[b].stop - 0.5]), *fr.position(a, [roi[a].start - 0.5,
                                                                                         roi[a].stop - 0.5])]
    return [float(v) for v in ext], AXES[a], AXES[b]


def symmetric_limit(arrays, percentile: float = 100.0) -> float:
    """Colour limit ``L`` of a diverging map centred on 0 (``vmin = -L, vmax = L``): the
    ``percentile`` of ``|v|`` over the finite values of every array (``1e-12`` if none)."""
    vals = [np.abs(np.asarray(a, dtype=np.float64)) for a in arrays if a is not None]
    vals = np.concatenate([v[np.isfinite(v)] for v in vals]) if vals else np.empty(0)
    lim = float(np.percentile(vals, percentile)) if vals.size else 0.0
    return lim if lim > 0 else 1e-12


def shared_colorbar(fig, image, axes, label: str):
    """One colour bar for all ``axes`` (their images share ``image``'s norm and map)."""
    return fig.colorbar(image, ax=list(np.ravel(axes)), shrink=0.8, label=label)


def check_figure_options(fmt: str, dpi: int | None) -> None:
    """Refuse a figure format not in :data:`FORMATS` or a resolution outside 10..2400 dpi
    (before any output is written)."""
    if fmt not in FORMATS:
        raise InputError(f"figure format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if dpi is not None and not (isinstance(dpi, (int, np.integer)) and 10 <= dpi <= 2400):
        raise InputError(f"dpi must be an integer from 10 to 2400, got {dpi!r}")


def save(fig, path, dpi: int | None = None) -> str:
    """Write ``fig`` to ``path`` (format from the extension, one of :data:`FORMATS`) at ``dpi``
    dots per inch (default :data:`DEFAULT_DPI`); returns ``str(path)``."""
    fmt = Path(path).suffix.lstrip(".").lower()
    if fmt not in FORMATS:
        raise InputError(f"{path}: figure format must be one of {', '.join(FORMATS)}")
    fig.savefig(path, dpi=dpi or DEFAULT_DPI, format=fmt)
    return str(path)


def panel(fig, ax, img, extent, title, xlabel, ylabel, cbar, **kw):
    """``img`` on ``ax`` (origin lower, nearest), with title, axis labels and a colour bar
    ``cbar`` (``None``: no colour bar, e.g. when the figure has one :func:`shared_colorbar`)."""
    im = ax.imshow(img, origin="lower", extent=extent, **{"interpolation": "nearest", **kw})
    ax.set_title(title, fontsize=10)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if cbar is not None:
        fig.colorbar(im, ax=ax, shrink=0.8, label=cbar)
    return im
