"""Metrology: the a-priori uncertainty test and its power law (paper section 4.2).

A-priori uncertainty (section 4.2)
----------------------------------
The reference is translated by a sub-voxel shift (default ``(0.5, 0.5, 0.5)`` voxel) with a
Fourier phase shift, the pair is correlated blindly for each element size ``ell``, and the
nodal displacements are compared with the prescribed shift: bias = mean error, uncertainty
= standard deviation about the mean, per component; strain uncertainty ``delta eps`` = the
largest absolute principal value of the mean strain (outermost elements left out). The
uncertainty ``sigma_U`` (RMS over the three components of the standard deviations) is
fitted by ``sigma_U = A^(alpha+1) ell^(-alpha)`` (the paper found ``A = 2.4`` voxels,
``alpha = 1.07``).

The shifted scan comes from :mod:`chunkdic.synth.fourier_shift`; the ZOI-size sweep (section 5.2,
Table 1) that uses this test is in :mod:`chunkdic.analysis.zoisweep`.
"""

from __future__ import annotations

import csv
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..engine.driver import correlate
from ..engine.front import prepare_run
from ..engine.meshes import box_at_level, parse_roi
from ..method.settings import Settings
from ..errors import InputError
from ..inputs import number
from ..io.handles import ArrayRef
from ..io.outputs import Outputs
from ..io.scan import open_scan
from ..results.strain import strain_summary
from ..scheduler import check_scheduler
from ..synth.fourier_shift import fourier_shift_scan
from ..plot.report import plot_uncertainty
from .challenge import challenge_numbers

log = logging.getLogger(__name__)

__all__ = [
    "fit_power_law",
    "PowerLaw",
    "uncertainty",
    "UncertaintyReport",
    "write_table",
]


# --------------------------------------------------------------------------- power law


@dataclass(frozen=True)
class PowerLaw:
    """``sigma = A^(alpha+1) ell^(-alpha)`` (paper section 4.2); ``A`` in voxels."""

    A: float
    alpha: float

    def __call__(self, ell):
        return self.A ** (self.alpha + 1) * np.asarray(ell, float) ** (-self.alpha)


def fit_power_law(ell: Sequence[float], sigma: Sequence[float]) -> PowerLaw:
    """Least-squares fit of ``log sigma = (alpha + 1) log A - alpha log ell``.

    Parameters
    ----------
    ell : sequence of float
        Element sizes, voxels (at least two distinct).
    sigma : sequence of float
        Uncertainties, voxels (positive).

    Returns
    -------
    PowerLaw

    Examples
    --------
    >>> law = fit_power_law([6, 8, 12, 16], PowerLaw(2.4, 1.07)([6, 8, 12, 16]))
    >>> round(law.A, 6), round(law.alpha, 6)
    (2.4, 1.07)
    """
    x = np.log(np.asarray(ell, float))
    y = np.asarray(sigma, float)
    if x.shape != y.shape or x.size < 2 or np.unique(x).size < 2:
        raise InputError("the power-law fit needs at least two distinct element sizes")
    if not np.all(np.isfinite(y) & (y > 0)):
        raise InputError(f"the power-law fit needs positive uncertainties, got {y.tolist()}")
    slope, intercept = np.polyfit(x, np.log(y), 1)
    alpha = -slope
    if abs(alpha + 1) < 1e-12:
        raise InputError("fitted exponent alpha = -1: A is undefined")
    return PowerLaw(float(np.exp(intercept / (alpha + 1))), float(alpha))


# --------------------------------------------------------------------------- tables


