"""Algorithm settings of one correlation: one frozen, validated, JSON-able record.

A :class:`Settings` is what :func:`chunkdic.correlate` runs with, what a result stores
(``info["settings"]``) and part of the resume fingerprint. Every field is checked when the
record is made, so a bad option is refused (:class:`InputError`, one line, exit 2 on the
command line) before anything is read or written.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields

from ..errors import InputError
from ..solve.regchoice import DEFAULT_RULE, RULES

INTERPOLATIONS = ("cubic", "linear")
GREY_MODELS = ("none", "global", "drift", "element")
REGULARIZATIONS = ("none", "tikhonov", "equilibrium-gap")
#: robust reweightings of the Tikhonov penalty by default (docs/engine.md, "Robust reweighting")
DEFAULT_REWEIGHTS = 1
#: edge (voxels of each level) of the brightness cells by default: affine offsets per cell of
#: ~32 voxels (docs/engine.md, "Brightness": less noise and MEI at ℓ = 8, no cost at 300³)
DEFAULT_GREY_CELL_VOXELS = 32.0


def _option(default, help: str, *, flag: str | None = None, choices: tuple | None = None, kind=None,
            metavar: str | None = None):
    """A settings field with its command-line option declared beside it (the CLI builds its
    options from these, :func:`chunkdic.cli.common.add_engine_options`): ``flag`` (default
    ``--`` + the name with dashes), ``help``, ``choices``, the value type ``kind`` (default:
    that of ``default``) and ``metavar``."""
    return field(default=default, metadata={"flag": flag, "help": help, "choices": choices,
                                            "type": kind or type(default), "metavar": metavar})


@dataclass(frozen=True)
class Settings:
    """Algorithm settings of one correlation (stored with the result).

    Parameters
    ----------
    element_size : int
        Element edge ``ell``, voxels of ``level`` (>= 2).
    level : int
        Pyramid level correlated last (0 = full resolution, 2 = the paper's 4³ compression).
    coarsest : int or None
        Coarsest pyramid level; ``None`` picks it automatically
        (:func:`chunkdic.engine.meshes.plan_meshes`).
    interpolation : {"cubic", "linear"}
        Interpolation of the deformed image (cubic B-spline, or the paper's trilinear).
    smoothing : float
        Standard deviation (voxels of each level, >= 0) of the Gaussian low-pass applied to
        both scans before correlating; 0 turns it off (the paper). docs/engine.md, "Image
        preparation".
    grey : {"none", "global", "drift", "element"}
        Brightness model between the scans (:mod:`chunkdic.method.brightness`); ``none`` is the
        paper's plain residual.
    grey_cell : float
        Edge (voxels of each level, >= 0) of the cells sharing one affine offset in the
        ``drift`` model, rounded to whole elements (:func:`chunkdic.method.brightness.offset_cell`;
        default :data:`DEFAULT_GREY_CELL_VOXELS`); 0 or at most ``ℓ``: one offset per element and one
        drift across the ROI. docs/engine.md, "Brightness".
    regularization : {"none", "tikhonov", "equilibrium-gap"}
        Penalty on the short wavelengths of the field (:mod:`chunkdic.solve.regularizer`).
    regularization_rule : {"discrepancy-texture", "discrepancy", "upre", "discrepancy-half", "discrepancy-kinks", "gcv", "l-curve"}
        How the automatic length is chosen (:func:`chunkdic.solve.regchoice.choose_length`;
        docs/engine.md compares them).
    regularization_length : float or None
        Its length ``ℓ_reg``, voxels of level 0 (> 0): wavelengths shorter than it are
        damped, longer ones left to the images. ``None``: chosen automatically
        (docs/engine.md, "Regularisation").
    regularization_reweights : int or None
        Robust reweightings of the Tikhonov penalty after the automatic length choice
        (>= 0): each frees the curvature terms far beyond the field's robust spread (the
        kinks of a band or a slip) and chooses the length again (docs/engine.md, "Robust
        reweighting"). ``None``: :data:`DEFAULT_REWEIGHTS` with Tikhonov and the automatic
        length, else 0; more than 0 is refused with the equilibrium gap or a given length.
    tolerance : float
        Convergence when ``max |δa|`` falls below it (voxels of ``level``; finite, >= 0;
        0 iterates until ``max_iterations``).
    coarse_tolerance : float
        The same on coarser levels, whose field is only a starting point.
    max_iterations : int
        Iteration cap per level (>= 1).
    block_elements : int or None
        Elements per block side; ``None`` uses ``chunkdic.block-voxels`` (config). Rounded
        down to whole brightness cells, one cell at least
        (:func:`chunkdic.method.brightness.aligned_block_elements`).
    """

    element_size: int
    level: int = _option(0, "pyramid level correlated last (default 0; 2: the paper's 4³ compression)")
    coarsest: int | None = _option(None, "coarsest pyramid level (default: automatic)", kind=int)
    interpolation: str = _option("cubic", "interpolation of the deformed scan (default cubic B-spline; linear: "
                                 "the paper's)", choices=INTERPOLATIONS)
    smoothing: float = _option(1.0, "Gaussian low-pass of both scans, voxels of each level (default 1; 0: the "
                               "paper's raw images)")
    grey: str = _option("drift", "brightness model between the scans (default drift: a gain and an affine offset "
                        "per cell of --grey-level-cell voxels; none: the paper's plain residual)",
                        flag="--grey-level", choices=GREY_MODELS)
    grey_cell: float = _option(DEFAULT_GREY_CELL_VOXELS, "edge of the cells sharing one affine brightness offset in "
                               "the drift model, voxels of each level, rounded to whole elements (default 32; 0: "
                               "one offset per element and one drift across the ROI, about a tenth more noise at "
                               "ℓ = 8, docs/engine.md)", flag="--grey-level-cell", metavar="VOXELS")
    regularization: str = _option("tikhonov", "penalty on the field's short wavelengths (default tikhonov, on "
                                  "its curvature)", choices=REGULARIZATIONS)
    regularization_rule: str = _option(DEFAULT_RULE, "how the automatic length is chosen (default discrepancy-texture: "
                                       "Morozov's principle, a feature's share of the budget set by how evenly the "
                                       "texture covers the nodes; discrepancy: Morozov's principle; upre: least "
                                       "predicted error; discrepancy-kinks: longer after a reweighting frees a slip or "
                                       "a band, docs/engine.md)",
                                       choices=RULES)
    regularization_length: float | None = _option(None, "its length, voxels of level 0 (default: chosen from the "
                                                  "data and printed)", kind=float, metavar="L")
    regularization_reweights: int | None = _option(
        None, "robust reweightings of the Tikhonov penalty after the length choice (default 1 with tikhonov and "
        "the automatic length; 0: the plain penalty)", kind=int, metavar="N")
    tolerance: float = _option(1e-3, "max |da| for convergence, voxels")
    coarse_tolerance: float = 1e-2  # not a command-line option
    max_iterations: int = _option(30, "Gauss-Newton iterations per level at most")
    block_elements: int | None = _option(None, "elements per block side (default: automatic, blocks of about "
                                         "chunkdic.block-voxels voxels per side; rounded down to whole brightness "
                                         "cells, one cell at least)", kind=int)

    def __post_init__(self):
        check = object.__setattr__
        check(self, "element_size", _integer(self.element_size, "element size", minimum=2))
        check(self, "level", _integer(self.level, "level", minimum=0))
        if self.coarsest is not None:
            check(self, "coarsest", _integer(self.coarsest, "coarsest level", minimum=0))
        _choice(self.interpolation, INTERPOLATIONS, "interpolation")
        check(self, "smoothing", _nonnegative_float(self.smoothing, "smoothing"))
        _choice(self.grey, GREY_MODELS, "grey-level model")
        check(self, "grey_cell", _nonnegative_float(self.grey_cell, "grey-level cell"))
        _choice(self.regularization, REGULARIZATIONS, "regularization")
        _choice(self.regularization_rule, RULES, "regularization rule")
        if self.regularization_length is not None:
            check(self, "regularization_length", _positive_float(self.regularization_length, "regularization length"))
        if self.regularization_reweights is not None:
            n = _integer(self.regularization_reweights, "regularization reweights", minimum=0)
            check(self, "regularization_reweights", n)
            if n and self.regularization != "tikhonov":
                raise InputError("regularization reweights apply to the tikhonov penalty only, not "
                                 f"{self.regularization}")
            if n and self.regularization_length is not None:
                raise InputError("regularization reweights need the automatic length (the length is chosen again "
                                 "after each): leave out the regularization length")
        check(self, "tolerance", _nonnegative_float(self.tolerance, "tolerance"))
        check(self, "coarse_tolerance", _nonnegative_float(self.coarse_tolerance, "coarse tolerance"))
        check(self, "max_iterations", _integer(self.max_iterations, "max iterations", minimum=1))
        if self.block_elements is not None:
            check(self, "block_elements", _integer(self.block_elements, "block elements", minimum=1))

    @property
    def reweights(self) -> int:
        """The robust reweightings the run makes (``regularization_reweights`` resolved)."""
        if self.regularization_reweights is not None:
            return self.regularization_reweights
        automatic = self.regularization == "tikhonov" and self.regularization_length is None
        return DEFAULT_REWEIGHTS if automatic else 0

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))

    @classmethod
    def options(cls) -> list[tuple[str, dict]]:
        """``(name, metadata)`` of every field that is a command-line option (not ``element_size``,
        which is given with a unit, see :mod:`chunkdic.io.units`), metadata with its ``default``."""
        return [(f.name, dict(f.metadata, default=f.default)) for f in fields(cls) if f.metadata]

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> "Settings":
        """Settings stored by a result (keys this version does not know are ignored)."""
        return cls(**{k: v for k, v in d.items() if k in cls.names()})


def _integer(value, name: str, *, minimum: int) -> int:
    try:
        out = int(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{name} must be an integer, got {value!r}") from None
    if out != value or out < minimum:
        raise InputError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return out


def _positive_float(value, name: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not (math.isfinite(out) and out > 0):
        raise InputError(f"{name} must be a finite number > 0, got {value!r}")
    return out


def _nonnegative_float(value, name: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not (math.isfinite(out) and out >= 0):
        raise InputError(f"{name} must be a finite number >= 0, got {value!r}")
    return out


def _choice(value, choices, name: str) -> str:
    if value not in choices:
        raise InputError(f"{name} must be one of {', '.join(choices)}; got {value!r}")
    return value
