"""Per-block numeric kernels of the C8-DIC engine: ``M``, ``b`` sums and the warp.

This module is their overview and compiles them all (:func:`warmup`); the kernels live in
:mod:`chunkdic.kernels.m` (``M``), :mod:`chunkdic.kernels.b` (``b`` sums),
:mod:`chunkdic.kernels.warp` (the warp), :mod:`chunkdic.kernels.rows` (the element row
segment they share) and :mod:`chunkdic.kernels.window` (the ``g`` window and argument checks).

A block is a box of whole elements (docs/architecture.md, "Coordinates and blocks"). A task
reads the block's region of the (prepared) reference ``f`` plus a one-voxel halo (clipped
at the volume boundary) and the window of the (prepared) deformed image ``g`` that
:func:`~chunkdic.kernels.window.g_window` says it needs, then calls the kernels. Every kernel returns
*mesh-sized* partial results on the block's own elements or nodes; partials on shared
face nodes add up in the engine.

Method: paper section 3, modified Gauss–Newton (section 3.1): ``M`` is built once from
``grad f``; each iteration needs ``b_(a,i) = sum_X N_a(X) d_i f(X) r(X)`` with the residual
``r = f(X) - (λ g(X + u(X)) + μ)``, where the brightness correction ``(λ, μ)`` is chosen by
:mod:`chunkdic.method.brightness` (``λ = 1, μ = 0`` is the paper). The kernels therefore return,
per element, the sums from which ``b`` and ``Σ r²`` follow for any ``(λ, μ)``
(:class:`chunkdic.kernels.blocks.ElementSums`): with ``d = f - g(X+u)`` and ``g' = g(X+u) - c`` (``c`` a centring
constant), ``r = d - α g' - μ'`` with ``α = λ - 1``, so

    b_e = Bd_e - α Bg_e - μ' B1_e,   Bq_e[a, i] = Σ_{X in e} N_a d_i f q,  q = d, g', 1

and ``Σ r²`` is a quadratic in ``(α, μ')`` of the moments ``n, Σd, Σg', Σd², Σdg', Σg'²``.
Writing ``r`` around ``d`` keeps the sums free of cancellation when ``λ ≈ 1, μ ≈ 0``.

Implementations (``impl=``): ``"numba"``, serial ``nogil`` kernels that sweep the block
once in raster order with no volume-sized temporaries (Dask provides the parallelism),
float32 images and float64 accumulators; ``"numpy"``, the plain NumPy/SciPy twins of
:mod:`chunkdic.kernels.twins`, written for obviousness: the oracle of the tests.

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
:func:`chunkdic.kernels.rows.segment_samples`, shared by both, tests the segment's end points once and takes
a check-free flat-index path (the vector cubic gather of :mod:`chunkdic.kernels.interp`) when every
tap lies inside the window and the volume (nearly always), the general per-voxel path
(validity test, clamping, mirror) otherwise. Arithmetic is float64 on float32 data.

Notes for callers (the engine)
------------------------------
- ``f`` halo: ``lo[i]``/``hi[i]`` is 1 where a halo voxel was read, 0 where the core touches
  the volume boundary; gradients then equal ``np.gradient`` of the whole volume (float32).
- ``g`` window: read ``g[kernels_window.g_window(...)]`` and pass its start as ``g_origin``; the kernels
  refuse (ValueError) a window that misses samples a valid voxel needs. For cubic, pass a
  window of float32 B-spline coefficients with ``prefiltered=True`` (what the engine does,
  :mod:`chunkdic.passes.prefilter`), or raw samples read with ``halo=chunkdic.bspline-halo`` (12)
  and let the kernels prefilter it (``scipy.ndimage.spline_filter``, mirror).
- Validity: a voxel counts when ``0 <= X_i + u_i <= g_shape_i - 1`` on every axis (a NaN
  displacement makes it invalid); invalid voxels are left out of every ``b`` sum and
  counted. ``M`` keeps every core voxel.
- :func:`warmup` compiles every kernel once per process.
"""

from __future__ import annotations

import os

import numpy as np

