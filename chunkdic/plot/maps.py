"""Maps of a result on the ROI plane normal to x (paper Figs. 9-10): displacement
components, ``eps_zz`` and the nodal uncertainty, one panel per result.

One idea: fields of several results side by side so that they can be compared at a
glance. Every figure therefore has

- the same extent on every panel (the union of the results' planes: results of different
  element sizes have slightly different ROIs),
- one colour bar for the whole figure (one colour scale across the results),
- a diverging colour map centred on 0 (``RdBu_r``, limits ``±max |v|``) for the signed
  quantities ``Uz``, ``Uy``, ``Ux`` and ``eps_zz``; ``magma`` from 0 for ``σ_U``,
- axes and displacements in the scan's physical unit when every result carries a voxel
  size of the same unit (:func:`chunkdic.plot.figures.frame`), else in voxels of the level.

Only mesh-sized arrays are read (the nodal field, the element strains); the C8 field is
evaluated on the plane on the client (an ROI plane, not a volume).
"""

from __future__ import annotations

import numpy as np

from ..results.result import Result
from ..results.strain import DEFAULT_MEASURE, MEASURE_SYMBOLS
from .figures import (
    as_results,
    common_frame,
    figure,
    mid_planes,
    panel,
    plane_extent,
    resolution_text,
    result_label,
    save,
    shared_colorbar,
    symmetric_limit,
)

__all__ = ["plot_u_maps", "plot_uz_maps", "plot_epszz_maps", "plot_uncertainty_map", "COMPONENTS"]

#: displacement components: name -> index in ``Result.displacement``
COMPONENTS = {"z": 0, "y": 1, "x": 2}


def _grid(n: int):
    cols = min(n, 2 if n == 4 else 3)
    return (n + cols - 1) // cols, cols


def _x_plane(results: list[Result]) -> int:
    """Mid-plane normal to x of the first result (the paper's x = 100 voxels)."""
    return mid_planes(results[0])["x"]


def _x_plane_map(res: Result, nodal: np.ndarray, x: int) -> np.ndarray:
    """A nodal field (k, nz, ny, nx) on the ROI plane normal to x, C8-interpolated: (k, Lz, Ly)."""
    roi = res.mesh.roi
    axes = (np.arange(roi[0].start, roi[0].stop, dtype=float), np.arange(roi[1].start, roi[1].stop, dtype=float),
            np.array([float(x)]))
    return res.mesh.evaluate_grid(nodal, axes)[..., 0]


def _panels(results, maps, extents, frames, title, path, *, cbar, cmap, vmin, vmax, dpi, suptitle,
            empty="no data", interpolation="nearest") -> str:
    """One panel per result on a common extent, one colour bar; ``maps[i] is None``: empty panel."""
    rows, cols = _grid(len(results))
    fig = figure(5.2 * cols + 0.8, 4.4 * rows)
    axs = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    ext = np.array(extents, dtype=float)
    xlim, ylim = (ext[:, 0].min(), ext[:, 1].max()), (ext[:, 2].min(), ext[:, 3].max())
    im = None
    for ax, res, m, e, fr in zip(axs, results, maps, extents, frames):
        if m is None:
            ax.set_title(f"{result_label(res)}, {resolution_text(res)}: {empty}", fontsize=10)
            ax.set_axis_off()
            continue
        im = panel(fig, ax, m, e, f"{result_label(res)}: {title(res)}", f"y ({fr.unit})", f"z ({fr.unit})", None, cmap=cmap,
                   vmin=vmin, vmax=vmax, interpolation=interpolation)
        ax.set_xlim(*xlim)
        ax.set_ylim(*ylim)
    for ax in axs[len(results):]:
        ax.set_visible(False)
    if im is not None:
        shared_colorbar(fig, im, [a for a in axs[:len(results)] if a.axison], cbar)
    fig.suptitle(suptitle)
    return save(fig, path, dpi)


def _ell(res: Result) -> str:
    return resolution_text(res)


def plot_u_maps(results, path, component: str = "z", *, x: int | None = None, dpi: int | None = None) -> str:
    """One displacement component on the plane normal to x, one panel per result (paper Fig. 9).

    Parameters
    ----------
    results : Result, path or sequence of them
        Results of the same pair (e.g. several element sizes).
    path : path
        Figure file (``.png``, ``.pdf`` or ``.svg``).
    component : {"z", "y", "x"}
        ``Uz``, ``Uy`` or ``Ux``.
    x : int, optional
        Plane index, voxels of the first result's level (default: its ROI mid-plane).
    dpi : int, optional
        Resolution (default :data:`chunkdic.plot.figures.DEFAULT_DPI`).

    Returns
    -------
    str
        ``path``.
    """
    results = as_results(results)
    c = COMPONENTS[component]
    x = _x_plane(results) if x is None else int(x)
    frames = common_frame(results)
    maps = [fr.length[c] * _x_plane_map(res, res.displacement[c:c + 1], x)[0] for res, fr in zip(results, frames)]
    lim = symmetric_limit(maps)
    extents = [plane_extent(res, 2, fr)[0] for res, fr in zip(results, frames)]
    name = f"U{component}"
    return _panels(results, maps, extents, frames, _ell, path, cbar=f"{name} ({frames[0].unit})", cmap="RdBu_r",
                   vmin=-lim, vmax=lim, dpi=dpi,
                   suptitle=f"{name} on the plane x = {x} (voxel of level {results[0].info.get('level', 0)})")


