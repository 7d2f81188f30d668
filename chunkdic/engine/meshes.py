"""Planning a correlation: the ROI on each pyramid level and its C8 mesh.

The ROI is given in level-0 voxels (what a user sees in a viewer). On the correlated level
it becomes the voxels of that level lying wholly inside it, trimmed, centred, to a whole
number of elements (the paper, section 4.1, adjusts its ROI the same way). Coarser levels
use the same element edge, but at least :data:`COARSE_MIN_ELEMENT` voxels of their own,
over their share of that ROI (paper section 3: the basis coarsens with the image; at
ℓ < 12 the mesh coarsens faster, so that large deformations are carried). docs/engine.md,
"ROI and meshes".
"""

from __future__ import annotations

from ..errors import InputError
from ..mesh import Mesh

Box = tuple[tuple[int, int], tuple[int, int], tuple[int, int]]

#: a coarser level is used only while its ROI spans at least this many voxels per axis
MIN_COARSE_EDGE = 24
#: smallest element edge on a coarser level, voxels of that level
COARSE_MIN_ELEMENT = 12


def parse_roi(roi) -> Box | None:
    """Parse ``"z0:z1,y0:y1,x0:x1"`` (or a sequence of 3 pairs/slices) to a box.

    Returns ``None`` for ``None``; raises :class:`InputError` for anything malformed.
    """
    if roi is None:
        return None
    if isinstance(roi, str):
        parts = roi.split(",")
        if len(parts) != 3:
            raise InputError(f"ROI {roi!r}: expected z0:z1,y0:y1,x0:x1")
        try:
            pairs = [tuple(int(v) for v in p.split(":")) for p in parts]
        except ValueError:
            raise InputError(f"ROI {roi!r}: bounds must be integers, as in 10:90,10:90,10:90") from None
    else:
        pairs = [(s.start, s.stop) if isinstance(s, slice) else tuple(s) for s in roi]
    if len(pairs) != 3 or any(len(p) != 2 for p in pairs):
        raise InputError(f"ROI {roi!r}: expected three ranges z0:z1,y0:y1,x0:x1")
    if any(a is None or b is None or b <= a for a, b in pairs):
        raise InputError(f"ROI {roi!r}: every range needs start < stop")
    return tuple((int(a), int(b)) for a, b in pairs)


def box_at_level(box: Box, factor: int) -> Box:
    """Voxels of a level ``factor`` times coarser that lie wholly inside ``box``."""
    return tuple((-(-a // factor), b // factor) for a, b in box)


def centred_mesh(box: Box, ell: int) -> Mesh | None:
    """Largest centred mesh of whole ``ell`` elements inside ``box`` (None if none fits)."""
    n = tuple((b - a) // ell for a, b in box)
    if min(n) < 1:
        return None
    origin = tuple(a + ((b - a) - k * ell) // 2 for (a, b), k in zip(box, n))
    return Mesh(origin, ell, n)


def coarse_element_size(ell: int, edge: int) -> int:
    """Element edge of a coarser level, voxels of that level: ``ell``, but at least
    :data:`COARSE_MIN_ELEMENT` (and at most the ROI's edge ``edge``, one element).

    A coarse level's field only starts the next finer mesh; elements of fewer voxels of a
    summed, low-passed level hold too little texture to move far (docs/engine.md, "ROI and
    meshes").
    """
    return min(max(int(ell), COARSE_MIN_ELEMENT), int(edge))


def default_margin(ell: int, min_margin: int = 0) -> int:
    """Margin (voxels) the default ROI leaves on each side of the level."""
    return max(2, ell // 4, int(min_margin))


def plan_meshes(ref_shape0, *, element_size: int, roi=None, level: int = 0, coarsest=None,
                min_margin: int = 0) -> dict[int, Mesh]:
    """Meshes per pyramid level, finest (``level``) first.

    Parameters
    ----------
    ref_shape0 : tuple of 3 int
        Shape of the reference at level 0.
    element_size : int
        Element edge ``ell``, voxels of ``level``.
    roi : str or sequence, optional
        ``"z0:z1,y0:y1,x0:x1"`` in level-0 voxels; default: the largest centred box of whole
        elements leaving :func:`default_margin` voxels on each side.
    min_margin : int
        Smallest default margin, voxels of ``level`` (the radius of the low-pass, whose
        result is exact only that far from the faces).
    level : int
        Correlated (finest) level.
    coarsest : int, optional
        Coarsest level; ``None``: the coarsest of ``level+1 … level+3`` whose ROI still
        spans :data:`MIN_COARSE_EDGE` voxels on every axis.

    Returns
    -------
    dict
        ``{level: Mesh}``, insertion order finest first.
    """
    ell = int(element_size)
    shape0 = tuple(int(n) for n in ref_shape0)
    box0 = parse_roi(roi)
    if box0 is None:
        shape = tuple(n // 2**level for n in shape0)
        margin = default_margin(ell, min_margin)
        mesh = centred_mesh(tuple((margin, n - margin) for n in shape), ell)
        if mesh is None:
            raise InputError(
                f"element size {ell} does not fit in the reference at level {level} "
                f"(shape {shape}, margin {margin}): choose a smaller element size or level"
            )
    else:
        for axis, ((a, b), n) in enumerate(zip(box0, shape0)):
            if a < 0 or b > n:
                raise InputError(
                    f"ROI {a}:{b} on axis {'zyx'[axis]} lies outside the reference (0:{n}, level-0 voxels)"
                )
        box = box_at_level(box0, 2**level)
        mesh = centred_mesh(box, ell)
        if mesh is None:
            raise InputError(
                f"element size {ell} is larger than the ROI at level {level} "
                f"({' x '.join(str(b - a) for a, b in box)} voxels)"
            )
    meshes = {level: mesh}
    top = level + 3 if coarsest is None else int(coarsest)
    if top < level:
        raise InputError(f"coarsest level {top} is finer than the correlated level {level}")
    box_fine = tuple((r.start, r.stop) for r in mesh.roi)
    for s in range(level + 1, top + 1):
        box = box_at_level(box_fine, 2 ** (s - level))
        edge = min(b - a for a, b in box)
        if coarsest is None and edge < MIN_COARSE_EDGE:
            break
        ell_s = coarse_element_size(ell, edge)
        if ell_s < 2:
            raise InputError(f"coarsest level {top} is too coarse for this ROI (edge {edge} voxels at level {s})")
        meshes[s] = centred_mesh(box, ell_s)
    return meshes