def write_table(rows: list[dict], columns: list[tuple[str, str, str]], csv_path=None, md_path=None,
                *, title: str | None = None) -> str:
    """Write rows as CSV and/or Markdown; returns the Markdown text.

    ``columns`` lists ``(key, header, format)``; the CSV uses the keys as headers and full
    precision, the Markdown the headers and formats.
    """
    if csv_path is not None:
        with open(csv_path, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow([k for k, _, _ in columns])
            for r in rows:
                w.writerow(["" if r.get(k) is None else r.get(k) for k, _, _ in columns])
    lines = [] if title is None else [title, ""]
    lines.append("| " + " | ".join(h for _, h, _ in columns) + " |")
    lines.append("|" + "|".join("---:" for _ in columns) + "|")
    for r in rows:
        cells = []
        for k, _, fmt in columns:
            v = r.get(k)
            cells.append("n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt))
        lines.append("| " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    if md_path is not None:
        Path(md_path).write_text(text)
    return text


UNCERTAINTY_COLUMNS = [
    ("element_size", "ZOI size (vox.)", "d"),
    ("bias_z", "bias Uz (vox.)", "+.4f"), ("bias_y", "bias Uy (vox.)", "+.4f"), ("bias_x", "bias Ux (vox.)", "+.4f"),
    ("std_z", "σ(Uz) (vox.)", ".4f"), ("std_y", "σ(Uy) (vox.)", ".4f"), ("std_x", "σ(Ux) (vox.)", ".4f"),
    ("sigma_u", "σ(U) (vox.)", ".4f"), ("bias", "|μ| (vox.)", ".4f"), ("u_rms", "u_rms (vox.)", ".4f"),
    ("delta_eps", "δε (–)", ".2e"),
    ("final_gap_percent", "gap (%)", ".3f"), ("nodes", "nodes", "d"), ("status", "status", "s"),
]




# --------------------------------------------------------------------------- uncertainty


@dataclass
class UncertaintyReport:
    """Outcome of :func:`uncertainty`.

    Attributes
    ----------
    rows : list of dict
        Per element size: ``element_size``, ``bias_z/y/x`` and ``std_z/y/x`` (voxels of the
        correlated level), ``sigma_u`` (RMS of the three std), ``delta_eps``,
        ``final_gap_percent``, ``nodes``, ``status``, ``result`` (path); the DVC Challenge 2.0
        ``noise_floor_z/y/x`` (= ``std``), ``u_rms_z/y/x`` and pooled ``bias``, ``noise_floor``,
        ``u_rms`` (:mod:`chunkdic.analysis.challenge`).
    fit : PowerLaw or None
        Fit of ``sigma_u`` against the element size (None with fewer than two sizes).
    shift : tuple of 3 float
        Prescribed shift, voxels.
    files : dict
        Paths of the written ``csv``, ``markdown``, ``plot`` and ``shifted`` volume.
    """

    rows: list[dict]
    fit: PowerLaw | None
    shift: tuple[float, float, float]
    files: dict = field(default_factory=dict)

    def markdown(self) -> str:
        text = write_table(self.rows, UNCERTAINTY_COLUMNS)
        t = ", ".join(f"{v:g}" for v in self.shift)
        text = f"A-priori uncertainty, Fourier shift ({t}) voxel (paper section 4.2)\n\n" + text
        if self.fit is not None:
            text += (f"\nPower-law fit σ(U) = A^(α+1) ℓ^(−α): A = {self.fit.A:.3g} voxel, "
                     f"α = {self.fit.alpha:.3g}\n")
        return text


def _ref_path(ref: ArrayRef) -> str:
    """A path that :func:`chunkdic.open_scan` opens as this array (its level 0)."""
    return str(Path(ref.path) / ref.key) if ref.kind == "zarr" and ref.key else ref.path


def _roi_at_level(roi, level: int):

    box = parse_roi(roi)
    return box if box is None else box_at_level(box, 2**level)


def _displacement_stats(result, t) -> dict:
    u = result.displacement.reshape(3, -1)
    err = u - np.asarray(t, float)[:, None]
    bias, std = err.mean(axis=1), u.std(axis=1)
    s = strain_summary(result, measure="small")  # the paper's small strain (rigid translations: the same)
    # the DVC Challenge 2.0 numbers: std is its noise floor (about the mean: the translation removed)
    challenge = {k: v for k, v in challenge_numbers(err).items() if k != "points"}
    return {**challenge,
        "element_size": int(result.info["element_size"]),
        "bias_z": float(bias[0]), "bias_y": float(bias[1]), "bias_x": float(bias[2]),
        "std_z": float(std[0]), "std_y": float(std[1]), "std_x": float(std[2]),
        "sigma_u": float(np.sqrt((std**2).mean())),
        "delta_eps": s.delta_eps,
        "final_gap_percent": 100 * float(result.info["final_gap"]),
        "nodes": int(u.shape[1]),
        "status": str(result.info.get("status")),
        "result": result.path,
    }


def check_element_sizes(element_sizes) -> list[int]:
    """Element sizes as distinct ints >= 2 (at least one); InputError otherwise."""
    sizes = [number(v, "element size", minimum=2, integer=True) for v in element_sizes]
    if not sizes:
        raise InputError("give at least one element size")
    if len(set(sizes)) != len(sizes):
        raise InputError(f"element sizes must be distinct, got {list(element_sizes)}")
    return sizes


def check_shift(shift) -> tuple[float, float, float]:
    """A shift as 3 finite floats (a scalar for all three axes), voxels; InputError otherwise."""
    try:
        t = tuple(float(v) for v in np.broadcast_to(np.asarray(shift, float), (3,)))
    except (TypeError, ValueError):
        raise InputError(f"shift must be a number or three numbers, got {shift!r}") from None
    if not all(math.isfinite(v) for v in t):
        raise InputError(f"shift must be finite, got {shift!r}")
    return t


def study_settings(settings: Settings | None, options: dict, defaults: dict) -> dict:
    """The keyword settings of every correlation of a study, but its element size: the
    fields of a template ``settings`` (as :func:`chunkdic.correlate` takes them), else the
    study's ``defaults``, then the keyword ``options`` (:class:`Settings` fields)."""
    base = defaults if settings is None else {k: v for k, v in settings.to_json().items() if k != "element_size"}
    return {**base, **options}


def check_plan(ref, deformed, sizes, given: dict, *, roi=None, roi_unit: str | None = None, caller: str):
    """Every element size must make a run of ``ref`` and ``deformed`` with the settings
    ``given`` (:func:`chunkdic.engine.front.prepare_run`: options, units, ROI and meshes;
    checked before any output); the ROI in level-0 voxels."""
    spec = None
    for ell in sizes:
        spec = prepare_run(ref, deformed, None, roi=roi, roi_unit=roi_unit, caller=caller,
                           **{**given, "element_size": ell})
    return spec.roi


#: the paper's analyses characterise the C8 basis itself: no regularisation unless asked for
PAPER_SETTINGS = {"regularization": "none"}


def uncertainty(scan, element_sizes: Sequence[int], out_dir, settings: Settings | None = None, *, shift=0.5,
                roi=None, roi_unit: str | None = None, scheduler=None, overwrite: bool = False,
                progress: Callable[[dict], None] | None = None, **options) -> UncertaintyReport:
    """A-priori displacement and strain uncertainty versus element size (paper section 4.2).

    Parameters
    ----------
    scan : path or array
        The reference scan (anything :func:`chunkdic.open_scan` takes).
    element_sizes : sequence of int
        Element edges ``ell``, voxels of ``level``.
    out_dir : path
        Directory for the shifted volume (``shifted.zarr``), one result per element size
        (``result-ell{ell}.zarr``), ``uncertainty.csv``, ``uncertainty.md`` and
        ``uncertainty.png``.
    shift : float or tuple of 3 float, keyword-only
        Prescribed translation ``(tz, ty, tx)``, voxels of ``level`` (paper: 0.5 each).
    settings : Settings, optional
        Every correlation's settings, as :func:`chunkdic.correlate` takes them; its
        ``element_size`` is replaced by each of ``element_sizes``.
    roi, roi_unit, scheduler
        As in :func:`chunkdic.correlate`.
    overwrite : bool
        Reuse a non-empty ``out_dir`` (its files are replaced).
    progress : callable(dict), optional
        Correlation events (see :func:`chunkdic.correlate`) plus ``{"stage": "shift",
        "fraction": f}`` and ``{"stage": "uncertainty", "element_size": ell, ...row}``.
    **options
        :class:`chunkdic.Settings` fields for every correlation, as :func:`chunkdic.correlate`
        takes them (over ``settings``'s). ``level``: the pyramid level correlated (the level
        is shifted, then correlated as level 0 of the pair; displacements are in its voxels).
        The analysis characterises the C8 basis (the paper's power law of ``σ`` against
        ``ℓ``), so without ``settings`` it runs without regularisation
        (:data:`PAPER_SETTINGS`) unless ``options`` asks for one: a regularised field's
        noise depends on ``ℓ_reg`` more than on ``ℓ``.

    Returns
    -------
    UncertaintyReport

    References
    ----------
    Roux, Hild, Viot, Bernard, section 4.2 (Fig. 5, ``A = 2.4`` voxels, ``alpha = 1.07``)
    and 5.2 (strain uncertainty, last column of Table 1).
    """

    sizes = check_element_sizes(element_sizes)
    given = study_settings(settings, options, PAPER_SETTINGS)
    t = check_shift(shift)
    src_scan = open_scan(scan)
    roi = check_plan(src_scan, src_scan, sizes, given, roi=roi, roi_unit=roi_unit, caller="uncertainty")
    check_scheduler(scheduler)
    plan = Outputs(inputs=[scan], overwrite=overwrite)
    out = plan.add(out_dir, "uncertainty").final
    with plan:  # a failure removes what this run wrote, never older files
        return _uncertainty(src_scan, sizes, out, t, roi, scheduler, progress, given)


def _uncertainty(src_scan, sizes, out: Path, t, roi, scheduler, progress, given: dict) -> UncertaintyReport:
    """:func:`uncertainty` once every input is checked and ``out`` is prepared; ``given``: the
    correlations' settings (:func:`study_settings`), ``roi`` in level-0 voxels."""
    given = dict(given)
    level = int(given.pop("level", 0))

    emit = progress or (lambda event: None)
    # a stored level is used in place; a missing one is written once into out_dir
    src = src_scan.refs([level], out)[level]
    t0 = time.perf_counter()
    shifted = fourier_shift_scan(src, out / "shifted.zarr", t, scheduler=scheduler, overwrite=True,
                                 progress=lambda f: emit({"stage": "shift", "fraction": f,
                                                          "seconds": time.perf_counter() - t0}))
    roi_l = _roi_at_level(roi, level)
    roi_arg = None if roi_l is None else ",".join(f"{a}:{b}" for a, b in roi_l)
    rows = []
    for ell in sizes:
        emit({"stage": "element-size", "element_size": ell})
        res = correlate(_ref_path(src), _ref_path(shifted), element_size=ell, roi=roi_arg, **given,
                        scheduler=scheduler, output=out / f"result-ell{ell}.zarr", overwrite=True,
                        progress=progress)
        row = _displacement_stats(res, t)
        log.info("a-priori test, ell %d: %s", ell, row)
        rows.append(row)
        emit({"stage": "uncertainty", **row})
    positive = [r for r in rows if r["sigma_u"] > 0]
    fit = fit_power_law([r["element_size"] for r in positive], [r["sigma_u"] for r in positive]) \
        if len({r["element_size"] for r in positive}) >= 2 else None
    report = UncertaintyReport(rows, fit, t)
    files = {"csv": str(out / "uncertainty.csv"), "markdown": str(out / "uncertainty.md"),
             "plot": str(out / "uncertainty.png"), "shifted": str(out / "shifted.zarr")}
    write_table(rows, UNCERTAINTY_COLUMNS + [("result", "result", "s")], files["csv"])
    Path(files["markdown"]).write_text(report.markdown())
    plot_uncertainty(report, files["plot"])
    report.files = files
    return report
