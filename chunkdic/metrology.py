"""Metrology: the a-priori uncertainty test and the ZOI-size sweep (paper sections 4.2, 5.2).

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

Out-of-core phase shift: exact, not windowed
--------------------------------------------
A phase shift multiplies the spectrum by ``exp(-2 pi i k . t)``, which is a product of one
factor per axis; so the shift of a whole volume equals three successive 1-D shifts, one per
axis. Each pass reads *pencils* (whole lines along the pass axis, a tile of the other two
axes), shifts every line with a 1-D FFT and writes the pencil back, tile by tile, into a
Zarr array in the output directory (each task owns whole chunks). Memory per task is one
pencil; the result equals a whole-volume FFT shift to float32 round-off (measured in
``tests/test_metrology.py``: max error ~1e-6 of the grey-level range on 48³), with no halo
to tune. This is preferred over block-wise FFTs with overlapping apodised halos, whose error
only decays with the halo width.

Each line is mirror-extended (half-sample symmetric, length ``2n``) before its FFT: the
periodic extension is then continuous, so a scan whose opposite faces differ does not ring
from its borders (the plain periodic shift would wrap the far face into the near one). The
Nyquist bin is multiplied by ``cos(pi t)`` (the real part of its phase factor), so that
every pass maps real lines to real lines; the whole-volume equivalent is the FFT shift of
the mirror-extended volume with that same real Nyquist factor.

ZOI sweep (section 5.2, Table 1)
--------------------------------
:func:`sweep` correlates a pair for several element sizes and tabulates ``<Ux>, <Uy>,
<Uz>`` (arithmetic mean of the nodal displacements), final gap, ``tr(eps)``, ``eps_zz``
(mean over the ROI without the outermost elements, and corrected by ``1 - 2 ell / L``,
section 5.4) and the a-priori ``delta eps`` of each element size.
"""

from __future__ import annotations

import csv
import logging
import math
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .inputs import check_finite, number
from .strain import mean_strain
from .handles import ArrayRef

log = logging.getLogger(__name__)

__all__ = [
    "fourier_shift_line",
    "fourier_shift_scan",
    "fit_power_law",
    "PowerLaw",
    "uncertainty",
    "UncertaintyReport",
    "sweep",
    "zoi_table",
    "write_zoi_table",
    "write_table",
]

#: edge of the (y, x) tile of a pencil and of the chunks of the shifted arrays
PENCIL_EDGE = 64


# --------------------------------------------------------------------------- phase shift


