"""The ZOI-size sweep of the paper's Table 1 (section 5.2).

:func:`sweep` correlates a pair for several element sizes and tabulates ``<Ux>, <Uy>,
<Uz>`` (arithmetic mean of the nodal displacements), final gap, ``tr(eps)``, ``eps_zz``
(mean over the ROI without the outermost elements, and corrected by ``1 - 2 ell / L``,
section 5.4) and the a-priori ``delta eps`` of each element size.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from pathlib import Path

from ..engine.driver import correlate
from ..method.settings import Settings
from ..errors import InputError
from ..io.outputs import Outputs
from ..results.result import Result, open_result
from ..results.strain import strain_summary
from ..scheduler import check_scheduler
from .metrology import (
    PAPER_SETTINGS,
    UncertaintyReport,
    check_element_sizes,
    check_plan,
    check_shift,
    study_settings,
    uncertainty,
    write_table,
)

__all__ = ["read_delta_eps", "sweep", "write_zoi_table", "zoi_table"]

SWEEP_COLUMNS = [
    ("element_size", "ZOI size (vox.)", "d"),
    ("mean_ux", "⟨Ux⟩ (vox.)", "+.3f"), ("mean_uy", "⟨Uy⟩ (vox.)", "+.3f"), ("mean_uz", "⟨Uz⟩ (vox.)", "+.3f"),
    ("final_gap_percent", "gap (%)", ".2f"),
    ("volume_change", "tr(ε) (–)", "+.4f"), ("eps_zz", "ε_zz (–)", "+.4f"),
    ("eps_zz_corrected", "ε_zz·(1−2ℓ/L) (–)", "+.4f"), ("delta_eps", "δε (–)", ".1e"),
    ("status", "status", "s"),
]


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

    rows = []
    for r in results:
        res = r if isinstance(r, Result) else open_result(r)
        ell = int(res.info["element_size"])
        s = strain_summary(res, measure="small")  # the paper's Table 1: small strain
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


def sweep(ref, deformed, element_sizes: Sequence[int], out_dir, settings: Settings | None = None, *, roi=None,
          roi_unit: str | None = None, uncertainty_from=None, a_priori: bool = True, shift=0.5, scheduler=None,
          overwrite: bool = False, progress: Callable[[dict], None] | None = None, **options) -> dict:
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
    settings : Settings, optional
        Every correlation's settings, as :func:`chunkdic.correlate` takes them; its
        ``element_size`` is replaced by each of ``element_sizes``.
    roi, roi_unit, scheduler
        As in :func:`chunkdic.correlate`.
    uncertainty_from : UncertaintyReport or path, optional
        Reuse the ``delta eps`` column of an earlier :func:`uncertainty` run (its CSV or
        directory) instead of running the a-priori test.
    a_priori : bool
        Without ``uncertainty_from``, run :func:`uncertainty` on ``ref`` (shift ``shift``)
        for the same sizes to fill ``delta eps``; ``False`` leaves the column empty.
    overwrite : bool
    progress : callable(dict), optional
    **options
        :class:`chunkdic.Settings` fields (``level``, ``interpolation``, …), as
        :func:`chunkdic.correlate` takes them; as for :func:`uncertainty`, without ``settings``
        the paper's analysis runs without regularisation unless asked for (:data:`PAPER_SETTINGS`).

    Returns
    -------
    dict
        ``rows`` (see :func:`zoi_table`), ``markdown``, ``csv``/``md`` paths and
        ``uncertainty`` (the report, if run).
    """

    sizes = check_element_sizes(element_sizes)
    given = study_settings(settings, options, PAPER_SETTINGS)
    check_shift(shift)
    roi = check_plan(ref, deformed, sizes, given, roi=roi, roi_unit=roi_unit, caller="sweep")
    d_eps = None
    if uncertainty_from is not None:
        d_eps = read_delta_eps(uncertainty_from)  # read first: a bad table must not cost a sweep
    check_scheduler(scheduler)
    earlier = [] if uncertainty_from is None or isinstance(uncertainty_from, UncertaintyReport) else [uncertainty_from]
    plan = Outputs(inputs=[ref, deformed, *earlier], overwrite=overwrite)
    out = plan.add(out_dir, "sweep").final
    with plan:  # a failure removes what this run wrote, never older files
        return _sweep(ref, deformed, sizes, out, roi, given, d_eps, a_priori, shift, scheduler, progress)


def _sweep(ref, deformed, sizes, out: Path, roi, given: dict, d_eps, a_priori: bool, shift, scheduler,
           progress) -> dict:
    """:func:`sweep` once every input is checked and ``out`` is prepared; ``given``: the
    correlations' settings (:func:`~chunkdic.analysis.metrology.study_settings`)."""

    emit = progress or (lambda event: None)
    results = []
    for ell in sizes:
        emit({"stage": "element-size", "element_size": ell})
        results.append(correlate(ref, deformed, element_size=ell, roi=roi, **given, scheduler=scheduler,
                                 output=out / f"result-ell{ell}.zarr", overwrite=True, progress=progress))
    report = None
    if d_eps is None and a_priori:
        emit({"stage": "a-priori"})
        report = uncertainty(ref, sizes, out / "uncertainty", shift=shift, roi=roi, scheduler=scheduler,
                             progress=progress, **given)
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
