"""What every ``chunkdic`` command prints: stderr lines and the progress events of a run.

Shared by :mod:`chunkdic.cli.app` and the ``_cli_*`` modules (one home, no import cycle).
"""

from __future__ import annotations

import math
import sys
import time

from ..method.events import EventText


def say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


#: the lines of the current run's events, each term explained once per run (the wording
#: lives below the CLI, in :mod:`chunkdic.method.events`, where the engine's log uses it too)
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


#: the shortest time between two progress lines of a step (the engine's block passes use the
#: same, :data:`chunkdic.passes.level.PROGRESS_SECONDS`)
PROGRESS_SECONDS = 5.0


class Progress:
    """Progress lines of one long step on stderr: at most one per ``every`` seconds.

    ``progress(fraction, stage=None)`` is what the writers call (``fraction`` in [0, 1] of
    the whole step, ``stage`` naming its part); a line with the fraction, the elapsed time
    and an ETA is said only when ``every`` seconds have passed since the step started or
    since its last line. :meth:`done` says ``STEP: 100%`` unless a line came less than
    ``every`` seconds before (the summary that follows says it is done). So a step shorter
    than ``every`` prints its 100 % line only, and no two progress lines of a step are less
    than ``every`` apart. ``header`` is said with the first call, once the inputs and
    outputs have been checked (a refused run prints its error line only).

    """

    def __init__(self, step: str, *, header: str | None = None, every: float = PROGRESS_SECONDS,
                 clock=time.monotonic, indent: str = "  "):
        self.step, self.header, self.every, self.clock, self.indent = step, header, every, clock, indent
        self.t0 = self.last = clock()
        self.lines = 0

    def _header(self) -> None:
        if self.header:
            say(self.header)
            self.header = None

    def __call__(self, fraction: float, stage: str | None = None) -> None:
        self._header()
        now = self.clock()
        if fraction < 1 and now - self.last >= self.every:
            elapsed = now - self.t0
            eta = f", ETA {elapsed * (1 - fraction) / fraction:.0f} s" if fraction > 0 else ""
            part = f" ({stage})" if stage and stage != self.step else ""
            say(f"{self.indent}{self.step}: {fraction:4.0%}{part} ({elapsed:.1f} s{eta})")
            self.last, self.lines = now, self.lines + 1

    def done(self) -> None:
        """The step's 100 % line, unless a line came less than ``every`` seconds ago."""
        self._header()
        now = self.clock()
        if not self.lines or now - self.last >= self.every:
            say(f"{self.indent}{self.step}: 100% ({now - self.t0:.1f} s)")
            self.last, self.lines = now, self.lines + 1


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
    ``cutcheck``), declared once; both go to :func:`chunkdic.plot.figures.save`."""
    from ..plot.figures import DEFAULT_DPI, FORMATS

    p.add_argument("--format", dest="fmt", choices=FORMATS, default="png",
                   help="file format of every figure (default png)")
    p.add_argument("--dpi", type=int, default=DEFAULT_DPI,
                   help=f"resolution of every figure, dots per inch (default {DEFAULT_DPI})")


def add_engine_options(p, **helps) -> None:
    """The correlation settings every correlating command takes, built from the fields of
    :class:`~chunkdic.method.settings.Settings` (their flag, help, choices and default are
    declared there, once), then ``--mask`` and ``--scheduler``.

    ``helps``: a different help text for some options (by field name), where a command
    uses the option differently (e.g. ``coarsest`` in a series).
    """
    from ..method.settings import Settings
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
    from ..method.settings import Settings

    return {**{name: getattr(args, name) for name, _ in Settings.options()}, "mask": args.mask,
            "scheduler": args.scheduler}


#: what a voxel size without a unit is told (a bare number would be silently read as µm)
NO_UNIT = ("{option} {value} has no unit: add it ({option} {value}um) or give --unit (micrometer/um, "
           "millimeter/mm, nanometer/nm); a voxel size's unit is never guessed")


def voxel_size_option(text, unit, option: str = "--voxel-size") -> tuple[str | None, str | None]:
    """``--voxel-size`` and ``--unit`` as ``(numbers, unit)``: the unit given with ``--unit``
    or as a suffix (``6.5um``, ``5,2.5,2.5um``); a voxel size without either is refused
    (one line), as are two different units. ``(None, unit)`` without a voxel size."""
    from ..errors import InputError
    from ..io.ngff import normalize_unit
    from ..io.units import parse_length

    if text is None:
        return None, unit
    parts = [p for p in str(text).replace(" ", ",").split(",") if p]
    parsed = [parse_length(p, option) for p in parts]
    for value, _ in parsed:
        if not (math.isfinite(value) and value > 0):
            raise InputError(f"{option} {text!r} must be one positive number or 3 (z,y,x)")
    units = {u for _, u in parsed if u} | ({normalize_unit(unit)} if unit else set())
    if len(units) > 1:
        raise InputError(f"{option} {text!r} and --unit {unit} name different units: give one")
    if not units:
        raise InputError(NO_UNIT.format(option=option, value=text))
    return ",".join(repr(v) for v, _ in parsed), units.pop()


def add_strain_option(p) -> None:
    """``--strain {small,green-lagrange}`` (default Green-Lagrange: a rigid rotation gives no strain)."""
    from ..results.strain import DEFAULT_MEASURE, MEASURES

    p.add_argument("--strain", dest="strain", choices=MEASURES, default=DEFAULT_MEASURE,
                   help="strain measure: green-lagrange (default; zero for a rigid rotation) or small "
                        "(the paper's; a rotation of t degrees shows as a strain of about -t^2/2 rad)")
