"""``chunkdic series``: a loading series, thin over :func:`chunkdic.series`.

Progress goes to stderr (the correlations' lines, one ``series:`` line per step), the
summary table to stderr and the series path to stdout. Bad input raises
:class:`chunkdic.errors.InputError` (one line, exit 2 in ``chunkdic.cli.app``).
"""

from __future__ import annotations

import argparse
import time

from .common import (
    add_engine_options,
    add_length_options,
    engine_options,
    length_options,
    print_progress,
    say,
)


def register(subparsers) -> None:
    """Add ``series`` to ``subparsers``."""
    p = subparsers.add_parser(
        "series", help="correlate a loading series: each scan against the previous one and the first",
        description="Scans in loading order, the reference first. Each scan is correlated against the previous "
                    "one (incremental, started from the previous increment, or from no motion or the rigid "
                    "translation when either matches better) and against the first (cumulative, "
                    "started from the previous cumulative field composed with the new increment, "
                    "u_0k(X) = u_0,k-1(X) + u_k-1,k(X + u_0,k-1(X))). Every step is a result group inside the "
                    "series output (steps/001-incremental, composed/002, steps/002-cumulative, ...). An "
                    "interrupted series resumes when the same command runs again: finished steps are skipped. "
                    "Exit 0 when every correlation converged, 1 otherwise, 2 on bad input.")
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scans in loading order (Zarr groups/arrays, .npy)")
    p.add_argument("-o", "--output", required=True, help="series path (Zarr v3 group)")
    add_length_options(p, every_step=" (the same for every step)")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--incremental", dest="mode", action="store_const", const="incremental",
                       help="only each scan against the previous one (cumulative fields composed from them)")
    which.add_argument("--cumulative", dest="mode", action="store_const", const="cumulative",
                       help="only each scan against the first (each started from the previous cumulative field)")
    p.set_defaults(mode="both")
    add_engine_options(
        p, coarsest="coarsest pyramid level (default: automatic for the first step; later steps start from the "
                    "previous field on --level)",
        regularization_length="its length, voxels of level 0 (default: chosen from the data at every step)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing series (one chunkdic wrote)")
    p.set_defaults(func=run_series)


def run_series(args: argparse.Namespace) -> int:
    from ..analysis.loadseries import series

    element_size, roi = length_options(args, args.scans[0])
    t0 = time.perf_counter()
    res = series(args.scans, args.output, mode=args.mode, element_size=element_size, roi=roi,
                 overwrite=args.overwrite, progress=print_progress, **engine_options(args))
    say(res.table())
    say(f"series of {len(args.scans)} scans in {time.perf_counter() - t0:.1f} s; mean displacements in voxels of "
        f"level {args.level}, eps_zz without the outer layer of elements (table in the group attributes)")
    print(args.output)
    converged = all(r["status"] in ("converged", "composed") for r in res.rows)
    return 0 if converged else 1
