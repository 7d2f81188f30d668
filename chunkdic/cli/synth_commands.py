"""``chunkdic synth``: write a synthetic reference/deformed pair with a known field."""

from __future__ import annotations

import sys
import time

from ..errors import InputError
from ..scheduler import SCHEDULER_HELP, dask_scheduler
from .common import Progress

FIELDS = ("none", "translation", "affine", "band", "star")
SPECIMENS = ("foam", "grains", "concrete")
CASES = ("fourier-shift", "shift", "band")
CT_OPTIONS = ("imaging", "angles", "filter", "blur", "rings", "gain", "offset", "drift", "texture_scale")
FOAM_OPTIONS = ("cell_size", "bead_size", "wall_width")
DEFAULT_TRANSLATION = (2.3, -1.4, 0.7)
DEFAULT_PERIODS = (16.0, 160.0)


def register(subparsers) -> None:
    """Add the ``synth`` subcommand to an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        "synth",
        help="write a synthetic reference/deformed pair with a known displacement field",
        description=(
            "Write OUT_DIR/ref.zarr and OUT_DIR/def.zarr (Zarr v3 scans) and "
            "OUT_DIR/field.json, the analytic displacement field. --specimen foam (default): "
            "a smooth procedural foam, g(X + u(X)) = f(X) exactly (up to rounding for integer "
            "dtypes). --specimen grains|concrete: a sharp-edged microstructure imaged like a "
            "CT scan slice by slice (projections, noise, filtered back-projection; or, with "
            "--imaging local, the reconstruction's measured blur and ramp-spectrum noise computed "
            "per chunk, for large scans), each scan with its own noise; the deformed scan is "
            "rendered from the deformed geometry (docs/synthetic.md). A synth killed midway "
            "resumes when the same command runs again (chunks already written are kept)."
        ),
    )
    p.add_argument("out_dir", metavar="OUT_DIR")
    p.add_argument("--shape", default="256", help="N or Z,Y,X (voxels; default 256)")
    p.add_argument("--specimen", choices=SPECIMENS, default="foam",
                   help="foam (default), or a CT-like specimen: grains, concrete")
    p.add_argument("--case", choices=CASES, default=None,
                   help="standard test case, overrides --field: fourier-shift (reference "
                        "Fourier-shifted by 0.5 voxel, CT specimens), shift (0.5 voxel "
                        "translation rendered with independent noise), band (-8%% strain, "
                        "6-voxel band at mid-height, lateral 0.05)")
    p.add_argument("--field", choices=FIELDS, default="translation",
                   help="displacement field (default translation)")
    p.add_argument("--translation", default=None,
                   help="tz,ty,tx voxels (translation default 2.3,-1.4,0.7; added to affine)")
    p.add_argument("--strain", type=float, default=None,
                   help="axial strain along z (affine default -0.01, band default -0.05)")
    p.add_argument("--shear", type=float, default=None,
                   help="affine shear dUz/dX = dUx/dZ (default 0.005)")
    p.add_argument("--lateral", type=float, default=0.3,
                   help="band lateral expansion factor (default 0.3)")
    p.add_argument("--band-width", type=float, default=None,
                   help="band width in voxels (default a quarter of the height)")
    p.add_argument("--amplitude", type=float, default=None,
                   help="star: amplitude of Ux, voxels (default 0.5)")
    p.add_argument("--periods", default=None, metavar="PMIN,PMAX",
                   help="star: period of the sine along z at the first and the last y, voxels "
                        "(default 16,160: 2 to 20 elements of 8 voxels)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dtype", choices=("uint8", "uint16", "float32"), default=None,
                   help="default uint8 (foam), uint16 (CT specimens)")
    p.add_argument("--chunks", type=int, default=None, help="chunk edge (default 128)")
    p.add_argument("--levels", type=int, default=0, help="pyramid levels to build")
    p.add_argument("--voxel-size", default=None, help="s or sz,sy,sx (physical units; default: none, sizes in voxels)")
    p.add_argument("--unit", default=None, help="length unit of --voxel-size (required with it), e.g. micrometer")
    p.add_argument("--cell-size", type=float, default=None, help="foam: mean cell size, voxels (default 8)")
    p.add_argument("--bead-size", type=float, default=None, help="foam: mean bead size, voxels (default 64)")
    p.add_argument("--wall-width", type=float, default=None,
                   help="foam: cell wall FWHM, voxels (default 2.5)")
    p.add_argument("--noise", type=float, default=None,
                   help="foam: std of additive noise, texture units ~0.05..1 (default 0); CT "
                        "specimens: std of the reconstruction noise as a fraction of the phase "
                        "contrast (default 0.02), independent in the two scans")
    ct = p.add_argument_group("CT specimens (grains, concrete)")
    ct.add_argument("--imaging", choices=("fbp", "local"), default=None,
                    help="fbp (default): projections and filtered back-projection slice by slice, "
                         "cost per voxel grows with the slice size (a 2048^3 pair: ~2 days on 2 cores); "
                         "local: the same phase maps seen through the FBP's measured blur plus "
                         "ramp-spectrum noise of the same --noise, computed per chunk "
                         "(cost per voxel independent of the size; docs/synthetic.md)")
    ct.add_argument("--texture-scale", type=float, default=None, metavar="FACTOR",
                    help="factor on every size of the microstructure (grains, aggregates, pores, the matrix "
                         "texture; default 1: autocorrelation length about 6 voxels, 2: 12, 4: 24; "
                         "docs/synthetic.md, \"Texture scale\")")
    ct.add_argument("--angles", type=int, default=None,
                    help="projections over 180 degrees (default pi/2 * max(ny, nx), Nyquist)")
    ct.add_argument("--filter", choices=("ramp", "hann"), default=None,
                    help="reconstruction filter (default ramp)")
    ct.add_argument("--blur", type=float, default=None, help="detector blur std, pixels (default 0)")
    ct.add_argument("--rings", type=float, default=None,
                    help="RMS of ring artefacts, fraction of the phase contrast (default 0)")
    ct.add_argument("--gain", type=float, default=None, help="deformed scan only: gain (default 1)")
    ct.add_argument("--offset", type=float, default=None,
                    help="deformed scan only: offset, fraction of the phase contrast (default 0)")
    ct.add_argument("--drift", type=float, default=None,
                    help="deformed scan only: linear drift along z over the height, fraction "
                         "of the phase contrast (default 0)")
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--scheduler", default=None, help=SCHEDULER_HELP + "; its workers must see OUT_DIR")
    p.set_defaults(func=run)


def _floats(text: str, name: str, n: int | None = None) -> tuple[float, ...]:
    try:
        v = tuple(float(t) for t in str(text).replace("x", ",").split(",") if t.strip())
    except ValueError:
        raise InputError(f"--{name} must be numbers separated by commas, got {text!r}") from None
    if n is not None and len(v) == 1:
        v = v * n
    if n is not None and len(v) != n:
        raise InputError(f"--{name} needs 1 or {n} values, got {text!r}")
    return v


def _shape(text: str) -> tuple[int, int, int]:
    v = _floats(text, "shape", 3)
    if any(s < 1 or s != int(s) for s in v):
        raise InputError(f"--shape must be positive integers, got {text!r}")
    return tuple(int(s) for s in v)


def build_field(args, shape):
    """The field selected by the command-line options (``None`` for ``--field none``)."""
    from ..synth import synthetic as S

    nz, ny, nx = shape
    center = ((nz - 1) / 2.0, (ny - 1) / 2.0, (nx - 1) / 2.0)
    if args.field == "none":
        return None
    if args.field == "translation":
        t = _floats(args.translation, "translation", 3) if args.translation else DEFAULT_TRANSLATION
        return S.Translation(t)
    if args.field == "affine":
        strain = -0.01 if args.strain is None else args.strain
        shear = 0.005 if args.shear is None else args.shear
        t = _floats(args.translation, "translation", 3) if args.translation else (0.0, 0.0, 0.0)
        a = ((strain, 0.0, shear), (0.0, 0.0, 0.0), (shear, 0.0, 0.0))
        return S.Affine(a, center=center, translation=t)
    if args.field == "star":
        amp = 0.5 if args.amplitude is None else args.amplitude
        pmin, pmax = _floats(args.periods, "periods", 2) if args.periods else DEFAULT_PERIODS
        return S.Star(amplitude=amp, period_min=pmin, period_max=pmax, y0=0.0, y1=float(max(ny - 1, 1)),
                      center_z=center[0])
    strain = -0.05 if args.strain is None else args.strain
    width = nz / 4.0 if args.band_width is None else args.band_width
    return S.Band(center_z=center[0], width=width, strain=strain, lateral=args.lateral,
                  center_y=center[1], center_x=center[2])


def _check_options(args) -> None:
    """Numeric options in range (one line naming the option), before anything is written."""
    from ..inputs import number

    if args.unit is not None and args.voxel_size is None:
        raise InputError("--unit was given without --voxel-size: pass both (--voxel-size 4.91 --unit micrometer)")
    for name, kw in (("noise", dict(minimum=0)), ("cell_size", dict(above=0)), ("bead_size", dict(above=0)),
                     ("wall_width", dict(above=0)), ("lateral", dict(above=-1)), ("band_width", dict(above=0)),
                     ("strain", dict(above=-1)), ("shear", {}), ("seed", dict(minimum=0, integer=True)),
                     ("levels", dict(minimum=0, integer=True)), ("chunks", dict(minimum=1, integer=True)),
                     ("angles", dict(minimum=1, integer=True)), ("blur", dict(minimum=0)), ("rings", dict(minimum=0)),
                     ("gain", dict(above=0)), ("offset", {}), ("drift", {}), ("amplitude", {}),
                     ("texture_scale", dict(above=0))):
        if getattr(args, name) is not None:
            number(getattr(args, name), "--" + name.replace("_", "-"), **kw)
    if args.periods is not None:
        for v in _floats(args.periods, "periods", 2):
            number(v, "--periods", above=0)
    star_only = [o for o in ("amplitude", "periods") if getattr(args, o) is not None]
    if star_only and (args.field != "star" or args.case is not None):
        raise InputError(f"--{star_only[0]} only applies to --field star")
    for name in ("translation", "voxel_size"):
        if getattr(args, name) is not None:
            for v in _floats(getattr(args, name), name.replace("_", "-"), 3):
                number(v, "--" + name.replace("_", "-"), above=0 if name == "voxel_size" else None)
    if args.voxel_size is not None and args.unit is None:
        raise InputError(f"--voxel-size {args.voxel_size} has no unit: give --unit (micrometer/um, millimeter/mm, "
                         "nanometer/nm); a voxel size's unit is never guessed")


def _specimen_options(args) -> dict:
    """The options given for the chosen specimen; options of the other kind are errors."""
    given = {k: getattr(args, k) for k in CT_OPTIONS + FOAM_OPTIONS if getattr(args, k) is not None}
    wrong = FOAM_OPTIONS if args.specimen != "foam" else CT_OPTIONS
    bad = ["--" + k.replace("_", "-") for k in wrong if k in given]
    if bad:
        kind = "the foam" if args.specimen != "foam" else "CT specimens (grains, concrete)"
        raise InputError(f"{', '.join(bad)} only apply to {kind}")
    return given


def run(args) -> int:
    """Run ``chunkdic synth``; returns the exit code."""
    from ..io.outputs import Outputs
    from ..scheduler import check_scheduler
    from ..synth import synthetic as S

    shape = _shape(args.shape)
    _check_options(args)
    vs = None if args.voxel_size is None else _floats(args.voxel_size, "voxel-size", 3)
    if args.chunks is not None and args.chunks < 1:
        raise InputError(f"--chunks must be positive, got {args.chunks}")
    fourier = False
    if args.case is not None:
        from ..synth.ctpair import standard_field

        fld, fourier = standard_field(args.case, shape)
    else:
        fld = build_field(args, shape)
    if fourier and args.specimen == "foam":
        raise InputError("--case fourier-shift needs a CT specimen (--specimen grains|concrete)")
    extra = _specimen_options(args)
    check_scheduler(args.scheduler)
    plan = Outputs(overwrite=args.overwrite)
    # checked before anything is written; removed if a fresh run fails. A folder left
    # incomplete by a killed run is continued (resume): its complete chunks are kept.
    entry = plan.add(args.out_dir, "synth", resumable=True)
    t0 = time.perf_counter()
    # the header is said once writing starts: a refused run prints its error line only
    again = " (resuming an interrupted run: its complete chunks are kept)" if entry.state == "resume" else ""
    progress = Progress("synth", header=f"synth: {args.out_dir} {args.specimen} shape {shape}, field "
                                        f"{'none' if fld is None else fld.to_json()}{again}", indent="")

    with plan, dask_scheduler(args.scheduler, announce=lambda msg: print(f"synth: {msg}", file=sys.stderr,
                                                                          flush=True)):
        res = S.synthesize(
            args.out_dir, shape, field=fld, seed=args.seed, dtype=args.dtype, chunks=args.chunks,
            voxel_size=vs, unit=args.unit, levels=args.levels, overwrite=False, resume=entry.state == "resume",
            progress=progress, specimen=args.specimen, noise=args.noise, fourier_shift=fourier,
            **extra,
        )
        progress.done()
    dt = time.perf_counter() - t0
    nvox = 2 * shape[0] * shape[1] * shape[2]
    print(f"synth: wrote {res['reference']} and {res['deformed']} ({nvox / dt / 1e6:.2f} "
          f"Mvoxel/s, {dt:.1f} s); field in {res['field_json']}", file=sys.stderr, flush=True)
    return 0
