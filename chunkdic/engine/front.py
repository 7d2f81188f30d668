"""The one front door of a correlation: arguments as the user gives them, the run as the engine takes it.

:func:`prepare_run` is shared by :func:`chunkdic.correlate`, :func:`chunkdic.plan`,
:func:`chunkdic.series` and the studies (:func:`chunkdic.uncertainty`, :func:`chunkdic.sweep`,
:func:`chunkdic.resolution`), so that each takes the same arguments and refuses the same
things with the same words: the keyword options (:class:`~chunkdic.method.settings.Settings`
fields) checked and folded into the settings; lengths given in a physical unit
(``element_size="80um"``, a ROI in ``roi_unit``) converted with the reference's voxel size
(:func:`chunkdic.io.units.lengths_in_voxels`); the scans opened; an earlier result to start
from checked against the reference; the coarsest level (with a start field, the correlated
one: no coarse level is needed to find large displacements); the ROI and the C8 mesh of
every level, kept away from the faces of ``g`` by the low-pass's margin
(:func:`chunkdic.passes.prefilter.face_margin`); a mask opened and checked. Nothing is
written.
"""

from __future__ import annotations

import dataclasses
import logging

from ..errors import InputError
from ..io.formats.anyscan import open_any
from ..io.scan import Scan, open_scan
from ..io.units import lengths_in_voxels
from ..mesh import Mesh
from ..method.settings import Settings
from ..passes.masks import check_mask_shape
from ..passes.prefilter import face_margin
from ..results.result import Result
from .initial import open_init
from .meshes import plan_meshes

log = logging.getLogger(__name__)

__all__ = ["RunSpec", "prepare_run", "settings_from"]


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """A correlation's inputs, checked: what it correlates, how, and on which meshes.

    Attributes
    ----------
    settings : Settings
        Lengths in voxels.
    f_scan, g_scan : Scan
        Reference and deformed scans.
    roi : str, sequence or None
        The ROI asked for, in level-0 voxels (None: the default box).
    meshes : dict of int to Mesh
        The C8 mesh of every level solved (voxels of that level).
    levels : list of int
        Those levels, coarsest first; the last is the correlated one.
    mask_scan : Scan, optional
        The specimen mask (any format :func:`chunkdic.io.formats.anyscan.open_any` reads).
    init : Result, optional
        An earlier result to start from (:func:`chunkdic.engine.initial.open_init`).
    """

    settings: Settings
    f_scan: Scan
    g_scan: Scan
    roi: object
    meshes: dict[int, Mesh]
    levels: list[int]
    mask_scan: Scan | None = None
    init: Result | None = None

    @property
    def finest(self) -> int:
        return self.levels[-1]


def prepare_run(ref, deformed, settings: Settings | None = None, *, roi=None, roi_unit: str | None = None,
                init=None, mask=None, caller: str = "correlate", **options) -> RunSpec:
    """The :class:`RunSpec` of a correlation of ``ref`` and ``deformed`` (module docstring).

    Parameters
    ----------
    ref, deformed, settings, roi, roi_unit, init, mask, **options
        As for :func:`chunkdic.correlate`.
    caller : str
        The public function's name, for the refusal of an unknown keyword.

    Raises
    ------
    TypeError
        An unknown keyword, or no ``element_size`` and no ``settings``.
    InputError
        Anything else that cannot be correlated (one line).
    """
    options, roi = voxel_lengths(settings, options, roi, roi_unit, ref)
    settings = settings_from(settings, options, caller)
    f_scan, g_scan = open_scan(ref), open_scan(deformed)
    for role, scan in (("reference", f_scan), ("deformed scan", g_scan)):
        if scan.dtype(0) == bool:  # a mask is bool; a scan to correlate must have grey levels
            raise InputError(f"the {role} is a two-level (bool) image: it has no sub-voxel information; correlate "
                             "the grey-level scan it was segmented from")
    earlier = None if init is None else open_init(init, f_scan.shape(0))
    # with a start field, no coarse level is needed to find the large displacements (chunkdic.engine.initial)
    coarsest = settings.level if init is not None and settings.coarsest is None else settings.coarsest
    meshes = plan_meshes(f_scan.shape(0), element_size=settings.element_size, roi=roi, level=settings.level,
                         coarsest=coarsest, min_margin=face_margin(settings.smoothing))
    levels = sorted(meshes, reverse=True)
    for s in levels:
        if min(g_scan.shape(s)) < 2:
            raise InputError(f"the deformed scan is too small at level {s} ({g_scan.shape(s)})")
    mask_scan = None if mask is None else open_any(mask)  # also a TIFF or HDF5 mask, read in place
    if mask_scan is not None:
        check_mask_shape(mask_scan, f_scan.shape(0))
    return RunSpec(settings, f_scan, g_scan, roi, meshes, levels, mask_scan, earlier)


def settings_from(settings: Settings | None, options: dict, caller: str = "correlate") -> Settings:
    """``settings`` (default ``Settings()``) with the keyword ``options`` of a call applied, checked."""
    unknown = set(options) - set(Settings.names())
    if unknown:
        raise TypeError(f"{caller}() got unexpected keyword arguments {sorted(unknown)}")
    if settings is None:
        if "element_size" not in options:
            raise TypeError(f"{caller}() needs element_size (or settings=Settings(...))")
        return Settings(**options)
    return dataclasses.replace(settings, **options)


def voxel_lengths(settings: Settings | None, options: dict, roi, roi_unit, ref) -> tuple[dict, object]:
    """``element_size`` and ``roi`` in voxels (physical lengths converted with the reference's
    voxel size, as the CLI converts them; each conversion logged)."""
    level = options.get("level", settings.level if settings is not None else 0)
    ell, roi, notes = lengths_in_voxels(options.get("element_size"), roi, roi_unit=roi_unit, reference=ref,
                                        level=level)
    for note in notes:
        log.info("%s", note)
    return ({**options, "element_size": ell} if "element_size" in options else options), roi
