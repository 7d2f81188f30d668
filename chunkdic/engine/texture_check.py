"""The reference's texture, read before a correlation's levels run.

One measurement (:func:`chunkdic.passes.texture.measure_texture`: :data:`CHECK_BOXES` boxes of
:data:`CHECK_EDGE` voxels inside the ROI of the correlated level, smaller ones that tile a
small ROI, at least 3 ℓ; each reduced by one task, the client never holds a voxel) answers
two questions:

- is ``ℓ`` below the smallest element size the texture supports (its weakly textured
  elements and its predicted noise, :func:`chunkdic.passes.texture.smallest_supported`), or
  does it support none (no texture above the noise, or a predicted noise above the limit at
  every size measured)? Then :func:`check_texture` warns in one line
  (:class:`ElementSizeWarning`); the correlation runs as asked, the regularisation filling
  in what the texture does not set (docs/engine.md, "Know your texture");
- how long are the texture's features? The autocorrelation length (the median over the
  axes) sets the regularisation length each level starts with
  (:func:`chunkdic.method.length.start_length`).
"""

from __future__ import annotations

import math

import numpy as np

from ..io.handles import ArrayRef
from ..mesh import Mesh
from ..method.events import Texture, emit
from ..method.length import START_LENGTH, start_length
from ..method.settings import Settings
from ..passes.texture import LADDER, TextureStats, measure_texture
from ..warn import warn_user

__all__ = ["ElementSizeWarning", "check_texture", "texture_length"]

#: boxes read before a correlation (edge in voxels of the level, or 3 ℓ when larger) and the
#: largest lag of their autocorrelation: 0.21 s warm on a 300³ ROI at ℓ = 8 and 0.14 s at ℓ = 12,
#: most of it the predicted noise's exact sub-mesh solve (a 2-core machine, load 1.4–1.9)
CHECK_EDGE = 48
CHECK_BOXES = 8
CHECK_LAG = 48


class ElementSizeWarning(UserWarning):
    """The element size is below the smallest the reference's texture supports, or it supports none."""


def _unsupported_words(ell: int, stats: TextureStats) -> str:
    """The one line of :class:`ElementSizeWarning`: ``ℓ`` below the smallest supported size, or
    no size supported (and why)."""
    if stats.smallest is None:
        lo, hi = min(stats.weak_fraction), max(stats.weak_fraction)
        sizes = f"{lo}–{hi}" if hi > lo else f"{lo}"
        where = (f": the reference's texture supports no element size of {sizes} voxels "
                 f"({stats.why_unsupported()}; image noise {stats.noise:.3g} grey levels, estimated)")
    else:
        sigma = stats.sigma_u.get(ell, (math.nan,))[0]
        where = (f" is below the smallest the reference's texture supports ({stats.smallest} voxels): "
                 f"{100 * stats.weak_fraction.get(ell, math.nan):.0f} % of its elements carry less texture than noise "
                 f"and its predicted noise without regularisation is {sigma:.2g} voxel "
                 f"(image noise {stats.noise:.3g} grey levels, estimated)")
    return (f"element size {ell} voxels{where}; the regularisation fills in what the texture does not set "
            f"(chunkdic texture REF tells more)")


def texture_length(stats: TextureStats) -> float:
    """One autocorrelation length from the three axes' (voxels): their median, an axis beyond
    the lags examined counted as the longest lag; NaN for a constant reference."""
    acl = np.array(stats.acl, dtype=float)
    acl[np.isinf(acl)] = CHECK_LAG
    acl = acl[np.isfinite(acl)]
    return float(np.median(acl)) if acl.size else math.nan


def check_texture(ref: ArrayRef, mesh: Mesh, settings: Settings, runner, progress=None) -> float:
    """The correlated level's texture (module docstring): warn when ``ℓ`` is below what it
    supports, report a coarse one (a :class:`~chunkdic.method.events.Texture` event) and return
    its autocorrelation length, voxels of the level.

    Parameters
    ----------
    ref : ArrayRef
        The reference on the correlated level.
    mesh : Mesh
        That level's mesh (its ROI is sampled).
    settings : Settings
    runner : object
        Where the box tasks run (``runner.map_unordered``).
    progress : callable, optional
    """
    ell = int(mesh.element_size)
    within = [(r.start, r.stop) for r in mesh.roi]
    # boxes of half the ROI's shortest side when smaller than CHECK_EDGE: eight that tile it
    edge = max(min(CHECK_EDGE, min(b - a for a, b in within) // 2), 3 * ell)
    # from ℓ up: whether ℓ is supported, and if not the smallest size that is
    ladder = sorted({*(e for e in LADDER if ell <= e and 2 * e <= edge), ell})
    stats = measure_texture(ref, runner.map_unordered, smoothing=settings.smoothing, edge=edge, boxes=CHECK_BOXES,
                            ladder=ladder, max_lag=CHECK_LAG, within=within)
    if stats.smallest is None or ell < stats.smallest:
        warn_user(_unsupported_words(ell, stats), ElementSizeWarning)
    length = texture_length(stats)
    event = Texture(level=settings.level, length=length, start_length=start_length(ell, length),
                    usual_length=START_LENGTH * ell, element_size=mesh.element_size, smallest=stats.smallest)
    if event.start_length != event.usual_length:
        emit(progress, event)
    return length
