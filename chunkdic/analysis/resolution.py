"""Spatial resolution, noise and their product (MEI), measured on a scan's own texture.

The DIC Challenge 2.0 (Reu et al., Exp. Mech. 2022) compares codes by two numbers measured
together at one setting: the **noise** ``n`` (σ of a translated pair) and the **spatial
resolution** ``l10 %``, the period below which a sine is attenuated by more than 10 %,
read along a *star* whose period rises across the image. Their product, the metrological
efficiency indicator ``MEI = n · l10 %``, cannot be improved by trading one for the other
along a code's own curve (a longer regularisation length lowers ``n`` and raises
``l10 %``); in 3-D the noise of a mean over a cube of edge ``l`` falls as ``l^-1.5``, so
``n · l10 %^1.5`` is the form that compares across lengths.

:func:`resolution` builds both pairs from the user's reference ``f`` (out of core,
:mod:`chunkdic.synth.scanpairs`), each scan with its own independent Gaussian noise:

- **translated**: ``f`` Fourier-shifted by ``shift`` (default 0.5 voxel on each axis,
  the paper's section 4.2 test); ``n`` = σ pooled over the three components at the nodes
  at least ``ell`` from the faces (:func:`chunkdic.analysis.scoring.score_displacement`);
- **star**: every x-line of ``f`` moved by ``Ux = A sin(2π (z - z_c) / λ(y))``,
  ``λ`` rising linearly from ``periods[0]`` to ``periods[1]`` over the rows read (at least
  ``ell`` from the faces) (:class:`chunkdic.synth.fields.Star`; default ``2 ℓ … 20 ℓ``).

``n`` is the DVC Challenge 2.0 noise floor (the standard deviation about the mean: the
translation only removed); the table adds the Challenge's bias ``|μ|`` and ``u_rms =
√(μ² + n²)`` over the same nodes (:mod:`chunkdic.analysis.challenge`).

Both are correlated with the same settings (element size, regularisation, any
:class:`chunkdic.Settings`) against the *same* noisy reference, the star first: with an
automatic regularisation length, the translated pair is correlated at the length chosen
on the star (the rule would pick its longest candidate on a translation: another setting,
whose tiny noise says nothing about the resolution measured). The star field is then
read **between the nodes** as the scoring rule does (trilinear on the node grid, every
voxel at least ``ell`` from the faces): per voxel row ``y``, the least-squares fit of the
measured ``Ux`` over ``(z, x)`` within one period around ``z_c`` by ``a · s(z) + b · c(z) +
const``, with ``s`` the imposed sine of that row and ``c`` its quadrature, plus the node
grid's first two aliases ``2π/ℓ ∓ k`` as nuisance terms (between the nodes a C8 field of a
sine is the sine and those aliases; without them the reading of one period depends on where
the nodes sit relative to ``z_c`` by up to ±30 % near ``λ = 2ℓ``), gives the amplitude ratio
``a / A`` at the period ``λ(y)``. A local-linear smoother in ``log λ`` (Gaussian kernel) makes the *smooth fit*,
and ``l10 %`` is the period at which it first rises through 0.9, from short periods up.

Memory: tasks read scans by path; the client holds the nodal fields and one y-plane of the
between-node field at a time, never a scan.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..engine.driver import correlate
from ..errors import InputError
from ..solve.transfer import THRESHOLD, c8_l10, c8_ratio  # noqa: F401  (c8_ratio: re-exported, used by tests)
from ..inputs import number
from ..io.handles import ArrayRef
from ..io.outputs import Outputs
from ..io.scan import open_scan
from ..mesh import Mesh
from ..method.settings import Settings
from ..scheduler import check_scheduler, open_runner
from ..synth.boolean import stream_key
from ..synth.fields import Star
from ..synth.fourier_shift import fourier_shift_scan
from ..synth.scanpairs import NOISE_KEYS, grey_moments, moved_copy
from .challenge import challenge_numbers
from .metrology import check_element_sizes, check_plan, check_shift, study_settings, write_table
from .scoring import score_displacement, scored_region

log = logging.getLogger(__name__)

__all__ = ["ResolutionReport", "c8_ratio", "c8_l10", "l10", "resolution", "star_ratios", "star_ratios_nodes"]

#: the threshold of the DIC Challenge 2.0 rule: amplitude attenuated by 10 %

RESOLUTION_COLUMNS = [
    ("element_size", "ℓ (vox.)", "d"),
    ("regularization", "regularisation", "s"),
    ("regularization_length", "ℓ_reg (vox.)", ".1f"),
    ("noise", "n (vox.)", ".4f"),
    ("bias", "|μ| (vox.)", ".4f"),
    ("u_rms", "u_rms (vox.)", ".4f"),
    ("l10", "l10 % (vox.)", ".1f"),
    ("l10_bound", "l10 % is", "s"),
    ("mei", "MEI = n·l10 % (vox.²)", ".3f"),
    ("mei3d", "n·l10 %^1.5 (vox.^2.5)", ".3f"),
    ("l10_c8", "l10 % of C8 alone (vox.)", ".1f"),
    ("status_translated", "status (translated)", "s"),
    ("status_star", "status (star)", "s"),
]


# --------------------------------------------------------------------------- C8 projection


# --------------------------------------------------------------------------- reading the star


def star_ratios(result, star: Star, volume_shape, ell: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Measured/imposed amplitude of the star per voxel row ``y``, read between the nodes.

    Parameters
    ----------
    result : Result
        A correlation of a star pair (level-0 voxels).
    star : Star
    volume_shape : tuple of 3 int
        ``(nz, ny, nx)`` of the reference scan.
    ell : float, optional
        Distance from the faces of the voxels read (default: the element size).

    Returns
    -------
    periods : ndarray, shape (m,), float64, voxels
        ``λ(y)`` of the rows read (rows with at least 3 voxels in the window, in y order).
    ratios : ndarray, shape (m,), float64
        ``a / A`` of each row.
    """
    return star_ratios_nodes(result.mesh.node_axes(), result.displacement, star, volume_shape,
                             float(result.info["element_size"]) if ell is None else ell)