from ..io.coarsen import coarsen_block, pyramid_dtype
from .b import b_kernel, b_sums, element_to_nodes
from .lowpass import lowpass_bspline
from .quantize import quantize_u16
from .m import m_block, m_kernel
from .pwrite import write_rows
from .warp import warp_block
from .window import INTERPOLATIONS

__all__ = ["warmup", "compiled_on_disk"]


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
    lowpass_bspline(f, 1.0, True)
    for wide in (True, False):
        quantize_u16(f, 0.0, 1.0, wide=wide)
    if hasattr(os, "pwrite"):  # POSIX: the prefilter's writes, uint16 regions and float32 crops
        fd = os.open(os.devnull, os.O_WRONLY)
        try:
            write_rows(fd, np.zeros((1, 1, 2), np.uint16), 0, 4, 4)
            write_rows(fd, f[:2, :2, 1:], 0, 16, 64)
        finally:
            os.close(fd)
    for interp in INTERPOLATIONS:
        sums = b_sums(f, lo, hi, ell, u, (1, 1, 1), f, (0, 0, 0), f.shape, interpolation=interp)
        element_to_nodes(sums.B[..., 0, :, :])
        warp_block(ell, u, (1, 1, 1), (2, 2, 2), f, (0, 0, 0), f.shape, interpolation=interp)
    # A block of f read from a read-only map is a type of its own to numba (and the first
    # 300³ run after a cache clear compiled it in the middle of level 0: 4.7 s)
    frozen = f.copy()
    frozen.flags.writeable = False
    b_sums(frozen, lo, hi, ell, u, (1, 1, 1), f, (0, 0, 0), f.shape)
    # the pyramid's 2×2×2 sums, for the integer scans CT gives (one type per level pair)
    for base in ("uint8", "uint16", "int16"):
        for s in range(1, 5):
            coarsen_block(np.zeros((2, 2, 2), pyramid_dtype(base, s - 1)), pyramid_dtype(base, s))


def compiled_on_disk() -> bool:
    """Whether numba's on-disk cache already holds the block kernels (a later run loads them).

    A first run on a machine compiles them (tens of seconds); callers say so before the
    wait. Reads numba's cache locator, not a public API: any surprise there answers True
    (no notice), never an error.
    """
    import os

    try:
        return all(os.path.exists(d._cache._cache_file._index_path) for d in (b_kernel, m_kernel))
    except Exception:  # noqa: BLE001 - numba internals changed: assume cached
        return True




#: modules whose numba kernels a correlation runs: the block kernels, the pyramid's sums,
#: the client's solver (a run compiles those missing from numba's cache)
KERNEL_MODULES = ("chunkdic.kernels.b", "chunkdic.kernels.m", "chunkdic.kernels.interp", "chunkdic.kernels.rows",
                  "chunkdic.kernels.warp", "chunkdic.kernels.lowpass", "chunkdic.kernels.pwrite", "chunkdic.kernels.quantize",
                  "chunkdic.io.coarsen",
                  "chunkdic.solve.stencil", "chunkdic.solve.galerkin", "chunkdic.solve.multigrid",
                  "chunkdic.solve.penalty")


def kernels_cached() -> bool:
    """Whether numba's on-disk cache holds every kernel of :data:`KERNEL_MODULES`, so a run
    loads them rather than compiling (its base memory is then :data:`WARM_BASE_BYTES`).

    Probing only the ``b`` and ``M`` kernels (:func:`chunkdic.kernels.compiled_on_disk`) is
    not enough: on a fresh clone whose first test ran those, the next run still compiled
    the solver's and the low-pass's kernels, and peaked 21 % above a plan that assumed
    the warm base. Reads numba's cache locator (not a public API): any surprise answers
    False, the higher estimate.
    """
    import importlib

    try:
        from numba.core.dispatcher import Dispatcher

        for name in KERNEL_MODULES:
            module = importlib.import_module(name)
            for obj in vars(module).values():
                if (isinstance(obj, Dispatcher) and obj.py_func.__module__ == name
                        and obj.targetoptions.get("inline") != "always"):  # inlined helpers have no cache
                    if not os.path.exists(obj._cache._cache_file._index_path):
                        return False
    except Exception:  # noqa: BLE001 - numba internals changed: assume a compiling run
        return False
    return True
