"""Per-block numeric kernels of the C8-DIC engine: gradients, interpolation, ``M`` and ``b``.

A block is a box of whole elements (docs/architecture.md, "Coordinates and blocks"). A task
reads the block's region of the reference ``f`` plus a one-voxel halo (clipped at the volume
boundary) and the window of the deformed image ``g`` that :func:`g_window` says it needs,
then calls the kernels below. Every kernel returns *mesh-sized* partial results on the
block's own nodes; partials on shared face nodes add up in the engine.

Method: paper (``shared/seed/000_36e77f3b0d6f3ed6.txt``) section 3, modified Gauss-Newton
(section 3.1): ``M`` is built once from ``grad f``; each iteration builds
``b_(a,i) = sum_X N_a(X) d_i f(X) r(X)`` with ``r = f(X) - g(X + u(X))`` and the engine solves
``M da = b`` for the increment ``da``. Gradients are centred finite differences and the
interpolation of ``g`` is trilinear (the paper's choices); a cubic B-spline is an option.

Every public kernel has two implementations, selected with ``impl=``:

``"numba"``
    serial ``nogil`` kernels (Dask provides the parallelism) that sweep the block once in
    raster order with no volume-sized temporaries; float32 images, float64 accumulators.
``"numpy"``
    a plain NumPy/SciPy twin written for obviousness (``np.gradient`` semantics,
    ``scipy.ndimage.map_coordinates``, ``einsum`` with :func:`chunkdic.mesh.shape_table`,
    explicit loops over elements). It is the oracle of the tests, not a production path.

Why the numba kernels are fast: the trilinear shape functions factor per axis,
``N_a N_b = prod_axes phi_{d_a}(xi) phi_{d_b}(xi)`` with ``phi_0 = 1 - xi``, ``phi_1 = xi``,
so an element's ``M`` is fully described by the 27 tensor moments
``T[pz, py, px, c] = sum_X psi_pz psi_py psi_px G_c`` (``psi_p``, ``p = d_a + d_b``, one of
``(1-xi)^2, xi(1-xi), xi^2``; ``G_c`` the 6 distinct products ``d_i f d_j f``). Reducing a
voxel row over ``x`` costs 18 multiply-adds per voxel instead of the 36 x 6 = 216 of the
direct sum; the same factorisation gives ``b`` with 6 per voxel. It is an exact reordering
of the sums (float64 round-off only).

Interpolation in the b pass and the warp (the hot loop, cubic above all): the voxels are
taken one element row segment at a time (``ell`` voxels along x, where the positions
``X + u(X)`` are affine). One test on the segment's end points decides whether every voxel
is valid and has all its taps inside the window and the volume (nearly always); those
voxels go through a loop with no per-voxel checks, flat indexing into the window, and for
cubic the vector kernel :func:`chunkdic.interp._cubic_taps` (each of the 16 rows of 4 contiguous
coefficients is one ``<4 x float>`` load; 20 ``<4 x double>`` multiply-adds per voxel
instead of 64 scalar ones: numba keeps LLVM's SLP vectoriser off, so plain code stays
scalar). The other segments use the general per-voxel path (validity test, clamping,
mirror about the volume faces). The residual and gradient of f are then taken in a second
pass over the segment, from one precomputed x-row of ``f`` and ``grad f``. Arithmetic is
float64 on float32 data throughout: float32 lanes were measured at most ~10% faster for a
~1e-7 relative error, not worth loosening the numba == numpy oracle tests.

Notes for callers (the engine)
------------------------------
- ``f`` halo: ``lo[i]``/``hi[i]`` is 1 where a halo voxel was read, 0 where the core touches
  the volume boundary; gradients then equal ``np.gradient`` of the whole volume (float32).
- ``g`` window: read exactly ``g[g_window(...)]`` and pass its start as ``g_origin``. The
  kernels refuse (ValueError) a window that misses samples a valid voxel needs. For cubic,
  either pass a window of precomputed float32 B-spline coefficients of the whole level with
  ``prefiltered=True`` (the fast path: no per-window filter), or pass
  ``halo=chunkdic.bspline-halo`` (12) to :func:`g_window` and let the kernels prefilter the
  raw window into float32 coefficients (``scipy.ndimage.spline_filter``, mirror).
- Validity: a voxel counts when ``0 <= X_i + u_i <= g_shape_i - 1`` on every axis (a
  NaN displacement makes it invalid); invalid voxels are left out of ``b`` and ``sum r^2``
  and counted in ``n_excluded``. ``M`` keeps every core voxel.
- The displacement at a voxel is evaluated with nested lerps ``a + xi (b - a)`` (z, then
  y, then x): the trilinear field ``sum_a N_a u_a``, exact for a uniform field, so an
  integer translation gives ``r == 0`` exactly with linear interpolation.
- :func:`warmup` compiles every kernel once per process (all kernels see one signature:
  inputs are converted to float32 / float64 C-contiguous first).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.ndimage as ndi

from chunkdic.interp import (
    _fast_bounds,
    _interp_cubic,
    _interp_inside,
    _interp_linear,
    _jit,
    _lerp,
    _segment_inside,
)
from chunkdic.mesh import LOCAL_NODES, shape_table

__all__ = [
    "gradient_block",
    "m_block",
    "g_window",
    "b_block",
    "warp_block",
    "warmup",
]

_IMPLS = ("numba", "numpy")
_INTERPOLATIONS = ("linear", "cubic")

# Index of the symmetric gradient product d_i f d_j f in the 6-vector G_c.
_SYM = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]], dtype=np.int64)


# --------------------------------------------------------------------------------------
# argument checks shared by both implementations
# --------------------------------------------------------------------------------------


def _core_shape(f: np.ndarray, lo, hi) -> tuple[int, int, int]:
    if f.ndim != 3:
        raise ValueError(f"f must be 3-D, got shape {f.shape}")
    lo = tuple(int(v) for v in lo)
    hi = tuple(int(v) for v in hi)
    if len(lo) != 3 or len(hi) != 3 or any(v not in (0, 1) for v in lo + hi):
        raise ValueError(f"lo and hi must be 3 values in {{0, 1}}, got {lo}, {hi}")
    core = tuple(n - a - b for n, a, b in zip(f.shape, lo, hi))
    if any(n < 1 for n in core):
        raise ValueError(f"f of shape {f.shape} with halo {lo}/{hi} has an empty core")
    return core


def _elements(core, ell: int) -> tuple[int, int, int]:
    ell = int(ell)
    if ell < 1 or any(n % ell for n in core):
        raise ValueError(f"core shape {tuple(core)} is not a multiple of ell={ell}")
    return tuple(n // ell for n in core)


def _check_impl(impl: str) -> None:
    if impl not in _IMPLS:
        raise ValueError(f"impl must be one of {_IMPLS}, got {impl!r}")


def _check_interpolation(interpolation: str) -> None:
    if interpolation not in _INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {_INTERPOLATIONS}, got {interpolation!r}")


def _check_nodes(u_nodes: np.ndarray, elems) -> np.ndarray:
    u_nodes = np.ascontiguousarray(u_nodes, dtype=np.float64)
    want = (3,) + tuple(e + 1 for e in elems)
    if u_nodes.shape != want:
        raise ValueError(f"u_nodes must have shape {want}, got {u_nodes.shape}")
    return u_nodes


def _xi(ell: int) -> np.ndarray:
    # local coordinate of voxel l inside its element, as in mesh.shape_table
    return (np.arange(ell) + 0.5) / ell


def _grad_index(n_core: int, lo: int, hi: int):
    """Per core index along one axis: neighbour indices in the padded array and the scale.

    Centred ``(f[i+1] - f[i-1]) * 0.5`` where both neighbours exist in the padded region,
    one-sided ``* 1`` where only one does (true volume boundary), 0 if neither (an axis of
    length 1): exactly ``np.gradient(..., edge_order=1)`` on the whole volume.
    """
    n_pad = n_core + lo + hi
    p = np.arange(n_core) + lo
    im = np.maximum(p - 1, 0)
    ip = np.minimum(p + 1, n_pad - 1)
    span = ip - im
    # 0.5 and 1.0 are exact in float32, so the product equals numpy's division by 2.
    sc = np.where(span == 2, 0.5, np.where(span == 1, 1.0, 0.0)).astype(np.float32)
    return im.astype(np.int64), ip.astype(np.int64), sc


# --------------------------------------------------------------------------------------
# gradient
# --------------------------------------------------------------------------------------


def gradient_block(f: np.ndarray, lo, hi) -> np.ndarray:
    """Centred-difference gradient of the reference over a block core.

    Parameters
    ----------
    f : ndarray, shape (core_z + lo[0] + hi[0], ...), any real dtype, grey levels
        Block region of the reference including its halo.
    lo, hi : tuple of 3 int in {0, 1}
        Halo voxels present before / after the core on each axis; 0 means the core touches
        the volume boundary there.

    Returns
    -------
    grad : ndarray, shape (3, *core_shape), float32, grey levels per voxel
        ``(d_z f, d_y f, d_x f)``. Computed in float32 from ``f.astype(float32)``:
        ``(f[i+1] - f[i-1]) / 2`` inside, one-sided ``f[i+1] - f[i]`` / ``f[i] - f[i-1]``
        at the volume boundary, i.e. identical to
        ``np.gradient(volume.astype(np.float32))`` restricted to the core.

    References
    ----------
    Paper section 3.1: "a simple finite difference scheme is used".

    Examples
    --------
    >>> f = np.arange(64, dtype=np.float32).reshape(4, 4, 4)
    >>> gradient_block(f, (0, 0, 0), (0, 0, 0))[:, 1, 1, 1].tolist()
    [16.0, 4.0, 1.0]
    """
    core = _core_shape(f, lo, hi)
    f32 = np.asarray(f, dtype=np.float32)
    out = np.empty((3,) + core, dtype=np.float32)
    for axis in range(3):
        im, ip, sc = _grad_index(core[axis], lo[axis], hi[axis])
        # bring the other two axes to their core range, then take neighbours along `axis`
        sl = [slice(lo[a], lo[a] + core[a]) for a in range(3)]
        sl[axis] = slice(None)
        sub = np.moveaxis(f32[tuple(sl)], axis, 0)
        d = (sub[ip] - sub[im]) * sc[:, None, None]
        out[axis] = np.moveaxis(d, 0, axis)
    return out


# --------------------------------------------------------------------------------------
# numba kernels (the interpolation of g is in chunkdic.interp)
# --------------------------------------------------------------------------------------


@_jit
def _m_kernel(fp, lo0, lo1, lo2, ell, nez, ney, nex, imz, ipz, scz, imy, ipy, scy, imx, ipx,
              scx, psi):
    """Element tensor moments T[ez, ey, ex, pz, py, px, c] and core min / max of f."""
    nx = nex * ell
    T = np.zeros((nez, ney, nex, 3, 3, 3, 6))
    prod = np.empty((6, nx))
    fmin = np.inf
    fmax = -np.inf
    for z in range(nez * ell):
        ez = z // ell
        lz = z - ez * ell
        zz = z + lo0
        for y in range(ney * ell):
            ey = y // ell
            ly = y - ey * ell
            yy = y + lo1
            zp, zm, sz = ipz[z], imz[z], scz[z]
            yp, ym, sy = ipy[y], imy[y], scy[y]
            # pass 1 over the row: gradient (float32, as gradient_block) and its 6 products
            for x in range(nx):
                xx = x + lo2
                v = fp[zz, yy, xx]
                if v < fmin:
                    fmin = v
                if v > fmax:
                    fmax = v
                gz = np.float64((fp[zp, yy, xx] - fp[zm, yy, xx]) * sz)
                gy = np.float64((fp[zz, yp, xx] - fp[zz, ym, xx]) * sy)
                gx = np.float64((fp[zz, yy, ipx[x]] - fp[zz, yy, imx[x]]) * scx[x])
                prod[0, x] = gz * gz
                prod[1, x] = gz * gy
                prod[2, x] = gz * gx
                prod[3, x] = gy * gy
                prod[4, x] = gy * gx
                prod[5, x] = gx * gx
            # pass 2: per element, reduce the row against psi_px, then spread over pz, py
            for ex in range(nex):
                x0 = ex * ell
                for c in range(6):
                    s0 = 0.0
                    s1 = 0.0
                    s2 = 0.0
                    for lx in range(ell):
                        p = prod[c, x0 + lx]
                        s0 += psi[0, lx] * p
                        s1 += psi[1, lx] * p
                        s2 += psi[2, lx] * p
                    for pz in range(3):
                        for py in range(3):
                            w = psi[pz, lz] * psi[py, ly]
                            T[ez, ey, ex, pz, py, 0, c] += w * s0
                            T[ez, ey, ex, pz, py, 1, c] += w * s1
                            T[ez, ey, ex, pz, py, 2, c] += w * s2
    return T, fmin, fmax


@_jit
def _assemble_stencil(T, sym):
    """Scatter element moments into the nodal 27-point stencil of the block."""
    nez, ney, nex = T.shape[0], T.shape[1], T.shape[2]
    S = np.zeros((nez + 1, ney + 1, nex + 1, 27, 3, 3))
    for ez in range(nez):
        for ey in range(ney):
            for ex in range(nex):
                for a in range(8):
                    az = a >> 2
                    ay = (a >> 1) & 1
                    ax = a & 1
                    for b in range(8):
                        bz = b >> 2
                        by = (b >> 1) & 1
                        bx = b & 1
                        k = 9 * (bz - az + 1) + 3 * (by - ay + 1) + (bx - ax + 1)
                        for i in range(3):
                            for j in range(3):
                                S[ez + az, ey + ay, ex + ax, k, i, j] += T[
                                    ez, ey, ex, az + bz, ay + by, ax + bx, sym[i, j]
                                ]
    return S


@_jit
def _row_field(u, c, ez, ey, ex, tz, ty):
    """Nodal field component c bilinearly interpolated at (tz, ty) on the two x-faces."""
    e00 = _lerp(u[c, ez, ey, ex], u[c, ez + 1, ey, ex], tz)
    e10 = _lerp(u[c, ez, ey + 1, ex], u[c, ez + 1, ey + 1, ex], tz)
    e01 = _lerp(u[c, ez, ey, ex + 1], u[c, ez + 1, ey, ex + 1], tz)
    e11 = _lerp(u[c, ez, ey + 1, ex + 1], u[c, ez + 1, ey + 1, ex + 1], tz)
    return _lerp(e00, e10, ty), _lerp(e01, e11, ty)




@_jit
def _b_kernel(fp, lo0, lo1, lo2, ell, nez, ney, nex, imz, ipz, scz, imy, ipy, scy, imx, ipx,
              scx, xi, u, c0, c1, c2, g, o0, o1, o2, n0, n1, n2, cubic):
    """One fused sweep: u(X), g(X+u), r, and b on the nodes; sum r^2 and counts.

    Per element row segment (ell voxels along x), the segment's end points decide once
    whether every voxel is valid and needs no clamping or mirroring (nearly always); such
    segments run a loop with no per-voxel checks and flat-index interpolation, the others
    the general per-voxel path. Both compute the same positions.
    """
    b = np.zeros((nez + 1, ney + 1, nex + 1, 3))
    ssr = 0.0
    nvalid = 0
    nbad = 0
    hi0 = n0 - 1.0
    hi1 = n1 - 1.0
    hi2 = n2 - 1.0
    gf = g.ravel()
    gs0 = g.shape[1] * g.shape[2]
    gs1 = g.shape[2]
    L0, H0, L1, H1, L2, H2 = _fast_bounds(g.shape, o0, o1, o2, n0, n1, n2, cubic)
    ff = fp.ravel()
    fs0 = fp.shape[1] * fp.shape[2]
    fs1 = fp.shape[2]
    ta = xi[0]
    tb = xi[ell - 1]
    nx = nex * ell
    gbuf = np.empty(ell)
    ok = np.empty(ell, dtype=np.bool_)
    # one x-row of f and of its gradient (float32 differences, as gradient_block)
    frow = np.empty((4, nx), dtype=np.float32)
    for z in range(nez * ell):
        ez = z // ell
        lz = z - ez * ell
        zz = z + lo0
        tz = xi[lz]
        X0 = c0 + z
        for y in range(ney * ell):
            ey = y // ell
            ly = y - ey * ell
            yy = y + lo1
            ty = xi[ly]
            X1 = c1 + y
            wz0 = 1.0 - tz
            wy0 = 1.0 - ty
            # flat offsets (unsigned: no wrap-around code) of the rows of f used by r and
            # the centred differences; contiguous loops that LLVM vectorises
            rc = np.uint64(zz * fs0 + yy * fs1 + lo2)
            rzp = np.uint64(ipz[z] * fs0 + yy * fs1 + lo2)
            rzm = np.uint64(imz[z] * fs0 + yy * fs1 + lo2)
            ryp = np.uint64(zz * fs0 + ipy[y] * fs1 + lo2)
            rym = np.uint64(zz * fs0 + imy[y] * fs1 + lo2)
            rx = np.uint64(zz * fs0 + yy * fs1)
            sz = scz[z]
            sy = scy[y]
            for x in range(nx):
                xu = np.uint64(x)
                frow[0, x] = ff[rc + xu]
                frow[1, x] = (ff[rzp + xu] - ff[rzm + xu]) * sz
                frow[2, x] = (ff[ryp + xu] - ff[rym + xu]) * sy
            for x in range(nx):
                frow[3, x] = (ff[rx + np.uint64(ipx[x])] - ff[rx + np.uint64(imx[x])]) * scx[x]
            for ex in range(nex):
                # the field along the row is linear in xi_x: two end values per component
                uz0, uz1 = _row_field(u, 0, ez, ey, ex, tz, ty)
                uy0, uy1 = _row_field(u, 1, ez, ey, ex, tz, ty)
                ux0, ux1 = _row_field(u, 2, ez, ey, ex, tz, ty)
                xa = c2 + ex * ell
                inside = (_segment_inside(X0, X0, uz0, uz1, ta, tb, L0, H0)
                          and _segment_inside(X1, X1, uy0, uy1, ta, tb, L1, H1)
                          and _segment_inside(xa, xa + ell - 1, ux0, ux1, ta, tb, L2, H2))
                # pass 1: g(X + u) of the segment into gbuf (ok[lx] False where invalid)
                if inside:
                    for lx in range(ell):
                        tx = xi[lx]
                        gbuf[lx] = _interp_inside(
                            g, gf, gs0, gs1, o0, o1, o2, cubic, X0 + _lerp(uz0, uz1, tx),
                            X1 + _lerp(uy0, uy1, tx), (xa + lx) + _lerp(ux0, ux1, tx))
                else:
                    for lx in range(ell):
                        tx = xi[lx]
                        p0 = X0 + _lerp(uz0, uz1, tx)
                        p1 = X1 + _lerp(uy0, uy1, tx)
                        p2 = (xa + lx) + _lerp(ux0, ux1, tx)
                        ok[lx] = 0.0 <= p0 <= hi0 and 0.0 <= p1 <= hi1 and 0.0 <= p2 <= hi2
                        if not ok[lx]:
                            nbad += 1
                        elif cubic:
                            gbuf[lx] = _interp_cubic(g, o0, o1, o2, n0, n1, n2, p0, p1, p2)
                        else:
                            gbuf[lx] = _interp_linear(g, o0, o1, o2, p0, p1, p2)
                # pass 2: residual, gradient, and the two x-face sums of the segment
                s0z = 0.0
                s0y = 0.0
                s0x = 0.0
                s1z = 0.0
                s1y = 0.0
                s1x = 0.0
                for lx in range(ell):
                    if not (inside or ok[lx]):
                        continue
                    x = ex * ell + lx
                    r = np.float64(frow[0, x]) - gbuf[lx]
                    gz = np.float64(frow[1, x]) * r
                    gy = np.float64(frow[2, x]) * r
                    gx = np.float64(frow[3, x]) * r
                    ssr += r * r
                    nvalid += 1
                    wx1 = xi[lx]
                    wx0 = 1.0 - wx1
                    s0z += wx0 * gz
                    s0y += wx0 * gy
                    s0x += wx0 * gx
                    s1z += wx1 * gz
                    s1y += wx1 * gy
                    s1x += wx1 * gx
                # spread the row sums over the 4 (dz, dy) node pairs of each x-face
                for dz in range(2):
                    wz = tz if dz else wz0
                    for dy in range(2):
                        w = wz * (ty if dy else wy0)
                        b[ez + dz, ey + dy, ex, 0] += w * s0z
                        b[ez + dz, ey + dy, ex, 1] += w * s0y
                        b[ez + dz, ey + dy, ex, 2] += w * s0x
                        b[ez + dz, ey + dy, ex + 1, 0] += w * s1z
                        b[ez + dz, ey + dy, ex + 1, 1] += w * s1y
                        b[ez + dz, ey + dy, ex + 1, 2] += w * s1x
    return b, ssr, nvalid, nbad


@_jit
def _warp_kernel(ell, nez, ney, nex, xi, u, c0, c1, c2, g, o0, o1, o2, n0, n1, n2, cubic):
    """g(X + u(X)) over the core (float32, NaN where invalid) and the validity mask.

    Same positions, segment test and interpolation paths as _b_kernel.
    """
    out = np.empty((nez * ell, ney * ell, nex * ell), dtype=np.float32)
    mask = np.zeros((nez * ell, ney * ell, nex * ell), dtype=np.bool_)
    hi0 = n0 - 1.0
    hi1 = n1 - 1.0
    hi2 = n2 - 1.0
    gf = g.ravel()
    gs0 = g.shape[1] * g.shape[2]
    gs1 = g.shape[2]
    L0, H0, L1, H1, L2, H2 = _fast_bounds(g.shape, o0, o1, o2, n0, n1, n2, cubic)
    ta = xi[0]
    tb = xi[ell - 1]
    for z in range(nez * ell):
        ez = z // ell
        tz = xi[z - ez * ell]
        X0 = c0 + z
        for y in range(ney * ell):
            ey = y // ell
            ty = xi[y - ey * ell]
            X1 = c1 + y
            for ex in range(nex):
                uz0, uz1 = _row_field(u, 0, ez, ey, ex, tz, ty)
                uy0, uy1 = _row_field(u, 1, ez, ey, ex, tz, ty)
                ux0, ux1 = _row_field(u, 2, ez, ey, ex, tz, ty)
                xa = c2 + ex * ell
                inside = (_segment_inside(X0, X0, uz0, uz1, ta, tb, L0, H0)
                          and _segment_inside(X1, X1, uy0, uy1, ta, tb, L1, H1)
                          and _segment_inside(xa, xa + ell - 1, ux0, ux1, ta, tb, L2, H2))
                for lx in range(ell):
                    x = ex * ell + lx
                    tx = xi[lx]
                    p0 = X0 + _lerp(uz0, uz1, tx)
                    p1 = X1 + _lerp(uy0, uy1, tx)
                    p2 = (c2 + x) + _lerp(ux0, ux1, tx)
                    if inside:
                        gw = _interp_inside(g, gf, gs0, gs1, o0, o1, o2, cubic, p0, p1, p2)
                    elif not (0.0 <= p0 <= hi0 and 0.0 <= p1 <= hi1 and 0.0 <= p2 <= hi2):
                        out[z, y, x] = np.nan
                        continue
                    elif cubic:
                        gw = _interp_cubic(g, o0, o1, o2, n0, n1, n2, p0, p1, p2)
                    else:
                        gw = _interp_linear(g, o0, o1, o2, p0, p1, p2)
                    out[z, y, x] = gw
                    mask[z, y, x] = True
    return out, mask


# --------------------------------------------------------------------------------------
# M
# --------------------------------------------------------------------------------------


def _m_numba(f32, lo, ell, elems):
    core = tuple(e * ell for e in elems)
    idx = [_grad_index(core[a], lo[a], f32.shape[a] - core[a] - lo[a]) for a in range(3)]
    xi = _xi(ell)
    psi = np.stack([(1.0 - xi) ** 2, xi * (1.0 - xi), xi**2])  # psi_p, p = d_a + d_b
    T, fmin, fmax = _m_kernel(f32, lo[0], lo[1], lo[2], ell, *elems, *idx[0], *idx[1],
                              *idx[2], psi)
    return _assemble_stencil(T, _SYM), float(fmin), float(fmax)


def _m_numpy(f32, lo, hi, ell, elems):
    grad = gradient_block(f32, lo, hi).astype(np.float64)
    W = shape_table(ell).reshape(-1, 8)
    S = np.zeros(tuple(e + 1 for e in elems) + (27, 3, 3))
    for ez, ey, ex in np.ndindex(*elems):
        sl = (slice(None),) + tuple(slice(e * ell, (e + 1) * ell) for e in (ez, ey, ex))
        G = grad[sl].reshape(3, -1)  # (3, ell^3)
        # Ke[a, i, b, j] = sum_v N_a N_b d_i f d_j f   (paper section 3, M_ij)
        Ke = np.einsum("va,vb,iv,jv->aibj", W, W, G, G, optimize=True)
        for a, da in enumerate(LOCAL_NODES):
            for b, db in enumerate(LOCAL_NODES):
                off = db - da
                k = 9 * (off[0] + 1) + 3 * (off[1] + 1) + (off[2] + 1)
                S[ez + da[0], ey + da[1], ex + da[2], k] += Ke[a, :, b, :]
    core = f32[lo[0]:lo[0] + grad.shape[1], lo[1]:lo[1] + grad.shape[2],
               lo[2]:lo[2] + grad.shape[3]]
    return S, float(core.min()), float(core.max())


def m_block(f: np.ndarray, lo, hi, ell: int, *, impl: str = "numba"):
    """Block contribution to the C8 matrix ``M`` as a nodal 27-point stencil.

    Parameters
    ----------
    f : ndarray, shape (core_z + lo[0] + hi[0], ...), any real dtype, grey levels
        Block region of the reference including its one-voxel halo (see
        :func:`gradient_block`). Converted to float32.
    lo, hi : tuple of 3 int in {0, 1}
        Halo voxels before / after the core per axis (0 at the volume boundary).
    ell : int
        Element edge, voxels. The core shape must be a multiple of ``ell``.
    impl : {"numba", "numpy"}, keyword-only
        Fused kernel or its NumPy twin (test oracle).

    Returns
    -------
    S : ndarray, shape (ez+1, ey+1, ex+1, 27, 3, 3), float64, grey levels^2
        ``S[n, k, i, j] = M[(n, i), (n + off_k, j)]`` with ``off_k`` from
        :data:`chunkdic.mesh.STENCIL_OFFSETS`, ``M_(a,i),(b,j) = sum_X N_a N_b d_i f d_j f`` over the
        core voxels; entries whose column node leaves the block's node grid are 0.
        Symmetric: ``S[n, k, i, j] == S[n + off_k, 26 - k, j, i]``.
    fmin, fmax : float
        Extreme grey levels of the core voxels (for the matching gap normalisation).

    Raises
    ------
    ValueError
        If the core shape is not a multiple of ``ell`` or ``lo``/``hi`` are not 0/1.

    References
    ----------
    Paper section 3, linear system ``M_ij a_j = b_i``; section 3.1 (``M`` is built once
    from the reference).
    """
    _check_impl(impl)
    core = _core_shape(f, lo, hi)
    elems = _elements(core, ell)
    f32 = np.ascontiguousarray(f, dtype=np.float32)
    lo = tuple(int(v) for v in lo)
    if impl == "numba":
        return _m_numba(f32, lo, int(ell), elems)
    return _m_numpy(f32, lo, tuple(int(v) for v in hi), int(ell), elems)


# --------------------------------------------------------------------------------------
# g window
# --------------------------------------------------------------------------------------


def g_window(core_origin, core_shape, u_nodes, g_shape, *, interpolation: str,
             halo: int = 0) -> tuple[slice, slice, slice]:
    """Region of the deformed image that :func:`b_block` / :func:`warp_block` need.

    A trilinear field stays within its nodal min / max, so positions ``X + u(X)`` over the
    core lie per axis within ``[o + min(u_i), o + n - 1 + max(u_i)]``. Only the part inside
    the validity domain ``[0, g_shape_i - 1]`` is needed (other voxels are excluded).

    Parameters
    ----------
    core_origin : tuple of 3 int, level voxels
        Absolute index of the first core voxel.
    core_shape : tuple of 3 int, voxels
    u_nodes : ndarray, shape (3, ez+1, ey+1, ex+1), float, voxels
        Nodal displacement over the block's nodes.
    g_shape : tuple of 3 int
        Shape of the whole deformed level.
    interpolation : {"linear", "cubic"}, keyword-only
        ``linear`` needs samples ``floor(x) .. floor(x) + 1``; ``cubic`` needs
        ``floor(x) - 1 .. floor(x) + 2`` plus ``halo`` voxels per side so that the
        per-window prefilter matches a whole-volume one.
    halo : int, keyword-only
        Extra voxels per side for the cubic prefilter (``chunkdic.bspline-halo``, 12 gives
        float32 precision). Ignored for ``linear``.

    Returns
    -------
    window : tuple of 3 slice
        Absolute level indices, clipped to ``[0, g_shape)``. If no core voxel can map into
        ``g`` the region is empty: ``(slice(0, 0),) * 3``; pass ``g[window]`` (shape with a
        0) and ``g_origin = (0, 0, 0)`` to the kernels, which then exclude every voxel.
    """
    _check_interpolation(interpolation)
    u_nodes = np.asarray(u_nodes, dtype=np.float64)
    if u_nodes.shape[0] != 3:
        raise ValueError(f"u_nodes must have 3 components first, got shape {u_nodes.shape}")
    extra = 1 + int(halo) if interpolation == "cubic" else 0
    out = []
    for i in range(3):
        n = int(g_shape[i])
        lo = max(core_origin[i] + float(u_nodes[i].min()), 0.0)
        hi = min(core_origin[i] + core_shape[i] - 1 + float(u_nodes[i].max()), n - 1.0)
        if not (lo <= hi):  # also catches NaN
            return (slice(0, 0),) * 3
        start = max(math.floor(lo) - extra, 0)
        # + 2: floor(x) + 1 inclusive; cubic adds floor(x) + 2 and the halo
        stop = min(math.floor(hi) + 2 + extra, n)
        out.append(slice(start, stop))
    return tuple(out)


# --------------------------------------------------------------------------------------
# b and warp
# --------------------------------------------------------------------------------------


def _prepare_g(g, g_origin, g_shape, interpolation, prefiltered=False):
    """Window as float32 samples (linear) or float32 B-spline coefficients (cubic).

    float32 coefficients: the images are float32 (architecture.md) and the B-spline
    reproduces samples with relative error ~1e-7 of the intensity range either way; float32
    halves the memory and bandwidth of the 64-tap gather, the hot loop of the cubic pass.
    """
    if g.ndim != 3 or len(g_origin) != 3 or len(g_shape) != 3:
        raise ValueError("g, g_origin and g_shape must be 3-D")
    if interpolation == "cubic" and g.size and not prefiltered:
        # scipy computes each line in float64 and stores float32
        return ndi.spline_filter(np.asarray(g, dtype=np.float32), order=3, mode="mirror",
                                 output=np.float32)
    return np.ascontiguousarray(g, dtype=np.float32)


def _check_window(g, g_origin, core_origin, core_shape, u_nodes, g_shape, interpolation):
    """Refuse a window that does not cover the samples valid voxels need."""
    need = g_window(core_origin, core_shape, u_nodes, g_shape, interpolation="linear")
    if need[0].stop == need[0].start:
        return False  # no voxel can be valid
    for i in range(3):
        o = int(g_origin[i])
        if o > need[i].start or o + g.shape[i] < need[i].stop:
            raise ValueError(
                f"g window [{o}, {o + g.shape[i]}) on axis {i} does not cover the needed "
                f"[{need[i].start}, {need[i].stop}); read it with g_window()"
            )
    return True


def _nodal_field(u_nodes, ell):
    """Trilinear interpolation of the nodal field at every core voxel, shape (3, *core).

    Separable 1-D lerps ``u[k] + xi (u[k+1] - u[k])`` along z, then y, then x: the same
    function as ``sum_a N_a u_a`` (mesh.shape_table) and exact for a uniform field.
    """
    xi = _xi(ell)
    v = u_nodes
    for axis in (1, 2, 3):
        n_el = v.shape[axis] - 1
        k = np.repeat(np.arange(n_el), ell)  # element of each voxel
        t = np.tile(xi, n_el)
        a = np.take(v, k, axis=axis)
        b = np.take(v, k + 1, axis=axis)
        shp = [1, 1, 1, 1]
        shp[axis] = -1
        v = a + t.reshape(shp) * (b - a)
    return v


def _warp_numpy(ell, u_nodes, core_origin, core_shape, gw, g_origin, g_shape,
                interpolation):
    """float64 g(X+u) and mask with map_coordinates; gw already prefiltered if cubic."""
    u = _nodal_field(u_nodes, ell)
    grids = np.meshgrid(*[np.arange(n) for n in core_shape], indexing="ij")
    pos = np.stack([core_origin[i] + grids[i] + u[i] for i in range(3)])
    mask = np.ones(core_shape, dtype=bool)
    for i in range(3):
        mask &= (pos[i] >= 0) & (pos[i] <= g_shape[i] - 1)
    out = np.full(core_shape, np.nan)
    if mask.any():
        local = np.stack([pos[i][mask] - g_origin[i] for i in range(3)])
        if interpolation == "cubic":
            # mirror at the window edges = mirror at the volume edges where they coincide;
            # elsewhere the taps stay inside the window (g_window)
            out[mask] = ndi.map_coordinates(gw, local, order=3, mode="mirror",
                                            prefilter=False, output=np.float64)
        else:
            out[mask] = ndi.map_coordinates(gw, local, order=1, mode="nearest",
                                            output=np.float64)
    return out, mask


def _setup_b(ell, u_nodes, core_origin, core_shape, g, g_origin, g_shape, interpolation,
             impl, prefiltered=False):
    _check_impl(impl)
    _check_interpolation(interpolation)
    elems = _elements(core_shape, ell)
    u_nodes = _check_nodes(u_nodes, elems)
    core_origin = tuple(int(v) for v in core_origin)
    g_origin = tuple(int(v) for v in g_origin)
    g_shape = tuple(int(v) for v in g_shape)
    g = np.asarray(g)
    any_valid = _check_window(g, g_origin, core_origin, core_shape, u_nodes, g_shape,
                              interpolation)
    gw = _prepare_g(g, g_origin, g_shape, interpolation, prefiltered) if any_valid else None
    return elems, u_nodes, core_origin, g_origin, g_shape, gw


def warp_block(ell: int, u_nodes: np.ndarray, core_origin, core_shape, g: np.ndarray,
               g_origin, g_shape, *, interpolation: str = "cubic", impl: str = "numba",
               prefiltered: bool = False):
    """The corrected deformed image ``g(X + u(X))`` over a block core.

    Parameters
    ----------
    ell : int
        Element edge, voxels.
    u_nodes : ndarray, shape (3, ez+1, ey+1, ex+1), float64, voxels
        Nodal displacement over the block's nodes.
    core_origin : tuple of 3 int
        Absolute level index of the first core voxel.
    core_shape : tuple of 3 int
        ``(ez*ell, ey*ell, ex*ell)``.
    g : ndarray, 3-D, any real dtype, grey levels
        Raw window of the deformed level starting at absolute index ``g_origin``; must
        contain :func:`g_window` (``halo`` extra voxels per side for cubic).
    g_origin : tuple of 3 int
    g_shape : tuple of 3 int
        Shape of the whole deformed level (validity domain and mirror boundary).
    interpolation : {"linear", "cubic"}, keyword-only
    impl : {"numba", "numpy"}, keyword-only

    Returns
    -------
    warped : ndarray, shape core_shape, float32, grey levels
        ``g(X + u(X))``; NaN where invalid.
    valid : ndarray, shape core_shape, bool
        ``0 <= X_i + u_i <= g_shape_i - 1`` on every axis.

    References
    ----------
    Paper section 3 ("the deformed image is corrected") and 3.1 (trilinear interpolation).
    """
    core_shape = tuple(int(v) for v in core_shape)
    elems, u_nodes, core_origin, g_origin, g_shape, gw = _setup_b(
        ell, u_nodes, core_origin, core_shape, g, g_origin, g_shape, interpolation, impl,
        prefiltered)
    if gw is None:
        return np.full(core_shape, np.nan, dtype=np.float32), np.zeros(core_shape, bool)
    if impl == "numba":
        return _warp_kernel(int(ell), *elems, _xi(int(ell)), u_nodes, *core_origin, gw,
                            *g_origin, *g_shape, interpolation == "cubic")
    out, mask = _warp_numpy(int(ell), u_nodes, core_origin, core_shape, gw, g_origin,
                            g_shape, interpolation)
    return out.astype(np.float32), mask


def b_block(f: np.ndarray, lo, hi, ell: int, u_nodes: np.ndarray, core_origin,
            g: np.ndarray, g_origin, g_shape, *, interpolation: str = "cubic",
            impl: str = "numba", prefiltered: bool = False):
    """Block contribution to the right-hand side ``b`` of one modified Gauss-Newton step.

    With the current field ``u``, ``b_(a,i) = sum_X N_a(X) d_i f(X) r(X)``,
    ``r = f(X) - g(X + u(X))``; solving ``M da = b`` gives the increment ``da`` (the
    linearisation ``g(X+u+du) ~ g(X+u) + grad f . du`` uses ``grad f`` for ``grad g``,
    paper section 3.1, so ``M`` never changes).

    Parameters
    ----------
    f : ndarray, shape (core + lo + hi), any real dtype, grey levels
        Block region of the reference with its one-voxel halo (see :func:`gradient_block`).
    lo, hi : tuple of 3 int in {0, 1}
    ell : int
        Element edge, voxels; the core shape must be a multiple of it.
    u_nodes : ndarray, shape (3, ez+1, ey+1, ex+1), float64, voxels
        Current nodal displacement over the block's nodes, components (z, y, x).
    core_origin : tuple of 3 int
        Absolute level index of the first core voxel.
    g : ndarray, 3-D, any real dtype, grey levels
        Raw window of the deformed level starting at ``g_origin``; must contain
        :func:`g_window` of the same interpolation (ValueError otherwise). For ``cubic`` the
        window is prefiltered here (``scipy.ndimage.spline_filter(mode="mirror")``, float32
        coefficients); it matches a whole-volume prefilter where the window carries a halo
        of 12 voxels or touches the volume boundary.
    g_origin : tuple of 3 int
    g_shape : tuple of 3 int
        Shape of the whole deformed level.
    interpolation : {"linear", "cubic"}, keyword-only
        Default ``"cubic"``; the paper's choice is ``"linear"``.
    impl : {"numba", "numpy"}, keyword-only
    prefiltered : bool, keyword-only
        ``cubic`` only: ``g`` already holds float32 B-spline coefficients of the deformed
        level (see :mod:`chunkdic.prefilter`), so no per-window prefilter is done.

    Returns
    -------
    b : ndarray, shape (ez+1, ey+1, ex+1, 3), float64, grey levels^2 / voxel
        Nodal right-hand side, components (z, y, x).
    ssr : float
        ``sum r^2`` over the valid core voxels, grey levels^2.
    n_valid, n_excluded : int
        Valid core voxels and voxels whose ``X + u(X)`` leaves ``[0, g_shape - 1]`` (dropped
        from ``b`` and ``ssr``); they add up to the core size.

    References
    ----------
    Paper section 3 (``b_i``) and 3.1 (modified Gauss-Newton, trilinear interpolation).

    Examples
    --------
    Identical images and a zero field give a zero right-hand side:

    >>> vol = np.random.default_rng(0).random((8, 8, 8)).astype(np.float32)
    >>> u = np.zeros((3, 3, 3, 3))
    >>> win = g_window((0, 0, 0), (8, 8, 8), u, vol.shape, interpolation="linear")
    >>> b, ssr, n_valid, n_excluded = b_block(
    ...     vol, (0, 0, 0), (0, 0, 0), 4, u, (0, 0, 0), vol[win],
    ...     tuple(s.start for s in win), vol.shape, interpolation="linear")
    >>> bool(np.all(b == 0)), ssr, n_valid, n_excluded
    (True, 0.0, 512, 0)
    """
    core = _core_shape(f, lo, hi)
    elems, u_nodes, core_origin, g_origin, g_shape, gw = _setup_b(
        ell, u_nodes, core_origin, core, g, g_origin, g_shape, interpolation, impl, prefiltered)
    ell = int(ell)
    lo = tuple(int(v) for v in lo)
    hi = tuple(int(v) for v in hi)
    if gw is None:
        return np.zeros(u_nodes.shape[1:] + (3,)), 0.0, 0, int(np.prod(core))
    f32 = np.ascontiguousarray(f, dtype=np.float32)
    if impl == "numba":
        idx = [_grad_index(core[a], lo[a], hi[a]) for a in range(3)]
        b, ssr, nv, nb = _b_kernel(f32, lo[0], lo[1], lo[2], ell, *elems, *idx[0], *idx[1],
                                   *idx[2], _xi(ell), u_nodes, *core_origin, gw, *g_origin,
                                   *g_shape, interpolation == "cubic")
        return b, float(ssr), int(nv), int(nb)
    # NumPy twin: warp, residual, then b per element with the shape table
    warped, mask = _warp_numpy(ell, u_nodes, core_origin, core, gw, g_origin, g_shape,
                               interpolation)
    fc = f32[lo[0]:lo[0] + core[0], lo[1]:lo[1] + core[1], lo[2]:lo[2] + core[2]]
    r = np.where(mask, fc.astype(np.float64) - warped, 0.0)
    grad = gradient_block(f32, lo, hi).astype(np.float64)
    gr = grad * r
    W = shape_table(ell).reshape(-1, 8)
    b = np.zeros(u_nodes.shape[1:] + (3,))
    for ez, ey, ex in np.ndindex(*elems):
        sl = tuple(slice(e * ell, (e + 1) * ell) for e in (ez, ey, ex))
        be = np.einsum("va,iv->ai", W, gr[(slice(None),) + sl].reshape(3, -1))
        for a, d in enumerate(LOCAL_NODES):
            b[ez + d[0], ey + d[1], ex + d[2]] += be[a]
    nv = int(mask.sum())
    return b, float(np.sum(r * r)), nv, int(mask.size - nv)


# --------------------------------------------------------------------------------------
# warm-up
# --------------------------------------------------------------------------------------


def warmup() -> None:
    """Compile every numba kernel on tiny inputs (call once per worker).

    With ``cache=True`` the machine code is also stored next to the module, so later
    processes load it instead of compiling.
    """
    ell = 2
    f = np.arange(4 * 4 * 4, dtype=np.float32).reshape(4, 4, 4)
    lo = hi = (1, 1, 1)
    m_block(f, lo, hi, ell)
    u = np.full((3, 2, 2, 2), 0.25)
    for interp in _INTERPOLATIONS:
        b_block(f, lo, hi, ell, u, (1, 1, 1), f, (0, 0, 0), f.shape, interpolation=interp)
        warp_block(ell, u, (1, 1, 1), (2, 2, 2), f, (0, 0, 0), f.shape,
                   interpolation=interp)
