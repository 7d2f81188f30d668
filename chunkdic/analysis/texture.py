"""Know your texture before you correlate: the report of ``chunkdic texture REF``.

For a reference scan, from sampled boxes read by tasks (:mod:`chunkdic.passes.texture`,
which measures; this module checks the inputs, runs it and words the report): the
autocorrelation length per axis, for each element size the fraction of weakly textured
elements and the noise the engine's model predicts at the nodes without regularisation,
and the smallest element size the texture supports for the noise (docs/engine.md, "Know
your texture"). ``correlate`` makes the same check of its own element size before it runs
(:func:`chunkdic.engine.texture_check.check_texture`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from ..passes.texture import MAX_LAG, SIGMA_LIMIT, WEAK_LIMIT, WEAK_SNR, TextureStats, measure_texture
from ..errors import InputError
from ..inputs import number
from ..io.owntree import remove
from ..io.scratch import make_scratch
from ..io.scan import open_scan
from ..scheduler import check_scheduler, open_runner

__all__ = ["TextureReport", "texture"]

#: element sizes of the report unless told (voxels)
DEFAULT_SIZES = (8, 12, 16)


@dataclass
class TextureReport:
    """The texture of a reference scan (:func:`texture`).

    Attributes
    ----------
    element_sizes : tuple of int
        The sizes asked for, voxels of ``level``.
    stats : TextureStats
        What was measured (:class:`chunkdic.passes.texture.TextureStats`).
    level : int
        The pyramid level measured.
    smoothing : float
        The engine's low-pass assumed, voxels.
    """

    element_sizes: tuple[int, ...]
    stats: TextureStats
    level: int = 0
    smoothing: float = 1.0

    @property
    def acl(self) -> tuple[float, float, float]:
        """Autocorrelation length per axis (z, y, x), voxels."""
        return self.stats.acl

    @property
    def smallest(self) -> int | None:
        """The smallest element size the texture supports (voxels), None if none of the sizes measured
        (``stats.why_unsupported()`` says why)."""
        return self.stats.smallest

    def lines(self) -> list[str]:
        """The report as text lines."""
        s = self.stats
        acl = ", ".join(f"≥ {MAX_LAG}" if math.isinf(a) else f"{a:.1f}" for a in s.acl)
        noise = f"{s.noise:.4g} grey levels per scan ({'estimated from the reference' if s.noise_estimated else 'given'})"
        out = [f"autocorrelation length (z, y, x): {acl} voxels",
               f"noise: {noise}; low-pass {self.smoothing:g} voxel; {s.boxes} box{'es' if s.boxes > 1 else ''} of ≤ {s.box_edge}³ voxels sampled",
               "element size | weakly textured elements | predicted σ_u median / 90 % (voxels, unregularised) | κ"]
        for ell in self.element_sizes:
            weak = s.weak_fraction.get(ell)
            med, q90 = s.sigma_u.get(ell, (math.nan, math.nan))
            out.append(f"{ell:>12} | {'-' if weak is None else f'{100 * weak:.1f} %':>24} | "
                       f"{med:.4f} / {q90:.4f} | {s.kappa.get(ell, math.nan):.1f}")
        head = "smallest element size the texture supports:"
        if s.smallest is None:
            out.append(f"{head} none of {', '.join(map(str, sorted(s.weak_fraction)))} voxels ({s.why_unsupported()})")
        else:
            out.append(f"{head} {s.smallest} voxels (at most {100 * WEAK_LIMIT:.0f} % more weakly textured elements, "
                       f"texture's gradient energy below {WEAK_SNR:g}× the noise's, than at the largest size, and a "
                       f"predicted σ_u median of at most {SIGMA_LIMIT:g} voxel)")
        return out

    def to_json(self) -> dict:
        """JSON-ready dict of the report."""
        d = asdict(self.stats)
        d["acl"] = [None if math.isinf(a) else a for a in d["acl"]]
        for key in ("weak_fraction", "sigma_u", "kappa"):
            d[key] = {str(k): v for k, v in d[key].items()}
        return {"element_sizes": list(self.element_sizes), "level": self.level, "smoothing": self.smoothing, **d,
                "why_unsupported": self.stats.why_unsupported() or None}


def texture(ref, element_sizes=DEFAULT_SIZES, *, noise: float | None = None, smoothing: float = 1.0,
            level: int = 0, scheduler=None, edge: int = 128) -> TextureReport:
    """What the texture of a reference scan supports (module docstring).

    Parameters
    ----------
    ref : str, Path, ndarray, dask array or zarr array/group
        The reference scan (any input :func:`chunkdic.open_scan` reads).
    element_sizes : sequence of int
        Element sizes to report on, voxels of ``level`` (none: the autocorrelation length and
        the weakly textured elements of :data:`~chunkdic.passes.texture.LADDER` only).
    noise : float, optional
        Std of the image noise of each scan, grey levels of ``level``; default estimated from
        the reference (robust spread of its second differences).
    smoothing : float
        The engine's Gaussian low-pass, voxels (``correlate``'s ``smoothing``; default 1).
    level : int
        Pyramid level to measure (the level the correlation runs on).
    scheduler : optional
        Where the tasks run (:func:`chunkdic.scheduler.open_runner`).
    edge : int
        Edge of the sampled boxes, voxels (at most :data:`~chunkdic.passes.texture.BOXES`).

    Returns
    -------
    TextureReport

    Examples
    --------
    >>> import numpy as np
    >>> from scipy.ndimage import gaussian_filter
    >>> f = gaussian_filter(np.random.default_rng(0).standard_normal((64, 64, 64)), 3.0)
    >>> report = texture(f, [8], noise=0.001)
    >>> 4.5 < report.acl[2] < 7.5  # a Gaussian filter of σ = 3: 1/e at 2σ = 6 voxels
    True
    """
    sizes = tuple(int(number(e, "--element-sizes", minimum=2, integer=True)) for e in element_sizes)
    if noise is not None:
        noise = float(number(noise, "--noise", above=0))
    smoothing = float(number(smoothing, "--smoothing", minimum=0))
    edge = int(number(edge, "--box", minimum=16, integer=True))
    scan = open_scan(ref)
    level = int(number(level, "--level", minimum=0, integer=True))
    if min(scan.shape(level)) < 2 * max((3, *sizes)):
        raise InputError(f"the reference at level {level} ({scan.shape(level)}) is too small for elements of "
                         f"{max(sizes, default=3)} voxels (two per axis at least)")
    check_scheduler(scheduler)
    scratch = make_scratch("chunkdic-texture-")
    try:
        with open_runner(scheduler) as runner:
            f = scan.refs([level], scratch, runner=runner)[level]
            stats = measure_texture(f, runner.map_unordered, element_sizes=sizes, noise=noise, smoothing=smoothing,
                                    edge=edge)
    finally:
        remove(scratch)
    return TextureReport(sizes, stats, level, smoothing)
