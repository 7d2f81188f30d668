"""``chunkdic`` command line: a thin layer over the Python API.

Bad input gets one line on stderr and exit status 2, with nothing written.
"""

from __future__ import annotations

import argparse
import errno
import logging
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from .errors import InputError
from .scheduler import SCHEDULER_HELP

EXIT_BAD_INPUT = 2


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2, as for every other bad input
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _format_event(event: dict) -> str | None:
    stage = event["stage"]
    if stage == "start":
        dash = ""  # the runner's description already names its dashboard
        roi = ",".join(f"{a}:{b}" for a, b in event["roi"])
        nodes = "x".join(str(n) for n in event["nodes"])
        line = f"running on {event['scheduler']}{dash}; levels {event['levels']}; ROI {roi} (level voxels); {nodes} nodes"
        if event.get("requested_roi"):
            asked = ",".join(f"{a}:{b}" for a, b in event["requested_roi"])
            line += f" (requested {asked} in level-0 voxels, trimmed to whole elements)"
        return line
    if stage == "matrix":
        rate = event["voxels"] / max(event["seconds"], 1e-9) / 1e6
        return f"level {event['level']}: M built over {event['blocks']} blocks in {event['seconds']:.1f} s ({rate:.1f} Mvoxel/s)"
    if stage == "rigid":
        t = ", ".join(f"{v:+.3f}" for v in event["translation"])
        return f"level {event['level']} rigid {event['iteration']:2d}: gap {100 * event['gap']:.3f}%  max|da| {event['max_delta']:.2e}  t=({t})"
    if stage == "gaps":
        return f"level {event['level']}: initial gap {100 * event['initial_gap']:.3f}%, after rigid translation {100 * event['rigid_gap']:.3f}%"
    if stage == "iteration":
        d = event.get("status", "final") if event["max_delta"] is None else f"{event['max_delta']:.2e}"
        return (
            f"level {event['level']} iter {event['iteration']:2d}: gap {100 * event['gap']:.3f}%  max|da| {d}"
            f"  excluded {event['excluded']}  ({event['seconds']:.1f} s)"
        )
    if stage == "blocks":
        return (f"  level {event['level']} {event['label']}: {event['done']}/{event['total']} blocks, "
                f"{event['rate'] / 1e6:.1f} Mvoxel/s, ETA {event['eta']:.0f} s")
    if stage == "regularization":
        corner = event.get("l_curve_length")
        corner = f"; L-curve corner {corner:.1f}" if corner is not None and math.isfinite(corner) else ""
        return (f"level {event['level']}: {event['kind']} regularisation length {event['length']:.1f} voxels "
                f"(chosen from the data{corner}; noise correlation factor {event['kappa']:.1f})")
    if stage == "resume":
        return f"resuming the interrupted run from its checkpoint: level {event['level']}, iteration {event['iteration']}"
    if stage == "level":
        return f"level {event['level']}: {event['status']}, gap {100 * event['gap']:.3f}% ({event['seconds']:.1f} s)"
    return None


def _print_progress(event: dict) -> None:
    line = _format_event(event)
    if line:
        _say(line)


def _summary(result, seconds: float) -> str:
    info = result.info
    u = result.displacement
    mean = ", ".join(f"<U{c}> {np.nanmean(u[i]):+.4f}" for i, c in enumerate("zyx"))
    roi = ",".join(f"{a}:{b}" for a, b in info["roi"])
    line = (
        f"{info['status']}: final gap {100 * info['final_gap']:.3f}% (initial {100 * info['initial_gap']:.3f}%, "
        f"rigid {100 * info['rigid_gap']:.3f}%); {mean} voxels of level {info['level']}; "
        f"ROI {roi}; excluded voxels {info['excluded_voxels']}; {seconds:.1f} s"
    )
    if result.uncertainty is not None and np.isfinite(result.uncertainty).any():
        line += f"; median nodal uncertainty {np.nanmedian(result.uncertainty):.4f} voxel"
    missing = info.get("nodes_without_data", 0) + info.get("masked_nodes", 0)
    if missing:
        line += f"; {missing} nodes not measured (NaN)"
    if info["status"] == "excluded":
        line += (f"\n  excluded: {100 * info.get('excluded_fraction', 0):.0f}% of the ROI maps outside the deformed "
                 "scan; the rest converged, but so large a share left out is not called converged")
    elif info["status"] == "stalled":
        line += "\n  stalled: neither the gap nor the increments improved for 4 passes; the best field is kept"
    return line


def cmd_correlate(args) -> int:
    from .engine import correlate

    t0 = time.perf_counter()
    result = correlate(
        args.ref, args.deformed, element_size=args.element_size, roi=args.roi, level=args.level,
        coarsest=args.coarsest, interpolation=args.interpolation, tolerance=args.tolerance,
        max_iterations=args.max_iterations, block_elements=args.block_elements,
        smoothing=args.smoothing, grey=args.grey_level, regularization=args.regularization,
        regularization_length=args.regularization_length, mask=args.mask,
        scheduler=args.scheduler, output=args.output, overwrite=args.overwrite, progress=_print_progress,
    )
    _say(_summary(result, time.perf_counter() - t0))
    print(args.output)
    return 0 if result.converged else 1


