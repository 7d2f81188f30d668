"""Laptop workflow: one correlation on the embedded scheduler (no cluster to set up).

chunkdic's default scheduler is a pool of threads in this process: tasks read their
blocks of the scans straight from the Zarr stores, so memory stays at a few blocks per
thread whatever the scan size. This script correlates two scans and prints the mean
strain; without scans it first writes a small synthetic pair with a known field and
prints the error against it.

Run here (a 64³ synthetic pair, a few seconds)::

    python workflows/laptop.py

On real scans (Zarr scan groups from ``chunkdic ingest``, or ``.npy``)::

    python workflows/laptop.py ref.zarr def.zarr --element-size 16 --workdir run1
    python workflows/laptop.py ref.zarr def.zarr --element-size 8 --level 2 --threads 4

Re-running the same command after an interruption (Ctrl-C, a closed lid, a crash)
resumes the correlation from its last checkpoint; a finished result is reused; pass
``--overwrite`` to start over.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import dask.config
import numpy as np

import chunkdic
from chunkdic.results.strain import strain_summary
from chunkdic.synth import synthetic


def show(event: dict) -> None:
    """Print one line per correlation event (``chunkdic correlate`` prints richer ones)."""
    stage = event["stage"]
    if stage == "start":
        print(f"  running on {event['scheduler']}; levels {event['levels']}; {event['nodes']} nodes", flush=True)
    elif stage == "iteration":
        print(f"  level {event['level']} iteration {event['iteration']:2d}: gap {100 * event['gap']:.3f} %", flush=True)
    elif stage == "level":
        print(f"  level {event['level']}: {event['status']} in {event['seconds']:.1f} s", flush=True)
    elif stage == "resume":
        print(f"  resuming from the checkpoint: level {event['level']}, iteration {event['iteration']}", flush=True)


def synthetic_pair(workdir: Path, size: int, overwrite: bool) -> dict:
    """A foam-like pair with a known affine field (-1 % along z, 0.5 % shear, a translation)."""
    c = (size - 1) / 2.0
    field = synthetic.Affine(matrix=((-0.01, 0.0, 0.005), (0.0, 0.0, 0.0), (0.005, 0.0, 0.0)),
                             center=(c, c, c), translation=(1.3, -0.7, 0.4))
    pair = workdir / "pair"
    if (pair / "field.json").exists() and not overwrite:
        print(f"reusing the synthetic pair in {pair}")
    else:
        print(f"writing a {size}^3 synthetic pair to {pair}")
        synthetic.synthesize(pair, (size,) * 3, field=field, seed=1, overwrite=True)
    return {"reference": str(pair / "ref.zarr"), "deformed": str(pair / "def.zarr"),
            "field": synthetic.load_field(pair)}


def correlate_once(ref, deformed, output: Path, *, overwrite: bool, **kw):
    """Correlate unless ``output`` already holds a complete result (then read it)."""
    if output.exists() and not overwrite:
        try:
            res = chunkdic.open_result(output)
            print(f"{output} is complete: reused (--overwrite to redo)")
            return res
        except chunkdic.InputError:
            pass  # an interrupted run: correlate() resumes it
    return chunkdic.correlate(ref, deformed, output=output, overwrite=overwrite, progress=show, **kw)


def nodal_error(result, field) -> np.ndarray:
    """RMS error of (Uz, Uy, Ux) at the nodes against ``field`` (voxels of the result's level)."""
    f = float(result.info["scale"])
    truth = field.displacement(*(f * result.node_coords + (f - 1) / 2)) / f
    return np.sqrt(((result.displacement - truth) ** 2).mean(axis=(1, 2, 3)))


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("ref", nargs="?", help="reference scan (default: a synthetic pair)")
    p.add_argument("deformed", nargs="?", help="deformed scan")
    p.add_argument("--workdir", default="chunkdic-laptop", help="output directory (default ./chunkdic-laptop)")
    p.add_argument("--size", type=int, default=64, help="edge of the synthetic scans (no scans given)")
    p.add_argument("--element-size", type=int, default=8, help="element edge, voxels of --level")
    p.add_argument("--level", type=int, default=0, help="pyramid level (2 = the paper's 4^3 compression)")
    p.add_argument("--roi", default=None, help="z0:z1,y0:y1,x0:x1 in level-0 voxels")
    p.add_argument("--threads", type=int, default=None, help="threads of the embedded scheduler (default: all cores)")
    p.add_argument("--overwrite", action="store_true", help="start over instead of resuming / reusing")
    args = p.parse_args(argv)
    if (args.ref is None) != (args.deformed is None):
        p.error("give both scans or none")

    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    field = None
    if args.ref is None:
        pair = synthetic_pair(workdir, args.size, args.overwrite)
        ref, deformed, field = pair["reference"], pair["deformed"], pair["field"]
    else:
        ref, deformed = args.ref, args.deformed

    t0 = time.perf_counter()
    with dask.config.set({"chunkdic.num-threads": args.threads}):
        result = correlate_once(ref, deformed, workdir / "result.zarr", overwrite=args.overwrite,
                                element_size=args.element_size, level=args.level, roi=args.roi)
    print(f"{result!r} in {time.perf_counter() - t0:.1f} s")
    s = strain_summary(result)
    print(f"mean strain without the outermost elements: eps_zz {s.eps_zz:+.5f}, tr {s.volume_change:+.5f}")
    out = {"result": result, "strain": s}
    if field is not None:
        out["rms_error"] = nodal_error(result, field)
        print("RMS nodal error vs the known field (Uz, Uy, Ux): "
              + ", ".join(f"{v:.4f}" for v in out["rms_error"]) + " voxel")
    return out


if __name__ == "__main__":
    main()