def _shift_factors(n: int, t: float) -> np.ndarray:
    """rfft multipliers of a length-``2n`` mirror-extended line shifted by ``t`` samples."""
    m = 2 * n
    k = np.arange(m // 2 + 1)
    phase = np.exp(-2j * np.pi * k * t / m)
    phase[-1] = np.cos(np.pi * t)  # Nyquist: real factor, real output
    return phase


def fourier_shift_line(a: np.ndarray, t: float, axis: int) -> np.ndarray:
    """Shift real lines along ``axis`` by ``t`` samples: ``out(x) = a(x - t)``.

    Parameters
    ----------
    a : ndarray, real
        Any shape; lines run along ``axis``.
    t : float
        Shift, samples (voxels).
    axis : int

    Returns
    -------
    ndarray, float32 (float64 input gives float64), same shape
        Each line mirror-extended to ``2n`` (half-sample symmetric), phase-shifted in
        Fourier space, and cropped back to ``n``.
    """
    import scipy.fft as sfft

    a = np.asarray(a)
    dtype = np.float64 if a.dtype == np.float64 else np.float32
    a = a.astype(dtype, copy=False)
    n = a.shape[axis]
    if t == 0 or n < 2:
        return a.copy()
    ext = np.concatenate([a, np.flip(a, axis=axis)], axis=axis)
    spec = sfft.rfft(ext, axis=axis, workers=1)
    shape = [1] * a.ndim
    shape[axis] = -1
    spec *= _shift_factors(n, t).astype(spec.dtype).reshape(shape)
    out = sfft.irfft(spec, n=2 * n, axis=axis, workers=1)
    return np.take(out, np.arange(n), axis=axis).astype(dtype, copy=False)


def shift_pencil_task(src: ArrayRef, out_path: str, out_key: str, axis: int, t: float, region,
                      check_input: bool = False) -> int:
    """Task: shift the pencil ``region`` (whole lines along ``axis``) and write it back.

    ``region`` covers whole chunks of the output (full extent along ``axis``, whole
    ``PENCIL_EDGE`` tiles or the array end on the other axes), so tasks never share a chunk.
    """
    import zarr

    data = src.read(region)
    if check_input:  # the first pass reads every voxel of the scan: NaN/inf cost nothing to find here
        check_finite(data, tuple(r.start for r in region), src.path if not src.key else f"{src.path}/{src.key}")
    shifted = fourier_shift_line(data, t, axis)
    arr = zarr.open_array(store=out_path, path=out_key or None, mode="r+")
    arr.with_config({"write_empty_chunks": True})[region] = shifted  # every chunk stored (integrity.py)
    return int(shifted.size)


def _pencils(shape, axis: int, edge: int):
    others = [a for a in range(3) if a != axis]
    tiles = [range(0, shape[a], edge) for a in others]
    for i in tiles[0]:
        for j in tiles[1]:
            region = [slice(0, shape[axis])] * 3
            region[others[0]] = slice(i, min(i + edge, shape[others[0]]))
            region[others[1]] = slice(j, min(j + edge, shape[others[1]]))
            yield tuple(region)


def fourier_shift_scan(src: ArrayRef, out, t, *, scheduler=None, overwrite: bool = False,
                       progress: Callable[[float], None] | None = None) -> ArrayRef:
    """Out-of-core sub-voxel translation ``g(x) = f(x - t)`` of a stored volume.

    Three passes of 1-D mirror-extended FFT shifts (z, then y, then x), each over pencils
    of whole lines, through float32 Zarr arrays (module docstring: exact equivalent of a
    whole-volume phase shift). Intermediate arrays live next to ``out`` and are removed.

    Parameters
    ----------
    src : ArrayRef
        The volume to shift, shape ``(nz, ny, nx)``, any real dtype.
    out : path
        Zarr v3 array to create (float32, chunks ``PENCIL_EDGE``³); ``chunkdic.complete``
        is set in its attributes last. It opens with :func:`chunkdic.open_scan`.
    t : float or tuple of 3 float
        Shift ``(tz, ty, tx)``, voxels; then ``f(X) = g(X + t)``.
    scheduler
        As in :func:`chunkdic.correlate`.
    overwrite : bool
    progress : callable(float), optional

    Returns
    -------
    ArrayRef
        Handle of the shifted volume.
    """
    import zarr

    from .scheduler import open_runner

    from .kinds import kind_of
    from .ownership import partial_name

    t = tuple(float(v) for v in np.broadcast_to(np.asarray(t, float), (3,)))
    out = Path(out)
    if out.exists() or out.is_symlink():
        if not overwrite:
            raise InputError(f"output {out} exists: choose another path or pass --overwrite")
        if kind_of(out)[0] != "shifted":
            raise InputError(f"output {out} is not a shifted volume chunkdic wrote: refusing to replace it")
        shutil.rmtree(out)
    shape = tuple(int(n) for n in src.shape)
    chunks = tuple(min(PENCIL_EDGE, n) for n in shape)
    tmp = partial_name(out)  # intermediate passes: a hidden sibling that names its owner
    stages = [(axis, ti) for axis, ti in enumerate(t) if ti != 0.0] or [(0, 0.0)]
    names = [(str(tmp), f"pass{i}") for i in range(len(stages) - 1)] + [(str(out), "")]
    try:
        if len(stages) > 1:
            zarr.open_group(str(tmp), mode="w", zarr_format=3)
        for path, key in names:
            zarr.create_array(store=path, name=key or None, shape=shape, chunks=chunks, dtype="float32",
                              compressors=None, zarr_format=3, overwrite=True,
                              attributes={"chunkdic": {"kind": "shifted", "complete": False}})
        total = sum(len(list(_pencils(shape, a, PENCIL_EDGE))) for a, _ in stages)
        done = 0
        current = src
        with open_runner(scheduler) as runner:
            for (axis, ti), (path, key) in zip(stages, names):
                args = [(current, path, key, axis, ti, r, current is src)
                        for r in _pencils(shape, axis, PENCIL_EDGE)]
                for _ in runner.map_unordered(shift_pencil_task, args):
                    done += 1
                    if progress is not None:
                        progress(done / total)
                current = ArrayRef("zarr", path, key, shape, "float32")
        arr = zarr.open_array(store=str(out), mode="r+")
        arr.update_attributes({"chunkdic": {"kind": "shifted", "complete": True, "fourier_shift": list(t),
                                            "method": "separable mirror-extended FFT phase shift"}})
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    from .handles import forget_open_arrays

    forget_open_arrays()
    return ArrayRef("zarr", str(out), "", shape, "float32")


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
    ("sigma_u", "σ(U) (vox.)", ".4f"), ("delta_eps", "δε (–)", ".2e"),
    ("final_gap_percent", "gap (%)", ".3f"), ("nodes", "nodes", "d"), ("status", "status", "s"),
]

