"""Contrast for viewers of a scan's sum pyramid: a level-0 window and a mean display pyramid.

One idea: a scan's level ``s`` holds ``2^s`` *sums* (shared/DESIGN.md), so its values grow
8× per level, while OME-NGFF 0.5 has one ``omero`` window per channel for all levels and no
per-level value scaling. napari-ome-zarr turns that window into the layer's
``contrast_limits`` for every level (napari shows the coarsest level in 3D and switches
levels with the zoom in 2D); neuroglancer likewise keeps one range while it switches
levels. No single window fits a sum pyramid, so:

- :func:`scan_window` gives the window of **level 0** (1st/99th percentile and min/max,
  estimated from the coarsest stored level divided by ``8^k``: the mean of level 0 over
  its ``2^k`` cubes). It is written to
  the scan's ``omero`` metadata when the pyramid is built, so a viewer showing level 0
  (napari 2D at full zoom, neuroglancer at full resolution) is not saturated.
- :func:`write_display` (``chunkdic pyramid SCAN --display``) writes the optional
  subgroup ``SCAN/display``: an OME-NGFF image whose levels ``1..k`` are the stored sums
  divided by ``8^t`` (float32; exact while the sums stay below 2^24), on the scan's own
  level-``t`` frame, with the same window; it fits every one of its levels. Level 0 is not
  copied (it would double the scan): open ``SCAN/display`` for overviews and 3D, ``SCAN``
  for full resolution.

:func:`windows` is the one window helper of chunkdic's viewer images (scans, their
display pyramid, the fields and corrected images): tasks read the chunks, the client
receives each chunk's extremes and a strided sample of at most :data:`WINDOW_SAMPLES`
voxels per channel in all, never a whole level (a 2048³ scan with 3 stored levels has a
256³ coarsest level, 64 MiB as float32; a fields image exported with few levels a far
larger one).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..scheduler import open_runner
from .handles import ref_dask
from .jsonfile import json_dict, read_json_object
from .ngff import complete_levels, ngff_attrs, omero, update_group_metadata
from .owntree import remove
from .scan import open_scan
from .siblings import final_name, partial_name, reclaim_stale_partials
from .store import compressors, store_array

log = logging.getLogger(__name__)

__all__ = ["own_display", "check_display_slot", "scan_window", "store_window", "write_display", "windows", "sample_step", "DISPLAY_GROUP",
           "WINDOW_SAMPLES"]

#: subgroup of a scan group holding the mean display pyramid
DISPLAY_GROUP = "display"
#: a contrast window's percentiles come from at most this many sampled voxels per channel
#: (the client holds them as float64: 16 MB); its min and max are exact
WINDOW_SAMPLES = 2_000_000


def own_display(path) -> bool | None:
    """What the scan group ``path`` holds under :data:`DISPLAY_GROUP`: ``None`` (nothing),
    ``True`` (chunkdic's mean pyramid, ``attrs["chunkdic"]["kind"] == "display"``, complete or
    not, or an empty directory: what a build killed right after making the folder leaves, which
    holds nothing to lose) or ``False`` (anything else: a user's array or group, or a link,
    which chunkdic never removes)."""
    node = Path(path) / DISPLAY_GROUP
    if not node.exists() and not node.is_symlink():
        return None
    if node.is_symlink():
        return False
    if node.is_dir() and not any(node.iterdir()):
        return True
    try:
        meta = read_json_object(node / "zarr.json")
        ck = json_dict(meta.get("attributes") or {}).get("chunkdic")
    except (OSError, ValueError):
        return False
    return meta.get("node_type") == "group" and isinstance(ck, dict) and ck.get("kind") == "display"


def remove_display(node: Path) -> None:
    """Remove chunkdic's ``display`` group ``node``, its ``zarr.json`` last: a removal killed
    halfway leaves a group still marked chunkdic's (or an empty folder), which the next build
    replaces, never a folder of arrays without the metadata that says whose they are."""
    for child in node.iterdir():
        if child.name != "zarr.json":
            remove(child)
    remove(node)


def check_display_slot(path) -> None:
    """Refuse (one line) to write ``--display`` where the scan holds a ``display`` node chunkdic did not write."""

    if own_display(path) is False:
        raise InputError(f"{path}/{DISPLAY_GROUP} exists and chunkdic did not write it: refusing to replace it "
                         f"(rename or move it, or leave out --display)")


def sample_step(shape, samples: int) -> int:
    """The smallest stride ``step`` whose grid ``[::step, ::step, ::step]`` over ``shape``
    holds at most ``samples`` voxels."""
    step = max(1, int(np.ceil((np.prod(shape, dtype=np.float64) / samples) ** (1 / 3))))
    while np.prod([-(-int(n) // step) for n in shape], dtype=np.float64) > samples:
        step += 1
    return step


def sample_task(store: str, path: str, region, channel: int | None, step: int, scale: float):
    """Task: one chunk of a stored array, read whole, for a contrast window.

    Parameters
    ----------
    store, path : str
        The Zarr store and the array in it: ``(nz, ny, nx)``, or ``(c, nz, ny, nx)`` with
        ``channel`` given.
    region : tuple of 3 (start, stop)
        The chunk (voxels of the array).
    channel : int or None
    step : int
        The stride of the sample grid, anchored at voxel 0 of the whole array (so that the
        chunks' samples together are the array's ``[::step, ::step, ::step]``).
    scale : float
        Factor applied to the values (``8^-k`` turns level-``k`` sums into level-0 means).

    Returns
    -------
    sample : ndarray, shape (n,), float64
        The finite values on the sample grid, times ``scale``.
    vmin, vmax : float
        Finite extremes of the whole chunk, times ``scale`` (``inf, -inf`` if none).
    """
    import zarr

    arr = zarr.open_array(store=store, path=path, mode="r")
    box = tuple(slice(a, b) for a, b in region)
    v = np.asarray(arr[box if channel is None else (channel, *box)], np.float64) * scale
    finite = np.isfinite(v)
    if not finite.any():
        return np.empty(0), np.inf, -np.inf
    grid = tuple(slice((-a) % step, None, step) for a, _ in region)
    sample = v[grid][finite[grid]]
    return sample, float(v[finite].min()), float(v[finite].max())


def windows(store: str, path: str, *, channels=(None,), scale: float = 1.0, runner=None,
            samples: int | None = None) -> list:
    """Contrast windows ``[start, end, min, max]`` of a stored array, one per channel, in tasks.

    One task per chunk and channel (:func:`sample_task`) reads its chunk and returns its
    exact extremes and its voxels on the grid of stride :func:`sample_step` (at most
    :data:`WINDOW_SAMPLES` per channel in all); the client keeps only those. ``start``,
    ``end`` are the 1st and 99th percentiles of the sample (exact while the array has at
    most :data:`WINDOW_SAMPLES` voxels per channel), ``min``, ``max`` exact. A channel
    whose percentiles coincide gets ``[min, max]``, or, constant, a window of half its
    value on either side; a channel with no finite value gets None.

    Parameters
    ----------
    store, path : str
        The Zarr store and the array (``(nz, ny, nx)``, or ``(c, nz, ny, nx)``).
    channels : sequence of (int or None), keyword-only
        The channels (``(None,)``: a 3-D array).
    scale : float, keyword-only
        Factor applied to every value.
    runner : optional
        A runner of :mod:`chunkdic.scheduler` (default: an embedded thread pool).
    samples : int, keyword-only
        The bound of the sample per channel (default :data:`WINDOW_SAMPLES`).
    """
    import contextlib

    import zarr

    arr = zarr.open_array(store=str(store), path=path, mode="r")
    shape, chunks = arr.shape[-3:], arr.chunks[-3:]
    step = sample_step(shape, samples or WINDOW_SAMPLES)
    regions = [((z, min(z + chunks[0], shape[0])), (y, min(y + chunks[1], shape[1])),
                (x, min(x + chunks[2], shape[2])))
               for z in range(0, shape[0], chunks[0]) for y in range(0, shape[1], chunks[1])
               for x in range(0, shape[2], chunks[2])]
    with contextlib.ExitStack() as stack:
        if runner is None:
            runner = stack.enter_context(open_runner(None))
        out = []
        for c in channels:
            tasks = [(str(store), path, r, c, step, scale) for r in regions]
            samples, lo, hi = [], np.inf, -np.inf
            for sample, vmin, vmax in runner.map_unordered(sample_task, tasks):
                samples.append(sample)
                lo, hi = min(lo, vmin), max(hi, vmax)
            out.append(window_of(np.concatenate(samples) if samples else np.empty(0), lo, hi))
    return out


def window_of(sample: np.ndarray, vmin: float, vmax: float) -> list[float] | None:
    """``[start, end, min, max]`` from a sample's 1st/99th percentiles and the extremes
    (:func:`windows`); None without a finite value."""
    if sample.size == 0 or not np.isfinite(vmin):
        return None
    lo, hi = (float(q) for q in np.percentile(sample, [1, 99]))
    if hi <= lo:
        if vmax > vmin:
            lo, hi = vmin, vmax
        else:  # a constant image (a pure translation's strain, an empty scan)
            lo, hi = lo - 0.5 * abs(lo) - 1e-6, hi + 0.5 * abs(hi) + 1e-6
    return [lo, hi, float(vmin), float(vmax)]


def scan_window(path: str, runner=None) -> list[float] | None:
    """``[start, end, min, max]`` of the scan's level-0 grey values for a viewer's contrast.

    :func:`windows` of the coarsest complete stored level ``k`` divided by ``8^k`` (the
    level-0 mean over each ``2^k`` cube): percentiles from at most :data:`WINDOW_SAMPLES`
    voxels, extremes exact, both computed by tasks chunk by chunk. None if the scan has
    no complete level (or no finite voxel).
    """
    import zarr

    g = zarr.open_group(store=str(path), mode="r")
    levels = complete_levels(g)
    if not levels:
        return None
    k = max(levels)
    return windows(str(path), str(k), scale=8.0**-k, runner=runner)[0]


def store_window(path: str) -> list[float] | None:
    """Compute :func:`scan_window` and keep it in ``attrs["chunkdic"]["display_window"]``,
    from which :func:`chunkdic.io.ngff.update_group_metadata` writes the scan's ``omero``."""
    import zarr

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

    scan = open_scan(path)
    levels = [s for s in scan.stored_levels() if s > 0]
    if not levels:
        raise InputError(f"{path} has no pyramid levels: give --levels N with --display")
    check_display_slot(path)
    root = zarr.open_group(store=str(path), mode="r+")
    node = Path(path) / DISPLAY_GROUP
    if own_display(path):
        remove_display(node)
    # marked chunkdic's before it has its name: made as a staged sibling and renamed, so that a
    # build killed at any point leaves either no display/, or one whose zarr.json says it is
    # chunkdic's (killed while zarr wrote that file in place, it left one no reader could trust
    # and the next build refused it); a staged group of a dead build is reclaimed
    reclaim_stale_partials(node)
    staged = partial_name(node)
    zarr.open_group(store=str(staged), mode="w-", attributes={"chunkdic": {"kind": "display", "complete": False}})
    os.rename(staged, node)
    g = zarr.open_group(store=str(path), path=DISPLAY_GROUP, mode="r+")
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
        "method": "chunkdic.io.display.write_display"})
    # the level-0 window the pyramid build stored (chunkdic.io.pyramid), else computed now
    window = info.get("display_window") or scan_window(str(path))
    if window is not None:
        ome["omero"] = omero([window])
    g.update_attributes({"ome": ome, "chunkdic": {"kind": "display", "levels": levels, "complete": True}})
    return levels
