"""Where a statistic is taken: the ROI, a box, a slab, a mask or label image, a line.

Every region is given in **level-0 voxels** of the reference scan (as ``correlate --roi``):
a box ``z0:z1,y0:y1,x0:x1`` covers voxels ``z0 … z1 - 1``, i.e. the continuous extent
``[z0 - 1/2, z1 - 1/2]`` (voxel ``i`` centred at ``i``); a slab ``z=a:b`` is the box that
spans the other two axes. A region selects the **nodes** whose positions lie in that extent
(displacement statistics) and the **elements** whose centres do (strain statistics). A mask
or label image (any scan format, the reference's level-0 shape) selects the elements of
which at least half the voxels carry the label (non-zero by default) and the nodes of those
elements; it is read by tasks, one row of elements at a time, never whole. A line
``z,y,x:z,y,x`` is sampled every ``step`` level-0 voxels (default a quarter of an element)
for a profile.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..io.handles import ArrayRef
from ..mesh import level0_position, level_to_level
from ..scheduler import open_runner

__all__ = ["Region", "roi_region", "box_region", "slab_region", "mask_region", "line_region", "parse_box",
           "parse_slab", "parse_point", "parse_line", "region_of"]

#: an element belongs to a mask region when at least this fraction of its voxels carries the label
MASK_FRACTION = 0.5


@dataclass(frozen=True)
class Region:
    """A set of nodes and elements of a result's mesh, or the points of a line.

    Attributes
    ----------
    kind : {"roi", "box", "slab", "mask", "line"}
    text : str
        How the region was given, for tables and titles.
    nodes : ndarray of bool, shape (nz, ny, nx), or None (a line)
    elements : ndarray of bool, shape (ez, ey, ex), or None (a line)
    points : ndarray, shape (n, 3), float64, or None
        A line's sample points, voxels of the result's level.
    distance : ndarray, shape (n,), float64, or None
        A line's sample points as the distance from its start, level-0 voxels.
    """

    kind: str
    text: str
    nodes: np.ndarray | None = field(default=None, repr=False)
    elements: np.ndarray | None = field(default=None, repr=False)
    points: np.ndarray | None = field(default=None, repr=False)
    distance: np.ndarray | None = field(default=None, repr=False)


def _numbers(text: str, what: str, count: int) -> list[float]:
    try:
        values = [float(v) for v in str(text).replace(" ", "").split(",")]
    except ValueError:
        values = []
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise InputError(f"{what} {text!r}: expected {count} numbers separated by commas")
    return values


def parse_point(text: str) -> tuple[float, float, float]:
    """``"z,y,x"`` (level-0 voxels) as a tuple of 3 floats; one-line InputError otherwise."""
    return tuple(_numbers(text, "point", 3))


def parse_box(text: str) -> tuple[tuple[float, float], ...]:
    """``"z0:z1,y0:y1,x0:x1"`` (level-0 voxels) as three ``(start, stop)`` pairs."""
    parts = str(text).replace(" ", "").split(",")
    try:
        pairs = [tuple(float(v) for v in p.split(":")) for p in parts]
    except ValueError:
        pairs = []
    if len(pairs) != 3 or any(len(p) != 2 or not all(map(math.isfinite, p)) or p[1] <= p[0] for p in pairs):
        raise InputError(f"box {text!r}: expected z0:z1,y0:y1,x0:x1 with start < stop on each axis (level-0 voxels)")
    return tuple(pairs)


def parse_slab(text: str) -> tuple[int, tuple[float, float]]:
    """``"z=a:b"`` (also ``y=``, ``x=``; level-0 voxels) as ``(axis, (a, b))``."""
    axis, _, span = str(text).replace(" ", "").partition("=")
    try:
        a, b = (float(v) for v in span.split(":"))
    except ValueError:
        a = b = math.nan
    if axis not in ("z", "y", "x") or not (math.isfinite(a) and math.isfinite(b) and b > a):
        raise InputError(f"slab {text!r}: expected AXIS=a:b with AXIS one of z, y, x and a < b (level-0 voxels)")
    return "zyx".index(axis), (a, b)


def parse_line(text: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """``"z,y,x:z,y,x"`` (level-0 voxels) as its two end points."""
    ends = str(text).replace(" ", "").split(":")
    if len(ends) != 2:
        raise InputError(f"line {text!r}: expected z,y,x:z,y,x (two points, level-0 voxels)")
    return parse_point(ends[0]), parse_point(ends[1])


def _level0_axes(result):
    """Node and element-centre positions per axis, level-0 voxels."""
    nodes = [level0_position(a, result.scale) for a in result.mesh.node_axes()]
    return nodes, [(a[1:] + a[:-1]) / 2 for a in nodes]


def _roi_text(result) -> str:
    return ",".join(f"{a}:{b}" for a, b in result.info.get("roi_level0", result.info["roi"]))


def roi_region(result) -> Region:
    """Every node and element of the result's mesh."""
    n = result.displacement.shape[1:]
    return Region("roi", f"ROI {_roi_text(result)}", np.ones(n, bool), np.ones(tuple(k - 1 for k in n), bool))


