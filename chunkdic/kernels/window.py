"""What a kernel call reads of ``g``: the window, its preparation, and the argument checks.

One idea: the region of the deformed image that a block's ``b`` pass
(:mod:`chunkdic.kernels.b`) or warp (:mod:`chunkdic.kernels.warp`) needs
(:func:`g_window`), its conversion to what the interpolation reads (:func:`prepare_window`),
and the checks every kernel entry point makes of its arguments (:func:`kernel_setup`).
Conventions: :mod:`chunkdic.kernels.jit`, "Notes for callers".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .blocks import check_nodes, elements_of
from .lowpass import lowpass_bspline

__all__ = ["IMPLEMENTATIONS", "INTERPOLATIONS", "KernelSetup", "check_choice", "element_activity", "g_window",
           "kernel_setup", "prepare_window"]

IMPLEMENTATIONS = ("numba", "numpy")
INTERPOLATIONS = ("linear", "cubic")


def element_activity(active, elems) -> np.ndarray:
    """The element activity of a block as uint8 (ez, ey, ex); all 1 by default."""
    if active is None:
        return np.ones(elems, np.uint8)
    active = np.ascontiguousarray(active, dtype=np.uint8)
    if active.shape != tuple(elems):
        raise ValueError(f"active must have shape {tuple(elems)}, got {active.shape}")
    return active


def check_choice(value, allowed, name):
    """Raise ValueError unless ``value`` is one of ``allowed`` (``name`` for the message)."""
    if value not in allowed:
        raise ValueError(f"{name} must be one of {allowed}, got {value!r}")


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
    check_choice(interpolation, INTERPOLATIONS, "interpolation")
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
    The prefilter is that of ``scipy.ndimage.spline_filter(order=3, mode="mirror")``
    (:func:`chunkdic.kernels.lowpass.lowpass_bspline`, to float32 round-off): it equals a
    whole-volume prefilter where the window carries ``chunkdic.bspline-halo`` voxels or
    touches the volume boundary.
    """
    if interpolation == "cubic" and g.size:
        return lowpass_bspline(g, 0.0, True)
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
class KernelSetup:
    """A kernel call's checked arguments and prepared ``g`` window (:func:`kernel_setup`)."""

    elems: tuple
    u_nodes: np.ndarray
    core_origin: tuple
    g_origin: tuple
    g_shape: tuple
    gw: np.ndarray | None  # prepared window; None when no voxel can be valid


def kernel_setup(ell, u_nodes, core_origin, core, g, g_origin, g_shape, interpolation, impl, prefiltered,
           margin) -> KernelSetup:
    """Check a ``b`` / warp call's arguments and prepare its window (None if no voxel can be valid)."""
    check_choice(impl, IMPLEMENTATIONS, "impl")
    check_choice(interpolation, INTERPOLATIONS, "interpolation")
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
    return KernelSetup(elems, u_nodes, core_origin, g_origin, g_shape, gw)
