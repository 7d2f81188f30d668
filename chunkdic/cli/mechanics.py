"""``chunkdic stats | gauge | crack``: what a mechanics paper reads off a result, thin over the API.

Tables go to stdout (text, ``--json`` or ``--csv``); progress and notes to stderr; bad input
is one line, exit 2 (``chunkdic.cli.app``).
"""

from __future__ import annotations

import argparse
import json
import time

from ..errors import InputError
from .common import add_figure_options, add_strain_option, say


def add_remove_rigid(p) -> None:
    """``--remove-rigid``: shown without the least-squares rigid motion of the nodes (reported)."""
    p.add_argument("--remove-rigid", action="store_true",
                   help="remove the least-squares rigid motion of the measured nodes first (Kabsch; printed with its "
                        "uncertainty): the field and small strains shown without it")


def add_export_options(p) -> None:
    """``export --displacements`` (OME-NGFF 0.6) and ``--pvd`` (a series for ParaView)."""
    p.add_argument("--displacements", metavar="OUT.zarr",
                   help="the displacement as an OME-NGFF 0.6 displacements transformation from the reference's frame "
                        "to the deformed scan's (a scene; the field on the C8 nodes, linear interpolation between "
                        "them is the measured field; physical units when the scan has a voxel size)")
    p.add_argument("--pvd", metavar="DIR",
                   help="a loading series (chunkdic series) as a ParaView time series: DIR/series.pvd and one .vtu "
                        "per step, every step's field from the reference")


def _output_format(p) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--json", action="store_true", help="print JSON instead of text")
    g.add_argument("--csv", action="store_true", help="print CSV (one header line) instead of text")


def register(subparsers) -> None:
    """Add ``stats``, ``gauge`` and ``crack`` to ``subparsers``."""

    p = subparsers.add_parser(
        "stats", help="mean, std and 95 %% interval of the mean of U and the strain over a region, or a profile",
        description="For each component of U (nodes) and of the strain (element centres) over the ROI, a box, a "
                    "slab, a mask or label image, or along a line (a profile): the mean, the population standard "
                    "deviation and the confidence interval of the mean from the solve's nodal covariance "
                    "(docs/statistics.md), with std/sqrt(n) beside it. Regions in level-0 voxels.")
    p.add_argument("result", metavar="RESULT.zarr")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--box", metavar="Z0:Z1,Y0:Y1,X0:X1", help="a box (level-0 voxels)")
    g.add_argument("--slab", metavar="AXIS=A:B", help="a slab across the ROI, e.g. z=20:40 (level-0 voxels)")
    g.add_argument("--mask", metavar="MASK", help="a mask or label image of the reference's shape (any scan format)")
    g.add_argument("--line", metavar="Z,Y,X:Z,Y,X", help="a profile along a line (level-0 voxels)")
    p.add_argument("--label", type=int, default=None, help="the label of --mask to use (default: every non-zero voxel)")
    p.add_argument("--step", type=float, default=None,
                   help="spacing of a profile's points, level-0 voxels (default: a quarter of an element)")
    p.add_argument("--truth", metavar="FIELD.json",
                   help="a known field (a synthetic pair's field.json or its folder): adds the DVC Challenge 2.0 bias, "
                        "noise floor and u_rms of the error")
    p.add_argument("--confidence", type=float, default=0.95, help="of the intervals")
    p.add_argument("--scheduler", default=None, help="where a --mask is read: threads (default), local[:N], tcp://…")
    add_strain_option(p)
    add_remove_rigid(p)
    _output_format(p)
    p.set_defaults(func=run_stats)

    p = subparsers.add_parser(
        "gauge", help="virtual extensometer: elongation and strain between two points or planes, per step of a series",
        description="Elongation and strain (with their interval) between two points (--points) or two mean planes "
                    "(--planes) of a result, or of every step of a loading series (chunkdic series). -o DIR writes "
                    "gauge.csv, gauge.json and the curve gauge.png. Points and planes in level-0 voxels.")
    p.add_argument("source", metavar="RESULT.zarr|SERIES.zarr")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--points", nargs=2, metavar="Z,Y,X", help="the gauge's two ends")
    g.add_argument("--planes", nargs=2, metavar="AXIS=POS", help="two planes normal to one axis, e.g. z=10 z=40")
    p.add_argument("--confidence", type=float, default=0.95, help="of the strain's interval")
    p.add_argument("-o", "--output", metavar="DIR", help="also write gauge.csv, gauge.json and the curve there")
    p.add_argument("--overwrite", action="store_true", help="replace the files of an earlier gauge -o DIR")
    add_figure_options(p)
    _output_format(p)
    p.set_defaults(func=run_gauge)

    p = subparsers.add_parser(
        "crack", help="find displacement discontinuities: each crack's surface, opening and sliding",
        description="Elements whose displacement gradient holds a significant, localised jump (the solve's "
                    "covariance gives its noise), one element across, grouped into cracks; the residual per element "
                    "(from the scans) says whether the jump leaves a misfit a smooth strain would not. Prints each "
                    "crack's mean opening and sliding with their uncertainty; -o DIR writes cracks.vtu (the surface, "
                    "ParaView), cracks-labels.zarr (napari labels), cracks.csv and cracks.json (docs/cracks.md).")
    p.add_argument("result", metavar="RESULT.zarr")
    p.add_argument("-o", "--output", metavar="DIR", help="write the surfaces, labels and tables there")
    p.add_argument("--ref", help="reference scan for the residual (default: the path recorded in the result)")
    p.add_argument("--deformed", help="deformed scan for the residual (default: the path recorded in the result)")
    p.add_argument("--no-residual", action="store_true", help="leave out the residual (the scans are not read)")
    p.add_argument("--units", choices=("voxels", "physical"), default="voxels",
                   help="coordinates of cracks.vtu: voxels of the result's level or the scan's unit")
    p.add_argument("--scheduler", default=None, help="where the residual is computed: threads (default), local[:N], …")
    p.add_argument("--overwrite", action="store_true", help="replace the files of an earlier crack -o DIR")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=run_crack)


