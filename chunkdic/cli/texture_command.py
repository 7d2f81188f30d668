"""``chunkdic texture``: what a reference scan's texture supports, before correlating."""

from __future__ import annotations

import argparse
import json

from ..scheduler import SCHEDULER_HELP


def register(subparsers) -> None:
    """Add ``texture`` to an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        "texture", help="autocorrelation length, weakly textured elements and predicted noise of a reference scan",
        description="Sample boxes of the reference REF (never the whole scan) and print: the autocorrelation "
                    "length per axis (lag of 1/e), for each element size the fraction of weakly textured "
                    "elements (the texture's mean squared gradient, after the engine's low-pass, below the "
                    "noise's) and the displacement noise the engine's model predicts at the nodes without "
                    "regularisation, and the smallest element size the texture supports for the noise "
                    "(docs/engine.md, \"Know your texture\").")
    p.add_argument("scan", metavar="REF")
    p.add_argument("-l", "--element-sizes", type=int, nargs="+", default=[8, 12, 16], metavar="ELL",
                   help="element edges, voxels of --level (default 8 12 16)")
    p.add_argument("--noise", type=float, default=None,
                   help="std of each scan's noise, grey levels of REF (default: estimated from REF, the robust "
                        "spread of its second differences)")
    p.add_argument("--smoothing", type=float, default=1.0,
                   help="the correlation's Gaussian low-pass, voxels (correlate --smoothing; default 1)")
    p.add_argument("--level", type=int, default=0, help="pyramid level measured (default 0)")
    p.add_argument("--box", type=int, default=128, help="edge of the sampled boxes, voxels (default 128; 8 at most)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--scheduler", default=None, help=SCHEDULER_HELP)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``chunkdic texture``; returns the exit code."""
    from ..analysis.texture import texture

    report = texture(args.scan, args.element_sizes, noise=args.noise, smoothing=args.smoothing, level=args.level,
                     scheduler=args.scheduler, edge=args.box)
    print(json.dumps(report.to_json(), indent=1) if args.json else "\n".join(report.lines()))
    return 0
