"""``chunkdic resolution``: noise, spatial resolution l10 % and MEI of a setting, on a scan's texture."""

from __future__ import annotations

import argparse
import time

from ..errors import InputError
from .common import add_engine_options, engine_options, format_event, say


def register(subparsers) -> None:
    """Add ``resolution`` to an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        "resolution", help="noise, spatial resolution l10 %% and MEI of a correlation setting on a scan's texture",
        description="From the reference scan REF, write a translated pair (Fourier shift) and a 3-D star "
                    "(Ux = A sin(2 pi (z - zc) / period(y)), period rising across y), each scan with its "
                    "own independent noise, correlate both with the given settings for each element size, "
                    "and report the noise n (sigma of the translated pair, pooled over components), the "
                    "spatial resolution l10 %% (the period at which a smooth fit of measured/imposed "
                    "amplitude along the star first rises through 0.9, DIC Challenge 2.0), MEI = n l10 %% "
                    "and n l10 %%^1.5. Writes resolution.csv/.json/.md into DIR (docs/engine.md).")
    p.add_argument("scan", metavar="REF")
    p.add_argument("--element-sizes", "-l", type=int, nargs="+", required=True, metavar="ELL",
                   help="element edges, voxels (one star and one translated pair each)")
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="output directory")
    p.add_argument("--noise", type=float, default=0.02,
                   help="std of the noise added independently to each scan, fraction of the texture's "
                        "contrast (twice the reference's grey-level std; default 0.02)")
    p.add_argument("--shift", default="0.5", metavar="T|TZ,TY,TX",
                   help="translation of the translated pair, voxels (default 0.5 on each axis)")
    p.add_argument("--amplitude", type=float, default=0.5, help="amplitude of the star, voxels (default 0.5)")
    p.add_argument("--periods", default=None, metavar="PMIN,PMAX",
                   help="periods of the star at the first and the last y read (ell from the faces), voxels (default 2 ell, 20 ell)")
    p.add_argument("--seed", type=int, default=0, help="seed of the added noises")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the output directory of an earlier resolution run")
    add_engine_options(p, level="pyramid level correlated: only 0 (the scale of the measurement)")
    p.set_defaults(func=run_resolution)


def _numbers(text: str, name: str, n: int) -> tuple[float, ...]:
    import math

    try:
        v = tuple(float(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise InputError(f"--{name} {text!r}: expected numbers separated by commas") from None
    if len(v) == 1 and n == 3:
        v = v * 3
    if len(v) != n or not all(math.isfinite(a) for a in v):
        raise InputError(f"--{name} {text!r}: expected {n} finite numbers separated by commas")
    return v


def _progress(event: dict) -> None:
    stage = event.get("stage")
    if stage == "write":
        f = event["fraction"]
        if f >= 1:
            say(f"  wrote {event['scan']} ({event['seconds']:.1f} s)")
        return
    if stage == "element-size":
        say(f"== element size {event['element_size']}, {event['pair']} pair ==")
        return
    if stage == "resolution":
        b = {"=": "", "<": "< ", ">": "> "}[event["l10_bound"]]
        say(f"ell {event['element_size']}: n = {event['noise']:.4f} voxel, l10 % = {b}{event['l10']:.1f} voxels, "
            f"MEI = {event['mei']:.3f}")
        return
    line = format_event(event)
    if line:
        say("  " + line)


def run_resolution(args: argparse.Namespace) -> int:
    from ..analysis.resolution import resolution

    opts = engine_options(args)
    scheduler = opts.pop("scheduler")
    if opts.pop("level") != 0:
        raise InputError("--level: the resolution is measured on level 0 only")
    shift = _numbers(args.shift, "shift", 3)
    periods = None if args.periods is None else _numbers(args.periods, "periods", 2)
    t0 = time.perf_counter()
    rep = resolution(args.scan, args.element_sizes, args.output, noise=args.noise, shift=shift,
                     amplitude=args.amplitude, periods=periods, seed=args.seed, scheduler=scheduler,
                     overwrite=args.overwrite, progress=_progress, **opts)
    print(rep.markdown())
    say(f"wrote {rep.files['csv']}, {rep.files['json']}, {rep.files['markdown']} ({time.perf_counter() - t0:.1f} s)")
    ok = all(r["status_translated"] == "converged" and r["status_star"] == "converged" for r in rep.rows)
    return 0 if ok else 1