def box_region(result, box, *, kind: str = "box", text: str | None = None) -> Region:
    """The nodes and element centres inside ``box`` (three ``(start, stop)``, level-0 voxels).

    Raises
    ------
    InputError
        The box holds no node or no element centre of the mesh.
    """
    box = parse_box(box) if isinstance(box, str) else tuple(tuple(float(v) for v in p) for p in box)
    text = text or "box " + ",".join(f"{a:g}:{b:g}" for a, b in box)
    nodes, centres = _level0_axes(result)
    tol = 1e-9

    def inside(axes):
        sel = [(a >= lo - 0.5 - tol) & (a <= hi - 0.5 + tol) for a, (lo, hi) in zip(axes, box)]
        return sel[0][:, None, None] & sel[1][None, :, None] & sel[2][None, None, :]

    region = Region(kind, text, inside(nodes), inside(centres))
    if not region.nodes.any() or not region.elements.any():
        raise InputError(f"{text} holds no {'node' if not region.nodes.any() else 'element centre'} of the mesh "
                         f"(ROI {_roi_text(result)}, level-0 voxels): choose a region inside the ROI")
    return region


def slab_region(result, axis, span=None) -> Region:
    """The box spanning the whole ROI but ``span = (a, b)`` (level-0 voxels) along ``axis`` (0, 1, 2 or
    ``"z=a:b"``)."""
    if isinstance(axis, str) and span is None:
        axis, span = parse_slab(axis)
    axis = "zyx".index(axis) if isinstance(axis, str) else int(axis)
    box = [(-math.inf, math.inf)] * 3
    box[axis] = tuple(float(v) for v in span)
    big = [(lo if math.isfinite(lo) else -1e18, hi if math.isfinite(hi) else 1e18) for lo, hi in box]
    return box_region(result, big, kind="slab", text=f"slab {'zyx'[axis]}={span[0]:g}:{span[1]:g}")


