"""What every ``chunkdic`` command prints: stderr lines and the progress events of a run.

Shared by :mod:`chunkdic.cli.app` and the ``_cli_*`` modules (one home, no import cycle).
"""

from __future__ import annotations

import math
import sys


def say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


#: what the progress lines of the current run have explained already, and the last rigid
#: gap per level (a rigid step that raises the gap is explained)
_RUN: dict = {"explained": set(), "rigid_gap": {}}

#: one-line explanations of terms that appear in progress lines and summaries
EXPLAIN = {
    "stalled": "stalled: neither the gap nor the increments improved for {patience} passes; the best field "
               "so far is kept and not called converged (try a larger --element-size or regularisation)",
    "excluded": "excluded: voxels whose X + u(X) falls outside the deformed scan; they are left out of the "
                "sums (a large share means the ROI reaches past what the deformed scan shows)",
    "diverged": "diverged: the gap grew far above its best; the best field so far is kept, not converged",
    "max-iterations": "max-iterations: --max-iterations reached before max|da| fell under --tolerance",
    "rigid-rise": "the gap rose: the previous rigid step overshot; this uniform translation is only the "
                  "starting estimate, which the C8 iterations refine",
    "rigid-worse": "a single mean translation fits this field worse than no motion (strain or rotation "
                   "dominate); it is only a starting estimate, which the C8 iterations refine",
}


def new_run() -> None:
    """Forget what an earlier run in this process explained (each run explains its terms once)."""
    _RUN["explained"].clear()
    _RUN["rigid_gap"].clear()


def explain(term: str) -> str:
    """The explanation of ``term`` on a line of its own, the first time in this run."""
    if term not in EXPLAIN or term in _RUN["explained"]:
        return ""
    _RUN["explained"].add(term)
    from ..engine.stopping import STALL_PATIENCE

    return "\n  (" + EXPLAIN[term].format(patience=STALL_PATIENCE) + ")"


def format_event(event: dict) -> str | None:
    stage = event["stage"]
    if stage == "start":
        roi = ",".join(f"{a}:{b}" for a, b in event["roi"])
        nodes = "x".join(str(n) for n in event["nodes"])
        line = f"running on {event['scheduler']}; levels {event['levels']}; ROI {roi} (level voxels); {nodes} nodes"
        if event.get("requested_roi"):
            asked = ",".join(f"{a}:{b}" for a, b in event["requested_roi"])
            line += f" (requested {asked} in level-0 voxels, trimmed to whole elements)"
        return line
    if stage == "plan":
        return event["plan"].line()
    if stage == "compile":
        if not event["done"]:
            return ("compiling the numba kernels (first run on this machine, about 20 s; "
                    "later runs load them from the cache)")
        return f"kernels compiled in {event['seconds']:.1f} s"
    if stage == "matrix":
        rate = event["voxels"] / max(event["seconds"], 1e-9) / 1e6
        return f"level {event['level']}: M built over {event['blocks']} blocks in {event['seconds']:.1f} s ({rate:.1f} Mvoxel/s)"
    if stage == "rigid":
        t = ", ".join(f"{v:+.3f}" for v in event["translation"])
        before = _RUN["rigid_gap"].get(event["level"]) if event["iteration"] else None
        _RUN["rigid_gap"][event["level"]] = event["gap"]
        rose = explain("rigid-rise") if before is not None and event["gap"] > before else ""
        return (f"level {event['level']} rigid {event['iteration']:2d}: gap {100 * event['gap']:.3f}%  "
                f"max|da| {event['max_delta']:.2e}  t=({t})" + rose)
    if stage == "gaps":
        worse = explain("rigid-worse") if event["rigid_gap"] > event["initial_gap"] else ""
        return (f"level {event['level']}: initial gap {100 * event['initial_gap']:.3f}%, after rigid translation "
                f"{100 * event['rigid_gap']:.3f}%" + worse)
    if stage == "iteration":
        d = event.get("status", "final") if event["max_delta"] is None else f"{event['max_delta']:.2e}"
        notes = (explain("excluded") if event["excluded"] else "") + explain(event.get("status") or "")
        return (
            f"level {event['level']} iter {event['iteration']:2d}: gap {100 * event['gap']:.3f}%  max|da| {d}"
            f"  excluded {event['excluded']}  ({event['seconds']:.1f} s)" + notes
        )
    if stage == "blocks":
        return (f"  level {event['level']} {event['label']}: {event['done']}/{event['total']} blocks, "
                f"{event['rate'] / 1e6:.1f} Mvoxel/s, ETA {event['eta']:.0f} s")
    if stage == "regularization":
        corner = event.get("l_curve_length")
        corner = f"; L-curve corner {corner:.1f}" if corner is not None and math.isfinite(corner) else ""
        return (f"level {event['level']}: {event['kind']} regularisation length {event['length']:.1f} voxels "
                f"(chosen from the data{corner}; noise correlation factor {event['kappa']:.1f})")
    if stage == "init":
        mean = ", ".join(f"{v:+.3f}" for v in event["mean"])
        return f"level {event['level']}: starting from the field of {event['path']} (mean {mean} voxels of the level)"
    if stage == "series-step":
        what = {"computed": "correlating", "resumed": "resuming", "done before": "done before, skipped:"}[event["run"]]
        return f"series: {what} {event['group']} (scans {event['pair']})"
    if stage == "resume":
        return f"resuming the interrupted run from its checkpoint: level {event['level']}, iteration {event['iteration']}"
    if stage == "level":
        return (f"level {event['level']}: {event['status']}, gap {100 * event['gap']:.3f}% "
                f"({event['seconds']:.1f} s)" + explain(event["status"]))
    return None


