"""Interpolation of the deformed image ``g`` in the numba kernels: trilinear and cubic B-spline.

The ``b`` pass and the warp of :mod:`chunkdic.kernels.jit` evaluate ``g`` at ``p = X + u(X)``
(absolute voxel coordinates of the level, voxel centres at integers) from a window of
``g`` with origin ``o`` (``o0, o1, o2``) in a volume of shape ``n`` (``n0, n1, n2``). The
functions below are serial ``nogil`` numba helpers; arithmetic is float64 on float32
(or float64) data.

Validity domain (docs/architecture.md, "Gradients and interpolation"): for both
interpolations a position counts when ``0 <= p_i <= n_i - 1`` on every axis (a NaN makes it
invalid). The caller tests validity and leaves invalid voxels out; the window it reads
(``chunkdic.kernels.window.g_window``) holds every sample that a valid position needs.

``linear`` (:func:`interp_linear`)
    trilinear, in the weight form ``(1-t) a + t b``: exact at ``t = 0`` and ``t = 1``, so an
    integer translation gives ``r == 0`` exactly. Indices are clamped into the window for
    memory safety; at the last sample the clamped cell gives weight 1 to that sample.
``cubic`` (:func:`interp_cubic`)
    cubic B-spline of a window of *coefficients*, not intensities:
    ``scipy.ndimage.spline_filter(order=3, mode="mirror")`` of ``g``, either of the whole
    level once (:mod:`chunkdic.passes.prefilter`) or per window extended by
    ``chunkdic.bspline-halo`` voxels (default 12; the prefilter's influence decays as
    ``0.268^d``). The value at ``p`` sums the 4 x 4 x 4 taps ``floor(p) - 1 .. floor(p) + 2``
    with the uniform cubic B-spline weights of the fractional offset ``t = p - floor(p)``
    on each axis (:func:`_bspline_weights`): ``(1-t)^3 / 6``, ``(4 - 6t^2 + 3t^3) / 6``,
    ``(1 + 3t + 3t^2 - 3t^3) / 6``, ``t^3 / 6``. Taps outside the volume are mirrored about
    its first and last voxel centres (period ``2(n-1)``, :func:`_tap`), exactly as
    ``scipy.ndimage.map_coordinates(order=3, mode="mirror")``.

Fast path (the hot loop, cubic above all): positions are affine along an element row
segment (``ell`` voxels along x), so :func:`segment_inside` tests the segment's end points,
with a safety margin, against the per-axis interval of :func:`fast_bounds` (every tap inside
the window and, for cubic, the volume: no clamping or mirroring, and all such positions
valid). Those voxels go through :func:`interp_inside`, which uses flat indexing into the
window: :func:`_linear_fast` (bit-identical to :func:`interp_linear`) or the hand-written
LLVM vector kernel :func:`_cubic_taps` (numba keeps LLVM's SLP vectoriser off, so plain code
stays scalar). :func:`lerp` (``a + t (b - a)``, exact for a uniform field) also evaluates
the displacement along the segment.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

# the numba decorators of the package's kernels (chunkdic.kernels_* import jit from here)
jit = numba.njit(nogil=True, cache=True)
# hot per-voxel helpers: inlined at numba IR level (LLVM's own heuristics left some of them
# as calls with ~30 arguments each, which made the voxel loop ~2x slower)
jit_inline = numba.njit(nogil=True, cache=True, inline="always")
# the block sweeps that sum (the b and M passes, the low-pass): LLVM may reassociate their
# sums and fuse a * b + c, which lets it vectorise them (no other fast-math flag: NaN tests
# such as taper's must stay). 8-30 % faster per block, results to ~1e-12 relative
# (docs/engine.md, "Reassociated sums in the kernels")
jit_sums = numba.njit(nogil=True, cache=True, fastmath={"reassoc", "contract"})


@jit
def lerp(a, b, t):
    # a + t (b - a) is exact when a == b: a uniform nodal field is reproduced bit for bit
    return a + t * (b - a)


@jit
def interp_linear(g, o0, o1, o2, p0, p1, p2):
    """Trilinear interpolation of the window g (origin o) at absolute position p.

    Indices are clamped into the window for memory safety; the caller guarantees (via
    g_window) that valid positions need no clamping beyond the last sample, where the
    clamped cell gives weight 1 to that sample.
    """
    n0, n1, n2 = g.shape
    x0 = p0 - o0
    x1 = p1 - o1
    x2 = p2 - o2
    i0 = max(min(int(math.floor(x0)), n0 - 2), 0)
    i1 = max(min(int(math.floor(x1)), n1 - 2), 0)
    i2 = max(min(int(math.floor(x2)), n2 - 2), 0)
    t0 = x0 - i0
    t1 = x1 - i1
    t2 = x2 - i2
    j0 = min(i0 + 1, n0 - 1)
    j1 = min(i1 + 1, n1 - 1)
    j2 = min(i2 + 1, n2 - 1)
    # weight form (1-t) a + t b: exact at t = 0 and t = 1 (integer positions)
    s0 = 1.0 - t0
    s1 = 1.0 - t1
    s2 = 1.0 - t2
    c00 = s2 * g[i0, i1, i2] + t2 * g[i0, i1, j2]
    c01 = s2 * g[i0, j1, i2] + t2 * g[i0, j1, j2]
    c10 = s2 * g[j0, i1, i2] + t2 * g[j0, i1, j2]
    c11 = s2 * g[j0, j1, i2] + t2 * g[j0, j1, j2]
    return s0 * (s1 * c00 + t1 * c01) + t0 * (s1 * c10 + t1 * c11)


@jit
def _tap(j, n, o, nw):
    """Local window index of absolute coefficient index j, mirrored about 0 and n-1.

    Same extension as scipy.ndimage mode='mirror' (period 2(n-1)); clamped into the window
    for memory safety.
    """
    if j < 0 or j > n - 1:
        if n == 1:
            j = 0
        else:
            period = 2 * (n - 1)
            j = abs(j) % period
            if j > n - 1:
                j = period - j
    loc = j - o
    if loc < 0:
        loc = 0
    elif loc > nw - 1:
        loc = nw - 1
    return loc


@jit
def _bspline_weights(t):
    t2 = t * t
    t3 = t2 * t
    s = 1.0 - t
    return (s * s * s / 6.0, (4.0 - 6.0 * t2 + 3.0 * t3) / 6.0,
            (1.0 + 3.0 * t + 3.0 * t2 - 3.0 * t3) / 6.0, t3 / 6.0)


@jit
def _taps(k, n, o, nw):
    """Local indices of the 4 taps k .. k+3 along one axis.

    Fast path when all four are inside the volume and the window (almost always); the slow
    path mirrors and clamps each tap (_tap).
    """
    loc = k - o
    if k >= 0 and k + 3 <= n - 1 and loc >= 0 and loc + 3 <= nw - 1:
        return loc, loc + 1, loc + 2, loc + 3
    return _tap(k, n, o, nw), _tap(k + 1, n, o, nw), _tap(k + 2, n, o, nw), _tap(k + 3, n, o, nw)


@jit
def _cubic_plane(c, zi, y0, y1, y2, y3, x0, x1, x2, x3, b0, b1, b2, b3, d0, d1, d2, d3):
    r0 = d0 * c[zi, y0, x0] + d1 * c[zi, y0, x1] + d2 * c[zi, y0, x2] + d3 * c[zi, y0, x3]
    r1 = d0 * c[zi, y1, x0] + d1 * c[zi, y1, x1] + d2 * c[zi, y1, x2] + d3 * c[zi, y1, x3]
    r2 = d0 * c[zi, y2, x0] + d1 * c[zi, y2, x1] + d2 * c[zi, y2, x2] + d3 * c[zi, y2, x3]
    r3 = d0 * c[zi, y3, x0] + d1 * c[zi, y3, x1] + d2 * c[zi, y3, x2] + d3 * c[zi, y3, x3]
    return b0 * r0 + b1 * r1 + b2 * r2 + b3 * r3


@jit
def interp_cubic(c, o0, o1, o2, n0, n1, n2, p0, p1, p2):
    """Cubic B-spline of the coefficient window c (origin o) at absolute position p.

    n is the shape of the whole volume: mirror reflection happens about its first and last
    voxel centres, exactly as scipy.ndimage.map_coordinates(mode='mirror').
    """
    w0, w1, w2 = c.shape
    f0 = math.floor(p0)
    f1 = math.floor(p1)
    f2 = math.floor(p2)
    a0, a1, a2, a3 = _bspline_weights(p0 - f0)
    b0, b1, b2, b3 = _bspline_weights(p1 - f1)
    d0, d1, d2, d3 = _bspline_weights(p2 - f2)
    z0, z1, z2, z3 = _taps(int(f0) - 1, n0, o0, w0)
    y0, y1, y2, y3 = _taps(int(f1) - 1, n1, o1, w1)
    x0, x1, x2, x3 = _taps(int(f2) - 1, n2, o2, w2)
    return (a0 * _cubic_plane(c, z0, y0, y1, y2, y3, x0, x1, x2, x3, b0, b1, b2, b3, d0, d1,
                              d2, d3)
            + a1 * _cubic_plane(c, z1, y0, y1, y2, y3, x0, x1, x2, x3, b0, b1, b2, b3, d0,
                                d1, d2, d3)
            + a2 * _cubic_plane(c, z2, y0, y1, y2, y3, x0, x1, x2, x3, b0, b1, b2, b3, d0,
                                d1, d2, d3)
            + a3 * _cubic_plane(c, z3, y0, y1, y2, y3, x0, x1, x2, x3, b0, b1, b2, b3, d0,
                                d1, d2, d3))


_CONTRACT = ("contract",)  # let LLVM fuse a * b + c into an FMA where the CPU has one

# 6 x the cubic B-spline weights as polynomials in the fractional offset t,
# w_k(t) = sum_j _BSPLINE6[j][k] t^j: (1-t)^3, 4 - 6t^2 + 3t^3, 1 + 3t + 3t^2 - 3t^3, t^3
_BSPLINE6 = ((1.0, 4.0, 1.0, 0.0), (-3.0, 0.0, 3.0, 0.0), (3.0, -6.0, 3.0, 0.0),
             (-1.0, 3.0, -3.0, 1.0))


@intrinsic
def _cubic_taps(typingctx, c, i, s0, s1, tz, ty, tx):
    """Cubic B-spline value sum_{z,y,x} w_z(tz) w_y(ty) w_x(tx) c[i + z s0 + y s1 + x].

    Hand-written LLVM vector IR: numba leaves LLVM's SLP vectoriser off, so plain code
    stays scalar (64 loads, converts and multiply-adds per voxel, ~2.5x slower). Each of
    the 16 rows of 4 contiguous coefficients is one <4 x float> load widened to
    <4 x double>; rows are combined with the y weights, then the z weights (the 4 lanes
    are the 4 x taps), then a dot product with the x weights. The weights of each axis are
    one <4 x double> Horner polynomial. All arithmetic is float64. Generic LLVM vectors:
    AVX2 FMAs here, SSE2 pairs on older CPUs. No bounds checks: the caller guarantees that
    every tap is inside the flat C-contiguous array c (float32 or float64).
    """
    sig = types.float64(c, types.intp, types.intp, types.intp, types.float64, types.float64,
                        types.float64)
    is32 = c.dtype == types.float32

    def codegen(context, builder, signature, args):
        data = cgutils.create_struct_proxy(signature.args[0])(context, builder,
                                                               value=args[0]).data
        i, s0, s1, tz, ty, tx = args[1:]
        f64 = ir.DoubleType()
        v4 = ir.VectorType(f64, 4)
        vin = ir.VectorType(ir.FloatType() if is32 else f64, 4)
        i32 = ir.IntType(32)
        undef = ir.Constant(v4, ir.Undefined)

        def splat(v, k):
            return builder.shuffle_vector(v, undef, ir.Constant(ir.VectorType(i32, 4), [k] * 4))

        def weights(t, scale=1.0):
            tv = splat(builder.insert_element(undef, t, ir.Constant(i32, 0)), 0)
            w = ir.Constant(v4, [scale * v for v in _BSPLINE6[3]])
            for j in (2, 1, 0):
                w = builder.fadd(builder.fmul(w, tv, flags=_CONTRACT),
                                 ir.Constant(v4, [scale * v for v in _BSPLINE6[j]]),
                                 flags=_CONTRACT)
            return w

        wz = weights(tz)
        wy = weights(ty)
        wx = weights(tx, 1.0 / 216.0)  # the three 1/6 factors, applied once
        by = [splat(wy, k) for k in range(4)]
        acc = None
        for z in range(4):
            plane = None
            for y in range(4):
                off = builder.add(builder.add(i, builder.mul(s0, ir.Constant(s0.type, z))),
                                  builder.mul(s1, ir.Constant(s1.type, y)))
                row = builder.load(builder.bitcast(builder.gep(data, [off]), vin.as_pointer()),
                                   align=4 if is32 else 8)
                if is32:
                    row = builder.fpext(row, v4)
                t = builder.fmul(row, by[y], flags=_CONTRACT)
                plane = t if plane is None else builder.fadd(plane, t, flags=_CONTRACT)
            t = builder.fmul(plane, splat(wz, z), flags=_CONTRACT)
            acc = t if acc is None else builder.fadd(acc, t, flags=_CONTRACT)
        acc = builder.fmul(acc, wx)
        e = [builder.extract_element(acc, ir.Constant(i32, k)) for k in range(4)]
        return builder.fadd(builder.fadd(e[0], e[1]), builder.fadd(e[2], e[3]))

    return sig, codegen


@jit_inline
def _linear_fast(g, i, s0, s1, t0, t1, t2):
    """Trilinear from the flat window g, corner at flat index i, no clamping.

    Same arithmetic, in the same order, as interp_linear: bit-identical results (for
    windows that start inside the volume, as g_window's do; see interp_inside).
    """
    # unsigned indices: numba emits no negative-index wrap-around for them
    a = np.uint64(i)
    j = a + np.uint64(s1)
    k = a + np.uint64(s0)
    m = k + np.uint64(s1)
    one = np.uint64(1)
    s0w = 1.0 - t0
    s1w = 1.0 - t1
    s2w = 1.0 - t2
    c00 = s2w * g[a] + t2 * g[a + one]
    c01 = s2w * g[j] + t2 * g[j + one]
    c10 = s2w * g[k] + t2 * g[k + one]
    c11 = s2w * g[m] + t2 * g[m + one]
    return s0w * (s1w * c00 + t1 * c01) + t0 * (s1w * c10 + t1 * c11)


@jit
def fast_bounds(gshape, o0, o1, o2, n0, n1, n2, cubic):
    """Per axis, the open interval (lo, hi) of positions p whose taps need no clamping or
    mirroring: linear taps floor(p), floor(p) + 1 inside the window; cubic taps
    floor(p) - 1 .. floor(p) + 2 inside the window and the volume. All such p are valid
    (0 <= p <= n - 1). Returned as floats lo0, hi0, lo1, hi1, lo2, hi2."""
    w0, w1, w2 = gshape
    if cubic:
        # first tap k = floor(p) - 1 in [max(o, 0), min(o + w, n) - 4]
        return (max(o0, 0) + 1.0, min(o0 + w0, n0) - 2.0, max(o1, 0) + 1.0,
                min(o1 + w1, n1) - 2.0, max(o2, 0) + 1.0, min(o2 + w2, n2) - 2.0)
    # first tap k = floor(p) in [o, o + w - 2] (window only, as interp_linear), p <= n - 1
    return (max(o0, 0) + 0.0, min(o0 + w0 - 1.0, n0 - 1.0), max(o1, 0) + 0.0,
            min(o1 + w1 - 1.0, n1 - 1.0), max(o2, 0) + 0.0, min(o2 + w2 - 1.0, n2 - 1.0))


@jit
def segment_inside(Xa, Xb, u0, u1, ta, tb, lo, hi):
    """True if the positions X + lerp(u0, u1, t) of a row segment, whose end points are
    (Xa, ta) and (Xb, tb), all lie in [lo, hi) with a safety margin.

    The positions are affine along the segment, so the end points bound them; the margin
    (far above the few-ulp rounding of the computed positions) makes the bound rigorous.
    NaN gives False.
    """
    pa = Xa + lerp(u0, u1, ta)
    pb = Xb + lerp(u0, u1, tb)
    m = 1e-9 * (1.0 + abs(Xa) + abs(Xb) + abs(u0) + abs(u1))
    lo += m
    hi -= m
    return lo <= pa <= hi and lo <= pb <= hi


@jit_inline
def interp_inside(g, gf, s0, s1, o0, o1, o2, cubic, p0, p1, p2):
    """g(p) where fast_bounds holds: flat indexing, no clamping or mirroring."""
    # float floor for the weights (short dependency chain), its integer for the index
    f0 = np.floor(p0)
    f1 = np.floor(p1)
    f2 = np.floor(p2)
    i = (int(f0) - o0) * s0 + (int(f1) - o1) * s1 + (int(f2) - o2)
    if cubic:
        # first of the 4 x 4 x 4 taps at floor(p) - 1 on each axis
        return _cubic_taps(gf, i - s0 - s1 - 1, s0, s1, p0 - f0, p1 - f1, p2 - f2)
    # (p - o) - floor(p - o) == p - floor(p): o is an integer and p - o is exact
    return _linear_fast(gf, i, s0, s1, p0 - f0, p1 - f1, p2 - f2)
