"""Whole-specimen workflow: raw scans → Zarr → pyramid → C8-DIC on level 2 → strain → report.

The paper (Roux, Hild, Viot, Bernard) had to cut an 800³ sub-volume out of a 2048²×2200
scan and compress it 4³ to fit a 2 GB laptop. Here the whole scan is converted once to a
chunked Zarr store (``ingest``), its ``2^s`` sum pyramid is built chunk by chunk
(``build_pyramid``; level 2 = the paper's 4³ super-voxels), and the correlation on level
2 starts from the coarsest useful level; only mesh-sized data is ever held in memory.
Every step is skipped when its output is already complete, so re-running after an
interruption continues where it stopped (the correlation from its last checkpoint).

Run here: two small synthetic raw files (uint16, the paper's compression band) are
written first, then the pipeline runs on them::

    python workflows/whole_specimen.py

On beamline scans (raw files of 2200 slices of 2048², 16 bit, little endian)::

    python workflows/whole_specimen.py scan0.raw scan1.raw --shape 2200,2048,2048 \\
        --dtype uint16 --voxel-size 4.91 --unit micrometer --workdir /data/run1 \\
        --scheduler local:4

``--scheduler`` is ``threads`` (default, embedded), ``local:N`` (a LocalCluster of N
workers on 127.0.0.1) or the address of a running scheduler (``tcp://host:8786``,
see docs/distributed.md). Outputs in ``--workdir``: ``ref.zarr``, ``def.zarr``
(scans with pyramids), ``result.zarr``, ``strain.json``, ``report/*.png``,
``result.vtu`` (mesh for ParaView).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import chunkdic
from chunkdic.synth import foam, synthetic


def show(event: dict) -> None:
    """Print one line per correlation event (``chunkdic correlate`` prints richer ones)."""
    stage = event["stage"]
    if stage == "start":
        dash = f", dashboard {event['dashboard']}" if event.get("dashboard") else ""
        print(f"  running on {event['scheduler']}{dash}; levels {event['levels']}", flush=True)
    elif stage == "iteration":
        print(f"  level {event['level']} iteration {event['iteration']:2d}: gap {100 * event['gap']:.3f} %", flush=True)
    elif stage == "level":
        print(f"  level {event['level']}: {event['status']} in {event['seconds']:.1f} s", flush=True)
    elif stage == "resume":
        print(f"  resuming from the checkpoint: level {event['level']}, iteration {event['iteration']}", flush=True)


def percent(label: str):
    """A ``progress(fraction)`` callback printing every 10 %."""
    t0, last = time.perf_counter(), [-1]

    def report(frac: float) -> None:
        pct = int(100 * min(frac, 1.0)) // 10 * 10
        if pct > last[0]:
            last[0] = pct
            print(f"  {label}: {pct:3d} % ({time.perf_counter() - t0:.1f} s)", flush=True)

    return report


def write_synthetic_raw(path: Path, shape, field, *, which: str, dtype: str, seed: int, cell_size: float) -> None:
    """Render a synthetic scan slab by slab into a raw file (stands in for a beamline file)."""
    nz, ny, nx = shape
    slab = max(1, (16 << 20) // (ny * nx))
    tmp = path.with_suffix(".part")
    with open(tmp, "wb") as fh:
        for z0 in range(0, nz, slab):
            block = foam.render((min(slab, nz - z0), ny, nx), origin=(z0, 0, 0), field=field,
                                which=which, dtype=dtype, seed=seed, cell_size=cell_size,
                                bead_size=8 * cell_size)
            fh.write(np.ascontiguousarray(block, dtype=np.dtype(dtype).newbyteorder("<")).tobytes())
    tmp.replace(path)


def synthetic_inputs(workdir: Path, size: int, field_kind: str, dtype: str, cell_size: float):
    """Two raw files with a known field: the paper's band (default) or an affine field."""
    c = (size - 1) / 2.0
    if field_kind == "band":
        field = synthetic.Band(center_z=c, width=size / 3.0, strain=-0.05, lateral=0.3, center_y=c, center_x=c)
    else:
        field = synthetic.Affine(matrix=((-0.02, 0.0, 0.0), (0.0, 0.006, 0.0), (0.0, 0.0, 0.006)),
                                 center=(c, c, c), translation=(2.0, -1.0, 0.5))
    raws = []
    for which in ("reference", "deformed"):
        path = workdir / f"{which}.raw"
        if not path.exists():
            print(f"writing the synthetic raw scan {path} ({size}^3 {dtype})", flush=True)
            write_synthetic_raw(path, (size,) * 3, field, which=which, dtype=dtype, seed=7, cell_size=cell_size)
        raws.append(path)
    return raws, field


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("ref_raw", nargs="?", help="reference raw scan (default: a synthetic one)")
    p.add_argument("def_raw", nargs="?", help="deformed raw scan")
    p.add_argument("--shape", default=None, help="Z,Y,X of the raw files (required with raw files)")
    p.add_argument("--dtype", default="uint16", help="sample type of the raw files")
    p.add_argument("--byte-order", default="little", choices=("little", "big"))
    p.add_argument("--offset", type=int, default=0, help="header bytes to skip")
    p.add_argument("--voxel-size", type=float, default=None, help="level-0 voxel size")
    p.add_argument("--unit", default=None, help="unit of --voxel-size, e.g. micrometer")
    p.add_argument("--workdir", default="chunkdic-specimen", help="output directory")
    p.add_argument("--size", type=int, default=160, help="edge of the synthetic scans (no raw files given)")
    p.add_argument("--field", choices=("band", "affine"), default="band", help="synthetic field")
    p.add_argument("--cell-size", type=float, default=8.0,
                   help="synthetic foam cell size, level-0 voxels (beads 8x larger); level 2 sees cells of "
                        "cell-size / 4 voxels")
    p.add_argument("--level", type=int, default=2, help="pyramid level correlated (2 = the paper's 4^3)")
    p.add_argument("--element-size", type=int, default=8, help="element edge, voxels of --level")
    p.add_argument("--levels", type=int, default=None, help="pyramid levels to store (default --level + 2)")
    p.add_argument("--scheduler", default=None, help="threads (default), local:N or tcp://host:8786")
    p.add_argument("--no-report", action="store_true", help="skip the figures")
    p.add_argument("--overwrite", action="store_true", help="redo every step")
    args = p.parse_args(argv)
    if (args.ref_raw is None) != (args.def_raw is None):
        p.error("give both raw files or none")
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    field = None
    if args.ref_raw is None:
        (ref_raw, def_raw), field = synthetic_inputs(workdir, args.size, args.field, args.dtype, args.cell_size)
        shape = (args.size,) * 3
    else:
        if args.shape is None:
            p.error("--shape Z,Y,X is required with raw files")
        ref_raw, def_raw = Path(args.ref_raw), Path(args.def_raw)
        shape = tuple(int(v) for v in args.shape.split(","))
    levels = args.levels if args.levels is not None else args.level + 2
    times = {}

    # 1. raw → Zarr v3 scan groups (chunk by chunk; nothing is loaded whole)
    t0 = time.perf_counter()
    scans = {}
    for name, raw in (("ref", ref_raw), ("def", def_raw)):
        out = workdir / f"{name}.zarr"
        try:
            if args.overwrite:
                raise chunkdic.InputError("redo")
            scans[name] = chunkdic.open_scan(out)
            print(f"{out}: already ingested")
        except chunkdic.InputError:
            print(f"ingesting {raw} -> {out}", flush=True)
            scans[name] = chunkdic.ingest(raw, out, shape=shape, dtype=args.dtype, byte_order=args.byte_order,
                                          offset=args.offset, voxel_size=args.voxel_size, unit=args.unit,
                                          overwrite=True, progress=percent(f"ingest {name}"))
    times["ingest"] = time.perf_counter() - t0

    # 2. the 2^s sum pyramids (complete levels are kept)
    t0 = time.perf_counter()
    for name in scans:
        scans[name] = chunkdic.build_pyramid(workdir / f"{name}.zarr", levels, overwrite=args.overwrite,
                                             progress=percent(f"pyramid {name}"))
    times["pyramid"] = time.perf_counter() - t0

    # 3. C8-DIC on --level, multiscale from the coarsest useful level (resumes if interrupted)
    t0 = time.perf_counter()
    output = workdir / "result.zarr"
    try:
        if args.overwrite:
            raise chunkdic.InputError("redo")
        result = chunkdic.open_result(output)
        print(f"{output}: already complete")
    except chunkdic.InputError:
        result = chunkdic.correlate(workdir / "ref.zarr", workdir / "def.zarr", element_size=args.element_size,
                                    level=args.level, scheduler=args.scheduler, output=output,
                                    overwrite=args.overwrite, progress=show)
    times["correlate"] = time.perf_counter() - t0
    print(repr(result))

    # 4. strain: mean over the ROI without the outermost elements (paper 5.2), principal values
    from chunkdic.results.strain import strain_summary

    s = strain_summary(result)
    (workdir / "strain.json").write_text(json.dumps(s.as_dict(), indent=1))
    print(f"mean strain: eps_zz {s.eps_zz:+.5f} (corrected {s.eps_zz_corrected:+.5f}), tr {s.volume_change:+.5f}, "
          f"principal {', '.join(f'{v:+.5f}' for v in s.principal)}")

    # 5. figures (mid-plane cuts, Uz and eps_zz maps, gap history) and the mesh for ParaView
    if not args.no_report:
        t0 = time.perf_counter()
        from chunkdic.export.meshfiles import write_vtk
        from chunkdic.plot.report import report

        # redrawn on every run: overwrite replaces only the figures and mesh an earlier run wrote
        figures = report(result, workdir / "report", overwrite=True,
                         progress=lambda msg: print("  " + msg, flush=True))
        write_vtk(result, workdir / "result.vtu", overwrite=True)
        times["report"] = time.perf_counter() - t0
    else:
        figures = {}
    print("seconds per step: " + ", ".join(f"{k} {v:.1f}" for k, v in times.items()))

    out = {"result": result, "strain": s, "figures": figures, "times": times, "scans": scans}
    if field is not None:
        f = float(result.info["scale"])
        truth = field.displacement(*(f * result.node_coords + (f - 1) / 2)) / f
        err = result.displacement - truth
        out["rms_error"] = np.sqrt((err**2).mean(axis=(1, 2, 3)))
        out["max_error"] = np.abs(err).max(axis=(1, 2, 3))
        print(f"nodal error vs the known field, voxels of level {args.level} (Uz, Uy, Ux): RMS "
              + ", ".join(f"{v:.4f}" for v in out["rms_error"]) + "; max "
              + ", ".join(f"{v:.4f}" for v in out["max_error"]))
    return out


if __name__ == "__main__":
    main()