def _print(obj, args) -> None:
    if args.json:
        print(json.dumps(obj.as_dict(), indent=2))
    elif args.csv:
        print(obj.csv(), end="")
    else:
        print(obj.text())


def run_stats(args: argparse.Namespace) -> int:
    from ..analysis.stats import stats
    from ..results.result import open_result

    res = open_result(args.result)
    out = stats(res, box=args.box, slab=args.slab, mask=args.mask, label=args.label, line=args.line,
                step=args.step, measure=args.strain, remove_rigid=args.remove_rigid, truth=args.truth,
                confidence=args.confidence, scheduler=args.scheduler)
    if out.rigid and not args.json:
        say(_rigid_text(out.rigid))
    _print(out, args)
    return 0


def _rigid_text(d: dict) -> str:
    from ..analysis.rigid import RigidMotion

    import numpy as np

    fields = {k: (np.asarray(v, float) if isinstance(v, list) else v) for k, v in d.items()}
    return RigidMotion(**fields).text()


def run_gauge(args: argparse.Namespace) -> int:
    from ..analysis.gauge import gauge
    from ..io.outputs import Outputs

    curve = gauge(args.source, points=args.points, planes=args.planes, confidence=args.confidence)
    if args.output:
        from ..plot.mechplots import plot_gauge

        plan = Outputs(inputs=[args.source], overwrite=args.overwrite)
        out = plan.add(args.output, "gauge").final
        with plan:
            (out / "gauge.csv").write_text(curve.csv())
            (out / "gauge.json").write_text(json.dumps(curve.as_dict(), indent=2) + "\n")
            path = plot_gauge(curve.as_dict(), out / f"gauge.{args.fmt}", dpi=args.dpi)
        say(f"wrote {out / 'gauge.csv'}, {out / 'gauge.json'}, {path}")
    _print(curve, args)
    return 0



def run_crack(args: argparse.Namespace) -> int:
    from ..analysis.cracks import find_cracks
    from ..io.outputs import Outputs
    from ..results import scans as resultscans
    from ..results.result import open_result
    from ..scheduler import check_scheduler

    res = open_result(args.result)
    res.check_displacement()
    if args.units == "physical" and res.voxel_size is None:
        raise InputError("this result has no voxel size: write the surfaces in voxels, or give the scans a voxel size")
    residual = None
    if not args.no_residual:
        check_scheduler(args.scheduler)
        try:
            resultscans.input_scans(res, args.ref, args.deformed)
        except InputError as exc:
            if args.ref or args.deformed:
                raise
            say(f"the residual is left out: {exc}")
            args.no_residual = True
    plan = None
    if args.output:
        plan = Outputs(inputs=resultscans.input_paths(res, args.ref, args.deformed), overwrite=args.overwrite)
        out = plan.add(args.output, "cracks").final
    if not args.no_residual:
        from ..analysis.residuals import element_residuals

        residual = element_residuals(res, ref=args.ref, deformed=args.deformed, scheduler=args.scheduler)
    cmap = find_cracks(res, residual=residual)
    if plan is not None:
        from ..export.crack_export import write_crack_files

        with plan:
            written = write_crack_files(res, cmap, out, units=args.units)
        say(f"wrote {', '.join(written['files'].values())} ({written['polygons']} surface pieces)")
    print(json.dumps(cmap.as_dict(), indent=2) if args.json else cmap.text(args.result))
    return 0


