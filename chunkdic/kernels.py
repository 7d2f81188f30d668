"""Per-block numeric kernels of the C8-DIC engine: ``M``, ``b`` sums and the warp.

A block is a box of whole elements (docs/architecture.md, "Coordinates and blocks"). A task
reads the block's region of the (prepared) reference ``f`` plus a one-voxel halo (clipped
at the volume boundary) and the window of the (prepared) deformed image ``g`` that
:func:`g_window` says it needs, then calls the kernels below. Every kernel returns
*mesh-sized* partial results on the block's own elements or nodes; partials on shared
face nodes add up in the engine.

Method: paper section 3, modified Gauss–Newton (section 3.1): ``M`` is built once from
``grad f``; each iteration needs ``b_(a,i) = sum_X N_a(X) d_i f(X) r(X)`` with the residual
``r = f(X) - (λ g(X + u(X)) + μ)``, where the brightness correction ``(λ, μ)`` is chosen by
:mod:`chunkdic.greylevel` (``λ = 1, μ = 0`` is the paper). The kernels therefore return,
per element, the sums from which ``b`` and ``Σ r²`` follow for any ``(λ, μ)``
(:class:`ElementSums`): with ``d = f - g(X+u)`` and ``g' = g(X+u) - c`` (``c`` a centring
constant), ``r = d - α g' - μ'`` with ``α = λ - 1``, so

    b_e = Bd_e - α Bg_e - μ' B1_e,   Bq_e[a, i] = Σ_{X in e} N_a d_i f q,  q = d, g', 1

and ``Σ r²`` is a quadratic in ``(α, μ')`` of the moments ``n, Σd, Σg', Σd², Σdg', Σg'²``.
Writing ``r`` around ``d`` keeps the sums free of cancellation when ``λ ≈ 1, μ ≈ 0``.

Implementations (``impl=``): ``"numba"``, serial ``nogil`` kernels that sweep the block
once in raster order with no volume-sized temporaries (Dask provides the parallelism),
float32 images and float64 accumulators; ``"numpy"``, the plain NumPy/SciPy twins of
:mod:`chunkdic.kernels_numpy`, written for obviousness: the oracle of the tests.

Why the numba kernels are fast: the trilinear shape functions factor per axis,
``N_a N_b = prod_axes phi_{d_a}(xi) phi_{d_b}(xi)`` with ``phi_0 = 1 - xi``, ``phi_1 = xi``,
so an element's ``M`` is described by the 27 tensor moments
``T[pz, py, px, c] = sum_X psi_pz psi_py psi_px G_c`` (``psi_p``, ``p = d_a + d_b``, one of
``(1-xi)^2, xi(1-xi), xi^2``; ``G_c`` the 6 distinct products ``d_i f d_j f``): reducing a
voxel row over ``x`` costs 18 multiply-adds per voxel instead of 216. The ``b`` sums
factor the same way (two x-face weights per voxel, spread over the four (dz, dy) node
pairs once per row segment). Both are exact reorderings of the sums.

Interpolation in the ``b`` pass and the warp (the hot loop): voxels are taken one element
row segment at a time (``ell`` voxels along x, where the positions ``X + u(X)`` are affine);
:func:`_segment_samples`, shared by both, tests the segment's end points once and takes
a check-free flat-index path (the vector cubic gather of :mod:`chunkdic.interp`) when every
tap lies inside the window and the volume (nearly always), the general per-voxel path
(validity test, clamping, mirror) otherwise. Arithmetic is float64 on float32 data.

Notes for callers (the engine)
------------------------------
- ``f`` halo: ``lo[i]``/``hi[i]`` is 1 where a halo voxel was read, 0 where the core touches
  the volume boundary; gradients then equal ``np.gradient`` of the whole volume (float32).
- ``g`` window: read ``g[g_window(...)]`` and pass its start as ``g_origin``; the kernels
  refuse (ValueError) a window that misses samples a valid voxel needs. For cubic, pass a
  window of float32 B-spline coefficients with ``prefiltered=True`` (what the engine does,
  :mod:`chunkdic.prefilter`), or raw samples read with ``halo=chunkdic.bspline-halo`` (12)
  and let the kernels prefilter it (``scipy.ndimage.spline_filter``, mirror).
- Validity: a voxel counts when ``0 <= X_i + u_i <= g_shape_i - 1`` on every axis (a NaN
  displacement makes it invalid); invalid voxels are left out of every ``b`` sum and
  counted. ``M`` keeps every core voxel.
- :func:`warmup` compiles every kernel once per process.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi

from . import kernels_numpy
from .blocks import LAGS, ElementSums, check_nodes, core_shape, elements_of, grad_index, gradient_block, voxel_xi
from .interp import (
    fast_bounds,
    interp_cubic,
    interp_inside,
    interp_linear,
    jit,
    jit_inline,
    lerp,
    segment_inside,
)

__all__ = [
    "ElementSums",
    "IMPLEMENTATIONS",
    "INTERPOLATIONS",
    "gradient_block",
    "grad_index",
    "m_block",
    "g_window",
    "prepare_window",
    "b_sums",
    "b_block",
    "warp_block",
    "voxel_xi",
    "warmup",
]

IMPLEMENTATIONS = ("numba", "numpy")
INTERPOLATIONS = ("linear", "cubic")
#: brightness models whose element moments condense ``M`` (see :func:`m_block`)
CONDENSED = {"none": 0, "global": 0, "drift": 1, "element": 2}

# Index of the symmetric gradient product d_i f d_j f in the 6-vector G_c.
_SYM = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]], dtype=np.int64)


def _active(active, elems) -> np.ndarray:
    """The element activity of a block as uint8 (ez, ey, ex); all 1 by default."""
    if active is None:
        return np.ones(elems, np.uint8)
    active = np.ascontiguousarray(active, dtype=np.uint8)
    if active.shape != tuple(elems):
        raise ValueError(f"active must have shape {tuple(elems)}, got {active.shape}")
    return active


def _check(value, allowed, name):
    if value not in allowed:
        raise ValueError(f"{name} must be one of {allowed}, got {value!r}")


# --------------------------------------------------------------------------------------
# M
# --------------------------------------------------------------------------------------
# --------------------------------------------------------------------------------------


@jit
def _row_field(u, c, ez, ey, ex, tz, ty):
    """Nodal field component c bilinearly interpolated at (tz, ty) on the two x-faces."""
    e00 = lerp(u[c, ez, ey, ex], u[c, ez + 1, ey, ex], tz)
    e10 = lerp(u[c, ez, ey + 1, ex], u[c, ez + 1, ey + 1, ex], tz)
    e01 = lerp(u[c, ez, ey, ex + 1], u[c, ez + 1, ey, ex + 1], tz)
    e11 = lerp(u[c, ez, ey + 1, ex + 1], u[c, ez + 1, ey + 1, ex + 1], tz)
    return lerp(e00, e10, ty), lerp(e01, e11, ty)


@jit
def _m_kernel(fp, lo0, lo1, lo2, ell, nez, ney, nex, imz, ipz, scz, imy, ipy, scy, imx, ipx,
              scx, psi, xi, center, u, c0, c1, c2, n0, n1, n2, vm_lo, masked, active):
    """Element tensor moments T, element brightness couplings C and moments K; min / max.

    ``C[e, q, a, i] = Σ N_a d_i f q`` for ``q = (f - center, 1)`` and
    ``K[e] = (n, Σ(f - c), Σ(f - c)²)``: what the Schur complement of a brightness model
    needs (:func:`_assemble_stencil`). With ``masked``, voxels whose ``X + u(X)`` leaves
    ``[vm_lo, n - 1 - vm_lo]`` are left out of T, C and K, and so are the elements whose
    ``active`` is 0 (min / max keep every core voxel).
    """
    nx = nex * ell
    T = np.zeros((nez, ney, nex, 3, 3, 3, 6))
    C = np.zeros((nez, ney, nex, 2, 8, 3))
    K = np.zeros((nez, ney, nex, 3))
    lags = np.zeros((3, LAGS + 1))
    prod = np.empty((9, nx))
    vm = np.ones(nx)
    fmin = np.inf
    fmax = -np.inf
    for z in range(nez * ell):
        ez = z // ell
        lz = z - ez * ell
        zz = z + lo0
        tz = xi[lz]
        for y in range(ney * ell):
            ey = y // ell
            ly = y - ey * ell
            yy = y + lo1
            ty = xi[ly]
            zp, zm, sz = ipz[z], imz[z], scz[z]
            yp, ym, sy = ipy[y], imy[y], scy[y]
            for ex in range(nex):
                if active[ez, ey, ex] == 0:
                    for lx in range(ell):
                        vm[ex * ell + lx] = 0.0
                    continue
                if not masked:
                    for lx in range(ell):
                        vm[ex * ell + lx] = 1.0
                    continue
                if masked:
                    uz0, uz1 = _row_field(u, 0, ez, ey, ex, tz, ty)
                    uy0, uy1 = _row_field(u, 1, ez, ey, ex, tz, ty)
                    ux0, ux1 = _row_field(u, 2, ez, ey, ex, tz, ty)
                    for lx in range(ell):
                        tx = xi[lx]
                        p0 = c0 + z + lerp(uz0, uz1, tx)
                        p1 = c1 + y + lerp(uy0, uy1, tx)
                        p2 = c2 + ex * ell + lx + lerp(ux0, ux1, tx)
                        vm[ex * ell + lx] = _taper(p0, p1, p2, n0, n1, n2, vm_lo)
            # pass 1 over the row: gradient (float32, as gradient_block) and its products
            for x in range(nx):
                xx = x + lo2
                v = fp[zz, yy, xx]
                if v < fmin:
                    fmin = v
                if v > fmax:
                    fmax = v
                # a weight w on every voxel's squared residual (the b passes' taper)
                w = vm[x]
                gz = np.float64((fp[zp, yy, xx] - fp[zm, yy, xx]) * sz)
                gy = np.float64((fp[zz, yp, xx] - fp[zz, ym, xx]) * sy)
                gx = np.float64((fp[zz, yy, ipx[x]] - fp[zz, yy, imx[x]]) * scx[x])
                prod[0, x] = w * gz * gz
                prod[1, x] = w * gz * gy
                prod[2, x] = w * gz * gx
                prod[3, x] = w * gy * gy
                prod[4, x] = w * gy * gx
                prod[5, x] = w * gx * gx
                prod[6, x] = w * gz
                prod[7, x] = w * gy
                prod[8, x] = w * gx
            # autocorrelation of the gradient along x (noise correlation estimate, LAGS)
            for i in range(3):
                for k in range(LAGS + 1):
                    acc = 0.0
                    for x in range(nx - k):
                        acc += prod[6 + i, x] * prod[6 + i, x + k]
                    lags[i, k] += acc
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
                # brightness couplings: x-face sums of grad f and grad f (f - c)
                k0 = 0.0
                k1 = 0.0
                k2 = 0.0
                for i in range(3):
                    a0 = 0.0
                    a1 = 0.0
                    b0 = 0.0
                    b1 = 0.0
                    for lx in range(ell):
                        gi = prod[6 + i, x0 + lx]
                        fv = np.float64(fp[zz, yy, x0 + lx + lo2]) - center
                        w1 = xi[lx]
                        w0 = 1.0 - w1
                        a0 += w0 * gi * fv
                        a1 += w1 * gi * fv
                        b0 += w0 * gi
                        b1 += w1 * gi
                        if i == 0:
                            w = vm[x0 + lx]
                            k0 += w
                            k1 += w * fv
                            k2 += w * fv * fv
                    for dz in range(2):
                        wz = tz if dz else 1.0 - tz
                        for dy in range(2):
                            w = wz * (ty if dy else 1.0 - ty)
                            a = 4 * dz + 2 * dy
                            C[ez, ey, ex, 0, a, i] += w * a0
                            C[ez, ey, ex, 0, a + 1, i] += w * a1
                            C[ez, ey, ex, 1, a, i] += w * b0
                            C[ez, ey, ex, 1, a + 1, i] += w * b1
                K[ez, ey, ex, 0] += k0
                K[ez, ey, ex, 1] += k1
                K[ez, ey, ex, 2] += k2
    return T, C, K, lags, fmin, fmax


@jit
def _assemble_stencil(T, C, K, sym, condensed):
    """Scatter element moments into the block's nodal 27-point stencil.

    ``condensed`` 0: plain ``M``; 1: minus the Schur complement of a per-element offset
    (``C1 C1ᵀ / n``); 2: of a per-element gain and offset (``[Cf C1] K⁻¹ [Cf C1]ᵀ``).
    """
    nez, ney, nex = T.shape[0], T.shape[1], T.shape[2]
    S = np.zeros((nez + 1, ney + 1, nex + 1, 27, 3, 3))
    inv = np.zeros((2, 2))
    for ez in range(nez):
        for ey in range(ney):
            for ex in range(nex):
                n, s1, s2 = K[ez, ey, ex, 0], K[ez, ey, ex, 1], K[ez, ey, ex, 2]
                inv[:, :] = 0.0
                if condensed == 1 and n > 0:
                    inv[1, 1] = 1.0 / n
                elif condensed == 2 and n > 0:
                    det = s2 * n - s1 * s1
                    if det > 1e-12 * s2 * n:
                        inv[0, 0] = n / det
                        inv[0, 1] = -s1 / det
                        inv[1, 0] = -s1 / det
                        inv[1, 1] = s2 / det
                    else:  # a flat element: offset only
                        inv[1, 1] = 1.0 / n
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
                                v = T[ez, ey, ex, az + bz, ay + by, ax + bx, sym[i, j]]
                                if condensed:
                                    for p in range(2):
                                        for q in range(2):
                                            v -= C[ez, ey, ex, p, a, i] * inv[p, q] * C[ez, ey, ex, q, b, j]
                                S[ez + az, ey + ay, ex + ax, k, i, j] += v
    return S


def m_block(f: np.ndarray, lo, hi, ell: int, *, impl: str = "numba", grey: str = "none",
            center: float = 0.0, u_nodes: np.ndarray | None = None, core_origin=None, g_shape=None,
            margin: int = 0, with_lags: bool = False, active: np.ndarray | None = None):
    """Block contribution to the C8 matrix ``M`` as a nodal 27-point stencil.

    Parameters
    ----------
    f : ndarray, shape (core_z + lo[0] + hi[0], ...), any real dtype, grey levels
        Block region of the (prepared) reference including its one-voxel halo (see
        :func:`gradient_block`). Converted to float32.
    lo, hi : tuple of 3 int in {0, 1}
        Halo voxels before / after the core per axis (0 at the volume boundary).
    ell : int
        Element edge, voxels. The core shape must be a multiple of ``ell``.
    impl : {"numba", "numpy"}, keyword-only
        Fused kernel or its NumPy twin (test oracle).
    grey : {"none", "global", "drift", "element"}, keyword-only
        Brightness model (:mod:`chunkdic.greylevel`). ``drift`` and ``element`` have
        per-element brightness unknowns, eliminated exactly (variable projection), so the
        Gauss–Newton matrix is ``M`` minus their Schur complement per element, with ``f``
        standing for ``g(X + u)`` as in the rest of the modified Gauss–Newton.
    center : float, keyword-only
        Centring constant ``c`` of the brightness sums (grey levels).
    u_nodes, core_origin, g_shape : keyword-only, optional
        The level's starting field over the block's nodes (3, ez+1, ey+1, ex+1), the
        block's first core voxel and the shape of ``g``: voxels whose ``X + u(X)`` leaves
        ``g`` are left out of ``M``, as the ``b`` passes leave them out, so that ``M``
        matches ``b`` where the field maps part of the ROI outside ``g`` (without it,
        nodes of partly excluded elements converge very slowly).
    margin : int, keyword-only
        Positions within ``margin`` voxels of a face of ``g`` count as outside (see
        :func:`b_sums`).
    active : ndarray, shape (ez, ey, ex), uint8, keyword-only, optional
        0 for the elements left out (:mod:`chunkdic.masks`); default all 1.
    with_lags : bool, keyword-only
        Also return ``lags`` (3, LAGS + 1): ``Σ w ∂_i f(x) w ∂_i f(x + k)`` along x, the
        autocorrelation of the sensitivities that estimates the noise correlation
        (:func:`chunkdic.noise.correlation_factor`). numba only.

    Returns
    -------
    S : ndarray, shape (ez+1, ey+1, ex+1, 27, 3, 3), float64, grey levels^2
        ``S[n, k, i, j] = M[(n, i), (n + off_k, j)]`` with ``off_k`` from
        :data:`chunkdic.mesh.STENCIL_OFFSETS`, ``M_(a,i),(b,j) = sum_X N_a N_b d_i f d_j f``
        over the core voxels (minus the condensation); entries whose column node leaves the
        block are 0. Symmetric: ``S[n, k, i, j] == S[n + off_k, 26 - k, j, i]``.
    fmin, fmax : float
        Extreme grey levels of the core voxels (for the matching gap normalisation).

    References
    ----------
    Paper section 3, linear system ``M_ij a_j = b_i``; section 3.1 (``M`` is built once
    from the reference).
    """
    _check(impl, IMPLEMENTATIONS, "impl")
    _check(grey, tuple(CONDENSED), "grey")
    core = core_shape(f, lo, hi)
    elems = elements_of(core, ell)
    f32 = np.ascontiguousarray(f, dtype=np.float32)
    lo = tuple(int(v) for v in lo)
    hi = tuple(int(v) for v in hi)
    masked = u_nodes is not None
    u = check_nodes(u_nodes if masked else np.zeros((3,) + tuple(e + 1 for e in elems)), elems)
    origin = tuple(int(v) for v in core_origin) if masked else (0, 0, 0)
    shape = tuple(int(v) for v in g_shape) if masked else (1, 1, 1)
    active = _active(active, elems)
    if impl == "numpy":
        return kernels_numpy.m_block_numpy(f32, lo, hi, int(ell), elems, CONDENSED[grey], float(center),
                                           u if masked else None, origin, shape, int(margin), active)
    ell = int(ell)
    idx = [grad_index(core[a], lo[a], hi[a]) for a in range(3)]
    xi = voxel_xi(ell)
    psi = np.stack([(1.0 - xi) ** 2, xi * (1.0 - xi), xi**2])  # psi_p, p = d_a + d_b
    T, C, K, lags, fmin, fmax = _m_kernel(f32, lo[0], lo[1], lo[2], ell, *elems, *idx[0], *idx[1], *idx[2],
                                          psi, xi, float(center), u, *origin, *shape, float(margin), masked,
                                          active)
    if with_lags:
        return _assemble_stencil(T, C, K, _SYM, CONDENSED[grey]), float(fmin), float(fmax), lags
    return _assemble_stencil(T, C, K, _SYM, CONDENSED[grey]), float(fmin), float(fmax)


# --------------------------------------------------------------------------------------
# the g window
# --------------------------------------------------------------------------------------


def g_window(core_origin, core_shape, u_nodes, g_shape, *, interpolation: str,
             halo: int = 0, margin: int = 0) -> tuple[slice, slice, slice]:
    """Region of the deformed image that :func:`b_sums` / :func:`warp_block` need.

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
        ``floor(x) - 1 .. floor(x) + 2``.
    halo : int, keyword-only
        Extra voxels per side (a window filtered by the task itself: Gaussian low-pass,
        cubic prefilter).
    margin : int, keyword-only
        Positions within ``margin`` voxels of a face of ``g`` are invalid (:func:`b_sums`).

    Returns
    -------
    window : tuple of 3 slice
        Absolute level indices, clipped to ``[0, g_shape)``. If no core voxel can map into
        ``g`` the region is empty: ``(slice(0, 0),) * 3``.
    """
    _check(interpolation, INTERPOLATIONS, "interpolation")
    u_nodes = np.asarray(u_nodes, dtype=np.float64)
    if u_nodes.shape[0] != 3:
        raise ValueError(f"u_nodes must have 3 components first, got shape {u_nodes.shape}")
    extra = int(halo) + (1 if interpolation == "cubic" else 0)
    out = []
    for i in range(3):
        n = int(g_shape[i])
        lo = max(core_origin[i] + float(u_nodes[i].min()), float(margin))
        hi = min(core_origin[i] + core_shape[i] - 1 + float(u_nodes[i].max()), n - 1.0 - margin)
        if not (lo <= hi):  # also catches NaN
            return (slice(0, 0),) * 3
        start = max(math.floor(lo) - extra, 0)
        # + 2: floor(x) + 1 inclusive; cubic adds floor(x) + 2
        stop = min(math.floor(hi) + 2 + extra, n)
        out.append(slice(start, stop))
    return tuple(out)


def prepare_window(g: np.ndarray, interpolation: str) -> np.ndarray:
    """A raw window as the kernels' float32 samples (linear) or B-spline coefficients (cubic).

    float32 coefficients: the images are float32 (architecture.md) and the B-spline
    reproduces samples with relative error ~1e-7 of the intensity range either way; float32
    halves the memory and bandwidth of the 64-tap gather, the hot loop of the cubic pass.
    The prefilter is ``scipy.ndimage.spline_filter(order=3, mode="mirror")``: it equals a
    whole-volume prefilter where the window carries ``chunkdic.bspline-halo`` voxels or
    touches the volume boundary.
    """
    if interpolation == "cubic" and g.size:
        return ndi.spline_filter(np.asarray(g, dtype=np.float32), order=3, mode="mirror", output=np.float32)
    return np.ascontiguousarray(g, dtype=np.float32)


def _check_window(g, g_origin, core_origin, core_shape, u_nodes, g_shape, margin):
    """Refuse a window that does not cover the samples valid voxels need; False if none can be valid."""
    need = g_window(core_origin, core_shape, u_nodes, g_shape, interpolation="linear", margin=margin)
    if need[0].stop == need[0].start:
        return False
    for i in range(3):
        o = int(g_origin[i])
        if o > need[i].start or o + g.shape[i] < need[i].stop:
            raise ValueError(
                f"g window [{o}, {o + g.shape[i]}) on axis {i} does not cover the needed "
                f"[{need[i].start}, {need[i].stop}); read it with g_window()"
            )
    return True


@dataclass
class _Setup:
    elems: tuple
    u_nodes: np.ndarray
    core_origin: tuple
    g_origin: tuple
    g_shape: tuple
    gw: np.ndarray | None  # prepared window; None when no voxel can be valid


def _setup(ell, u_nodes, core_origin, core, g, g_origin, g_shape, interpolation, impl, prefiltered,
           margin) -> _Setup:
    _check(impl, IMPLEMENTATIONS, "impl")
    _check(interpolation, INTERPOLATIONS, "interpolation")
    elems = elements_of(core, ell)
    u_nodes = check_nodes(u_nodes, elems)
    core_origin = tuple(int(v) for v in core_origin)
    g_origin = tuple(int(v) for v in g_origin)
    g_shape = tuple(int(v) for v in g_shape)
    g = np.asarray(g)
    any_valid = _check_window(g, g_origin, core_origin, core, u_nodes, g_shape, margin)
    gw = None
    if any_valid:
        gw = np.ascontiguousarray(g, dtype=np.float32) if prefiltered else prepare_window(g, interpolation)
    return _Setup(elems, u_nodes, core_origin, g_origin, g_shape, gw)


# --------------------------------------------------------------------------------------
# the shared segment loop, b sums and the warp
# --------------------------------------------------------------------------------------


@jit
def _valid_bounds(b, n0, n1, n2, m):
    """Fast-path bounds narrowed to where every weight is 1: ``[m + 1, n - 2 - m]`` (:func:`_taper`)."""
    m = m + 1.0
    return (max(b[0], m), min(b[1], n0 - 1.0 - m), max(b[2], m), min(b[3], n1 - 1.0 - m),
            max(b[4], m), min(b[5], n2 - 1.0 - m))


@jit_inline
def _taper(p0, p1, p2, n0, n1, n2, m):
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
def _segment_samples(u, ez, ey, ex, tz, ty, X0, X1, xa, ell, xi, g, gf, gs0, gs1, o0, o1, o2,
                     n0, n1, n2, vm_lo, bounds, cubic, gbuf, wt):
    """``g(X + u(X))`` over one element row segment (``ell`` voxels along x from ``xa``).

    Fills ``gbuf`` and the weights ``wt`` (:func:`_taper`; 0 where ``X + u`` leaves
    ``[vm_lo, n - 1 - vm_lo]``) and returns the number of voxels of weight 0. The
    positions are affine along the segment: when both end points pass
    :func:`chunkdic.interp.segment_inside` (bounds at least one voxel inside that box)
    every voxel has weight 1 and takes the check-free flat path; otherwise each voxel is
    weighted and clamped or mirrored as needed.
    """
    uz0, uz1 = _row_field(u, 0, ez, ey, ex, tz, ty)
    uy0, uy1 = _row_field(u, 1, ez, ey, ex, tz, ty)
    ux0, ux1 = _row_field(u, 2, ez, ey, ex, tz, ty)
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
        wt[lx] = _taper(p0, p1, p2, n0, n1, n2, vm_lo)
        if wt[lx] == 0.0:
            nbad += 1
        elif cubic:
            gbuf[lx] = interp_cubic(g, o0, o1, o2, n0, n1, n2, p0, p1, p2)
        else:
            gbuf[lx] = interp_linear(g, o0, o1, o2, p0, p1, p2)
    return nbad


@jit_inline
def _spread(Be, q, a, w, s0z, s0y, s0x, s1z, s1y, s1x):
    """Add ``w`` × the two x-face sums of quantity ``q`` to local nodes ``a`` and ``a + 1``."""
    Be[q, a, 0] += w * s0z
    Be[q, a, 1] += w * s0y
    Be[q, a, 2] += w * s0x
    Be[q, a + 1, 0] += w * s1z
    Be[q, a + 1, 1] += w * s1y
    Be[q, a + 1, 2] += w * s1x


@jit_inline
def _gram_row(Ge, n, sd, sg, sq, sdd, sdg, sgg, sdq, sgq, sqq, zt, yt):
    """Add a row segment to the upper triangle of the element Gram of
    ``v = (d, g', 1, z~, y~, x~)`` (weights ``w``; :func:`_symmetrize` completes it).

    ``sq, sdq, sgq, sqq``: the segment's sums with ``x~``; ``z~ = zt``, ``y~ = yt`` on the row.
    """
    Ge[0, 0] += sdd
    Ge[0, 1] += sdg
    Ge[0, 2] += sd
    Ge[0, 3] += zt * sd
    Ge[0, 4] += yt * sd
    Ge[0, 5] += sdq
    Ge[1, 1] += sgg
    Ge[1, 2] += sg
    Ge[1, 3] += zt * sg
    Ge[1, 4] += yt * sg
    Ge[1, 5] += sgq
    Ge[2, 2] += n
    Ge[2, 3] += zt * n
    Ge[2, 4] += yt * n
    Ge[2, 5] += sq
    Ge[3, 3] += zt * zt * n
    Ge[3, 4] += zt * yt * n
    Ge[3, 5] += zt * sq
    Ge[4, 4] += yt * yt * n
    Ge[4, 5] += yt * sq
    Ge[5, 5] += sqq


@jit
def _symmetrize(G):
    """Copy the upper triangle of every element's Gram onto its lower triangle."""
    for ez in range(G.shape[0]):
        for ey in range(G.shape[1]):
            for ex in range(G.shape[2]):
                for j in range(6):
                    for k in range(j + 1, 6):
                        G[ez, ey, ex, k, j] = G[ez, ey, ex, j, k]


@jit
def _b_kernel(fp, lo0, lo1, lo2, ell, nez, ney, nex, imz, ipz, scz, imy, ipy, scy, imx, ipx,
              scx, xi, u, c0, c1, c2, g, o0, o1, o2, n0, n1, n2, vm_lo, cubic, center, active):
    """One fused sweep: ``g(X + u)``, ``d``, ``g'`` and the per-element sums (ElementSums).

    Elements whose ``active`` is 0 are skipped (their voxels have weight 0 and are not
    counted as excluded)."""
    B = np.zeros((nez, ney, nex, 6, 8, 3))
    G = np.zeros((nez, ney, nex, 6, 6))
    lags = np.zeros((6, LAGS + 1))
    nbad = 0
    gf = g.ravel()
    gs0 = g.shape[1] * g.shape[2]
    gs1 = g.shape[2]
    bounds = _valid_bounds(fast_bounds(g.shape, o0, o1, o2, n0, n1, n2, cubic), n0, n1, n2, vm_lo)
    ff = fp.ravel()
    fs0 = fp.shape[1] * fp.shape[2]
    fs1 = fp.shape[2]
    nx = nex * ell
    gbuf = np.empty(ell)
    wt = np.empty(ell)
    # one x-row of f and of its gradient (float32 differences, as gradient_block)
    frow = np.empty((4, nx), dtype=np.float32)
    drow = np.zeros(nx)  # the row's d, g' and weights, for the residual's autocorrelation
    grow = np.zeros(nx)
    wrow = np.zeros(nx)
    for z in range(nez * ell):
        ez = z // ell
        zz = z + lo0
        tz = xi[z - ez * ell]
        X0 = c0 + z
        for y in range(ney * ell):
            ey = y // ell
            yy = y + lo1
            ty = xi[y - ey * ell]
            X1 = c1 + y
            # flat offsets (unsigned: no wrap-around code) of the rows of f used by d and
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
                xa = c2 + ex * ell
                if active[ez, ey, ex] == 0:
                    for lx in range(ell):
                        wt[lx] = 0.0
                        wrow[ex * ell + lx] = 0.0
                    continue
                nbad += _segment_samples(u, ez, ey, ex, tz, ty, X0, X1, xa, ell, xi, g, gf, gs0, gs1,
                                         o0, o1, o2, n0, n1, n2, vm_lo, bounds, cubic, gbuf, wt)
                # x-face sums (w0 = 1 - xi, w1 = xi) of grad f times d, g', 1 and x~ = xi - 1/2
                d0z = d0y = d0x = d1z = d1y = d1x = 0.0
                g0z = g0y = g0x = g1z = g1y = g1x = 0.0
                e0z = e0y = e0x = e1z = e1y = e1x = 0.0
                q0z = q0y = q0x = q1z = q1y = q1x = 0.0
                n = sd = sg = sq = sdd = sdg = sgg = sdq = sgq = sqq = 0.0
                for lx in range(ell):
                    w = wt[lx]
                    x = ex * ell + lx
                    wrow[x] = w
                    if w == 0.0:
                        continue
                    gv = gbuf[lx]
                    d = np.float64(frow[0, x]) - gv
                    gp = gv - center
                    drow[x] = d
                    grow[x] = gp
                    gz = np.float64(frow[1, x]) * w
                    gy = np.float64(frow[2, x]) * w
                    gx = np.float64(frow[3, x]) * w
                    w1 = xi[lx]
                    w0 = 1.0 - w1
                    q = w1 - 0.5
                    n += w
                    sd += w * d
                    sg += w * gp
                    sq += w * q
                    sdd += w * d * d
                    sdg += w * d * gp
                    sgg += w * gp * gp
                    sdq += w * d * q
                    sgq += w * gp * q
                    sqq += w * q * q
                    e0z += w0 * gz
                    e0y += w0 * gy
                    e0x += w0 * gx
                    e1z += w1 * gz
                    e1y += w1 * gy
                    e1x += w1 * gx
                    d0z += w0 * gz * d
                    d0y += w0 * gy * d
                    d0x += w0 * gx * d
                    d1z += w1 * gz * d
                    d1y += w1 * gy * d
                    d1x += w1 * gx * d
                    g0z += w0 * gz * gp
                    g0y += w0 * gy * gp
                    g0x += w0 * gx * gp
                    g1z += w1 * gz * gp
                    g1y += w1 * gy * gp
                    g1x += w1 * gx * gp
                    q0z += w0 * gz * q
                    q0y += w0 * gy * q
                    q0x += w0 * gx * q
                    q1z += w1 * gz * q
                    q1y += w1 * gy * q
                    q1x += w1 * gx * q
                if n == 0.0:
                    continue
                # the element's Gram of (d, g', 1, z~, y~, x~); z~, y~ are constant on the row
                zt = tz - 0.5
                yt = ty - 0.5
                _gram_row(G[ez, ey, ex], n, sd, sg, sq, sdd, sdg, sgg, sdq, sgq, sqq, zt, yt)
                # spread the row sums over the 4 (dz, dy) node pairs of each x-face
                Be = B[ez, ey, ex]
                for dz in range(2):
                    wz = tz if dz else 1.0 - tz
                    for dy in range(2):
                        w = wz * (ty if dy else 1.0 - ty)
                        a = 4 * dz + 2 * dy
                        _spread(Be, 0, a, w, d0z, d0y, d0x, d1z, d1y, d1x)
                        _spread(Be, 1, a, w, g0z, g0y, g0x, g1z, g1y, g1x)
                        _spread(Be, 2, a, w, e0z, e0y, e0x, e1z, e1y, e1x)
                        _spread(Be, 3, a, w * zt, e0z, e0y, e0x, e1z, e1y, e1x)
                        _spread(Be, 4, a, w * yt, e0z, e0y, e0x, e1z, e1y, e1x)
                        _spread(Be, 5, a, w, q0z, q0y, q0x, q1z, q1y, q1x)
            # autocorrelation of the residual along x (noise correlation estimate, LAGS):
            # the client forms that of r = d - α g' from these (blocks.ElementSums.lags)
            for k in range(LAGS + 1):
                sdd_k = 0.0
                cnt = 0.0
                sdg_k = 0.0
                sgg_k = 0.0
                for x in range(nx - k):
                    ww = wrow[x] * wrow[x + k]
                    sdd_k += ww * drow[x] * drow[x + k]
                    sdg_k += ww * (drow[x] * grow[x + k] + grow[x] * drow[x + k])
                    sgg_k += ww * grow[x] * grow[x + k]
                    cnt += ww
                lags[0, k] += sdd_k
                lags[1, k] += cnt
                lags[2, k] += sdg_k
                lags[3, k] += sgg_k
            for x in range(nx):
                lags[4, 0] += wrow[x] * drow[x]
                lags[5, 0] += wrow[x] * grow[x]
    _symmetrize(G)
    return B, G, lags, nbad


@jit
def _warp_kernel(ell, nez, ney, nex, xi, u, c0, c1, c2, g, o0, o1, o2, n0, n1, n2, vm_lo, cubic):
    """``g(X + u(X))`` over the core (float32, NaN where invalid) and the validity mask."""
    out = np.empty((nez * ell, ney * ell, nex * ell), dtype=np.float32)
    mask = np.zeros((nez * ell, ney * ell, nex * ell), dtype=np.bool_)
    gf = g.ravel()
    gs0 = g.shape[1] * g.shape[2]
    gs1 = g.shape[2]
    bounds = _valid_bounds(fast_bounds(g.shape, o0, o1, o2, n0, n1, n2, cubic), n0, n1, n2, vm_lo)
    gbuf = np.empty(ell)
    wt = np.empty(ell)
    for z in range(nez * ell):
        ez = z // ell
        tz = xi[z - ez * ell]
        for y in range(ney * ell):
            ey = y // ell
            ty = xi[y - ey * ell]
            for ex in range(nex):
                _segment_samples(u, ez, ey, ex, tz, ty, c0 + z, c1 + y, c2 + ex * ell, ell, xi, g, gf,
                                 gs0, gs1, o0, o1, o2, n0, n1, n2, vm_lo, bounds, cubic, gbuf, wt)
                for lx in range(ell):
                    x = ex * ell + lx
                    mask[z, y, x] = wt[lx] > 0.0
                    out[z, y, x] = gbuf[lx] if wt[lx] > 0.0 else np.nan
    return out, mask


def b_sums(f: np.ndarray, lo, hi, ell: int, u_nodes: np.ndarray, core_origin, g: np.ndarray,
           g_origin, g_shape, *, interpolation: str = "cubic", impl: str = "numba",
           prefiltered: bool = False, center: float = 0.0, margin: int = 0,
           active: np.ndarray | None = None) -> ElementSums:
    """Per-element sums of one modified Gauss–Newton pass over a block (module docstring).

    Parameters
    ----------
    f : ndarray, shape (core + lo + hi), any real dtype, grey levels
        Block region of the (prepared) reference with its one-voxel halo.
    lo, hi : tuple of 3 int in {0, 1}
    ell : int
        Element edge, voxels; the core shape must be a multiple of it.
    u_nodes : ndarray, shape (3, ez+1, ey+1, ex+1), float64, voxels
        Current nodal displacement over the block's nodes, components (z, y, x).
    core_origin : tuple of 3 int
        Absolute level index of the first core voxel.
    g : ndarray, 3-D, grey levels
        Window of the deformed level starting at ``g_origin`` covering :func:`g_window`:
        raw samples, or (``prefiltered``) the prepared float32 samples / B-spline
        coefficients of :mod:`chunkdic.prefilter`.
    g_origin, g_shape : tuple of 3 int
        Window origin; shape of the whole deformed level.
    interpolation : {"linear", "cubic"}, keyword-only
    impl : {"numba", "numpy"}, keyword-only
    prefiltered : bool, keyword-only
        ``g`` is already what the interpolation reads (no per-window cubic prefilter here).
    center : float, keyword-only
        Centring constant ``c`` of ``g' = g(X+u) - c`` (grey levels; the level's mid-range).
    margin : int, keyword-only
        A voxel is valid when ``margin <= X_i + u_i <= g_shape_i - 1 - margin`` on every axis;
        the data beyond still serve the interpolation and its prefilter (the engine
        excludes where the low-pass of ``g`` is not exact, :func:`chunkdic.prefilter.face_margin`).
    active : ndarray, shape (ez, ey, ex), uint8, keyword-only, optional
        0 for the elements left out (:mod:`chunkdic.masks`): no sums, not counted as
        excluded. Default all 1.

    Returns
    -------
    ElementSums

    References
    ----------
    Paper section 3 (``b_i``) and 3.1 (modified Gauss-Newton, trilinear interpolation).
    """
    core = core_shape(f, lo, hi)
    st = _setup(ell, u_nodes, core_origin, core, g, g_origin, g_shape, interpolation, impl, prefiltered, margin)
    ell = int(ell)
    lo = tuple(int(v) for v in lo)
    hi = tuple(int(v) for v in hi)
    active = _active(active, st.elems)
    if st.gw is None:
        n_off = int(np.sum(active == 0)) * ell**3
        return ElementSums(np.zeros(st.elems + (6, 8, 3)), np.zeros(st.elems + (6, 6)), int(np.prod(core)) - n_off,
                           np.zeros((6, LAGS + 1)))
    f32 = np.ascontiguousarray(f, dtype=np.float32)
    if impl == "numpy":
        return kernels_numpy.b_sums_numpy(f32, lo, hi, ell, st.u_nodes, st.core_origin, st.gw, st.g_origin,
                                          st.g_shape, interpolation, float(center), int(margin), active)
    idx = [grad_index(core[a], lo[a], hi[a]) for a in range(3)]
    B, gram, lags, nbad = _b_kernel(f32, lo[0], lo[1], lo[2], ell, *st.elems, *idx[0], *idx[1], *idx[2],
                             voxel_xi(ell), st.u_nodes, *st.core_origin, st.gw, *st.g_origin, *st.g_shape,
                             float(margin), interpolation == "cubic", float(center), active)
    return ElementSums(B, gram, int(nbad), lags)


def b_block(f: np.ndarray, lo, hi, ell: int, u_nodes: np.ndarray, core_origin, g: np.ndarray,
            g_origin, g_shape, *, interpolation: str = "cubic", impl: str = "numba",
            prefiltered: bool = False):
    """The paper's ``b`` over a block: no brightness correction (``r = f - g(X + u)``).

    Same parameters as :func:`b_sums`. Returns ``(b, ssr, n_valid, n_excluded)``: ``b``
    of shape (ez+1, ey+1, ex+1, 3), float64, grey levels² / voxel; ``ssr = Σ w r²`` over the
    valid voxels (weights ``w``, see :class:`ElementSums`); valid and excluded voxel counts
    (they add up to the core size).

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
    sums = b_sums(f, lo, hi, ell, u_nodes, core_origin, g, g_origin, g_shape, interpolation=interpolation,
                  impl=impl, prefiltered=prefiltered)
    b = element_to_nodes(sums.B[..., 0, :, :])
    n_core = int(np.prod(core_shape(f, lo, hi)))
    return b, float(sums.gram[..., 0, 0].sum()), n_core - sums.n_excluded, sums.n_excluded


@jit
def _element_to_nodes(E):
    nez, ney, nex = E.shape[0], E.shape[1], E.shape[2]
    out = np.zeros((nez + 1, ney + 1, nex + 1, 3))
    for ez in range(nez):
        for ey in range(ney):
            for ex in range(nex):
                for a in range(8):
                    for i in range(3):
                        out[ez + (a >> 2), ey + ((a >> 1) & 1), ex + (a & 1), i] += E[ez, ey, ex, a, i]
    return out


def element_to_nodes(E: np.ndarray) -> np.ndarray:
    """Add per-element local-node values ``E (ez, ey, ex, 8, 3)`` into nodal ``(ez+1, ey+1, ex+1, 3)``."""
    return _element_to_nodes(np.ascontiguousarray(E, dtype=np.float64))


def warp_block(ell: int, u_nodes: np.ndarray, core_origin, core_shape, g: np.ndarray,
               g_origin, g_shape, *, interpolation: str = "cubic", impl: str = "numba",
               prefiltered: bool = False, margin: int = 0):
    """The corrected deformed image ``g(X + u(X))`` over a block core.

    Parameters
    ----------
    ell : int
        Element edge, voxels.
    u_nodes : ndarray, shape (3, ez+1, ey+1, ex+1), float64, voxels
    core_origin, core_shape : tuple of 3 int
        Absolute level index of the first core voxel; ``(ez*ell, ey*ell, ex*ell)``.
    g : ndarray, 3-D, grey levels
        Window of the deformed level (see :func:`b_sums`).
    g_origin, g_shape : tuple of 3 int
    interpolation : {"linear", "cubic"}, keyword-only
    impl : {"numba", "numpy"}, keyword-only
    prefiltered : bool, keyword-only
    margin : int, keyword-only
        See :func:`b_sums`.

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
    core = tuple(int(v) for v in core_shape)
    st = _setup(ell, u_nodes, core_origin, core, g, g_origin, g_shape, interpolation, impl, prefiltered, margin)
    if st.gw is None:
        return np.full(core, np.nan, dtype=np.float32), np.zeros(core, bool)
    if impl == "numpy":
        out, mask, _ = kernels_numpy.warp_numpy(int(ell), st.u_nodes, st.core_origin, core, st.gw, st.g_origin,
                                                st.g_shape, interpolation, int(margin))
        return out.astype(np.float32), mask
    return _warp_kernel(int(ell), *st.elems, voxel_xi(int(ell)), st.u_nodes, *st.core_origin, st.gw,
                        *st.g_origin, *st.g_shape, float(margin), interpolation == "cubic")


def warmup() -> None:
    """Compile every numba kernel on tiny inputs (call once per worker).

    With ``cache=True`` the machine code is also stored next to the module, so later
    processes load it instead of compiling.
    """
    ell = 2
    f = np.arange(4 * 4 * 4, dtype=np.float32).reshape(4, 4, 4)
    lo = hi = (1, 1, 1)
    u = np.full((3, 2, 2, 2), 0.25)
    for grey in ("none", "element"):
        m_block(f, lo, hi, ell, grey=grey)
    m_block(f, lo, hi, ell, with_lags=True, active=np.ones((1, 1, 1), np.uint8))
    m_block(f, lo, hi, ell, u_nodes=u, core_origin=(1, 1, 1), g_shape=f.shape)
    for interp in INTERPOLATIONS:
        sums = b_sums(f, lo, hi, ell, u, (1, 1, 1), f, (0, 0, 0), f.shape, interpolation=interp)
        element_to_nodes(sums.B[..., 0, :, :])
        warp_block(ell, u, (1, 1, 1), (2, 2, 2), f, (0, 0, 0), f.shape, interpolation=interp)
