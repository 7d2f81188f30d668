"""Loading series: scans 0..n of one specimen, incremental and cumulative fields.

In an interrupted test every scan ``k`` is correlated against the previous one
(*incremental*, ``u_{k-1→k}``) and/or against the first (*cumulative*, ``u_{0→k}``).
All fields are Lagrangian, each in the frame of its own reference scan, so increments
compose, they do not add. The cumulative field composed from the increments, in the
reference frame, at the reference mesh's nodes ``X``::

    u_{0→k}(X) = u_{0→k-1}(X) + u_{k-1→k}(X + u_{0→k-1}(X))

the increment evaluated with its C8 shape functions at the current position of each
node, by :func:`chunkdic.mesh.carry_field` with the policy of a start field
(:mod:`chunkdic.engine.initial`): outside the increment's mesh the linear extension of the
nearest element up to one element beyond, constant further out; nodes it did not
measure take the mean of the measured ones.

Layout of the output, one Zarr v3 group ``attrs["chunkdic"] = {"kind": "series", ...}``::

    series.zarr/steps/001-incremental   result, scan 0 → 1 (also the cumulative field of step 1)
    series.zarr/steps/002-incremental   result, scan 1 → 2, started from step 1's increment
    series.zarr/composed/002            result-like group: u_{0→2} composed (no correlation)
    series.zarr/steps/002-cumulative    result, scan 0 → 2, started from composed/002
    ...

With ``mode="cumulative"`` only, step ``k`` is started from step ``k-1``'s cumulative
field and nothing is composed; with ``mode="incremental"`` only, ``composed/k`` is built
from ``composed/k-1`` (``steps/001-incremental`` for ``k = 2``) and the increments.
Every group is a normal result (:func:`chunkdic.open_result`, ``strain``, ``export``);
``composed/k`` has an empty history and ``status = "composed"``.

Resuming: the series group is written in place, marked incomplete until the end, with a
fingerprint of its scans (content identities), settings, ROI and mode. Re-running the
same command skips the steps already complete and resumes the interrupted one from its
own checkpoint (:mod:`chunkdic.engine.checkpoint`); each step's fingerprint covers the result
it starts from (``init``), so a step is never resumed from another start.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ..engine.checkpoint import fingerprint, identify_input
from ..engine.driver import correlate
from ..engine.front import prepare_run
from ..method.study_events import Event, SeriesStep, emit
from ..method.start import filled
from ..engine.meshes import parse_roi
from ..method.settings import Settings
from ..errors import DiskSpaceError, InputError
from ..io.diskspace import disk_cause
from ..io.formats.anyscan import open_any
from ..io.jsonfile import json_dict, read_json_object
from ..io.kinds import kind_of
from ..io.locks import OutputLock, reclaim_stale_locks
from ..io.outputrules import inside
from ..io.outputs import Outputs
from ..io.owntree import remove
from ..io.scan import open_scan
from ..io.scratch import reclaim_stale_scratch
from ..io.siblings import reclaim_stale_partials
from ..io.units import check_voxel_sizes
from ..mesh import carry_field
from ..results.result import HISTORY_FIELDS, Result, open_result
from ..results.strain import strain_summary
from ..scheduler import check_scheduler, local_workers, start_local_cluster

__all__ = ["series", "open_series", "SeriesResult", "compose", "MODES"]

MODES = ("both", "incremental", "cumulative")


@dataclasses.dataclass
class SeriesResult:
    """Outcome of :func:`series`.

    Attributes
    ----------
    path : str
        The series group.
    rows : list of dict
        The summary table, one row per group (``step``, ``pair``, ``kind``, ``group``,
        ``status``, ``run`` = computed / resumed / done before, ``gap``, ``mean``
        (Uz, Uy, Ux, voxels of the level), ``eps_zz``, ``seconds``).
    cumulative : dict of int -> Result
        ``u_{0→k}`` for every step ``k``: the cumulative correlation when there is one,
        else the composed field.
    """

    path: str
    rows: list
    cumulative: dict

    def table(self) -> str:
        """The summary as aligned text lines."""
        head = (f"{'step':>4}  {'pair':<5}  {'kind':<11}  {'status':<14}  {'run':<11}  {'gap %':>7}  "
                f"{'<Uz>':>8}  {'<Uy>':>8}  {'<Ux>':>8}  {'eps_zz':>9}")
        lines = [head]
        for r in self.rows:
            gap = "" if r["gap"] is None else f"{100 * r['gap']:.3f}"
            lines.append(f"{r['step']:>4}  {r['pair']:<5}  {r['kind']:<11}  {r['status']:<14}  {r['run']:<11}  "
                         f"{gap:>7}  " + "  ".join(f"{v:+8.4f}" for v in r["mean"]) + f"  {r['eps_zz']:+9.5f}")
        return "\n".join(lines)


def compose(cumulative: Result, increment: Result) -> np.ndarray:
    """``u_{0→k}`` at the nodes of ``cumulative`` from ``u_{0→k-1}`` and ``u_{k-1→k}``.

    Parameters
    ----------
    cumulative : Result
        ``u_{0→k-1}``: nodes ``X`` and displacement (3, nz, ny, nx), voxels of its level.
    increment : Result
        ``u_{k-1→k}`` on its own mesh, on the same pyramid level.

    Returns
    -------
    ndarray, shape (3, nz, ny, nx), float64, voxels
        ``u_{0→k-1}(X) + u_{k-1→k}(X + u_{0→k-1}(X))``; NaN where ``u_{0→k-1}`` is.
    """
    if cumulative.level != increment.level:
        raise InputError("compose: both fields must be on the same pyramid level")
    X, u = cumulative.node_coords, cumulative.displacement
    level = increment.level
    return u + carry_field(filled(increment.displacement), increment.mesh, level, X + np.nan_to_num(u), level,
                           clamp=True)


def series(
    scans: Sequence,
    output,
    settings: Settings | None = None,
    *,
    mode: str = "both",
    roi=None,
    scheduler=None,
    overwrite: bool = False,
    progress: Callable[[Event], None] | None = None,
    mask=None,
    roi_unit: str | None = None,
    **options,
) -> SeriesResult:
    """Correlate a loading series: each scan against the previous one and/or the first.

    Parameters
    ----------
    scans : sequence of str or Path
        Scans in loading order, the reference first (at least 2, on disk, same shape).
    output : str or Path
        The series group (Zarr v3), module docstring for its layout. Resumed when it holds
        an interrupted series of the same scans and settings; a complete one is replaced
        only with ``overwrite``.
    settings : Settings, optional
        As for :func:`chunkdic.correlate`; keyword ``options`` (``element_size=8``, ...)
        override or make it. The same settings and ROI for every step.
    mode : {"both", "incremental", "cumulative"}
        Which fields to correlate (module docstring).
    roi, scheduler, mask, roi_unit :
        As for :func:`chunkdic.correlate` (``element_size="80um"`` too: physical lengths are
        converted with the first scan's voxel size).
    progress : callable, optional
        The events of :func:`chunkdic.correlate`, each with ``group`` (the step being
        computed), and a :class:`~chunkdic.method.study_events.SeriesStep` when a step starts
        or is skipped.

    Returns
    -------
    SeriesResult

    Examples
    --------
    >>> s = chunkdic.series(["s0.zarr", "s1.zarr", "s2.zarr"], "series.zarr", element_size=8)  # doctest: +SKIP
    >>> print(s.table())  # doctest: +SKIP
    """
    scans = list(scans)
    if mode not in MODES:
        raise InputError(f"series mode must be one of {', '.join(MODES)}, got {mode!r}")
    if len(scans) < 2:
        raise InputError(f"a series needs at least 2 scans (the reference first), got {len(scans)}")
    opened = []
    for i, s in enumerate(scans):
        if not isinstance(s, (str, Path)):
            raise InputError(f"series scan {i}: give a path (a series is resumable, so its scans live on disk)")
        if not Path(s).exists():
            raise InputError(f"series scan {i} {s} does not exist")
        opened.append(open_scan(s))
    check_voxel_sizes({f"series scan {i} ({s})": sc for i, (s, sc) in enumerate(zip(scans, opened))})
    shape0 = opened[0].shape(0)
    for i, sc in enumerate(opened[1:], 1):
        if sc.shape(0) != shape0:
            raise InputError(f"series scan {i} {scans[i]} has shape {sc.shape(0)}, the reference {scans[0]} has "
                             f"{shape0}: every scan of a series must have the reference's shape")
    # the settings, ROI and meshes every step will have (refused here, before any output)
    spec = prepare_run(scans[0], scans[1], settings, roi=roi, roi_unit=roi_unit, mask=mask, caller="series",
                       **options)
    settings, roi = spec.settings, spec.roi
    check_scheduler(scheduler)
    identities = [identify_input(s, sc) for s, sc in zip(scans, opened)]
    series_print = fingerprint({"scans": identities, "settings": settings.to_json(), "roi": parse_roi(roi),
                                "mode": mode, "mask": None if mask is None else identify_input(mask, open_any(mask))})
    if not overwrite and _completed(output, series_print):  # the same command again: nothing to do
        if progress is not None:
            progress({"stage": "complete", "path": str(output)})
        return open_series(output)
    plan = Outputs(inputs=(*scans, mask), overwrite=overwrite)
    entry = plan.add(output, "series", resumable=True)
    out = Path(output)
    with OutputLock(out):
        fresh = entry.state != "resume"
        if not fresh:
            _check_resumable(out, series_print)
            _reclaim_dead_runs(out)
        else:
            plan.__enter__()  # removes the old series that --overwrite replaces (checked: ours)
            _create(out, series_print, scans, settings, mode)
        try:
            with inside(out), _one_cluster(scheduler) as sched:
                result = _run(scans, out, settings, mode, roi, sched, progress, mask)
        except (InputError, OSError) as exc:
            cause = disk_cause(exc)
            if cause is not None and _resumable(out):
                # a full (read-only, failing) disk is no bad input: the complete steps and the
                # interrupted step's checkpoint stay, and the message says how to resume
                done = sum(_complete(p) for p in sorted((out / "steps").glob("*")))
                raise DiskSpaceError(f"{cause}; the series in {out} is kept (marked incomplete, {done} step"
                                     f"{'' if done == 1 else 's'} complete): free space and run the same command "
                                     "again to resume, or remove it", cause=cause, kept=True) from None
            if fresh:  # a refused step, or a disk error before anything resumable: nothing of this run stays
                plan.rollback()
            if isinstance(exc, OSError) and cause is not None:
                raise DiskSpaceError(f"{cause}: nothing of the series {out} was kept", cause=cause) from None
            raise
        _finish(out, result.rows)
    return result


def _resumable(out: Path) -> bool:
    """The series holds something a re-run continues from: a complete step result, or a
    step's saved checkpoint (:mod:`chunkdic.engine.checkpoint`)."""
    for step in sorted((out / "steps").glob("*")) if (out / "steps").is_dir() else []:
        found, complete = kind_of(step)
        if found == "result" and (complete or "checkpoint" in _attrs(step)):
            return True
    return False


def _attrs(group: Path) -> dict:
    try:
        meta = read_json_object(group / "zarr.json")
        return dict(json_dict(json_dict(meta.get("attributes") or {}).get("chunkdic") or {}))
    except (OSError, ValueError):
        return {}


def open_series(path) -> SeriesResult:
    """Read a complete series written by :func:`series` (its summary and cumulative fields).

    Raises
    ------
    InputError
        Not a chunkdic series, or an interrupted one (run the same command again).
    """
    import zarr

    path = Path(path)
    found, complete = kind_of(path)
    if found != "series":
        raise InputError(f"{path} is not a chunkdic loading series")
    if not complete:
        raise InputError(f"series {path} is incomplete (run the same command again to resume it)")
    rows = list(zarr.open_group(str(path), mode="r").attrs["chunkdic"]["summary"])
    cumulative = {}
    for r in rows:  # per step, the last field from the reference: cumulative > composed > first increment
        if r["pair"].startswith("0→"):
            cumulative[r["step"]] = r["group"]
    return SeriesResult(str(path), rows, {k: open_result(path / g) for k, g in sorted(cumulative.items())})


@contextlib.contextmanager
def _one_cluster(scheduler):
    """``local[:N]``: one LocalCluster for the whole series (each correlation would start its own)."""
    if not (isinstance(scheduler, str) and scheduler.startswith("local")):
        yield scheduler
        return

    client, cluster = start_local_cluster(local_workers(scheduler))
    try:
        yield client
    finally:
        client.close()
        cluster.close()


def _create(out: Path, print_: str, scans, settings: Settings, mode: str) -> None:
    import zarr

    root = zarr.open_group(str(out), mode="w", zarr_format=3)
    root.attrs["chunkdic"] = {"kind": "series", "complete": False, "fingerprint": print_, "mode": mode,
                              "scans": [str(Path(s).resolve()) for s in scans], "settings": settings.to_json()}
    root.require_group("steps")
    if mode != "cumulative":
        root.require_group("composed")


def _reclaim_dead_runs(out: Path) -> None:
    """What a killed run left inside the series (it holds the series' lock now): the locks and
    staged copies of its steps. A step killed right after its commit is complete, so no
    run writes it again and takes its lock over: the lock would stay for ever. The killed
    run's scratch too: a re-run with only complete steps left makes none (which would
    reclaim it)."""
    reclaim_stale_scratch()
    for folder in (out / "steps", out / "composed"):
        if folder.is_dir():
            reclaim_stale_partials(folder / "_")
            reclaim_stale_locks(folder)


def _completed(output, print_: str) -> bool:
    """``output`` is the complete series of this very command (its fingerprint)."""
    p = Path(output)
    try:
        return not p.is_symlink() and kind_of(p) == ("series", True) and _attrs(p).get("fingerprint") == print_
    except (OSError, ValueError):
        return False


def _check_resumable(out: Path, print_: str) -> None:
    import zarr

    attrs = dict(zarr.open_group(str(out), mode="r").attrs.get("chunkdic", {}))
    if attrs.get("fingerprint") != print_:
        raise InputError(f"output {out} holds an interrupted series made with other scans or settings: pass "
                         "--overwrite to start again")


def _finish(out: Path, rows: list) -> None:
    import zarr

    root = zarr.open_group(str(out), mode="r+")
    root.attrs["chunkdic"] = {**dict(root.attrs["chunkdic"]), "summary": json.loads(json.dumps(rows)),
                              "complete": True}


def _run(scans, out: Path, settings: Settings, mode: str, roi, scheduler, progress, mask) -> SeriesResult:
    rows, cumulative = [], {}
    increment = None
    n = len(scans) - 1
    for k in range(1, n + 1):
        if mode != "cumulative":
            name = f"{k:03d}-incremental"
            increment = _step(out, name, scans[k - 1], scans[k], increment, settings, roi, scheduler,
                              progress, mask, rows, k, f"{k - 1}→{k}", "incremental")
            if k == 1:
                cumulative[1] = increment
                continue
            composed = _composed(out, k, cumulative[k - 1], increment, rows)
            if mode == "incremental":
                cumulative[k] = composed
                continue
            start = composed
        else:
            start = cumulative.get(k - 1)
        name = f"{k:03d}-cumulative"
        cumulative[k] = _step(out, name, scans[0], scans[k], start, settings, roi, scheduler, progress, mask,
                              rows, k, f"0→{k}", "cumulative")
    return SeriesResult(str(out), rows, cumulative)


def _step(out: Path, name: str, ref, deformed, start: Result | None, settings: Settings, roi, scheduler,
          progress, mask, rows: list, k: int, pair: str, kind: str) -> Result:
    """One correlation of the series: skipped when complete, resumed when interrupted."""
    path = out / "steps" / name
    t0 = time.perf_counter()
    run = "computed"
    _remove_debris(path)
    if path.exists() and _complete(path):
        res, run = open_result(path), "done before"
        emit(progress, SeriesStep(group=name, pair=pair, run=run))
    else:
        if path.exists():
            run = "resumed"
        emit(progress, SeriesStep(group=name, pair=pair, run=run))

        def tagged(event, name=name):  # the correlation's events, named by the step they belong to
            if progress is not None:
                progress(dataclasses.replace(event, group=name))

        res = correlate(ref, deformed, settings, roi=roi, scheduler=scheduler, output=path,
                        progress=tagged, mask=mask, init=start)
    rows.append(_row(res, k, pair, kind, f"steps/{name}", run, time.perf_counter() - t0))
    return res


def _composed(out: Path, k: int, previous: Result, increment: Result, rows: list) -> Result:
    """``composed/k``: ``u_{0→k}`` from ``u_{0→k-1}`` and ``u_{k-1→k}``, saved as a result group."""
    path = out / "composed" / f"{k:03d}"
    if path.exists() and _complete(path):
        res = open_result(path)
        run = "done before"
    else:
        u = compose(previous, increment)
        info = {key: previous.info[key] for key in ("element_size", "roi", "roi_level0", "level", "scale",
                                                    "levels", "voxel_size", "unit", "input_shapes", "settings")
                if key in previous.info}
        info.update(status="composed", converged=bool(previous.converged and increment.converged),
                    final_gap=float("nan"), initial_gap=None, rigid_gap=None,
                    composed_from=[previous.path, increment.path], created=time.strftime("%Y-%m-%dT%H:%M:%S%z"))
        history = {name: np.zeros(0, dtype=np.int32 if name in ("level", "iteration") else np.float64)
                   for name in HISTORY_FIELDS}
        res = Result(u, previous.node_coords, history, info)
        res.save(path)
        res.path = str(path)
        run = "computed"
    rows.append(_row(res, k, f"0→{k}", "composed", f"composed/{k:03d}", run, 0.0))
    return res


def _remove_debris(path: Path) -> None:
    """Remove what a write of this series left at one of its own step paths without a result's
    readable metadata: a full disk (or a kill) while the step was being created can leave its
    ``zarr.json`` cut short, and correlate would refuse the folder as foreign, so that the same
    command could never resume. Only the series writes under its ``steps/``, and it holds the
    series' lock (its fingerprint checked): a folder there that is not a result is its own
    debris. A recognisable result (complete, or with its checkpoint) is kept."""
    if path.is_dir() and not path.is_symlink() and kind_of(path)[0] is None:
        remove(path)


def _complete(path: Path) -> bool:

    found, complete = kind_of(path)
    return found == "result" and complete


def _row(res: Result, k: int, pair: str, kind: str, group: str, run: str, seconds: float) -> dict:
    u = res.displacement
    gap = res.info.get("final_gap")
    try:  # over the mask's active elements only
        eps_zz = float(strain_summary(res).eps_zz)
    except InputError:  # no measured element: no mean strain
        eps_zz = float("nan")
    return {"step": k, "pair": pair, "kind": kind, "group": group, "status": str(res.info.get("status")),
            "run": run, "gap": None if gap is None or not np.isfinite(gap) else float(gap),
            "mean": [float(np.nanmean(u[c])) for c in range(3)], "eps_zz": eps_zz, "seconds": round(seconds, 2),
            "level": res.level}


