"""What every ``chunkdic`` command prints: stderr lines and the progress events of a run.

Shared by :mod:`chunkdic.cli.app` and the ``_cli_*`` modules (one home, no import cycle).
"""

from __future__ import annotations

import sys

from ..engine.events import EXPLAIN, EventText  # noqa: F401  (EXPLAIN: app's summary)


def say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


#: the lines of the current run's events, each term explained once per run (the wording
#: lives below the CLI, in :mod:`chunkdic.engine.events`, where the engine's log uses it too)
_TEXT = EventText(explain=True)


def new_run() -> None:
    """Forget what an earlier run in this process explained (each run explains its terms once)."""
    _TEXT.reset()


def explain(term: str) -> str:
    """The explanation of ``term`` on a line of its own, the first time in this run."""
    return _TEXT.explain(term)


def format_event(event: dict) -> str | None:
    """The progress line of an engine event (None for events the CLI does not print)."""
    return _TEXT(event)


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
    reference scan ``ref`` (opened only then) by :func:`chunkdic.io.units.lengths_in_voxels`,
    as the Python API converts them; each conversion said on stderr."""
    from ..io.units import lengths_in_voxels

    ell, roi, notes = lengths_in_voxels(args.element_size, args.roi, roi_unit=args.roi_unit, reference=ref,
                                        level=args.level)
    for line in notes:
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
