"""``chunkdic correlate2d | cutcheck``: 2-D Q4-DIC and the paper's cut check, thin over the API.

Each subcommand function takes the parsed ``argparse`` namespace and returns the exit code;
bad input raises :class:`chunkdic.errors.InputError` (one line, exit 2 in ``chunkdic.cli.app``).
Progress goes to stderr, results to stdout.
"""

from __future__ import annotations

import argparse
import json
import math
import time

from .common import add_figure_options, say


def register(subparsers) -> None:
    """Add ``correlate2d`` and ``cutcheck`` to ``subparsers``."""
    p = subparsers.add_parser(
        "correlate2d", help="2-D global DIC (bilinear Q4 elements) between two images",
        description="Multiscale Q4-DIC between two 2-D images (.npy, TIFF, PNG, ...): the engine's 2-D "
                    "sibling (same conventions: axes (y, x), pixel centres, f(X) = g(X + u(X))). Prints a "
                    "summary of the nodal displacement; nothing is written.")
    p.add_argument("ref", metavar="A", help="reference image")
    p.add_argument("deformed", metavar="B", help="deformed image")
    p.add_argument("--element-size", "-l", type=int, required=True, help="element edge, pixels")
    p.add_argument("--roi", help="y0:y1,x0:x1 in pixels (default: the image less max(2, ell/4) pixels per side)")
    p.add_argument("--interpolation", choices=("cubic", "linear"), default="cubic",
                   help="interpolation of the deformed image (default cubic B-spline)")
    p.add_argument("--smoothing", type=float, default=0.0,
                   help="Gaussian low-pass of both images, pixels of each level (default 0)")
    p.add_argument("--coarsest", type=int, default=None, help="coarsest pyramid level (default: automatic)")
    p.add_argument("--tolerance", type=float, default=1e-3, help="max |da| for convergence, pixels (default 1e-3)")
    p.add_argument("--max-iterations", type=int, default=30, help="per level (default 30)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run_correlate2d)

    p = subparsers.add_parser(
        "cutcheck", help="the paper's check of a result: 2-D Q4-DIC of mid-plane cuts (section 5.3)",
        description="2-D Q4-DIC of the reference against the corrected deformed scan on the three ROI "
                    "mid-planes (normal to z, y, x), with the result's element size. Per cut: mean, standard "
                    "deviation and maximum of the 2-D displacement (pixels) and its correlation length. A "
                    "cut passes when its mean is below max(0.02 px, 3 x the predicted uncertainty of the mean), "
                    "its std below max(0.02 px, 2 x the 2-D correlation's noise floor on that cut), both "
                    "floors from the 3-D run's noise estimate (0.02 px, the paper's bound, without one), and "
                    "its correlation length below one element; exit 0 when every cut passes, otherwise "
                    "exit 1. Writes cutcheck.png (or .pdf, .svg: --format) and cutcheck.json into DIR.")
    p.add_argument("result", metavar="RESULT.zarr")
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="directory for the figure and cutcheck.json")
    p.add_argument("--ref", help="reference scan (default: the path recorded in the result)")
    p.add_argument("--deformed", help="deformed scan (default: the path recorded in the result)")
    p.add_argument("--scheduler", default=None,
                   help="where the cut planes are computed: threads (default), local[:N], or tcp://host:port")
    p.add_argument("--json", action="store_true", help="print one JSON object per cut (a list)")
    add_figure_options(p)
    p.add_argument("--overwrite", action="store_true", help="replace the files of an earlier cut check in DIR")
    p.set_defaults(func=run_cutcheck)


def _fmt(v: float, spec: str = ".4f") -> str:
    return format(v, spec) if math.isfinite(v) else "nan"


def run_correlate2d(args: argparse.Namespace) -> int:
    from ..analysis.q4 import correlate2d
    from ..analysis.q4mesh import read_image
    from ..inputs import number

    number(args.element_size, "--element-size", minimum=2, integer=True)  # before reading anything
    f, g = read_image(args.ref), read_image(args.deformed)
    t0 = time.perf_counter()
    res = correlate2d(f, g, element_size=args.element_size, roi=args.roi, coarsest=args.coarsest,
                      interpolation=args.interpolation, smoothing=args.smoothing, tolerance=args.tolerance,
                      max_iterations=args.max_iterations)
    s = res.summary()
    if args.json:
        print(json.dumps(s, indent=2))
    else:
        roi = ",".join(f"{a}:{b}" for a, b in s["roi"])
        print(f"{s['status']}: final gap {100 * s['gap']:.3f}% (initial {100 * s['initial_gap']:.3f}%); "
              f"<Uy> {s['mean']['y']:+.4f} <Ux> {s['mean']['x']:+.4f} pixel (std {_fmt(s['std']['y'])}, "
              f"{_fmt(s['std']['x'])}); {'x'.join(map(str, s['nodes']))} nodes of ell = {s['element_size']}, "
              f"ROI {roi}, levels {s['levels']}; excluded pixels {s['excluded_pixels']}; "
              f"{time.perf_counter() - t0:.2f} s")
    return 0 if res.converged else 1


def _rule(cuts, threshold: float) -> str:
    """The bounds the verdict applied, in words and numbers (per cut, z y x)."""
    from ..analysis.crosscheck import K_MEAN, K_NOISE

    if not any(math.isfinite(c.floor) for c in cuts):
        return f"mean and std below {threshold} pixel: the paper's bound, the result has no noise estimate"
    means = "/".join(f"{c.bound_mean:.3g}" for c in cuts)
    stds = "/".join(f"{c.bound:.3g}" for c in cuts)
    return (f"mean below max({threshold}, {K_MEAN:g} x its predicted uncertainty) = {means} pixel and std below "
            f"max({threshold}, {K_NOISE:g} x the noise floor) = {stds} pixel on cuts "
            f"{'/'.join(c.axis for c in cuts)}")


def run_cutcheck(args: argparse.Namespace) -> int:
    from ..analysis.crosscheck import THRESHOLD, cutcheck

    t0 = time.perf_counter()
    cuts = cutcheck(args.result, args.output, ref=args.ref, deformed=args.deformed, scheduler=args.scheduler,
                    overwrite=args.overwrite, progress=say, fmt=args.fmt, dpi=args.dpi)
    if args.json:
        print(json.dumps([c.as_dict() for c in cuts], indent=2))
    else:
        print("cut  index   mean     std      max      corr. length  2-D status   verdict (pixels)")
        for c in cuts:
            print(f"{c.axis:>3}  {c.index:5d}  {_fmt(c.mean)}  {_fmt(c.std)}  {_fmt(c.max)}  {_fmt(c.correlation_length, '10.1f')}"
                  f"    {c.status:<11}  {'ok' if c.passed else 'FAILED'}")
    say(f"cut check: {'passed' if all(c.passed for c in cuts) else 'FAILED'} ({_rule(cuts, THRESHOLD)}, "
        f"correlation length below one element, on every cut; {time.perf_counter() - t0:.1f} s)")
    return 0 if all(c.passed for c in cuts) else 1