def star_ratios_nodes(node_axes, u, star: Star, volume_shape, ell: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`star_ratios` for a field on any regular grid of points (another code's, too).

    Parameters
    ----------
    node_axes : sequence of 3 ndarray, float, voxels
        Grid positions along ``z, y, x`` (evenly spaced, the same step on every axis).
    u : ndarray, shape (3, gz, gy, gx), float, voxels
        Displacement at the grid points (NaN where a point failed); read trilinearly
        between them.
    star, volume_shape, ell
        As in :func:`star_ratios` (``ell``: distance from the faces of the voxels read).
    """

    node_axes = [np.asarray(a, np.float64) for a in node_axes]
    grid = float(node_axes[0][1] - node_axes[0][0])
    mesh = Mesh(origin=tuple(float(a[0]) + 0.5 for a in node_axes), element_size=grid,
                shape=tuple(a.size - 1 for a in node_axes))
    ell = float(ell)
    u = np.asarray(u, np.float64)
    axes = []
    for a, n in zip(node_axes, volume_shape):
        lo = max(math.ceil(a[0] - 1e-9), math.ceil(ell - 0.5 - 1e-9))
        hi = min(math.floor(a[-1] + 1e-9), math.floor(n - 0.5 - ell + 1e-9))
        axes.append(np.arange(lo, hi + 1, dtype=np.float64))
    z, ys, x = axes
    periods, ratios = [], []
    for y in ys:
        lam = float(star.period(y))
        zw = z[np.abs(z - star.center_z) <= lam / 2.0]
        if zw.size < 4 or x.size == 0:
            continue
        ux = mesh.evaluate_grid(u, (zw, np.array([y]), x))[2, :, 0, :]  # (nz_w, nx)
        ok = np.isfinite(ux)
        if ok.sum() < 8:
            continue
        d = np.broadcast_to((zw - star.center_z)[:, None], ux.shape)[ok]
        k = 2.0 * np.pi / lam
        cols = [np.sin(k * d), np.cos(k * d), np.ones(d.size)]
        half = max(float(np.abs(d).max()), 1.0)
        if abs(abs(2.0 * np.pi / grid - k) - k) * half < 0.5:
            continue  # λ near 2ℓ: the grid's alias is the sine itself within the window, no reading
        for kk in (2.0 * np.pi / grid - k, 2.0 * np.pi / grid + k):  # the node grid's first aliases
            cols += [np.sin(kk * d), np.cos(kk * d)]
        coef = np.linalg.lstsq(np.stack(cols, axis=1), ux[ok], rcond=1e-8)[0]
        periods.append(lam)
        ratios.append(coef[0] / star.amplitude)
    return np.asarray(periods), np.asarray(ratios)


def smooth_fit(periods, ratios, *, bandwidth: float = 0.1) -> np.ndarray:
    """Local-linear fit of ``ratios`` against ``log periods`` (Gaussian kernel, ``bandwidth`` in ln λ)."""
    t = np.log(np.asarray(periods, np.float64))
    r = np.asarray(ratios, np.float64)
    out = np.empty_like(r)
    for i, t0 in enumerate(t):
        w = np.exp(-0.5 * ((t - t0) / bandwidth) ** 2)
        d = t - t0
        sw, swd, swd2 = w.sum(), (w * d).sum(), (w * d * d).sum()
        swr, swdr = (w * r).sum(), (w * d * r).sum()
        det = sw * swd2 - swd * swd
        out[i] = swr / sw if det <= 1e-12 * sw * sw else (swd2 * swr - swd * swdr) / det
    return out


def l10(periods, ratios, *, threshold: float = THRESHOLD) -> tuple[float, str]:
    """The period at which the smooth fit of ``ratios`` first rises through ``threshold``.

    Returns
    -------
    l10 : float, voxels
        Linear interpolation between the two fitted rows around the crossing; the
        shortest period read if the fit starts above the threshold, the longest if it
        never reaches it.
    bound : {"=", "<", ">"}
        ``"<"``/``">"`` when ``l10`` is a bound (no crossing within the periods read).
    """
    p = np.asarray(periods, np.float64)
    if p.size < 2:
        raise InputError("the star was read on fewer than 2 rows: use a larger scan or a smaller element size")
    order = np.argsort(p)
    p = p[order]
    f = smooth_fit(p, np.asarray(ratios, np.float64)[order])
    if f[0] >= threshold:
        return float(p[0]), "<"
    for i in range(1, p.size):
        if f[i - 1] < threshold <= f[i]:
            w = (threshold - f[i - 1]) / (f[i] - f[i - 1])
            return float(p[i - 1] + w * (p[i] - p[i - 1])), "="
    return float(p[-1]), ">"


# --------------------------------------------------------------------------- the measurement


@dataclass
class ResolutionReport:
    """Outcome of :func:`resolution`: one row per element size (``RESOLUTION_COLUMNS``)
    plus each star's profile (``profiles[ell] = (periods, ratios, fit)``) and the files written."""

    rows: list[dict]
    profiles: dict = field(default_factory=dict)
    noise_std: float = 0.0
    files: dict = field(default_factory=dict)

    def markdown(self) -> str:
        text = write_table(self.rows, RESOLUTION_COLUMNS)
        return ("Noise n (translated pair), spatial resolution l10 % (star, DIC Challenge 2.0 rule) "
                f"and MEI; independent noise σ = {self.noise_std:.4g} grey levels in each scan\n\n" + text)


def _level0_path(ref: ArrayRef) -> str:
    return str(Path(ref.path) / ref.key) if ref.kind == "zarr" and ref.key else ref.path


def resolution(scan, element_sizes, out_dir, settings: Settings | None = None, *, noise: float = 0.02, shift=0.5,
               amplitude: float = 0.5, periods: tuple[float, float] | None = None, seed: int = 0, scheduler=None,
               overwrite: bool = False, progress: Callable[[dict], None] | None = None,
               **options) -> ResolutionReport:
    """Noise, spatial resolution l10 % and MEI of a correlation setting, on a scan's texture.

    Parameters
    ----------
    scan : path or array
        The reference scan (anything :func:`chunkdic.open_scan` takes); level 0 is used.
    element_sizes : sequence of int
        Element edges ``ell``, voxels (one star pair and one translated pair each).
    out_dir : path
        Folder for the scans (``reference.zarr``, ``translated.zarr``,
        ``star-ell{ell}.zarr``), the results, ``resolution.csv``, ``resolution.json``,
        ``resolution.md`` and ``star-ell{ell}.csv`` (ratio per period and its fit).
    noise : float, keyword-only
        Standard deviation of the noise added independently to each scan, as a fraction of
        the texture's contrast, taken as twice the reference's grey-level standard deviation
        (exact for two phases of equal fractions; 0.98 of the phase contrast on the grains
        specimen). ``0``: no noise added (the pair then shares the scan's own noise).
    shift : float or tuple of 3 float
        Translation of the translated pair, voxels.
    amplitude : float
        Amplitude ``A`` of the star, voxels.
    periods : (float, float), optional
        Periods of the star at the first and the last row read (ℓ from the faces), voxels (default ``2 ℓ, 20 ℓ``).
    seed : int
        Seed of the noises.
    scheduler, overwrite, progress
        As in :func:`chunkdic.analysis.metrology.uncertainty`; progress also receives
        ``{"stage": "resolution", ...row}``.
    settings : Settings, optional
        Every correlation's settings, as :func:`chunkdic.correlate` takes them (level 0; its
        ``element_size`` replaced by each of ``element_sizes``).
    **options
        :class:`chunkdic.Settings` fields of every correlation, as :func:`chunkdic.correlate`
        takes them (default: the engine's, i.e. Tikhonov with an automatic length).

    Returns
    -------
    ResolutionReport

    References
    ----------
    Reu et al., DIC Challenge 2.0, Exp. Mech. 62 (2022): the star, l10 % and MEI.
    """

    sizes = check_element_sizes(element_sizes)
    t = check_shift(shift)
    noise = number(noise, "noise", minimum=0)
    amplitude = number(amplitude, "amplitude")
    if amplitude == 0:
        raise InputError("the star's amplitude must not be 0")
    seed = number(seed, "seed", minimum=0, integer=True)
    if periods is not None:
        periods = tuple(float(v) for v in periods)
        if len(periods) != 2 or not all(math.isfinite(v) and v > 0 for v in periods):
            raise InputError(f"periods must be two positive numbers, got {periods!r}")
    src_scan = open_scan(scan)
    given = study_settings(settings, options, {"regularization": "tikhonov"})
    if given.get("level", 0) != 0:
        raise InputError("the resolution is measured on level 0 only")
    check_plan(src_scan, src_scan, sizes, given, caller="resolution")
    check_scheduler(scheduler)
    plan = Outputs(inputs=[scan], overwrite=overwrite)
    out = plan.add(out_dir, "resolution").final
    with plan:  # a failure removes what this run wrote, never older files
        return _resolution(src_scan, sizes, out, noise, t, amplitude, periods, seed, scheduler, progress, given)


def _resolution(src_scan, sizes, out: Path, noise, t, amplitude, periods, seed, scheduler, progress,
                options) -> ResolutionReport:

    emit = progress or (lambda event: None)
    src = src_scan.refs([0], out)[0]
    shape = tuple(int(n) for n in src.shape)
    t0 = time.perf_counter()

    def stage(name):
        return lambda f: emit({"stage": "write", "scan": name, "fraction": f, "seconds": time.perf_counter() - t0})

    with open_runner(scheduler) as runner:
        _, sd = grey_moments(src, runner)
        std = noise * 2.0 * sd
        keys = {k: int(stream_key(seed, v)) for k, v in NOISE_KEYS.items()}
        ref = moved_copy(src, out / "reference.zarr", runner=runner, noise=std, key=keys["reference"],
                         attrs={"resolution": {"role": "reference", "noise": std}}, progress=stage("reference"))
    shifted = fourier_shift_scan(src, out / "shifted.zarr", t, scheduler=scheduler, overwrite=True,
                                 progress=stage("shifted"))
    with open_runner(scheduler) as runner:
        trans = moved_copy(shifted, out / "translated.zarr", runner=runner, noise=std, key=keys["translated"],
                           attrs={"resolution": {"role": "translated", "shift": list(t), "noise": std}},
                           progress=stage("translated"))
    import shutil

    shutil.rmtree(out / "shifted.zarr", ignore_errors=True)
    settings = {"element_size": None, **options}  # options: every correlation's settings (study_settings)
    rows, profiles = [], {}
    for ell in sizes:
        lo, hi = periods if periods is not None else (2.0 * ell, 20.0 * ell)
        # the periods span the rows that are read (at least ell from the faces)
        y0, y1 = ell - 0.5, shape[1] - 0.5 - ell
        if y1 <= y0:
            y0, y1 = 0.0, float(max(shape[1] - 1, 1))
        star = Star(amplitude=amplitude, period_min=lo, period_max=hi, y0=y0, y1=y1,
                    center_z=(shape[0] - 1) / 2.0)
        with open_runner(scheduler) as runner:
            sp = moved_copy(src, out / f"star-ell{ell}.zarr", runner=runner, noise=std, key=keys["star"] + ell,
                            star=star, attrs={"resolution": {"role": "star", "field": star.to_json(), "noise": std}},
                            progress=stage(f"star-ell{ell}"))
        settings["element_size"] = ell
        emit({"stage": "element-size", "element_size": ell, "pair": "star"})
        rs = correlate(_level0_path(ref), _level0_path(sp), **settings, scheduler=scheduler,
                       output=out / f"result-star-ell{ell}.zarr", overwrite=True, progress=progress)
        # the noise of the *same* setting: an automatic length is the one chosen on the star
        # (on a translation the rule picks the longest candidate, a different setting)
        reg = rs.info.get("regularization") or {}
        same = dict(settings)
        if reg.get("kind", "none") != "none" and reg.get("length") is not None:
            same["regularization_length"] = float(reg["length"])
        emit({"stage": "element-size", "element_size": ell, "pair": "translated"})
        rt = correlate(_level0_path(ref), _level0_path(trans), **same, scheduler=scheduler,
                       output=out / f"result-translated-ell{ell}.zarr", overwrite=True, progress=progress)
        sc = score_displacement(rt.node_coords, rt.displacement, t, shape, ell)
        per, rat = star_ratios(rs, star, shape, ell)
        length, bound = l10(per, rat)
        fit = smooth_fit(per, rat)
        profiles[ell] = (per, rat, fit)
        row = {
            "element_size": ell,
            "regularization": str(reg.get("kind", options.get("regularization", "tikhonov"))),
            "regularization_length": _length(reg),
            "regularization_automatic": bool(reg.get("automatic", False)),
            "noise": sc.sigma, "noise_rms": sc.rms, "nodes_scored": sc.n_points,
            # the DVC Challenge 2.0 bias and u_rms of the same nodes (noise = its noise floor)
            **_challenge(rt, t, shape, ell),
            "l10": length, "l10_bound": bound,
            "mei": sc.sigma * length, "mei3d": sc.sigma * length ** 1.5,
            "l10_c8": c8_l10(ell),
            "status_translated": str(rt.info.get("status")), "status_star": str(rs.info.get("status")),
            "period_min": lo, "period_max": hi, "amplitude": amplitude,
        }
        rows.append(row)
        log.info("resolution, ell %d: %s", ell, row)
        emit({"stage": "resolution", **row})
        with open(out / f"star-ell{ell}.csv", "w") as fh:
            fh.write("period,ratio,fit\n")
            for a, b, c in zip(per, rat, fit):
                fh.write(f"{a:.6g},{b:.6g},{c:.6g}\n")
    report = ResolutionReport(rows, profiles, std)
    files = {"csv": str(out / "resolution.csv"), "json": str(out / "resolution.json"),
             "markdown": str(out / "resolution.md")}
    keys_all = [k for k, _, _ in RESOLUTION_COLUMNS] + [k for k in rows[0] if k not in {c for c, _, _ in RESOLUTION_COLUMNS}]
    write_table(rows, [(k, k, "") for k in keys_all], files["csv"])
    Path(files["json"]).write_text(json.dumps({"kind": "resolution", "noise_std_grey": std, "shift": list(t),
                                               "seed": seed, "options": options, "rows": rows}, indent=2))
    Path(files["markdown"]).write_text(report.markdown())
    report.files = files
    return report


def _challenge(result, t, shape, ell) -> dict:
    """Pooled bias and ``u_rms`` of the translated pair over the scored nodes (:mod:`.challenge`)."""
    inside = scored_region(result.node_coords, shape, ell)
    err = result.displacement.reshape(3, -1)[:, inside] - np.asarray(t, float)[:, None]
    d = challenge_numbers(err)
    return {"bias": d["bias"], "u_rms": d["u_rms"], **{f"bias_{c}": d[f"bias_{c}"] for c in "zyx"}}


def _length(reg: dict):
    v = reg.get("length")
    return None if v is None else float(v)