def plot_uz_maps(results, path, *, x: int | None = None, dpi: int | None = None) -> str:
    """``Uz`` on the plane normal to x (paper Fig. 9): :func:`plot_u_maps` with ``component="z"``."""
    return plot_u_maps(results, path, "z", x=x, dpi=dpi)


def plot_uncertainty_map(results, path, *, x: int | None = None, dpi: int | None = None) -> str:
    """Per-node standard uncertainty ``σ_U`` (pooled over the three components) on the plane
    normal to x, one panel per result (``Result.uncertainty``; docs/engine.md).

    Returns ``path``; results without an uncertainty are shown as empty panels.
    """
    results = as_results(results)
    x = _x_plane(results) if x is None else int(x)
    frames = common_frame(results)
    maps = []
    for res, fr in zip(results, frames):
        if res.uncertainty is None:
            maps.append(None)
            continue
        u = res.uncertainty * np.asarray(fr.length)[:, None, None, None]
        maps.append(_x_plane_map(res, np.sqrt(np.mean(u**2, axis=0))[None], x)[0])
    vmax = max([float(np.nanmax(m)) for m in maps if m is not None and np.isfinite(m).any()] or [1.0])
    extents = [plane_extent(res, 2, fr)[0] for res, fr in zip(results, frames)]
    return _panels(results, maps, extents, frames, _ell, path, cbar=f"σ_U ({frames[0].unit})", cmap="magma",
                   vmin=0.0, vmax=vmax, dpi=dpi, empty="no uncertainty in this result",
                   suptitle=f"Per-node displacement uncertainty σ_U on the plane x = {x}")


def _epszz_plane(res: Result, x: float, strain: str = "small"):
    """eps_zz on the plane ``x`` at the element centres (linear along x between centre
    layers) and the centre coordinates ``(cz, cy)``, level voxels."""
    mesh = res.mesh
    eps = res.element_strain(strain)[0, 0]  # (ez, ey, ex)
    centres = mesh.element_axes()
    cx = centres[2]
    if len(cx) == 1:
        layer = eps[:, :, 0]
    else:
        k = int(np.clip(np.searchsorted(cx, x) - 1, 0, len(cx) - 2))
        w = float(np.clip((x - cx[k]) / mesh.element_size, 0.0, 1.0))
        layer = (1 - w) * eps[:, :, k] + w * eps[:, :, k + 1]
    return layer, centres[0], centres[1]


def plot_epszz_maps(results, path, *, x: int | None = None, step: float = 0.5, dpi: int | None = None,
                    strain: str = DEFAULT_MEASURE) -> str:
    """``eps_zz`` on the plane normal to x, interpolated linearly between element centres
    (paper Fig. 10: "linearly interpolated between element centers where the element strain
    has been imposed"), one panel per result, one colour bar.

    The map covers the hull of the element centres (half an element inside the ROI);
    along x, the two nearest layers of centres are interpolated linearly too.

    Parameters
    ----------
    results : Result, path or sequence of them
    path : path
        Figure file (``.png``, ``.pdf`` or ``.svg``).
    x : int, optional
        Plane index (default: mid-plane of the first result's ROI).
    step : float
        Pixel size of the rendered map, voxels.
    dpi : int, optional
    strain : {"green-lagrange", "small"}
        Strain measure (:mod:`chunkdic.results.strain`; default Green–Lagrange, zero for a rigid rotation).
    """
    from scipy.interpolate import RegularGridInterpolator

    results = as_results(results)
    x = _x_plane(results) if x is None else int(x)
    frames = common_frame(results)
    maps, extents = [], []
    for res, fr in zip(results, frames):
        layer, cz, cy = _epszz_plane(res, x, strain)
        if len(cz) < 2 or len(cy) < 2:
            zz, yy, img = cz, cy, layer
        else:
            zz = np.arange(cz[0], cz[-1] + 1e-9, step)
            yy = np.arange(cy[0], cy[-1] + 1e-9, step)
            interp = RegularGridInterpolator((cz, cy), layer, method="linear")
            img = interp(np.stack(np.meshgrid(zz, yy, indexing="ij"), axis=-1))
        maps.append(img)
        extents.append([*map(float, fr.position(1, [yy[0], yy[-1]])), *map(float, fr.position(0, [zz[0], zz[-1]]))])
    lim = symmetric_limit(maps)
    sym = MEASURE_SYMBOLS[strain]
    return _panels(results, maps, extents, frames, _ell, path, cbar=f"{sym}_zz (–)", cmap="RdBu_r", vmin=-lim,
                   vmax=lim, dpi=dpi, interpolation="bilinear",
                   suptitle=f"{sym}_zz ({strain} strain) on the plane x = {x}, linear between element centres")