def without_rigid(res, remove: bool):
    """``(result shown, rigid motion or None)``: the result without its least-squares rigid
    motion when ``remove`` (``--remove-rigid``)."""
    if not remove:
        return res, None
    from ..analysis.rigid import fit_rigid, remove_rigid

    motion = fit_rigid(res)
    return remove_rigid(res, motion), motion


def run_repeat(args: argparse.Namespace, progress) -> int:
    """``uncertainty SCAN --repeat SCAN2 …``: the noise floors of repeated scans (``progress``: the
    correlations' events, as ``uncertainty`` prints them)."""
    from ..analysis.repeats import repeat_noise

    def events(event: dict) -> None:
        if event.get("stage") != "repeat":
            progress(event)
            return
        say(f"ell {event['element_size']}: spatial noise floor {event['spatial']:.4f}, temporal {event['temporal']:.4f} "
            f"voxel ({event['fields']} field(s)), bias {event['bias']:.4f}, u_rms {event['u_rms']:.4f}")

    t0 = time.perf_counter()
    rep = repeat_noise([args.scan, *args.repeat], args.element_sizes, args.output, roi=args.roi, level=args.level,
                       interpolation=args.interpolation, scheduler=args.scheduler, overwrite=args.overwrite,
                       progress=events)
    print(rep.markdown())
    say(f"wrote {rep.files['csv']}, {rep.files['markdown']} ({time.perf_counter() - t0:.1f} s)")
    return 0 if all(set(r["status"].split(",")) == {"converged"} for r in rep.rows) else 1


def profile_figure(args: argparse.Namespace):
    """The maker of ``report --profile``'s figure: every result's profile along the line, checked
    now (a line outside a result's ROI is refused before any figure is written)."""
    from ..analysis.regions import line_region, parse_line
    from ..analysis.stats import profile
    from ..results.result import open_result
    from ..plot.mechplots import plot_profile

    ends = parse_line(args.profile)
    results = [open_result(r) for r in args.results]
    regions = [line_region(r, *ends) for r in results]
    labels = args.labels or [str(r) for r in args.results]

    def make(path, dpi):
        profiles = [profile(r, g, measure=args.strain, remove_rigid=args.remove_rigid).as_dict()
                    for r, g in zip(results, regions)]
        return plot_profile(profiles, path, labels=labels if len(results) > 1 else None, dpi=dpi)

    return make


def export_series(args: argparse.Namespace) -> int:
    """``export SERIES --pvd DIR``: the ParaView time series of a loading series."""
    from ..analysis.loadseries import open_series
    from ..export.pvd import write_pvd

    others = [f"--{n}" for n in ("vtk", "csv", "corrected", "fields", "displacements") if getattr(args, n)]
    if others or not args.pvd:
        raise InputError("a loading series exports as a ParaView time series: give --pvd DIR"
                         + (f", not {', '.join(others)} (export one step's result for those)" if others else ""))
    series = open_series(args.result)
    if not series.cumulative:
        raise InputError(f"series {args.result} has no step: nothing to export")
    transform = (lambda res: without_rigid(res, True)[0]) if args.remove_rigid else None
    out = write_pvd(series, args.pvd, units=args.units, strain=args.strain, overwrite=args.overwrite,
                    transform=transform)
    say(f"{out['path']}: {out['steps']} steps (the reference and {out['steps'] - 1} fields)")
    print(out["path"])
    return 0


def export_displacements(res, path, work, units) -> None:
    """``export --displacements``: the OME-NGFF 0.6 field into the staged path ``work``."""
    from ..export.ngff_displacements import write_displacements_store

    out = write_displacements_store(res, work, units=units)
    say(f"{path}: OME-NGFF {out['levels'][0][1:]} nodes, {len(out['levels'])} levels, in "
        f"{out['unit'] or 'level-0 voxels'}")