def cmd_demo(args) -> int:
    """Synthesize a foam pair with a known field, correlate it, compare with the truth."""
    from .inputs import number
    from .outputs import Outputs
    from .scheduler import check_scheduler

    number(args.size, "--size", minimum=16, integer=True)
    number(args.element_size, "--element-size", minimum=2, maximum=args.size // 3, integer=True)
    number(args.seed, "--seed", minimum=0, integer=True)
    check_scheduler(args.scheduler)
    plan = Outputs(overwrite=args.overwrite)
    plan.add(args.directory, "demo")
    with plan:  # a failure removes what the demo wrote
        return _demo(args)


def _demo(args) -> int:
    from . import synthetic
    from .engine import correlate

    out = Path(args.directory)
    result_path = out / "result.zarr"
    field = synthetic.Affine(
        matrix=((-0.01, 0.0, 0.005), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
        center=tuple(n / 2 for n in (args.size,) * 3),
        translation=(2.3, -1.4, 0.7),
    )
    _say(f"synthesizing a {args.size}^3 foam pair in {out} (affine field: -1% along z, 0.5% shear, translation)")
    paths = synthetic.synthesize(out, (args.size,) * 3, field=field, seed=args.seed)
    t0 = time.perf_counter()
    result = correlate(paths["reference"], paths["deformed"], element_size=args.element_size,
                       scheduler=args.scheduler, output=result_path, progress=_print_progress)
    _say(_summary(result, time.perf_counter() - t0))
    truth = field.displacement(*result.node_coords)
    err = result.displacement - truth
    rms = np.sqrt((err**2).mean(axis=(1, 2, 3)))
    _say("RMS nodal error vs the known field: " + ", ".join(f"U{c} {v:.4f}" for c, v in zip("zyx", rms)) + " voxel")
    print(result_path)
    return 0 if result.converged else 1


def _add_correlate(sub) -> None:
    p = sub.add_parser("correlate", help="measure the displacement field between two scans (C8-DIC)")
    p.add_argument("ref", help="reference scan: Zarr group/array, .npy")
    p.add_argument("deformed", help="deformed scan: Zarr group/array, .npy")
    p.add_argument("-o", "--output", required=True, help="result path (Zarr v3 group)")
    p.add_argument("--element-size", "-l", type=int, required=True, help="element edge, voxels of --level")
    p.add_argument("--roi", help="z0:z1,y0:y1,x0:x1 in level-0 voxels (default: centred box)")
    p.add_argument("--level", type=int, default=0, help="pyramid level correlated last (default 0)")
    p.add_argument("--coarsest", type=int, default=None, help="coarsest pyramid level (default: automatic)")
    p.add_argument("--interpolation", choices=("cubic", "linear"), default="cubic",
                   help="interpolation of the deformed scan (default cubic B-spline; linear: the paper's)")
    p.add_argument("--smoothing", type=float, default=1.0,
                   help="Gaussian low-pass of both scans, voxels of each level (default 1; 0: the paper's raw images)")
    p.add_argument("--grey-level", choices=("none", "global", "drift", "element"), default="drift",
                   help="brightness model between the scans (default drift: a gain, a linear drift and an offset "
                        "per element; none: the paper's plain residual)")
    p.add_argument("--regularization", choices=("none", "tikhonov", "equilibrium-gap"), default="tikhonov",
                   help="penalty on the field's short wavelengths (default tikhonov, on its curvature)")
    p.add_argument("--regularization-length", type=float, default=None, metavar="L",
                   help="its length, voxels of level 0 (default: chosen from the data and printed)")
    p.add_argument("--mask", default=None, help="specimen mask of the reference's shape (non-zero = material)")
    p.add_argument("--tolerance", type=float, default=1e-3, help="max |da| for convergence, voxels")
    p.add_argument("--max-iterations", type=int, default=30)
    p.add_argument("--block-elements", type=int, default=None, help="elements per block side")
    p.add_argument("--scheduler", default=None, help=SCHEDULER_HELP)
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=cmd_correlate)


def _add_demo(sub) -> None:
    p = sub.add_parser("demo", help="run the whole pipeline on a built-in synthetic foam specimen")
    p.add_argument("directory", nargs="?", default="chunkdic-demo", help="where to write (default ./chunkdic-demo)")
    p.add_argument("--size", type=int, default=96, help="edge of the synthetic scans, voxels")
    p.add_argument("--element-size", type=int, default=12)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--scheduler", default=None, help=SCHEDULER_HELP)
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=cmd_demo)


def build_parser() -> argparse.ArgumentParser:
    from . import _cli_q4, _cli_report, _cli_scan, _cli_synth

    parser = _Parser(prog="chunkdic", description="Out-of-core C8 digital volume correlation.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log details")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _add_correlate(sub)
    _cli_scan.register(sub)
    _cli_synth.register(sub)
    _cli_report.register(sub)
    _cli_q4.register(sub)
    _add_demo(sub)
    p = sub.add_parser("versions", help="print versions for bug reports")
    p.set_defaults(func=lambda args: print(__import__("chunkdic").show_versions()) or 0)
    return parser


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    _say(f"chunkdic: warning: {message}")


#: file-system errors reported in one line (disk full, read-only, permissions, I/O)
_FS_ERRORS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG, errno.EIO}


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s")
    warnings.showwarning = _one_line_warning
    try:
        return args.func(args)
    except InputError as exc:
        _say(f"chunkdic: error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}")
        return EXIT_BAD_INPUT
    except OSError as exc:
        if exc.errno not in _FS_ERRORS:
            raise
        # the outputs of the run were removed on the way out (chunkdic.outputs)
        where = f": {exc.filename}" if exc.filename else ""
        _say(f"chunkdic: error: {exc.strerror or exc}{where}")
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        _say("chunkdic: interrupted")
        return 130


if __name__ == "__main__":
    sys.exit(main())
