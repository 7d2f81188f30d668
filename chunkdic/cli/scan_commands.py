"""``chunkdic ingest`` and ``chunkdic pyramid``: thin command-line layer over the scan API."""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from ..errors import InputError
from ..scheduler import SCHEDULER_HELP, dask_scheduler
from .common import Progress, say, voxel_size_option


def register(subparsers) -> None:
    """Add the ``ingest``, ``pyramid`` and ``mask`` subcommands to an ``argparse`` subparsers object."""
    m = subparsers.add_parser(
        "mask", help="a specimen mask of a scan (threshold, holes filled, largest component), for --mask and napari",
        description="Material = SCAN > threshold (Otsu's by default, from the histogram accumulated chunk by chunk), "
                    "optionally inside --cylinder or --box, holes of every z-slice filled, optionally only the "
                    "largest connected component; written chunk by chunk as an OME-NGFF labels image (1 = "
                    "material) on the scan's grid: napari shows it as a Labels layer, correlate --mask reads it.")
    m.add_argument("scan", metavar="SCAN", help="the scan (Zarr, .npy, TIFF file or folder, HDF5 file.h5[:/dataset])")
    m.add_argument("-o", "--output", required=True, metavar="MASK.zarr", help="labels image to create")
    m.add_argument("--threshold", default="otsu", metavar="otsu|none|VALUE",
                   help="material is SCAN > VALUE (default otsu; none: every voxel, with --cylinder/--box)")
    m.add_argument("--no-fill", dest="fill_holes", action="store_false",
                   help="keep the holes (default: fill the holes of every z-slice)")
    m.add_argument("--largest", action="store_true", help="keep only the largest connected component")
    m.add_argument("--cylinder", metavar="CY,CX,R", help="only inside this cylinder along z (voxels)")
    m.add_argument("--box", metavar="Z0:Z1,Y0:Y1,X0:X1", help="only inside this box (voxels)")
    m.add_argument("--scheduler", default=None, help=SCHEDULER_HELP)
    m.add_argument("--overwrite", action="store_true", help="replace a mask that chunkdic wrote")
    m.set_defaults(func=run_mask)

    p = subparsers.add_parser(
        "ingest", help="convert a scan (TIFF slices/stack, raw, HDF5, npy) to a Zarr v3 scan group",
        description="Convert a scan to a Zarr v3 group with OME-NGFF 0.5 metadata, chunk by chunk. "
                    "SRC: folder of 2-D TIFF slices (natural order), 3-D TIFF, raw binary file "
                    "(with --shape and --dtype), file.h5:/path/to/dataset, .npy, or a Zarr array/group.",
    )
    p.add_argument("src", metavar="SRC")
    p.add_argument("out", metavar="OUT.zarr", help="scan group to create (missing parent directories are made)")
    p.add_argument("--voxel-size", metavar="V",
                   help="voxel size with its unit: 6.5um, or one number or Z,Y,X with --unit (default: from metadata)")
    p.add_argument("--unit", "--voxel-unit", dest="unit",
                   help="length unit of --voxel-size, e.g. micrometer (um), millimeter (mm); required with a bare "
                        "--voxel-size (a unit is never guessed)")
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
    args.voxel_size, args.unit = voxel_size_option(args.voxel_size, args.unit)
    with dask_scheduler(args.scheduler, announce=say):
        return _ingest(args)


def _ingest(args: argparse.Namespace) -> int:
    from ..io.formats.ingest import ingest

    levels = f" and pyramid levels 1..{args.levels}" if args.levels else ""
    t0 = time.perf_counter()
    # level 0 and the pyramid are written together, in a staged copy renamed into place at
    # the end (chunkdic.io.outputs): all or nothing
    progress = Progress("ingest" + (" + pyramid" if args.levels else ""), header=f"ingest {args.src} -> {args.out}{levels}")
    scan = ingest(args.src, args.out, voxel_size=args.voxel_size, unit=args.unit, chunks=args.chunks,
                  shape=args.shape, dtype=args.dtype, byte_order=args.byte_order, offset=args.offset,
                  dataset=args.dataset, overwrite=args.overwrite, levels=args.levels, progress=progress)
    progress.done()
    _summary(scan, time.perf_counter() - t0, _nbytes(scan, 0), "read")
    return 0


def run_mask(args: argparse.Namespace) -> int:
    """``chunkdic mask``: the mask's path on stdout, what it holds on stderr."""
    from ..io.masking import make_mask

    out = make_mask(args.scan, args.output, threshold=args.threshold, fill_holes=args.fill_holes,
                    largest=args.largest, cylinder=args.cylinder, box=args.box, scheduler=args.scheduler,
                    overwrite=args.overwrite, progress=say)
    thr = "every voxel" if out["threshold"] is None else f"threshold {out['threshold']:g}"
    say(f"{args.output}: {out['material']} material voxels ({100 * out['fraction']:.1f} %), {thr}; "
        f"{out['seconds']:.1f} s")
    print(args.output)
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
        progress = Progress("pyramid", header=header)
        scan = build_pyramid(args.scan, args.levels, overwrite=args.overwrite, progress=progress,
                             display=args.display)
        progress.done()
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
