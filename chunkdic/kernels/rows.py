"""One element row segment of the ``b`` pass and the warp: the shared inline numba helpers.

One idea: ``g(X + u(X))`` and the voxel weights over ``ell`` voxels along x inside one
element, where the positions are affine (:func:`segment_samples`), with the nodal field
on the row (:func:`row_field`) and the weight of a position near the faces of ``g``
(:func:`taper`). The ``b`` pass (:mod:`chunkdic.kernels.b`) and the warp
(:mod:`chunkdic.kernels.warp`) share :func:`segment_samples`; the masked ``M`` pass
(:mod:`chunkdic.kernels.m`) uses the field and the weight. These are called from numba
functions of other modules, so they are imported at module level there.
"""

from __future__ import annotations

from .interp import (
    interp_cubic,
    interp_inside,
    interp_linear,
    jit,
    jit_inline,
    lerp,
    segment_inside,
)

__all__ = ["row_field", "segment_samples", "taper", "valid_bounds"]


@jit
def row_field(u, c, ez, ey, ex, tz, ty):
    """Nodal field component c bilinearly interpolated at (tz, ty) on the two x-faces."""
    e00 = lerp(u[c, ez, ey, ex], u[c, ez + 1, ey, ex], tz)
    e10 = lerp(u[c, ez, ey + 1, ex], u[c, ez + 1, ey + 1, ex], tz)
    e01 = lerp(u[c, ez, ey, ex + 1], u[c, ez + 1, ey, ex + 1], tz)
    e11 = lerp(u[c, ez, ey + 1, ex + 1], u[c, ez + 1, ey + 1, ex + 1], tz)
    return lerp(e00, e10, ty), lerp(e01, e11, ty)


@jit
def valid_bounds(b, n0, n1, n2, m):
    """Fast-path bounds narrowed to where every weight is 1: ``[m + 1, n - 2 - m]`` (:func:`taper`)."""
    m = m + 1.0
    return (max(b[0], m), min(b[1], n0 - 1.0 - m), max(b[2], m), min(b[3], n1 - 1.0 - m),
            max(b[4], m), min(b[5], n2 - 1.0 - m))


@jit_inline
def taper(p0, p1, p2, n0, n1, n2, m):
    """Weight of a position: its distance (voxels, at most 1) inside ``[m, n - 1 - m]`` on every axis.

    A voxel's weight falls linearly to 0 over the last voxel before the boundary of the
    usable part of ``g``, so that the sums, hence ``b``, change continuously when an
    iteration moves voxels across it (a hard cut made boundary nodes oscillate).
    """
    if p0 != p0 or p1 != p1 or p2 != p2:  # NaN: min() would drop it
        return 0.0
    d = min(p0 - m, n0 - 1.0 - m - p0, p1 - m, n1 - 1.0 - m - p1, p2 - m, n2 - 1.0 - m - p2)
    if not d > 0.0:
        return 0.0
    return d if d < 1.0 else 1.0


@jit_inline
def segment_samples(u, ez, ey, ex, tz, ty, X0, X1, xa, ell, xi, g, gf, gs0, gs1, o0, o1, o2,
                     n0, n1, n2, vm_lo, bounds, cubic, gbuf, wt):
    """``g(X + u(X))`` over one element row segment (``ell`` voxels along x from ``xa``).

    Fills ``gbuf`` and the weights ``wt`` (:func:`taper`; 0 where ``X + u`` leaves
    ``[vm_lo, n - 1 - vm_lo]``) and returns the number of voxels of weight 0. The
    positions are affine along the segment: when both end points pass
    :func:`chunkdic.kernels.interp.segment_inside` (bounds at least one voxel inside that box)
    every voxel has weight 1 and takes the check-free flat path; otherwise each voxel is
    weighted and clamped or mirrored as needed.
    """
    uz0, uz1 = row_field(u, 0, ez, ey, ex, tz, ty)
    uy0, uy1 = row_field(u, 1, ez, ey, ex, tz, ty)
    ux0, ux1 = row_field(u, 2, ez, ey, ex, tz, ty)
    ta = xi[0]
    tb = xi[ell - 1]
    inside = (segment_inside(X0, X0, uz0, uz1, ta, tb, bounds[0], bounds[1])
              and segment_inside(X1, X1, uy0, uy1, ta, tb, bounds[2], bounds[3])
              and segment_inside(xa, xa + ell - 1, ux0, ux1, ta, tb, bounds[4], bounds[5]))
    nbad = 0
    if inside:
        for lx in range(ell):
            tx = xi[lx]
            gbuf[lx] = interp_inside(g, gf, gs0, gs1, o0, o1, o2, cubic, X0 + lerp(uz0, uz1, tx),
                                     X1 + lerp(uy0, uy1, tx), (xa + lx) + lerp(ux0, ux1, tx))
            wt[lx] = 1.0
        return 0
    for lx in range(ell):
        tx = xi[lx]
        p0 = X0 + lerp(uz0, uz1, tx)
        p1 = X1 + lerp(uy0, uy1, tx)
        p2 = (xa + lx) + lerp(ux0, ux1, tx)
        wt[lx] = taper(p0, p1, p2, n0, n1, n2, vm_lo)
        if wt[lx] == 0.0:
            nbad += 1
            gbuf[lx] = 0.0  # finite: the sums multiply it by its weight 0
        elif cubic:
            gbuf[lx] = interp_cubic(g, o0, o1, o2, n0, n1, n2, p0, p1, p2)
        else:
            gbuf[lx] = interp_linear(g, o0, o1, o2, p0, p1, p2)
    return nbad
