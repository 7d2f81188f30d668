"""Loading-series workflow: scans 0..n of one specimen, incremental and cumulative fields.

A thin copy of :func:`chunkdic.series` (``chunkdic series SCAN0 SCAN1 ... -o series.zarr``):
in an interrupted test (the paper's drop-tower impacts, a scan after each) every scan
``k`` is correlated against the previous one (incremental field ``u_{k-1,k}``, started
from the previous increment) and against the reference (cumulative ``u_{0,k}``, started
from the previous cumulative field composed with the new increment). Fields are
Lagrangian (in the frame of their own reference scan), so increments compose, they do
not add::

    u_{0,n}(X) = u_{0,n-1}(X) + u_{n-1,n}(X + u_{0,n-1}(X))

(:func:`chunkdic.analysis.loadseries.compose`). The script compares, at every step, the composed field
with the correlated cumulative one, and both with the truth when the scans are synthetic.

Run here (scans 0..3 of a 64³ synthetic specimen under growing compression)::

    python workflows/loading_series.py

On real scans (stored scan groups, in loading order, the reference first)::

    python workflows/loading_series.py scan0.zarr scan1.zarr scan2.zarr scan3.zarr \\
        --element-size 8 --level 2 --scheduler local:4 --workdir series

Everything goes to ``WORKDIR/series.zarr`` (steps/001-incremental, composed/002,
steps/002-cumulative, ...); re-run after an interruption to continue (finished steps are
skipped, the interrupted one resumes from its checkpoint); ``--overwrite`` redoes all.
With one ``--scheduler local:N`` the cluster is started once and kept for the series.
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
    """Print one line per step and per finished level (``chunkdic series`` prints richer progress)."""
    if event["stage"] == "series-step":
        print(f"  {event['group']} (scans {event['pair']}): {event['run']}", flush=True)
    elif event["stage"] == "level":
        print(f"    level {event['level']}: {event['status']}, gap {100 * event['gap']:.3f} % "
              f"({event['seconds']:.1f} s)", flush=True)
    elif event["stage"] == "resume":
        print(f"    resuming from the checkpoint: level {event['level']}, iteration {event['iteration']}", flush=True)


def series_fields(n_steps: int, size: int, step_strain: float, kind: str):
    """Known fields ``u_{0,k}`` of the synthetic series (k = 1..n): growing compression."""
    c = (size - 1) / 2.0
    fields = []
    for k in range(1, n_steps + 1):
        e = k * step_strain
        if kind == "band":
            fields.append(synthetic.Band(center_z=c, width=size / 3.0, strain=e, lateral=0.3,
                                         center_y=c, center_x=c))
        else:
            # axial compression, lateral expansion, a slow rigid drift of the specimen
            fields.append(synthetic.Affine(matrix=((e, 0.0, 0.0), (0.0, -0.3 * e, 0.0), (0.0, 0.0, -0.3 * e)),
                                           center=(c, c, c), translation=(0.4 * k, -0.25 * k, 0.15 * k)))
    return fields


def write_series(workdir: Path, size: int, fields, overwrite: bool) -> list[Path]:
    """Scan 0 (reference texture) and scans 1..n (deformed by ``fields``), chunk by chunk."""
    scans = []
    for k, field in enumerate([None] + list(fields)):
        path = workdir / "scans" / f"scan{k}.zarr"
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            if overwrite:
                raise chunkdic.InputError("redo")
            chunkdic.open_scan(path)
        except chunkdic.InputError:
            lazy = foam.as_dask((size,) * 3, chunks=64, field=field, seed=5,
                                which="reference" if field is None else "deformed", dtype="uint8")
            chunkdic.write_scan(path, lazy, overwrite=True)
        scans.append(path)
    return scans


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scans", nargs="*", help="scans in loading order, the reference first (default: synthetic)")
    p.add_argument("--workdir", default="chunkdic-series", help="output directory")
    p.add_argument("--size", type=int, default=64, help="edge of the synthetic scans")
    p.add_argument("--steps", type=int, default=3, help="synthetic loading steps after the reference")
    p.add_argument("--step-strain", type=float, default=-0.01, help="axial strain added per step (synthetic)")
    p.add_argument("--field", choices=("affine", "band"), default="affine", help="synthetic field")
    p.add_argument("--element-size", type=int, default=8, help="element edge, voxels of --level")
    p.add_argument("--level", type=int, default=0, help="pyramid level correlated")
    p.add_argument("--roi", default=None, help="z0:z1,y0:y1,x0:x1 in level-0 voxels (same for every pair)")
    p.add_argument("--scheduler", default=None, help="threads (default), local:N or tcp://host:8786")
    p.add_argument("--overwrite", action="store_true", help="redo every correlation")
    args = p.parse_args(argv)
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    fields = None
    if args.scans:
        if len(args.scans) < 2:
            p.error("give at least two scans")
        scans = [Path(s) for s in args.scans]
    else:
        fields = series_fields(args.steps, args.size, args.step_strain, args.field)
        print(f"writing a synthetic series of {args.steps + 1} scans of {args.size}^3 in {workdir / 'scans'}")
        scans = write_series(workdir, args.size, fields, args.overwrite)

    scheduler, cluster = args.scheduler, None
    if isinstance(scheduler, str) and scheduler.startswith("local"):
        # one cluster for the whole series (chunkdic would start one per correlation)
        from chunkdic.scheduler import start_local_cluster

        n = scheduler.partition(":")[2]
        scheduler, cluster = start_local_cluster(int(n) if n else None)
        print(f"LocalCluster on 127.0.0.1, dashboard {scheduler.dashboard_link}")

    f = 2.0**args.level
    t0 = time.perf_counter()
    try:
        try:  # done before: read it (a re-run continues an interrupted series; --overwrite redoes it)
            if args.overwrite:
                raise chunkdic.InputError("redo")
            out = chunkdic.open_series(workdir / "series.zarr")
        except chunkdic.InputError:
            out = chunkdic.series(scans, workdir / "series.zarr", element_size=args.element_size, level=args.level,
                                  roi=args.roi, scheduler=scheduler, overwrite=args.overwrite, progress=show)
    finally:
        if cluster is not None:
            scheduler.close()
            cluster.close()
    print(out.table())
    first = out.cumulative[1]
    X = first.node_coords
    rows = []
    for k in range(1, len(scans)):
        # composed from the increments (step 1: the increment itself) vs the correlated cumulative field
        composed = first if k == 1 else chunkdic.open_result(workdir / "series.zarr" / "composed" / f"{k:03d}")
        direct = out.cumulative[k]
        naive = sum(chunkdic.open_result(workdir / "series.zarr" / "steps" / f"{i:03d}-incremental").displacement
                    for i in range(1, k + 1))  # wrong: ignores where the point has moved
        diff = composed.displacement - direct.displacement
        row = {"step": k, "direct_status": direct.info["status"],
               "cumulative_vs_direct_rms": float(np.sqrt((diff**2).sum(axis=0).mean())),
               "cumulative_vs_direct_max": float(np.sqrt((diff**2).sum(axis=0)).max()),
               "naive_sum_vs_direct_rms": float(np.sqrt(((naive - direct.displacement) ** 2).sum(axis=0).mean())),
               "mean_uz": float(composed.displacement[0].mean())}
        if fields is not None:
            truth = fields[k - 1].displacement(*(f * X + (f - 1) / 2)) / f
            for name, u in (("cumulative", composed.displacement), ("direct", direct.displacement)):
                e = np.sqrt(((u - truth) ** 2).sum(axis=0))
                row[f"{name}_error_rms"] = float(np.sqrt((e**2).mean()))
                row[f"{name}_error_max"] = float(e.max())
        rows.append(row)
        print(f"step {k}: |composed - cumulative| RMS {row['cumulative_vs_direct_rms']:.4f}, "
              f"max {row['cumulative_vs_direct_max']:.4f} voxel (plain sum of the increments: RMS "
              f"{row['naive_sum_vs_direct_rms']:.4f})"
              + (f"; error vs truth RMS composed {row['cumulative_error_rms']:.4f}, cumulative "
                 f"{row['direct_error_rms']:.4f} voxel" if fields is not None else ""), flush=True)
    (workdir / "series.json").write_text(json.dumps(rows, indent=1))
    print(f"{len(scans) - 1} steps in {time.perf_counter() - t0:.1f} s; table in {workdir / 'series.json'}; "
          f"every field in {workdir / 'series.zarr'}")
    return {"rows": rows, "node_coords": X, "cumulative": out.cumulative[len(scans) - 1].displacement}


if __name__ == "__main__":
    main()