def _mask_task(ref: ArrayRef, region, ell0: int, label) -> np.ndarray:
    """Task: per element of one row of elements (level-0 ``region``), the voxels carrying ``label``."""
    data = ref.read(tuple(slice(a, b) for a, b in region))
    hit = (data != 0) if label is None else (data == label)
    n = tuple((b - a) // ell0 for a, b in region)
    return hit.reshape(n[0], ell0, n[1], ell0, n[2], ell0).sum(axis=(1, 3, 5), dtype=np.int64)


def mask_region(result, mask, *, label: int | None = None, scheduler=None) -> Region:
    """The elements of which at least :data:`MASK_FRACTION` of the voxels carry ``label`` in ``mask``.

    Parameters
    ----------
    result : Result
    mask : path or array
        A scan of the reference's level-0 shape (any format :func:`chunkdic.io.formats.open_any`
        reads): a mask (non-zero) or a label image.
    label : int, optional
        The label to select (default: every non-zero voxel).
    scheduler
        Where the tasks run (:func:`chunkdic.scheduler.open_runner`). A mask not stored as Zarr
        is copied for them into a scratch directory (``chunkdic.scratch-directory``), removed
        afterwards.

    Raises
    ------
    InputError
        The mask's shape is not the reference's, or no element carries the label.
    """
    import shutil

    from ..io.formats.anyscan import open_any
    from ..io.ownership import make_scratch

    scan = open_any(mask)
    expected = (result.info.get("input_shapes") or {}).get("reference")
    shape = tuple(int(n) for n in scan.shape(0))
    if expected is not None and tuple(expected) != shape:
        raise InputError(f"mask {mask}: shape {shape} is not the reference scan's {tuple(expected)}")
    ell0 = int(result.info["element_size"]) * int(result.scale)
    roi0 = [(int(a), int(b)) for a, b in result.info.get("roi_level0", result.info["roi"])]
    if any(b > n for (_, b), n in zip(roi0, shape)):
        raise InputError(f"mask {mask}: shape {shape} does not hold the result's ROI {_roi_text(result)}")
    text = f"mask {mask}" + (f" label {label}" if label is not None else "")
    tmp = make_scratch("chunkdic-region-")
    try:
        ref = scan.refs([0], tmp)[0]
        rows = [((z, z + ell0), roi0[1], roi0[2]) for z in range(roi0[0][0], roi0[0][1], ell0)]
        counts = np.zeros(tuple((b - a) // ell0 for a, b in roi0), np.int64)
        with open_runner(scheduler) as runner:
            for z, c in runner.map_unordered(_mask_row, [(ref, r, ell0, label) for r in rows]):
                counts[(z - roi0[0][0]) // ell0] = c[0]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    elements = counts >= MASK_FRACTION * ell0**3
    if not elements.any():
        raise InputError(f"{text}: no element of the mesh has at least half its voxels "
                         f"{'non-zero' if label is None else f'labelled {label}'}")
    nodes = np.zeros(tuple(n + 1 for n in elements.shape), bool)
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                nodes[dz:dz + elements.shape[0], dy:dy + elements.shape[1], dx:dx + elements.shape[2]] |= elements
    return Region("mask", text, nodes, elements)


def _mask_row(ref, region, ell0, label):
    """Task: ``(first z, counts)`` of one row of elements (:func:`_mask_task`)."""
    return region[0][0], _mask_task(ref, region, ell0, label)


def line_region(result, start, end, *, step: float | None = None) -> Region:
    """Sample points from ``start`` to ``end`` (level-0 voxels) every ``step`` level-0 voxels.

    Raises
    ------
    InputError
        The ends coincide, or a point lies outside the mesh (the ROI's node box).
    """
    a, b = np.asarray(start, np.float64), np.asarray(end, np.float64)
    length = float(np.linalg.norm(b - a))
    if not length > 0:
        raise InputError("line: its two ends coincide")
    step = float(step) if step is not None else int(result.info["element_size"]) * result.scale / 4.0
    if not (math.isfinite(step) and step > 0):
        raise InputError(f"line step must be a positive number of voxels, got {step!r}")
    n = max(int(math.floor(length / step + 1e-9)) + 1, 2)
    t = np.linspace(0.0, 1.0, n) if abs((n - 1) * step - length) < 1e-9 else np.arange(n) * step / length
    pts0 = a[None] + t[:, None] * (b - a)[None]
    nodes, _ = _level0_axes(result)
    lo = np.array([ax[0] for ax in nodes]) - 1e-9
    hi = np.array([ax[-1] for ax in nodes]) + 1e-9
    outside = ~np.all((pts0 >= lo) & (pts0 <= hi), axis=1)
    if outside.any():
        p = pts0[np.argmax(outside)]
        raise InputError(f"line: the point ({', '.join(f'{v:g}' for v in p)}) lies outside the mesh (nodes from "
                         f"({', '.join(f'{v:g}' for v in lo + 1e-9)}) to ({', '.join(f'{v:g}' for v in hi - 1e-9)}), "
                         "level-0 voxels)")
    text = "line " + ",".join(f"{v:g}" for v in a) + ":" + ",".join(f"{v:g}" for v in b)
    return Region("line", text, points=level_to_level(pts0, 0, result.level), distance=t * length)


def region_of(result, *, box=None, slab=None, mask=None, label=None, line=None, step=None,
              scheduler=None) -> Region:
    """The one region the options name (none: the ROI); more than one is refused."""
    given = [k for k, v in (("box", box), ("slab", slab), ("mask", mask), ("line", line)) if v is not None]
    if len(given) > 1:
        raise InputError(f"give one region, not {' and '.join(given)}")
    if label is not None and mask is None:
        raise InputError("--label selects a label of --mask: give the mask too")
    if box is not None:
        return box_region(result, box)
    if slab is not None:
        return slab_region(result, slab) if isinstance(slab, str) else slab_region(result, *slab)
    if mask is not None:
        return mask_region(result, mask, label=label, scheduler=scheduler)
    if line is not None:
        ends = parse_line(line) if isinstance(line, str) else line
        return line_region(result, *ends, step=step)
    return roi_region(result)
