"""``chunkdic strain | uncertainty | sweep | table | report | export``: analyses of results, thin over the API.

Each subcommand function takes the parsed ``argparse`` namespace and returns the exit code;
bad input raises :class:`chunkdic.errors.InputError` (one line, exit 2 in ``chunkdic.cli.app``).
Progress goes to stderr, results (tables, paths) to stdout.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ..errors import InputError
from .common import Progress, add_figure_options, add_strain_option, say
from .mechanics import (add_export_options, add_remove_rigid, export_displacements, export_series, profile_figure,
                        run_repeat, without_rigid)


def _sizes_arg(p) -> None:
    p.add_argument("--element-sizes", "-l", type=int, nargs="+", required=True, metavar="ELL",
                   help="element edges, voxels of --level (paper: 16 12 8 6)")


def _common_corr(p) -> None:
    p.add_argument("--roi", help="z0:z1,y0:y1,x0:x1 in level-0 voxels (default: centred box)")
    p.add_argument("--level", type=int, default=0, help="pyramid level correlated (default 0)")
    p.add_argument("--interpolation", choices=("cubic", "linear"), default="cubic")
    p.add_argument("--scheduler", default=None, help="threads (default), local[:N], or tcp://host:port")
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="output directory")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the output directory of an earlier run of the same command")


def register(subparsers) -> None:
    """Add ``strain``, ``uncertainty``, ``sweep``, ``table``, ``report`` and ``export`` to ``subparsers``."""
    p = subparsers.add_parser(
        "strain", help="mean strain of a result (without the outermost elements), principal strains",
        description="Element strains at the element centres (C8), their mean over the ROI without the "
                    "outermost layer of elements (paper 5.2), the (1 - 2 ell / L) correction (5.4), "
                    "tr(eps), eps_zz and principal strains.")
    p.add_argument("result", metavar="RESULT.zarr")
    p.add_argument("--all-elements", action="store_true", help="keep the outermost layer in the mean")
    add_strain_option(p)
    add_remove_rigid(p)
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=run_strain)

    p = subparsers.add_parser(
        "uncertainty", help="a-priori uncertainty vs element size: Fourier-shifted reference (paper 4.2)",
        description="Translate the reference by a sub-voxel Fourier phase shift (out of core, exact), "
                    "correlate it against the reference for each element size, tabulate bias and standard "
                    "deviation of the nodal displacement and the strain uncertainty, fit "
                    "sigma_U = A^(alpha+1) ell^(-alpha). Writes uncertainty.csv/.md/.png into DIR.")
    p.add_argument("scan", metavar="SCAN")
    _sizes_arg(p)
    p.add_argument("--shift", default="0.5", metavar="T|TZ,TY,TX",
                   help="prescribed translation, voxels of --level (default 0.5 on each axis)")
    p.add_argument("--repeat", nargs="+", metavar="SCAN2", default=None,
                   help="repeated scans of the unloaded specimen: each is correlated against SCAN instead of a "
                        "shifted copy; the table gives the spatial and temporal noise floors (iDICs guide) and the "
                        "DVC Challenge bias and u_rms against zero motion (--shift is not used)")
    _common_corr(p)
    p.set_defaults(func=run_uncertainty)

    p = subparsers.add_parser(
        "sweep", help="ZOI-size sweep: the paper's Table 1 for a pair of scans",
        description="Correlate REF and DEF for each element size and tabulate <Ux>, <Uy>, <Uz>, final gap, "
                    "tr(eps), eps_zz (also corrected by 1 - 2 ell / L) and the a-priori strain uncertainty "
                    "(zoi_table.md / zoi_table.csv in DIR).")
    p.add_argument("ref", metavar="REF")
    p.add_argument("deformed", metavar="DEF")
    _sizes_arg(p)
    _common_corr(p)
    p.add_argument("--uncertainty", metavar="DIR|CSV",
                   help="take delta eps from an earlier `chunkdic uncertainty` run instead of running it")
    p.add_argument("--no-a-priori", action="store_true", help="leave the delta eps column empty")
    p.add_argument("--shift", default="0.5", metavar="T|TZ,TY,TX", help="shift of the a-priori test")
    p.set_defaults(func=run_sweep)

    p = subparsers.add_parser(
        "table", help="the paper's Table 1 from existing results (one per element size)",
        description="Tabulate <Ux>, <Uy>, <Uz>, final gap, tr(eps), eps_zz (also corrected by 1 - 2 ell / L) "
                    "and delta eps (from --uncertainty) for results already computed.")
    p.add_argument("results", metavar="RESULT.zarr", nargs="+")
    p.add_argument("--uncertainty", metavar="DIR|CSV", help="delta eps from a `chunkdic uncertainty` run")
    p.add_argument("-o", "--output", metavar="DIR", help="also write zoi_table.md and zoi_table.csv there")
    p.add_argument("--overwrite", action="store_true", help="replace the tables of an earlier `table -o DIR`")
    p.set_defaults(func=run_table)

    p = subparsers.add_parser(
        "report", help="figures of one or several results (cuts, U and eps_zz maps, eps_zz(z) profile, residual, gap)",
        description="Mid-plane cuts of reference/deformed/corrected images with f - g and f - corrected, "
                    "residual, Uz/Uy/Ux and eps_zz maps on the mid-plane normal to x (one panel per result, "
                    "one colour bar), the eps_zz(z) profile per element layer (with the truth for a synthetic "
                    "pair; numbers in epszz_profile.csv), gap per iteration and level (paper Figs. 6-10). "
                    "Axes in the scan's unit when it has a voxel size.")
    p.add_argument("results", metavar="RESULT.zarr", nargs="+")
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="directory for the PNG files")
    p.add_argument("--ref", help="reference scan (default: the path recorded in the result)")
    p.add_argument("--deformed", help="deformed scan (default: the path recorded in the result)")
    p.add_argument("--interpolation", choices=("cubic", "linear"), default=None,
                   help="interpolation of the deformed scan in the cuts (default: the result's)")
    p.add_argument("--scheduler", default=None,
                   help="where the cut planes are computed: threads (default), local[:N], or tcp://host:port")
    p.add_argument("--cuts-from", metavar="RESULT.zarr", default=None,
                   help="the result (one of those given) whose field the cut figures use (default: the first)")
    p.add_argument("--label", dest="labels", action="append", metavar="NAME", default=None,
                   help="name of a result in every legend and panel title, once per result in their order "
                        "(default: each result's file stem)")
    add_strain_option(p)
    add_remove_rigid(p)
    p.add_argument("--profile", metavar="Z,Y,X:Z,Y,X", default=None,
                   help="also plot U and the normal strains along this line with their uncertainty bands "
                        "(profile.png; level-0 voxels; `chunkdic stats --line` prints the numbers)")
    add_figure_options(p)
    p.add_argument("--overwrite", action="store_true", help="replace the figures of an earlier report in DIR")
    p.set_defaults(func=run_report)

    p = subparsers.add_parser(
        "export", help="VTK mesh (ParaView), node CSV, corrected image and residual volumes, fields for viewers",
        description="--vtk: C8 mesh as VTK hexahedra with nodal displacement and element strains (a .vtu "
                    "also holds element size, level, voxel size, unit, gap, status and version as field "
                    "data); --csv: one line per node under one header line (pandas.read_csv reads it), "
                    "metadata in NODES.csv.json; --corrected: g(X+u(X)) and f - g(X+u(X)) over the ROI as "
                    "Zarr arrays; --fields: Uz, Uy, Ux, |U|, eps_zz, equivalent strain and residual as one "
                    "OME-NGFF multiscale image on the scan's level-0 grid (--fields-level S: its level-S grid) "
                    "(napari, neuroglancer). The size of --corrected and --fields is said first and refused when "
                    "the free disk cannot hold it. Strains of --vtk and --fields: --strain (default Green-Lagrange).")
    p.add_argument("result", metavar="RESULT.zarr|SERIES.zarr")
    p.add_argument("--vtk", metavar="OUT.vtu", help="VTK file (.vtu or .vtk)")
    p.add_argument("--csv", metavar="NODES.csv", help="node table")
    p.add_argument("--corrected", metavar="OUT.zarr", help="OME-NGFF image (channels corrected, residual) on the scan's grid at the result's level")
    p.add_argument("--fields", metavar="OUT.zarr",
                   help="OME-NGFF image (channels Uz, Uy, Ux, |U|, eps_zz, eps_eq, residual) on the scan's grid")
    add_export_options(p)
    p.add_argument("--fields-level", metavar="S", type=_level, default=0,
                   help="write --fields on the scan's level-S grid (2^S voxels per axis; 8^-S of the size): "
                        "0 (default) the full grid; 2 puts a 2048^3 scan's fields on 512^3. The residual channel "
                        "is the mean |r| over each voxel when S is coarser than the result's level")
    p.add_argument("--units", choices=("voxels", "physical"), default=None,
                   help="coordinates of --vtk/--csv/--pvd (voxels of the result's level) and displacement of --fields "
                        "(level-0 voxels): voxels (default) or physical; --displacements: physical when the scan has "
                        "a voxel size, else level-0 voxels")
    p.add_argument("--ref", help="reference scan for --corrected/--fields (default: recorded path)")
    p.add_argument("--deformed", help="deformed scan for --corrected/--fields (default: recorded path)")
    p.add_argument("--scheduler", default=None,
                   help="where --corrected/--fields are computed: threads (default), local[:N], or tcp://host:port")
    add_strain_option(p)
    add_remove_rigid(p)
    p.add_argument("--overwrite", action="store_true", help="replace outputs that an earlier export wrote")
    p.set_defaults(func=run_export)


# --------------------------------------------------------------------------- helpers


def _level(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}")
    return value


def _shift(text: str):
    try:
        vals = [float(v) for v in str(text).split(",")]
    except ValueError:
        raise InputError(f"--shift {text!r}: expected a number or TZ,TY,TX") from None
    if len(vals) not in (1, 3) or not all(np.isfinite(vals)):
        raise InputError(f"--shift {text!r}: expected a number or three numbers TZ,TY,TX")
    return tuple(vals * 3) if len(vals) == 1 else tuple(vals)


#: the progress of the Fourier shift under way (its events carry fractions)
_SHIFT: dict = {}


def _whole(stage: str, f: float) -> float:
    """The fraction of a whole fields export from its stage's (level 0 ~ 90 % of the work:
    its tasks evaluate the field and the residual; the pyramid levels are means)."""
    return 0.9 * f if stage == "fields" else 0.9 + 0.1 * f


def _progress(event: dict) -> None:
    from .common import format_event

    stage = event.get("stage")
    if stage == "shift":
        f = event["fraction"]
        if f <= 0 or "shift" not in _SHIFT:  # a new shift (one per uncertainty run)
            _SHIFT["shift"] = Progress("Fourier shift")
        _SHIFT["shift"](f)
        if f >= 1:
            _SHIFT.pop("shift").done()
        return
    if stage == "element-size":
        say(f"== element size {event['element_size']} ==")
        return
    if stage == "a-priori":
        say("== a-priori uncertainty (Fourier-shifted reference) ==")
        return
    if stage == "uncertainty":
        say(f"ell {event['element_size']}: bias ({event['bias_z']:+.4f}, {event['bias_y']:+.4f}, "
             f"{event['bias_x']:+.4f}) std ({event['std_z']:.4f}, {event['std_y']:.4f}, {event['std_x']:.4f}) voxel, "
             f"delta eps {event['delta_eps']:.2e}, gap {event['final_gap_percent']:.3f}%")
        return
    line = format_event(event)
    if line:
        say("  " + line)


def _fmt_tensor(t) -> str:
    rows = ["      " + "  ".join(f"{v:+.3e}" for v in row) for row in np.asarray(t)]
    return "\n".join(rows)


_MEASURE_NAMES = {"small": "small", "green-lagrange": "Green-Lagrange"}


def rotation_warning(summary) -> str | None:
    """The line that says a small strain cannot take the rotations present (None when it can)."""
    from ..results.strain import ROTATION_WARNING

    if summary.measure == "small" and summary.max_rotation > ROTATION_WARNING:
        return (f"elements rotate by up to {summary.max_rotation:.2f} deg (> {ROTATION_WARNING:g}): small strain "
                f"counts that rotation as strain; use --strain green-lagrange")
    return None


def _correction_lines(summary, factors: str) -> list[str]:
    """The (1 - 2 ell / L) line when its assumption holds, else why it is not shown."""
    if summary.correction_applies:
        return [f"corrected by (1 - 2 ell / L) per axis ({factors}) (paper 5.4; assumes the strain is localised "
                "inside, the outer layer unstrained):",
                f"  tr(eps) = {summary.volume_change_corrected:+.5f}   eps_zz = {summary.eps_zz_corrected:+.5f}"]
    if not any(summary.excluded):
        return []
    if summary.measure == "small" and summary.correction_axes[0]:
        return [f"eps_zz corrected by (1 - 2 ell / L) = {summary.factor[0]:.4f} along z (paper 5.4; assumes the strain "
                "is localised inside along z, the outer layers normal to z unstrained; the layers normal to "
                f"{', '.join('zyx'[j] for j in (1, 2) if summary.excluded[j] and not summary.correction_axes[j])} "
                "are strained, so no other component is corrected):",
                f"  eps_zz = {summary.eps_zz_corrected:+.5f}"]
    if summary.measure != "small":
        return ["(the (1 - 2 ell / L) correction of paper 5.4 is a small-strain one: --strain small shows it "
                "when it applies)"]
    return [f"(the (1 - 2 ell / L) correction of paper 5.4 is not shown: it assumes an unstrained outer layer, "
            f"whose mean eps_zz here is {summary.outer[0, 0]:+.5f}: the strain is not localised, and the mean "
            "above is the estimate)"]


def _resolution_note(result) -> str:
    """``; spatial resolution >= N voxels`` when the result records its nominal l10 %."""
    l10 = (result.info.get("regularization") or {}).get("nominal_l10")
    return f"; spatial resolution >= {l10:.0f} level-0 voxels (nominal l10 %)" if l10 else ""


def format_strain(summary, result) -> str:
    """Text block printed by ``chunkdic strain``."""
    ell = result.info["element_size"]
    n = result.mesh.shape
    used = "x".join(str(k) for k in summary.elements)
    excl = "without the outermost layer" if any(summary.excluded) else "all elements"
    f = ", ".join(f"{v:.4f}" for v in summary.factor)
    length = result.voxel_length()
    size = "" if length is None else (" = " + "x".join(f"{ell * v:.4g}" for v in dict.fromkeys(length.tolist()))
                                      + f" {result.info.get('unit') or 'unit'}")
    return "\n".join([
        f"{result.path}: {'x'.join(map(str, n))} elements of ell = {ell} voxels{size} "
        f"(level {result.info.get('level', 0)})" + _resolution_note(result),
        f"{_MEASURE_NAMES[summary.measure]} strain, mean over {used} elements ({excl}), axes (z, y, x); "
        f"largest element rotation {summary.max_rotation:.2f} deg:",
        _fmt_tensor(summary.mean),
        f"  tr(eps) = {summary.volume_change:+.5f}   eps_zz = {summary.eps_zz:+.5f}",
        f"  principal strains: {', '.join(f'{v:+.5f}' for v in summary.principal)}   "
        f"max |principal| = {summary.delta_eps:.5f}",
        *_correction_lines(summary, f),
        f"mean over all {'x'.join(map(str, n))} elements: tr(eps) = {np.trace(summary.mean_all):+.5f}   "
        f"eps_zz = {summary.mean_all[0, 0]:+.5f}",
    ])


# --------------------------------------------------------------------------- commands


def run_strain(args: argparse.Namespace) -> int:
    from ..results.result import open_result
    from ..results.strain import strain_summary

    res = open_result(args.result)
    res.check_displacement()
    res, rigid = without_rigid(res, args.remove_rigid)
    s = strain_summary(res, exclude_outer=not args.all_elements, measure=args.strain)  # a mask's active elements only
    warning = rotation_warning(s)
    if warning:
        say(f"warning: {warning}")
    if args.json:
        out = {"result": res.path, "element_size": res.info["element_size"], **s.as_dict()}
        length = res.voxel_length()
        if length is not None:  # strains are dimensionless; the element's size in the scan's unit
            out.update(element_size_physical=(res.info["element_size"] * length).tolist(),
                       voxel_size=list(res.info["voxel_size"]), unit=res.info.get("unit"))
        if rigid is not None:
            out["rigid_removed"] = rigid.as_dict()
        print(json.dumps(out, indent=2))
    else:
        if rigid is not None:
            say(rigid.text())
        print(format_strain(s, res))
    return 0


def run_uncertainty(args: argparse.Namespace) -> int:
    from ..analysis.metrology import uncertainty

    if args.repeat:
        return run_repeat(args, _progress)
    t0 = time.perf_counter()
    rep = uncertainty(args.scan, args.element_sizes, args.output, shift=_shift(args.shift), roi=args.roi,
                      level=args.level, interpolation=args.interpolation, scheduler=args.scheduler,
                      overwrite=args.overwrite, progress=_progress)
    print(rep.markdown())
    say(f"wrote {rep.files['csv']}, {rep.files['markdown']}, {rep.files['plot']} "
         f"({time.perf_counter() - t0:.1f} s)")
    return 0 if all(r["status"] == "converged" for r in rep.rows) else 1


def run_sweep(args: argparse.Namespace) -> int:
    from ..analysis.zoisweep import sweep

    t0 = time.perf_counter()
    out = sweep(args.ref, args.deformed, args.element_sizes, args.output, roi=args.roi, level=args.level,
                interpolation=args.interpolation, uncertainty_from=args.uncertainty,
                a_priori=not args.no_a_priori, shift=_shift(args.shift), scheduler=args.scheduler,
                overwrite=args.overwrite, progress=_progress)
    print(out["markdown"])
    say(f"wrote {out['md']}, {out['csv']} ({time.perf_counter() - t0:.1f} s)")
    return 0 if all(r["status"] == "converged" for r in out["rows"]) else 1


def run_table(args: argparse.Namespace) -> int:
    from ..analysis.zoisweep import read_delta_eps, write_zoi_table, zoi_table
    from ..io.outputs import Outputs
    from ..results.result import open_result

    results = [open_result(r) for r in args.results]
    for res in results:
        res.check_displacement()
    rows = zoi_table(results, delta_eps=read_delta_eps(args.uncertainty))
    if not args.output:
        print(write_zoi_table(rows))
        return 0
    plan = Outputs(inputs=[*args.results, *([args.uncertainty] if args.uncertainty else [])],
                   overwrite=args.overwrite)
    out = plan.add(args.output, "table").final
    with plan:
        text = write_zoi_table(rows, out)
    print(text)
    return 0


def run_report(args: argparse.Namespace) -> int:
    from ..scheduler import check_scheduler
    from ..plot.report import report

    check_scheduler(args.scheduler)
    extra = {} if args.profile is None else {"profile": profile_figure(args)}
    shown = (lambda res: without_rigid(res, True)[0]) if args.remove_rigid else None
    paths = report(args.results, args.output, ref=args.ref, deformed=args.deformed,
                   interpolation=args.interpolation, scheduler=args.scheduler, overwrite=args.overwrite,
                   progress=say, cuts_from=args.cuts_from, fmt=args.fmt, dpi=args.dpi, labels=args.labels,
                   strain=args.strain, shown=shown, extra=extra)
    for p in paths.values():
        print(p)
    return 0


def run_export(args: argparse.Namespace) -> int:
    from ..io.outputs import Outputs
    from ..results import scans as resultscans
    from ..results.result import open_result
    from ..scheduler import check_scheduler
    from ..export import meshfiles as export

    from ..io.kinds import kind_of

    units, args.units = args.units, args.units or "voxels"  # --displacements: physical when it can
    if kind_of(Path(args.result))[0] == "series":
        return export_series(args)
    if args.pvd:
        raise InputError("--pvd writes a loading series (chunkdic series): give the series store")
    if not (args.vtk or args.csv or args.corrected or args.fields or args.displacements):
        raise InputError("nothing to export: give --vtk, --csv, --corrected, --fields and/or --displacements")
    res = open_result(args.result)
    res.check_displacement()
    if args.units == "physical" and not res.info.get("voxel_size"):
        raise InputError("this result has no voxel size: export in voxels, or give the scans a voxel size")
    if args.fields_level and not args.fields:
        raise InputError("--fields-level applies to --fields: give --fields OUT.zarr")
    if args.remove_rigid and (args.corrected or args.fields):
        raise InputError("--remove-rigid applies to --vtk, --csv and --displacements: the corrected image and the "
                         "fields' residual need the measured field (export them in a command of their own)")
    res, rigid = without_rigid(res, args.remove_rigid)
    if rigid is not None:
        say(rigid.text())
    if args.corrected or args.fields:
        scans = resultscans.input_scans(res, args.ref, args.deformed)
        check_scheduler(args.scheduler)
    # every output checked (and every input) before the first is written; all or nothing
    plan = Outputs(inputs=resultscans.input_paths(res, args.ref, args.deformed), overwrite=args.overwrite)
    entries = {name: plan.add(path, kind) for name, path, kind in
               (("vtk", args.vtk, "vtk"), ("csv", args.csv, "csv"),
                ("csv-meta", args.csv and export.csv_sidecar(args.csv), "csv-meta"),
                ("corrected", args.corrected, "corrected"), ("fields", args.fields, "fields"),
                ("displacements", args.displacements, "displacements"))
               if path}
    # the free disk, once the paths are checked; the sizes are said once the outputs are ours (locked)
    sizes = _plan_images(res, args, scans[0].shape(0)) if args.corrected or args.fields else []
    with plan:
        for line in sizes:
            say(line)
        _export(res, args, {k: e.work for k, e in entries.items()})
        if args.displacements:
            export_displacements(res, args.displacements, entries["displacements"].work, units)
    for name in ("vtk", "csv", "corrected", "fields", "displacements"):
        if name in entries:
            print(getattr(args, name))
    return 0


def _plan_images(res, args: argparse.Namespace, shape0) -> list[str]:
    """The size of ``--corrected`` and ``--fields`` against the free disk of where they go (both
    counted together when on one file system): refused in one line (exit 2) when they cannot
    fit, else one line per image to say before the export starts."""
    from ..io.diskspace import same_device
    from ..export.corrected_image import plan_corrected
    from ..export.fields_image import plan_fields

    lines, first = [], None
    if args.corrected:
        first = plan_corrected(shape0, res.level, args.corrected)
        lines.append(f"{args.corrected}: {first['line']}")
    if args.fields:
        also = first["bytes"] if first is not None and same_device(args.corrected, args.fields) else 0
        lines.append(f"{args.fields}: " + plan_fields(shape0, args.fields, grid_level=args.fields_level,
                                                      also=also)["line"])
    return lines


def _export(res, args: argparse.Namespace, work: dict) -> None:
    """The writes of ``chunkdic export`` into the staged paths ``work``."""
    from ..export import meshfiles as export
    from ..export.corrected_image import write_corrected

    if args.vtk:
        info = export.write_vtk_file(res, work["vtk"], units=args.units, strain=args.strain)
        say(f"{args.vtk}: {info['points']} points, {info['cells']} hexahedra ({info['strain']} strain), "
            f"coordinates in {info['unit']}"
             + ("; run facts in its field data" if str(args.vtk).lower().endswith(".vtu") else ""))
    if args.csv:
        n = export.write_nodes_csv_files(res, work["csv"], work["csv-meta"], units=args.units,
                                         name=Path(args.csv).name)
        say(f"{args.csv}: {n} nodes (metadata in {export.csv_sidecar(args.csv)})")
    if args.corrected:
        progress = Progress("corrected image")
        out = write_corrected(res, work["corrected"], ref=args.ref, deformed=args.deformed,
                              scheduler=args.scheduler, progress=progress)
        progress.done()
        say(f"{args.corrected}: corrected and residual, gap {100 * out['gap']:.3f}% over {out['valid']} voxels "
             f"({out['excluded']} excluded)")
    if args.fields:
        _export_fields(res, args, work["fields"])


def _export_fields(res, args: argparse.Namespace, work) -> None:
    """``export --fields``: the fields image into the staged path ``work``, with progress lines."""
    from ..export.voxel_values import CHANNELS
    from ..export.fields_image import write_fields

    progress = Progress("fields")  # its stages: "fields" (level 0), then "level t" of the pyramid
    out = write_fields(res, work, ref=args.ref, deformed=args.deformed, units=args.units,
                       grid_level=args.fields_level, scheduler=args.scheduler, progress=lambda stage, f: progress(_whole(stage, f), stage),
                       strain=args.strain)
    progress.done()
    say(f"{args.fields}: {', '.join(CHANNELS)} on {len(out['levels'])} levels "
         f"({'x'.join(map(str, out['levels'][0]))} voxels at level 0 = the scan's level {args.fields_level}, "
         f"{out['voxels']} in the ROI)")
