"""Contrast for viewers of a scan's sum pyramid: a level-0 window and a mean display pyramid.

One idea: a scan's level ``s`` holds ``2^s`` *sums* (shared/DESIGN.md), so its values grow
8× per level, while OME-NGFF 0.5 has one ``omero`` window per channel for all levels and no
per-level value scaling. napari-ome-zarr turns that window into the layer's
``contrast_limits`` for every level (napari shows the coarsest level in 3D and switches
levels with the zoom in 2D); neuroglancer likewise keeps one range while it switches
levels. No single window fits a sum pyramid, so:

- :func:`scan_window` gives the window of **level 0** (1st/99th percentile and min/max,
  estimated from the coarsest stored level divided by ``8^k``: the mean of level 0 over
  its ``2^k`` cubes, read by the client at ``8^-k`` of the scan's size). It is written to
  the scan's ``omero`` metadata when the pyramid is built, so a viewer showing level 0
  (napari 2D at full zoom, neuroglancer at full resolution) is not saturated.
- :func:`write_display` (``chunkdic pyramid SCAN --display``) writes the optional
  subgroup ``SCAN/display``: an OME-NGFF image whose levels ``1..k`` are the stored sums
  divided by ``8^t`` (float32; exact while the sums stay below 2^24), on the scan's own
  level-``t`` frame, with the same window; it fits every one of its levels. Level 0 is not
  copied (it would double the scan): open ``SCAN/display`` for overviews and 3D, ``SCAN``
  for full resolution.
"""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["scan_window", "store_window", "write_display", "DISPLAY_GROUP", "WINDOW_SAMPLES"]

#: subgroup of a scan group holding the mean display pyramid
DISPLAY_GROUP = "display"
#: the client reads at most about this many voxels of the coarsest level for the window
WINDOW_SAMPLES = 2_000_000


def scan_window(path: str) -> list[float] | None:
    """``[start, end, min, max]`` of the scan's level-0 grey values for a viewer's contrast.

    The 1st and 99th percentiles (``start``, ``end``) and the extremes of the coarsest
    complete stored level ``k`` divided by ``8^k`` (the level-0 mean over each ``2^k``
    cube; strided so that at most about :data:`WINDOW_SAMPLES` voxels are read). None if
    the scan has no complete level.
    """
    import zarr

    from .ngff import complete_levels

    g = zarr.open_group(store=str(path), mode="r")
    levels = complete_levels(g)
    if not levels:
        return None
    k = max(levels)
    arr = g[str(k)]
    step = max(1, int(np.ceil((np.prod(arr.shape) / WINDOW_SAMPLES) ** (1 / 3))))
    v = np.asarray(arr[::step, ::step, ::step], np.float64).ravel() / 8.0**k
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None
    lo, hi = (float(q) for q in np.percentile(v, [1, 99]))
    if hi <= lo:
        lo, hi = float(v.min()), float(v.max()) + (1.0 if v.max() == v.min() else 0.0)
    return [lo, hi, float(v.min()), float(v.max())]


def store_window(path: str) -> list[float] | None:
    """Compute :func:`scan_window` and keep it in ``attrs["chunkdic"]["display_window"]``,
    from which :func:`chunkdic.ngff.update_group_metadata` writes the scan's ``omero``."""
    import zarr

    from .ngff import update_group_metadata

    window = scan_window(path)
    g = zarr.open_group(store=str(path), mode="r+")
    info = dict(g.attrs.get("chunkdic") or {})
    info["display_window"] = window
    g.update_attributes({"chunkdic": info})
    update_group_metadata(str(path))
    return window


def write_display(path: str, *, progress=None) -> list[int]:
    """Write ``path/display``: levels ``1..k`` of the scan as means (sums / ``8^t``).

    Parameters
    ----------
    path : str
        A scan group with complete pyramid levels ``1..k``.
    progress : callable(float), optional
        Fraction of levels done.

    Returns
    -------
    list of int
        The levels written.

    Each level is written by dask tasks, one per chunk of the scan's level (each task owns
    its chunk); the group's OME-NGFF metadata is written last.
    """
    import zarr

    from .errors import InputError
    from .handles import ref_dask
    from .ngff import ngff_attrs, omero
    from .ownership import final_name
    from .store import compressors, store_array
    from .volume import open_scan

    scan = open_scan(path)
    levels = [s for s in scan.stored_levels() if s > 0]
    if not levels:
        raise InputError(f"{path} has no pyramid levels: give --levels N with --display")
    root = zarr.open_group(store=str(path), mode="r+")
    if DISPLAY_GROUP in root:
        del root[DISPLAY_GROUP]
    g = root.create_group(DISPLAY_GROUP)
    refs = scan.stored_refs()
    chunk0 = tuple(root["0"].chunks)
    for i, s in enumerate(levels):
        ref = refs[s]
        chunks = tuple(min(c, n) for c, n in zip(chunk0, ref.shape))
        g.create_array(str(s), shape=ref.shape, chunks=chunks, dtype="float32",
                              compressors=compressors("float32"), dimension_names=("z", "y", "x"))
        # a power of two: the division is exact in float64, the float32 cast exact below 2^24
        means = (ref_dask(ref, chunks=chunks).astype(np.float64) / 8.0**s).astype(np.float32)
        # the one chunk writer: tasks own whole chunks (checked), progress from futures too
        store_array(means, str(path), f"{DISPLAY_GROUP}/{s}", progress, i / len(levels), (i + 1) / len(levels))
    info = dict(root.attrs.get("chunkdic") or {})
    vs = info.get("voxel_size")
    ome = ngff_attrs(levels, tuple(vs) if vs else None, info.get("unit"), final_name(str(path)) + "/display")
    ome["multiscales"][0].update(type="mean", metadata={
        "description": "level s of the scan divided by 8^s (the mean over 2^s voxels per axis), float32, "
                       "on the scan's level-s frame; level 0 is the scan's own (not copied)",
        "method": "chunkdic.display.write_display"})
    window = scan_window(str(path))
    if window is not None:
        ome["omero"] = omero(window)
    g.update_attributes({"ome": ome, "chunkdic": {"kind": "display", "levels": levels, "complete": True}})
    return levels
