"""``chunkdic`` command line: a thin layer over the Python API.

Bad input gets one line on stderr and exit status 2, with nothing written.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import logging
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from ..method.events import EXPLAIN, log as event_log
from ..errors import InputError, WorkerLostError
from ..results.result import FLAG_MISMATCH
from ..scheduler import SCHEDULER_HELP
from .rerun import judged_run
from .common import (
    add_engine_options,
    add_length_options,
    engine_options,
    length_options,
    new_run,
    print_progress,
    say,
)

EXIT_BAD_INPUT = 2
EXIT_FAILED = 1  # the run could not finish (not converged, a cluster that lost its workers)


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2, as for every other bad input
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")


class _HelpFormatter(argparse.HelpFormatter):
    """Every option's default in its help, unless the help already names it.

    Unlike ``argparse.ArgumentDefaultsHelpFormatter`` this leaves alone a help that says
    ``default`` itself (many say what ``None`` means: "default: automatic"), flags, and
    required options; an option without help still gets its default.
    """

    def _get_help_string(self, action):
        text = action.help or ""
        if (action.default is argparse.SUPPRESS or action.required or action.nargs == 0
                or (not action.option_strings and action.nargs != "?") or "default" in text.lower()):
            return text
        shown = "none" if action.default is None else "%(default)s"
        return f"{text} (default: {shown})".strip()


class _QuietStderr:
    """``-q``: stderr keeps only chunkdic's own error and warning lines (``chunkdic: …``);
    progress and summaries are dropped. Results still go to stdout."""

    def __init__(self, stream):
        self.stream, self.pending = stream, ""

    def write(self, text: str) -> int:
        self.pending += text
        *lines, self.pending = self.pending.split("\n")
        for line in lines:
            if line.startswith("chunkdic: "):
                self.stream.write(line + "\n")
        return len(text)

    def flush(self) -> None:
        self.stream.flush()

    def __getattr__(self, name):  # fileno, isatty, encoding, ... of the real stream
        return getattr(self.stream, name)


def _summary(result, seconds: float) -> str:
    info = result.info
    u = result.displacement
    mean = ", ".join(f"<U{c}> {np.nanmean(u[i]):+.4f}" for i, c in enumerate("zyx"))
    roi = ",".join(f"{a}:{b}" for a, b in info["roi"])
    length = result.voxel_length()  # physical size of a level voxel, (z, y, x); None without a voxel size
    unit = info.get("unit") or "unit"
    physical = ""
    if length is not None:  # the same means in the scan's unit (physical units end to end)
        physical = " (" + ", ".join(f"{np.nanmean(u[i]) * length[i]:+.4g}" for i in range(3)) + f" {unit})"
    line = (
        f"{info['status']}: final gap {100 * info['final_gap']:.3f}% (initial {100 * info['initial_gap']:.3f}%, "
        f"rigid {100 * info['rigid_gap']:.3f}%); {mean} voxels of level {info['level']}{physical}; "
        f"ROI {roi}; excluded voxels {info['excluded_voxels']}; {seconds:.1f} s"
    )
    reg = info.get("regularization") or {}
    if reg.get("nominal_l10"):
        line += (f"; spatial resolution >= {reg['nominal_l10']:.0f} level-0 voxels (l10 %, from l and "
                 + (f"the {reg['kind']} length {reg['length']:.0f}" if reg.get("length") else "no regularisation")
                 + "; `chunkdic resolution` measures it)")
    if result.uncertainty is not None and np.isfinite(result.uncertainty).any():
        sigma = np.nanmedian(result.uncertainty)
        line += f"; median nodal uncertainty {sigma:.4f} voxel"
        if length is not None:
            line += f" ({sigma * float(np.mean(length)):.3g} {unit})"
    missing = info.get("nodes_without_data", 0) + info.get("masked_nodes", 0)
    if missing:
        line += f"; {missing} nodes not measured (NaN)"
    if info["status"] == "excluded":
        line += (f"\n  excluded: {100 * info.get('excluded_fraction', 0):.0f}% of the ROI maps outside the deformed "
                 "scan; the rest converged, but so large a share left out is not called converged")
    elif info["status"] == "weak-texture":
        line += (f"\n  weak-texture: {info.get('weak_nodes', 0)} of the measured nodes see too little texture to be "
                 "measured (their values come from the regularisation); the rest converged, but so large a share "
                 "is not called converged (mask the untextured region, or a larger --element-size)")
    elif info["status"] == "mismatch":
        bad = int(np.count_nonzero(result.flags & FLAG_MISMATCH)) if result.flags is not None else 0
        line += (f"\n  mismatch: {bad} of the measured nodes leave a residual that is not noise (the deformed scan "
                 "does not match the reference there, whatever the field; flagged in the result); the iterations "
                 "converged, but so large a share is not called converged (check the scans, or mask that region)")
    elif info["status"] in ("stalled", "diverged", "max-iterations"):
        from ..method.stopping import STALL_PATIENCE

        line += "\n  " + EXPLAIN[info["status"]].format(patience=STALL_PATIENCE)
    if info["excluded_voxels"] and info["status"] != "excluded":
        line += "\n  " + EXPLAIN["excluded"]
    return line


def cmd_correlate(args) -> int:
    from ..engine.driver import correlate

    element_size, roi = length_options(args, args.ref)
    if args.plan:
        return _print_plan(args, element_size, roi)
    t0 = time.perf_counter()
    result = correlate(args.ref, args.deformed, element_size=element_size, roi=roi, init=args.init,
                       output=args.output, overwrite=args.overwrite, progress=print_progress,
                       memory_target=args.memory_target, crack=args.crack, **engine_options(args))
    say(_summary(result, time.perf_counter() - t0))
    print(args.output)
    return 0 if result.converged else 1


def _print_plan(args, element_size, roi) -> int:
    """``correlate --plan``: the plan on stdout, nothing written; exit 2 if the run would be refused."""
    from ..engine.runplan import plan

    p = plan(args.ref, args.deformed, element_size=element_size, roi=roi, init=args.init, output=args.output,
             memory_target=args.memory_target, calibrate=not args.no_calibration, **engine_options(args))
    print(p.summary())
    p.check()
    return 0


def cmd_demo(args) -> int:
    """Synthesize a foam pair with a known field, correlate it, compare with the truth."""
    from ..inputs import number
    from ..io.outputs import Outputs
    from ..scheduler import check_scheduler

    number(args.size, "--size", minimum=16, integer=True)
    number(args.element_size, "--element-size", minimum=2, maximum=args.size // 3, integer=True)
    number(args.seed, "--seed", minimum=0, integer=True)
    check_scheduler(args.scheduler)
    plan = Outputs(overwrite=args.overwrite)
    plan.add(args.directory, "demo")
    with plan:  # a failure removes what the demo wrote
        return _demo(args)


def _compile_in_background():
    """On a first run, compile the correlation kernels into numba's on-disk cache in two more
    processes (the block kernels; the client's solver and V-cycle) while this one
    synthesizes the demo's scans; the correlation then loads them. An empty list when the
    cache is warm.

    Measured on a 2-core machine with a fresh cache (96³ demo): first iteration line at
    22.8 s when the kernels compiled after the synthesis, 17.8 s with one background
    process; with the fused prefilter and the V-cycle (about 10 s more to compile) 22.9 s
    with one process, 18.6 s with two.
    """
    import subprocess

    from ..kernels import jit as kernels

    if kernels.compiled_on_disk():
        return []
    say("compiling the numba kernels in the background (first run on this machine)")
    return [subprocess.Popen([sys.executable, "-c", f"from chunkdic import {m}; {m}.warmup()"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for m in ("kernels", "solve")]


def _wait_for_compile(processes, *, every: float | None = None, clock=time.monotonic, sleep=time.sleep) -> float:
    """Wait for the compiling processes, saying every ``every`` seconds (default
    :data:`~chunkdic.cli.common.PROGRESS_SECONDS`) how many are done, so that a first run
    is never silent; returns the seconds waited."""
    from .common import PROGRESS_SECONDS

    every = PROGRESS_SECONDS if every is None else every
    t0 = last = clock()
    while True:
        done = sum(p.poll() is not None for p in processes)
        now = clock()
        if done == len(processes):
            return now - t0
        if now - last >= every:
            say(f"  compiling the numba kernels: {done} of {len(processes)} processes done "
                f"({now - t0:.0f} s; first run on this machine only)")
            last = now
        sleep(0.2)


def _demo(args) -> int:
    from ..engine.driver import correlate
    from ..synth import synthetic

    out = Path(args.directory)
    result_path = out / "result.zarr"
    field = synthetic.Affine(
        matrix=((-0.01, 0.0, 0.005), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
        center=tuple(n / 2 for n in (args.size,) * 3),
        translation=(2.3, -1.4, 0.7),
    )
    say(f"synthesizing a {args.size}^3 foam pair in {out} (affine field: -1% along z, 0.5% shear, translation)")
    compiling = _compile_in_background()
    paths = synthetic.synthesize(out, (args.size,) * 3, field=field, seed=args.seed)
    if compiling:  # the kernels were being compiled into numba's cache meanwhile
        waited = _wait_for_compile(compiling)
        say(f"kernels compiled (waited {waited:.1f} s after the synthesis)")
    t0 = time.perf_counter()
    result = correlate(paths["reference"], paths["deformed"], element_size=args.element_size,
                       scheduler=args.scheduler, output=result_path, progress=print_progress)
    say(_summary(result, time.perf_counter() - t0))
    truth = field.displacement(*result.node_coords)
    err = result.displacement - truth
    rms = np.sqrt((err**2).mean(axis=(1, 2, 3)))
    say("RMS nodal error vs the known field: " + ", ".join(f"U{c} {v:.4f}" for c, v in zip("zyx", rms)) + " voxel")
    print(result_path)
    return 0 if result.converged else 1


def _add_correlate(sub) -> None:
    p = sub.add_parser(
        "correlate", help="measure the displacement field between two scans (C8-DIC)",
        description="Global C8 digital volume correlation of DEFORMED against REF (cubic 8-node elements of "
                    "edge --element-size), coarse to fine over the scans' 2^s sum pyramid, out of core. "
                    "Writes a Zarr v3 result (xarray.open_zarr reads it); progress on stderr, the result "
                    "path on stdout; exit 0 when converged, 1 otherwise, 2 on bad input. An interrupted run "
                    "resumes when the same command runs again.")
    p.add_argument("ref", help="reference scan: Zarr group/array, .npy")
    p.add_argument("deformed", help="deformed scan: Zarr group/array, .npy")
    p.add_argument("-o", "--output", required=True, help="result path (Zarr v3 group)")
    add_length_options(p)
    add_engine_options(p)
    p.add_argument("--init", default=None, metavar="RESULT",
                   help="start from this earlier result's field when it matches better than no motion and "
                        "the rigid translation (lowest gap; any element size, ROI or level of the same "
                        "reference; the run then starts on --level unless --coarsest is given)")
    p.add_argument("--crack", default=None, metavar="LABELS",
                   help="a known crack surface: a label image of the reference's shape (non-zero voxels = the "
                        "surface; Zarr, .npy, TIFF, HDF5): the elements it cuts are split, each side with its own "
                        "node copies, the Tikhonov penalty released across it (docs/cracks.md)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--memory-target", default=None, metavar="SIZE",
                   help="peak memory per process to plan for, e.g. 2GiB (default: chunkdic.memory-target, else "
                        "none): blocks are sized to fit it; a run that cannot fit is refused")
    p.add_argument("--plan", action="store_true",
                   help="print the plan (levels, meshes, blocks, memory per task and client, scratch disk, "
                        "estimated time from a short calibration) and exit, writing nothing")
    p.add_argument("--no-calibration", action="store_true",
                   help="with --plan: estimate the time without timing this machine (6 Mvoxel/s per task "
                        "assumed), for a cluster other than the machine that plans")
    p.set_defaults(func=cmd_correlate)


def _add_demo(sub) -> None:
    p = sub.add_parser(
        "demo", help="run the whole pipeline on a built-in synthetic foam specimen",
        description="Synthesize a foam pair with a known affine field (-1% along z, 0.5% shear, a "
                    "translation), correlate it and print the RMS nodal error against the truth.")
    p.add_argument("directory", nargs="?", default="chunkdic-demo", help="where to write (default ./chunkdic-demo)")
    p.add_argument("--size", type=int, default=96, help="edge of the synthetic scans, voxels")
    p.add_argument("--element-size", type=int, default=12, help="element edge, voxels")
    p.add_argument("--seed", type=int, default=1, help="seed of the synthetic texture")
    p.add_argument("--scheduler", default=None, help=SCHEDULER_HELP)
    p.add_argument("--overwrite", action="store_true", help="replace an earlier demo folder")
    p.set_defaults(func=cmd_demo)


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__
    from . import mechanics as _cli_mechanics
    from . import q4_commands as _cli_q4
    from . import report_commands as _cli_report
    from . import resolution_command as _cli_resolution
    from . import scan_commands as _cli_scan
    from . import series_command as _cli_series
    from . import synth_commands as _cli_synth
    from . import texture_command as _cli_texture
    from . import view_command as _cli_view

    parser = _Parser(prog="chunkdic", description="Out-of-core C8 digital volume correlation.",
                     formatter_class=_HelpFormatter)
    parser.add_argument("--version", action="version", version=f"chunkdic {__version__}")
    _verbosity(parser, 0)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _add_correlate(sub)
    _cli_scan.register(sub)
    _cli_synth.register(sub)
    _cli_report.register(sub)
    _cli_mechanics.register(sub)
    _cli_resolution.register(sub)
    _cli_texture.register(sub)
    _cli_q4.register(sub)
    _cli_series.register(sub)
    _cli_view.register(sub)
    _add_demo(sub)
    p = sub.add_parser("versions", help="print versions for bug reports",
                       description="Print the versions of Python, chunkdic and its dependencies, for bug reports.")
    p.set_defaults(func=lambda args: print(__import__("chunkdic").show_versions()) or 0)
    _polish(sub)
    return parser


def _verbosity(parser: argparse.ArgumentParser, default) -> None:
    """``-v`` / ``-q`` on ``parser`` (the last one given wins)."""
    parser.add_argument("-v", "--verbose", dest="verbosity", action="store_const", const=1, default=default,
                        help="log details")
    parser.add_argument("-q", "--quiet", dest="verbosity", action="store_const", const=-1, default=default,
                        help="no progress or summary on stderr: only errors, warnings and the results on stdout")


def _polish(sub) -> None:
    """Every subcommand: ``-v``/``-q`` also after its name, defaults shown in its help, a
    description (its one-line help when it has none)."""
    helps = {a.dest: a.help for a in sub._choices_actions}
    for name, p in sub.choices.items():
        # SUPPRESS: absent after the subcommand, the value given before it (or 0) stays
        _verbosity(p, argparse.SUPPRESS)
        p.formatter_class = _HelpFormatter
        if not p.description:
            p.description = (helps.get(name) or name)[:1].upper() + (helps.get(name) or name)[1:] + "."


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    say(f"chunkdic: warning: {message}")


#: file-system errors reported in one line (disk full, read-only, permissions, I/O)
_FS_ERRORS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG, errno.EIO}
#: errors of a path itself (an input, a mask, the scratch directory), and what to do about them
_PATH_ERRORS = {errno.ENAMETOOLONG: "a name longer than the file system's NAME_MAX (255 bytes) or a path longer "
                                    "than its PATH_MAX: use shorter names, or a shorter path (a link, cd)",
                errno.ELOOP: "it lies under a loop of symbolic links: choose another path"}


def _shown(path) -> str:
    """A path for an error line: its start and end when it is long."""
    text = os.fsdecode(path) if path is not None else "(a path)"
    return text if len(text) <= 120 else f"{text[:60]}…{text[-50:]}"


@contextlib.contextmanager
def _dask_logs(verbose: bool):
    """Dask's cluster logs (scheduler, nanny and worker lines of ``distributed``, ~50 lines
    for a ``local:2`` run) below WARNING during a command unless ``-v``: in this process's
    ``dask.config`` and in the environment that a LocalCluster's worker processes inherit.
    A level the user set (``DASK_LOGGING__DISTRIBUTED``, a Dask YAML file) is kept; both are
    restored afterwards (``main`` also runs inside other programs and tests)."""
    import dask.config

    key = "DASK_LOGGING__DISTRIBUTED"
    if verbose or key in os.environ or dask.config.get("logging.distributed", "info") != "info":
        yield
        return
    logger = logging.getLogger("distributed")
    level = logger.level
    os.environ[key] = "warning"
    try:
        with dask.config.set({"logging.distributed": "warning"}):
            logger.setLevel(logging.WARNING)  # distributed sets it from dask.config when imported
            yield
    finally:
        del os.environ[key]
        # distributed imported meanwhile would have set its default, INFO
        logger.setLevel(logging.INFO if level == logging.NOTSET and "distributed" in sys.modules else level)


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = {1: logging.INFO, 0: logging.WARNING, -1: logging.ERROR}[args.verbosity]
    logging.basicConfig(level=level, format="%(message)s")
    warnings.showwarning = _one_line_warning
    new_run()
    stderr, events_level = sys.stderr, event_log.level
    if args.verbosity < 0:
        sys.stderr = _QuietStderr(stderr)
    # every engine event reaches stderr through the command's progress callback (print_progress):
    # the engine's own log of them would print each line a second time under -v (restored after:
    # an API call later in the same process logs its events)
    event_log.setLevel(logging.CRITICAL + 1)
    try:
        with _dask_logs(args.verbosity > 0):
            return _dispatch(args)
    finally:
        sys.stderr = stderr
        event_log.setLevel(events_level)


def _check_cwd() -> None:
    """A working directory removed under the process (``cd d; rm -r ../d``): every relative
    path and ``os.getcwd()`` fail, and so would LocalCluster workers started in it; refused
    in one line before anything starts (the same wording as the output checks)."""
    try:
        os.getcwd()
    except FileNotFoundError:
        from ..io.outputrules import CWD_GONE

        raise InputError(CWD_GONE) from None


def _dispatch(args) -> int:
    try:
        _check_cwd()
        with judged_run(args) as done:
            return 0 if done else args.func(args)
    except InputError as exc:
        # whatever failed, a working directory removed during the run is why (its outputs went with it)
        say(f"chunkdic: error: {_cwd_gone() or (str(exc).splitlines()[0] if str(exc) else type(exc).__name__)}")
        return EXIT_BAD_INPUT
    except OSError as exc:
        if isinstance(exc, FileNotFoundError) and _cwd_gone():
            say(f"chunkdic: error: {_cwd_gone()}")
            return EXIT_BAD_INPUT
        if exc.errno in _PATH_ERRORS:  # a path no file system takes, met wherever it was first used
            say(f"chunkdic: error: {_shown(exc.filename)}: {exc.strerror} ({errno.errorcode[exc.errno]}): "
                + _PATH_ERRORS[exc.errno])
            return EXIT_BAD_INPUT
        if exc.errno not in _FS_ERRORS:
            raise
        # the outputs of the run were removed on the way out (chunkdic.io.outputs)
        where = f": {exc.filename}" if exc.filename else ""
        say(f"chunkdic: error: {exc.strerror or exc}{where}")
        return EXIT_BAD_INPUT
    except WorkerLostError as exc:  # no bad input: the cluster failed; the same command resumes
        say(f"chunkdic: error: {exc}")
        return EXIT_FAILED
    except KeyboardInterrupt:
        say("chunkdic: interrupted")
        return 130


def _cwd_gone() -> str | None:
    """The error line for a working directory removed during the run, or None while it exists."""
    try:
        os.getcwd()
    except FileNotFoundError:
        from ..io.outputrules import CWD_GONE

        return CWD_GONE.replace("(it was removed)", "(it was removed during the run)")
    return None


if __name__ == "__main__":
    sys.exit(main())