def print_progress(event: dict) -> None:
    line = format_event(event)
    if line:
        say(line)


def add_length_options(p, *, every_step: str = "") -> None:
    """``--element-size``, ``--roi`` and ``--roi-unit``, in voxels or a physical unit
    (:mod:`chunkdic.io.units`), declared once (``correlate``, ``series``); ``every_step``: a
    note appended to their help."""
    p.add_argument("--element-size", "-l", required=True, metavar="ELL",
                   help="element edge, voxels of --level, or a physical length such as 60um (converted with "
                        "the reference scan's voxel size and rounded to whole voxels)" + every_step)
    p.add_argument("--roi", help="z0:z1,y0:y1,x0:x1 in level-0 voxels, or in --roi-unit, or with a unit suffix "
                                 "(0:500,0:500,0:500um) (default: centred box)" + every_step)
    p.add_argument("--roi-unit", default=None, metavar="UNIT",
                   help="length unit of --roi, e.g. um (default: voxels)")


def length_options(args, ref) -> tuple[int, str | None]:
    """``--element-size`` and ``--roi`` (:func:`add_length_options`) in voxels, converted
    when given in a physical unit (``60um``, ``--roi-unit um``) with the voxel size of the
    reference scan ``ref`` (opened only then); each conversion said on stderr."""
    from ..io.units import element_size_voxels, parse_length, roi_voxels

    physical = parse_length(args.element_size)[1] is not None or args.roi_unit is not None or (
        args.roi is not None and not args.roi.strip()[-1:].isdigit())
    scan = None
    if physical:
        from ..io.scan import open_scan

        scan = open_scan(ref)
    ell, note = element_size_voxels(args.element_size, scan, args.level)
    roi, roi_note = (None, None) if args.roi is None else roi_voxels(args.roi, scan, args.roi_unit)
    for line in (note, roi_note):
        if line:
            say(line)
    return ell, roi


def add_figure_options(p) -> None:
    """``--format png|pdf|svg`` and ``--dpi`` of the commands that write figures (``report``,
    ``cutcheck``), declared once; both go to :func:`chunkdic.views.figures.save`."""
    from ..views.figures import DEFAULT_DPI, FORMATS

    p.add_argument("--format", dest="fmt", choices=FORMATS, default="png",
                   help="file format of every figure (default png)")
    p.add_argument("--dpi", type=int, default=DEFAULT_DPI,
                   help=f"resolution of every figure, dots per inch (default {DEFAULT_DPI})")


def add_engine_options(p, **helps) -> None:
    """The correlation settings every correlating command takes, built from the fields of
    :class:`~chunkdic.engine.settings.Settings` (their flag, help, choices and default are
    declared there, once), then ``--mask`` and ``--scheduler``.

    ``helps``: a different help text for some options (by field name), where a command
    uses the option differently (e.g. ``coarsest`` in a series).
    """
    from ..engine.settings import Settings
    from ..scheduler import SCHEDULER_HELP

    for name, meta in Settings.options():
        flag = meta["flag"] or "--" + name.replace("_", "-")
        kw = {"choices": meta["choices"]} if meta["choices"] else {"type": meta["type"]}
        if meta["metavar"]:
            kw["metavar"] = meta["metavar"]
        p.add_argument(flag, dest=name, default=meta["default"], help=helps.get(name, meta["help"]), **kw)
    p.add_argument("--mask", dest="mask", default=None,
                   help="specimen mask of the reference's shape (non-zero = material): Zarr, .npy, TIFF file or "
                        "folder of TIFF slices, HDF5 (file.h5[:/dataset])")
    p.add_argument("--scheduler", dest="scheduler", default=None, help=helps.get("scheduler", SCHEDULER_HELP))


def engine_options(args) -> dict:
    """The keyword arguments of :func:`chunkdic.correlate` from :func:`add_engine_options`' options."""
    from ..engine.settings import Settings

    return {**{name: getattr(args, name) for name, _ in Settings.options()}, "mask": args.mask,
            "scheduler": args.scheduler}