SWEEP_COLUMNS = [
    ("element_size", "ZOI size (vox.)", "d"),
    ("mean_ux", "⟨Ux⟩ (vox.)", "+.3f"), ("mean_uy", "⟨Uy⟩ (vox.)", "+.3f"), ("mean_uz", "⟨Uz⟩ (vox.)", "+.3f"),
    ("final_gap_percent", "gap (%)", ".2f"),
    ("volume_change", "tr(ε) (–)", "+.4f"), ("eps_zz", "ε_zz (–)", "+.4f"),
    ("eps_zz_corrected", "ε_zz·(1−2ℓ/L) (–)", "+.4f"), ("delta_eps", "δε (–)", ".1e"),
    ("status", "status", "s"),
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
        ``final_gap_percent``, ``nodes``, ``status``, ``result`` (path).
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
    from .planning import box_at_level, parse_roi

    box = parse_roi(roi)
    return box if box is None else box_at_level(box, 2**level)


def _displacement_stats(result, t) -> dict:
    u = result.displacement.reshape(3, -1)
    err = u - np.asarray(t, float)[:, None]
    bias, std = err.mean(axis=1), u.std(axis=1)
    s = mean_strain(result.displacement, result.info["element_size"])
    return {
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


def _element_sizes(element_sizes) -> list[int]:
    sizes = [number(v, "element size", minimum=2, integer=True) for v in element_sizes]
    if not sizes:
        raise InputError("give at least one element size")
    if len(set(sizes)) != len(sizes):
        raise InputError(f"element sizes must be distinct, got {list(element_sizes)}")
    return sizes


def _shift3(shift) -> tuple[float, float, float]:
    try:
        t = tuple(float(v) for v in np.broadcast_to(np.asarray(shift, float), (3,)))
    except (TypeError, ValueError):
        raise InputError(f"shift must be a number or three numbers, got {shift!r}") from None
    if not all(math.isfinite(v) for v in t):
        raise InputError(f"shift must be finite, got {shift!r}")
    return t


def _check_plan(scan, sizes, roi, level: int, interpolation: str, options: dict | None = None) -> None:
    """Every element size must fit the scan's ROI at ``level`` (checked before any output)."""
    from .planning import plan_meshes
    from .prefilter import face_margin
    from .settings import Settings

    given = {k: v for k, v in {**PAPER_SETTINGS, **(options or {})}.items() if k in Settings.names()}
    for ell in sizes:
        settings = Settings(element_size=ell, level=level, interpolation=interpolation, **given)  # validates
        plan_meshes(scan.shape(0), element_size=ell, roi=roi, level=level,
                    min_margin=face_margin(settings.smoothing))


#: the paper's analyses characterise the C8 basis itself: no regularisation unless asked for
PAPER_SETTINGS = {"regularization": "none"}


def uncertainty(scan, element_sizes: Sequence[int], out_dir, *, shift=0.5, roi=None, level: int = 0,
                interpolation: str = "cubic", scheduler=None, overwrite: bool = False,
                progress: Callable[[dict], None] | None = None, options: dict | None = None) -> UncertaintyReport:
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
    roi : str, optional
        ``"z0:z1,y0:y1,x0:x1"`` in level-0 voxels (default: centred box).
    level : int
        Pyramid level correlated (the level is shifted, then correlated as level 0 of
        the pair; displacements are in its voxels).
    interpolation : {"cubic", "linear"}
    scheduler
        As in :func:`chunkdic.correlate`.
    overwrite : bool
        Reuse a non-empty ``out_dir`` (its files are replaced).
    progress : callable(dict), optional
        Correlation events (see :func:`chunkdic.correlate`) plus ``{"stage": "shift",
        "fraction": f}`` and ``{"stage": "uncertainty", "element_size": ell, ...row}``.
    options : dict, optional
        More :class:`chunkdic.Settings` fields for every correlation. The analysis
        characterises the C8 basis (the paper's power law of ``σ`` against ``ℓ``), so it runs
        without regularisation (:data:`PAPER_SETTINGS`) unless ``options`` asks for one: a
        regularised field's noise depends on ``ℓ_reg`` more than on ``ℓ``.

    Returns
    -------
    UncertaintyReport

    References
    ----------
    Roux, Hild, Viot, Bernard, section 4.2 (Fig. 5, ``A = 2.4`` voxels, ``alpha = 1.07``)
    and 5.2 (strain uncertainty, last column of Table 1).
    """
    from .volume import open_scan

    from .outputs import Outputs
    from .scheduler import check_scheduler

    sizes = _element_sizes(element_sizes)
    t = _shift3(shift)
    level = number(level, "level", minimum=0, integer=True)
    src_scan = open_scan(scan)
    _check_plan(src_scan, sizes, roi, level, interpolation, options)
    check_scheduler(scheduler)
    plan = Outputs(inputs=[scan], overwrite=overwrite)
    out = plan.add(out_dir, "uncertainty").final
    with plan:  # a failure removes what this run wrote, never older files
        return _uncertainty(src_scan, sizes, out, t, roi, level, interpolation, scheduler, progress, options)


def _uncertainty(src_scan, sizes, out: Path, t, roi, level: int, interpolation: str, scheduler,
                 progress, options) -> UncertaintyReport:
    """:func:`uncertainty` once every input is checked and ``out`` is prepared."""
    from .engine import correlate
    from .report import plot_uncertainty

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
        res = correlate(_ref_path(src), _ref_path(shifted), element_size=ell, roi=roi_arg, interpolation=interpolation,
                        **{**PAPER_SETTINGS, **(options or {})},
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


# --------------------------------------------------------------------------- sweep


def read_delta_eps(source) -> dict[int, float]:
    """``{ell: delta_eps}`` from an UncertaintyReport, an uncertainty CSV or its directory."""
    if source is None:
        return {}
    if isinstance(source, UncertaintyReport):
        return {r["element_size"]: r["delta_eps"] for r in source.rows}
    p = Path(source)
    if p.is_dir():
        p = p / "uncertainty.csv"
    if not p.is_file():
        raise InputError(f"no uncertainty table at {p} (run `chunkdic uncertainty` first)")
    out = {}
    try:
        with open(p, newline="") as fh:
            for line, r in enumerate(csv.DictReader(fh), start=2):
                try:
                    ell, d = int(r["element_size"]), float(r["delta_eps"])
                except (KeyError, TypeError, ValueError):
                    raise InputError(f"uncertainty table {p}, line {line}: expected numbers in the columns "
                                     "element_size and delta_eps (a table written by `chunkdic uncertainty`)") from None
                if ell < 1 or not math.isfinite(d):
                    raise InputError(f"uncertainty table {p}, line {line}: element_size {ell}, delta_eps {d}")
                out[ell] = d
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"uncertainty table {p} cannot be read: {exc}".splitlines()[0]) from None
    if not out:
        raise InputError(f"uncertainty table {p} has no rows")
    return out


def zoi_table(results, *, delta_eps: dict[int, float] | None = None) -> list[dict]:
    """Rows of the paper's Table 1 from results of several element sizes.

    Parameters
    ----------
    results : sequence of Result or path
    delta_eps : dict of int to float, optional
        A-priori strain uncertainty per element size (from :func:`uncertainty`).

    Returns
    -------
    list of dict
        Per result, sorted by decreasing element size: ``element_size``, ``mean_ux``,
        ``mean_uy``, ``mean_uz`` (arithmetic mean of the nodal values, voxels of the
        level), ``final_gap_percent``, ``volume_change`` and ``eps_zz`` (mean over the ROI
        without the outermost elements), ``volume_change_corrected`` and
        ``eps_zz_corrected`` (times ``1 - 2 ell / L``), ``delta_eps``, ``status``, ``result``.
    """
    from .result import Result, open_result

    rows = []
    for r in results:
        res = r if isinstance(r, Result) else open_result(r)
        ell = int(res.info["element_size"])
        s = mean_strain(res.displacement, ell)
        u = res.displacement
        rows.append({
            "element_size": ell,
            "mean_ux": float(u[2].mean()), "mean_uy": float(u[1].mean()), "mean_uz": float(u[0].mean()),
            "final_gap_percent": 100 * float(res.info["final_gap"]),
            "volume_change": s.volume_change, "eps_zz": s.eps_zz,
            "volume_change_corrected": s.volume_change_corrected, "eps_zz_corrected": s.eps_zz_corrected,
            "delta_eps": (delta_eps or {}).get(ell),
            "status": str(res.info.get("status")),
            "result": res.path,
        })
    return sorted(rows, key=lambda row: -row["element_size"])


def sweep(ref, deformed, element_sizes: Sequence[int], out_dir, *, roi=None, level: int = 0,
          interpolation: str = "cubic", uncertainty_from=None, a_priori: bool = True, shift=0.5,
          scheduler=None, overwrite: bool = False,
          progress: Callable[[dict], None] | None = None, options: dict | None = None) -> dict:
    """The ZOI-size sweep of paper Table 1: correlate for each element size, tabulate.

    Parameters
    ----------
    ref, deformed : path or array
        The scans.
    element_sizes : sequence of int
        Element edges, voxels of ``level`` (paper: 16 12 8 6).
    out_dir : path
        Receives ``result-ell{ell}.zarr`` per size, ``zoi_table.csv`` and ``zoi_table.md``
        (and ``uncertainty/`` when the a-priori test runs).
    roi, level, interpolation, scheduler
        As in :func:`chunkdic.correlate`.
    uncertainty_from : UncertaintyReport or path, optional
        Reuse the ``delta eps`` column of an earlier :func:`uncertainty` run (its CSV or
        directory) instead of running the a-priori test.
    a_priori : bool
        Without ``uncertainty_from``, run :func:`uncertainty` on ``ref`` (shift ``shift``)
        for the same sizes to fill ``delta eps``; ``False`` leaves the column empty.
    overwrite : bool
    progress : callable(dict), optional
    options : dict, optional
        More :class:`chunkdic.Settings` fields; as for :func:`uncertainty`, the paper's
        analysis runs without regularisation unless asked for (:data:`PAPER_SETTINGS`).

    Returns
    -------
    dict
        ``rows`` (see :func:`zoi_table`), ``markdown``, ``csv``/``md`` paths and
        ``uncertainty`` (the report, if run).
    """
    from .outputs import Outputs
    from .scheduler import check_scheduler
    from .volume import open_scan

    sizes = _element_sizes(element_sizes)
    level = number(level, "level", minimum=0, integer=True)
    _shift3(shift)
    f_scan = open_scan(ref)
    open_scan(deformed)
    _check_plan(f_scan, sizes, roi, level, interpolation, options)
    d_eps = None
    if uncertainty_from is not None:
        d_eps = read_delta_eps(uncertainty_from)  # read first: a bad table must not cost a sweep
    check_scheduler(scheduler)
    given = [] if uncertainty_from is None or isinstance(uncertainty_from, UncertaintyReport) else [uncertainty_from]
    plan = Outputs(inputs=[ref, deformed, *given], overwrite=overwrite)
    out = plan.add(out_dir, "sweep").final
    with plan:  # a failure removes what this run wrote, never older files
        return _sweep(ref, deformed, sizes, out, roi, level, interpolation, d_eps, a_priori, shift, scheduler,
                      progress, options)


def _sweep(ref, deformed, sizes, out: Path, roi, level: int, interpolation: str, d_eps, a_priori: bool, shift,
           scheduler, progress, options) -> dict:
    """:func:`sweep` once every input is checked and ``out`` is prepared."""
    from .engine import correlate

    emit = progress or (lambda event: None)
    results = []
    for ell in sizes:
        emit({"stage": "element-size", "element_size": ell})
        results.append(correlate(ref, deformed, element_size=ell, roi=roi, level=level,
                                 interpolation=interpolation, scheduler=scheduler,
                                 **{**PAPER_SETTINGS, **(options or {})},
                                 output=out / f"result-ell{ell}.zarr", overwrite=True, progress=progress))
    report = None
    if d_eps is None and a_priori:
        emit({"stage": "a-priori"})
        report = uncertainty(ref, sizes, out / "uncertainty", shift=shift, roi=roi, level=level,
                             interpolation=interpolation, scheduler=scheduler, progress=progress,
                             options=options)
        d_eps = read_delta_eps(report)
    elif d_eps is None:
        d_eps = {}
    rows = zoi_table(results, delta_eps=d_eps)
    md = write_zoi_table(rows, out)
    return {"rows": rows, "markdown": md, "csv": str(out / "zoi_table.csv"), "md": str(out / "zoi_table.md"),
            "uncertainty": report}


def write_zoi_table(rows: list[dict], out_dir=None) -> str:
    """Markdown of :func:`zoi_table` rows; with ``out_dir`` (an existing folder, prepared by
    the caller), also ``zoi_table.md`` and ``zoi_table.csv`` (the CSV adds
    ``volume_change_corrected`` and the result paths)."""
    csv_path = md_path = None
    if out_dir is not None:
        csv_path, md_path = Path(out_dir) / "zoi_table.csv", Path(out_dir) / "zoi_table.md"
        write_table(rows, SWEEP_COLUMNS + [("volume_change_corrected", "volume_change_corrected", "+.4f"),
                                           ("result", "result", "s")], csv_path)
    title = "ZOI-size sweep (paper Table 1); strains: mean over the ROI without the outermost elements"
    return write_table(rows, SWEEP_COLUMNS, None, md_path, title=title)
