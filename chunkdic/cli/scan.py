"""``chunkdic ingest`` and ``chunkdic pyramid``: thin command-line layer over the scan API."""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from ..errors import InputError
from ..scheduler import SCHEDULER_HELP, dask_scheduler
from .common import say


def register(subparsers) -> None:
    """Add the ``ingest`` and ``pyramid`` subcommands to an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        "ingest", help="convert a scan (TIFF slices/stack, raw, HDF5, npy) to a Zarr v3 scan group",
        description="Convert a scan to a Zarr v3 group with OME-NGFF 0.5 metadata, chunk by chunk. "
                    "SRC: folder of 2-D TIFF slices (natural order), 3-D TIFF, raw binary file "
                    "(with --shape and --dtype), file.h5:/path/to/dataset, .npy, or a Zarr array/group.",
    )
    p.add_argument("src", metavar="SRC")
    p.add_argument("out", metavar="OUT.zarr", help="scan group to create (missing parent directories are made)")
    p.add_argument("--voxel-size", metavar="V", help="voxel size: one number or Z,Y,X (default: from metadata)")
    p.add_argument("--unit", help="length unit of --voxel-size, e.g. micrometer (um), millimeter (mm)")
    p.add_argument("--chunks", type=int, metavar="N", help="Zarr chunk edge in voxels (default 128)")
    p.add_argument("--shape", metavar="Z,Y,X", help="raw input: array shape")
    p.add_argument("--dtype", help="raw input: uint8, uint16, float32 (also int16, uint32, int32, float64)")
    p.add_argument("--byte-order", default="little", choices=("little", "big"), help="raw input (default little)")
    p.add_argument("--offset", type=int, default=0, metavar="N", help="raw input: header bytes to skip")
    p.add_argument("--dataset", help="HDF5 dataset path (or write SRC as file.h5:/path/to/dataset)")
    p.add_argument("--levels", type=int, default=0, metavar="N",
                   help="also build pyramid levels 1..N (2 = the paper's 4^3 compression)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing OUT.zarr")
    p.add_argument("--scheduler", default=None, help=SCHEDULER_HELP + "; its workers must see SRC and OUT.zarr")
    p.set_defaults(func=run_ingest)

    q = subparsers.add_parser(
        "pyramid", help="add 2x2x2-sum pyramid levels 1..N to a scan group",
        description="Add levels 1..N (each the 2x2x2 sum of the level below, exact integer sums) to a "
                    "scan group; complete levels are kept unless --overwrite.",
    )
    q.add_argument("scan", metavar="SCAN.zarr")
    q.add_argument("--levels", type=int, required=True, metavar="N")
    q.add_argument("--overwrite", action="store_true", help="rebuild levels that are already complete")
    q.add_argument("--display", action="store_true",
                   help="also write SCAN.zarr/display: levels 1..N as means (sums / 8^s) for viewers, "
                        "one contrast window for every level (default: off)")
    q.add_argument("--scheduler", default=None, help=SCHEDULER_HELP + "; its workers must see SCAN.zarr")
    q.set_defaults(func=run_pyramid)


class _Printer:
    """Progress lines on stderr, every 10 %; ``header`` is printed with the first call, once
    the inputs and outputs have been checked (a refused run prints its error line only)."""

    def __init__(self, step: str, header: str | None = None):
        self.step, self.next, self.t0 = step, 0.1, time.perf_counter()
        self.header = header

    def __call__(self, frac: float) -> None:
        if self.header:
            say(self.header)
            self.header = None
        if frac + 1e-9 >= self.next:
            say(f"  {self.step}: {min(frac, 1.0):4.0%}  ({time.perf_counter() - self.t0:.1f} s)")
            while self.next <= frac + 1e-9:
                self.next += 0.1


def _du(path: Path) -> int:
    total = 0
    for root, _, files in os.walk(path):
        for f in files:
            try:
                total += os.path.getsize(os.path.join(root, f))
            except OSError:
                pass
    return total


def _summary(scan, seconds: float, nbytes_in: int, what: str) -> None:
    levels = scan.stored_levels()
    shapes = ", ".join(f"{s}:{'x'.join(map(str, scan.shape(s)))} {scan.dtype(s)}" for s in levels)
    size = _du(Path(scan.path)) if scan.path else 0
    vs = f"{scan.voxel_size} {scan.unit or ''}".strip() if scan.voxel_size else "none"
    say(f"{scan.path}: levels {shapes}; voxel size {vs}; {size / 1e6:.1f} MB on disk (all levels); "
         f"{what} {nbytes_in / 1e6:.1f} MB in {seconds:.1f} s "
         f"= {nbytes_in / 1e6 / max(seconds, 1e-9):.1f} MB/s")


def run_ingest(args: argparse.Namespace) -> int:
    """``chunkdic ingest``: returns the exit code (errors raise :class:`InputError`)."""
    if args.levels < 0:
        raise InputError(f"--levels must be >= 0, got {args.levels}")
    if args.chunks is not None and args.chunks < 1:
        raise InputError(f"--chunks must be a positive integer, got {args.chunks}")
    if args.offset < 0:
        raise InputError(f"--offset must be >= 0, got {args.offset}")
    with dask_scheduler(args.scheduler, announce=say):
        return _ingest(args)


def _ingest(args: argparse.Namespace) -> int:
    from ..io.formats.ingest import ingest

    levels = f" and pyramid levels 1..{args.levels}" if args.levels else ""
    t0 = time.perf_counter()
    # level 0 and the pyramid are written together, in a staged copy renamed into place at
    # the end (chunkdic.io.outputs): all or nothing
    scan = ingest(args.src, args.out, voxel_size=args.voxel_size, unit=args.unit, chunks=args.chunks,
                  shape=args.shape, dtype=args.dtype, byte_order=args.byte_order, offset=args.offset,
                  dataset=args.dataset, overwrite=args.overwrite, levels=args.levels,
                  progress=_Printer("ingest" + (" + pyramid" if args.levels else ""),
                                    header=f"ingest {args.src} -> {args.out}{levels}"))
    _summary(scan, time.perf_counter() - t0, _nbytes(scan, 0), "read")
    return 0


def run_pyramid(args: argparse.Namespace) -> int:
    """``chunkdic pyramid``: returns the exit code (errors raise :class:`InputError`)."""
    from ..io.pyramid import build_pyramid
    from ..io.scan import open_scan

    before = open_scan(args.scan).stored_levels() if Path(args.scan).exists() else []
    header = (f"pyramid {args.scan}: levels 1..{args.levels}"
              + (f" (complete already: {[s for s in before if s]})" if len(before) > 1 and not args.overwrite else ""))
    with dask_scheduler(args.scheduler, announce=say):
        t0 = time.perf_counter()
        scan = build_pyramid(args.scan, args.levels, overwrite=args.overwrite,
                             progress=_Printer("pyramid", header=header), display=args.display)
        if args.display:
            shown = [s for s in scan.stored_levels() if s > 0]
            say(f"{args.scan}/display: levels {shown} as means (sums / 8^s), one contrast window")
    _summary(scan, time.perf_counter() - t0, _nbytes(scan, 0), "pyramid from level 0 of")
    return 0


def _nbytes(scan, s: int) -> int:
    n = 1
    for v in scan.shape(s):
        n *= v
    return n * scan.dtype(s).itemsize
