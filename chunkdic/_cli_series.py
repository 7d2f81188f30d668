"""``chunkdic series``: a loading series, thin over :func:`chunkdic.series`.

Progress goes to stderr (the correlations' lines, one ``series:`` line per step), the
summary table to stderr and the series path to stdout. Bad input raises
:class:`chunkdic.errors.InputError` (one line, exit 2 in ``chunkdic.cli``).
"""

from __future__ import annotations

import argparse
import time

from ._cli_common import print_progress, say
from .scheduler import SCHEDULER_HELP


def register(subparsers) -> None:
    """Add ``series`` to ``subparsers``."""
    p = subparsers.add_parser(
        "series", help="correlate a loading series: each scan against the previous one and the first",
        description="Scans in loading order, the reference first. Each scan is correlated against the previous "
                    "one (incremental, started from the previous increment) and against the first (cumulative, "
                    "started from the previous cumulative field composed with the new increment, "
                    "u_0k(X) = u_0,k-1(X) + u_k-1,k(X + u_0,k-1(X))). Every step is a result group inside the "
                    "series output (steps/001-incremental, composed/002, steps/002-cumulative, ...). An "
                    "interrupted series resumes when the same command runs again: finished steps are skipped. "
                    "Exit 0 when every correlation converged, 1 otherwise, 2 on bad input.")
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scans in loading order (Zarr groups/arrays, .npy)")
    p.add_argument("-o", "--output", required=True, help="series path (Zarr v3 group)")
    p.add_argument("--element-size", "-l", type=int, required=True, metavar="ELL",
                   help="element edge, voxels of --level (the same for every step)")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--incremental", dest="mode", action="store_const", const="incremental",
                       help="only each scan against the previous one (cumulative fields composed from them)")
    which.add_argument("--cumulative", dest="mode", action="store_const", const="cumulative",
                       help="only each scan against the first (each started from the previous cumulative field)")
    p.set_defaults(mode="both")
    p.add_argument("--roi", help="z0:z1,y0:y1,x0:x1 in level-0 voxels, the same for every step (default: centred box)")
    p.add_argument("--level", type=int, default=0, help="pyramid level correlated last")
    p.add_argument("--coarsest", type=int, default=None,
                   help="coarsest pyramid level (default: automatic for the first step; later steps start "
                        "from the previous field on --level)")
    p.add_argument("--interpolation", choices=("cubic", "linear"), default="cubic",
                   help="interpolation of the deformed scan")
    p.add_argument("--smoothing", type=float, default=1.0, help="Gaussian low-pass of both scans, voxels")
    p.add_argument("--grey-level", choices=("none", "global", "drift", "element"), default="drift",
                   help="brightness model between the scans")
    p.add_argument("--regularization", choices=("none", "tikhonov", "equilibrium-gap"), default="tikhonov",
                   help="penalty on the field's short wavelengths")
    p.add_argument("--regularization-length", type=float, default=None, metavar="L",
                   help="its length, voxels of level 0 (default: chosen from the data at every step)")
    p.add_argument("--mask", default=None, help="specimen mask of the reference's shape (non-zero = material)")
    p.add_argument("--tolerance", type=float, default=1e-3, help="max |da| for convergence, voxels")
    p.add_argument("--max-iterations", type=int, default=30, help="Gauss-Newton iterations per level at most")
    p.add_argument("--block-elements", type=int, default=None,
                   help="elements per block side (default: automatic)")
    p.add_argument("--scheduler", default=None, help=SCHEDULER_HELP)
    p.add_argument("--overwrite", action="store_true", help="replace an existing series (one chunkdic wrote)")
    p.set_defaults(func=run_series)


def run_series(args: argparse.Namespace) -> int:
    from .loadseries import series

    t0 = time.perf_counter()
    res = series(args.scans, args.output, mode=args.mode, element_size=args.element_size, roi=args.roi,
                 level=args.level, coarsest=args.coarsest, interpolation=args.interpolation,
                 smoothing=args.smoothing, grey=args.grey_level, regularization=args.regularization,
                 regularization_length=args.regularization_length, tolerance=args.tolerance,
                 max_iterations=args.max_iterations, block_elements=args.block_elements, mask=args.mask,
                 scheduler=args.scheduler, overwrite=args.overwrite, progress=print_progress)
    say(res.table())
    say(f"series of {len(args.scans)} scans in {time.perf_counter() - t0:.1f} s; mean displacements in voxels of "
        f"level {args.level}, eps_zz without the outer layer of elements (table in the group attributes)")
    print(args.output)
    converged = all(r["status"] in ("converged", "composed") for r in res.rows)
    return 0 if converged else 1
