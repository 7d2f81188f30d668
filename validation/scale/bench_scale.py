"""End-to-end scale benchmark: synthesize → pyramid → correlate → strain → report.

The whole pipeline of a specimen, out of core, on a ``LocalCluster`` of ``--workers``
single-threaded worker processes (so that the client and the workers are separate
processes and their peak memory is measured separately):

1. synthesize a reference/deformed pair of ``--size``³ ``--dtype`` scans with the paper's
   compression-band field (``synthetic.Band``: -5 % axial strain in a band a quarter of
   the height wide, lateral expansion 0.3), chunk by chunk, by the workers;
2. build the ``2^s`` sum pyramids of both scans (level 2 = the paper's 4³ compression);
3. correlate on ``--level`` (default 2) with ``ell = --element-size`` (default 8),
   starting on the coarsest useful level (chosen by the engine);
4. mean strain (without the outermost elements) and the report figures.

Per stage it prints: wall time; voxels per second (synthesize/pyramid: level-0 voxels of
both scans; correlate: voxel passes = ROI voxels x passes over them, M + rigid + every
Gauss-Newton pass, all levels); the peak resident memory of the client process (which
also hosts the LocalCluster's scheduler) and of each worker process (kernel high-water
mark ``VmHWM``, reset at the start of every stage through ``/proc/self/clear_refs``, and a
50 ms psutil sampler as a fallback); the bytes that all processes read and wrote
(``read_chars`` / ``write_chars`` of ``psutil.Process.io_counters``: what the processes
asked of the file system, page-cache hits included); the size on disk of the stores. At
the end: the nodal displacement error (RMS and max over nodes, per component and of the
vector) against the known field, in voxels of the correlated level and of level 0.

``--iterations-only`` skips strain and report, runs ``--iterations`` Gauss-Newton
iterations per level (tolerance 0) and extrapolates a full run: the measured time of every
level (``M``, B-spline prefilter, gap evaluations, passes) plus ``N - --iterations`` more
passes on ``--level`` at the median measured pass time (``N`` = ``--assume-iterations``),
and the same times 8 and 64 for 2x and 4x the edge.

Usage (the commands of the table in docs/distributed.md)::

    python validation/scale/bench_scale.py --size 512
    python validation/scale/bench_scale.py --size 1024
    python validation/scale/bench_scale.py --size 1024 --level 0 --element-size 16 --iterations-only
    python validation/scale/bench_scale.py --size 2048 --workdir /big/disk   # 34 GB of uint16 scans

Data go to ``--workdir/scale<size>`` and are deleted at the end unless ``--keep``.
A JSON record of the run is written next to them (and kept).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import shutil
import sys
import threading
import time
from pathlib import Path

GiB = 1024**3
MiB = 1024**2


# --------------------------------------------------------------------------- memory / io probes


def _hwm_bytes() -> int | None:
    """Peak RSS of this process since the last reset (Linux ``VmHWM``), bytes."""
    try:
        with open("/proc/self/status") as fh:
            m = re.search(r"VmHWM:\s+(\d+)\s+kB", fh.read())
        return int(m.group(1)) * 1024 if m else None
    except OSError:
        return None


def _reset_hwm() -> bool:
    """Reset ``VmHWM`` to the current RSS (Linux >= 4.0); False if not possible."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


class _Sampler:
    """Peak RSS of this process: kernel high-water mark, and a 50 ms sampling thread."""

    def __init__(self, interval: float = 0.05):
        import psutil

        self._proc = psutil.Process()
        self._interval = interval
        self._lock = threading.Lock()
        self._peak = self._proc.memory_info().rss
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="rss-sampler", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.wait(self._interval):
            rss = self._proc.memory_info().rss
            with self._lock:
                self._peak = max(self._peak, rss)

    def reset(self) -> None:
        _reset_hwm()
        with self._lock:
            self._peak = self._proc.memory_info().rss

    def read(self) -> dict:
        io = self._proc.io_counters()
        with self._lock:
            sampled = self._peak
        hwm = _hwm_bytes()
        return {
            "peak_rss": max(sampled, hwm or 0),
            "rss": self._proc.memory_info().rss,
            "read_chars": getattr(io, "read_chars", io.read_bytes),
            "write_chars": getattr(io, "write_chars", io.write_bytes),
            "pid": self._proc.pid,
        }

    def stop(self) -> None:
        self._stop.set()


def _worker_start_sampler(dask_worker=None):
    """Runs on every worker (``client.run``): attach a sampler to the worker object."""
    if getattr(dask_worker, "_bench_sampler", None) is None:
        dask_worker._bench_sampler = _Sampler()
    return True


def _worker_reset(dask_worker=None):
    dask_worker._bench_sampler.reset()
    return dask_worker._bench_sampler.read()


def _worker_read(dask_worker=None):
    return dask_worker._bench_sampler.read()


class Monitor:
    """Per-stage wall time, peak memory of the client and of each worker, bytes read/written."""

    def __init__(self, client):
        self.client = client
        self.local = _Sampler()
        client.run(_worker_start_sampler)
        self.stages: list[dict] = []

    def _snapshot(self, reset: bool) -> dict:
        if reset:
            self.local.reset()
        workers = self.client.run(_worker_reset if reset else _worker_read)
        return {"client": self.local.read(), "workers": workers}

    @contextlib.contextmanager
    def stage(self, name: str, **extra):
        before = self._snapshot(reset=True)
        print(f"== {name} ...", flush=True)
        t0 = time.perf_counter()
        row = {"stage": name, **extra}
        try:
            yield row
        finally:
            row["seconds"] = time.perf_counter() - t0
            after = self._snapshot(reset=False)
            row["client_peak_rss"] = after["client"]["peak_rss"]
            row["worker_peak_rss"] = {w: a["peak_rss"] for w, a in sorted(after["workers"].items())}
            procs = [("client", before["client"], after["client"])] + [
                (w, before["workers"].get(w), a) for w, a in after["workers"].items()
            ]
            read = written = 0
            for _, b, a in procs:
                if b is None or b.get("pid") != a.get("pid"):  # a restarted worker: count from zero
                    b = {"read_chars": 0, "write_chars": 0}
                read += a["read_chars"] - b["read_chars"]
                written += a["write_chars"] - b["write_chars"]
            row["bytes_read"], row["bytes_written"] = read, written
            self.stages.append(row)
            print(_stage_line(row), flush=True)

    def close(self) -> None:
        self.local.stop()


# --------------------------------------------------------------------------- helpers


def _du(*paths) -> int:
    total = 0
    for p in paths:
        p = Path(p)
        if p.is_file():
            total += p.stat().st_size
        for root, _, files in os.walk(p):
            for f in files:
                with contextlib.suppress(OSError):
                    total += os.stat(os.path.join(root, f)).st_size
    return total


def _fmt_bytes(n: float) -> str:
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if abs(n) >= size:
            return f"{n / size:.2f} {unit}"
    return f"{n:.0f} B"


def _fmt_rate(v: float) -> str:
    return f"{v / 1e6:.1f} M" if v >= 1e5 else f"{v / 1e3:.1f} k"


def _stage_line(row: dict) -> str:
    rate = row.get("voxels", 0) / max(row["seconds"], 1e-9)
    workers = ", ".join(f"{r / MiB:.0f}" for r in row["worker_peak_rss"].values())
    return (
        f"   {row['stage']}: {row['seconds']:.1f} s, {_fmt_rate(rate)}voxel/s, peak RSS client "
        f"{row['client_peak_rss'] / MiB:.0f} MiB, workers [{workers}] MiB, read {_fmt_bytes(row['bytes_read'])}, "
        f"written {_fmt_bytes(row['bytes_written'])}"
        + (f", on disk {_fmt_bytes(row['disk'])}" if "disk" in row else "")
    )


def _print_event(event: dict) -> None:
    from chunkdic.cli.common import format_event

    line = format_event(event)
    if line:
        print("   " + line, flush=True)


def _fraction_printer(step: str):
    """``progress(fraction)`` callback printing every 10 % with the elapsed time and an ETA."""
    t0, next_ = time.perf_counter(), [0.1]

    def report(frac: float) -> None:
        if frac + 1e-9 < next_[0]:
            return
        dt = time.perf_counter() - t0
        eta = dt * (1 - frac) / frac if frac > 0 else math.nan
        print(f"   {step}: {frac:4.0%} ({dt:.0f} s, about {eta:.0f} s left)", flush=True)
        while next_[0] <= frac + 1e-9:
            next_[0] += 0.1

    return report


def _voxel_passes(events: list[dict]) -> tuple[int, dict]:
    """Voxels processed by the correlation: per level, ROI voxels x passes (M, rigid, b)."""
    per_level: dict[int, dict] = {}
    voxels: dict[int, int] = {}
    for e in events:
        s = e.get("level")
        if e["stage"] == "matrix":
            voxels[s] = e["voxels"]
            per_level.setdefault(s, {"passes": 0, "iterations": 0, "seconds": 0.0})["passes"] += 1
        elif e["stage"] in ("rigid", "iteration"):
            d = per_level.setdefault(s, {"passes": 0, "iterations": 0, "seconds": 0.0})
            d["passes"] += 1
            if e["stage"] == "iteration":
                d["iterations"] += 1
        elif e["stage"] == "gaps":
            per_level[s]["passes"] += 2
        elif e["stage"] == "level":
            per_level[s]["seconds"] = e["seconds"]
            per_level[s]["status"] = e["status"]
    total = 0
    for s, d in per_level.items():
        d["voxels"] = voxels.get(s, 0)
        total += d["voxels"] * d["passes"]
    return total, per_level


def _truth(result, field, level: int):
    """The prescribed field at the result's nodes, (3, nz, ny, nx) voxels of ``level``."""
    f = 2.0**level
    x0 = f * result.node_coords + (f - 1) / 2  # DESIGN.md: level-s voxel centre in level 0
    return field.displacement(*x0) / f


def _error(result, field, level: int) -> dict:
    """Nodal error against the known field (level voxels and level-0 voxels)."""
    import numpy as np

    truth = _truth(result, field, level)
    err = result.displacement - truth
    norm = np.sqrt((err**2).sum(axis=0))
    out = {
        "rms": [float(np.sqrt((err[i] ** 2).mean())) for i in range(3)],
        "max": [float(np.abs(err[i]).max()) for i in range(3)],
        "rms_vector": float(np.sqrt((norm**2).mean())),
        "max_vector": float(norm.max()),
        "truth_range": [float(np.ptp(truth[i])) for i in range(3)],
    }
    out["rms_vector_level0"] = out["rms_vector"] * 2**level
    out["max_vector_level0"] = out["max_vector"] * 2**level
    return out


def _same_pair(pair_dir: Path, field, n: int, args) -> bool:
    """Whether ``pair_dir`` holds a complete synthetic pair of this size, dtype, seed and field."""
    from chunkdic.synth import synthetic

    try:
        meta = synthetic.load_metadata(pair_dir)
        scan = __import__("chunkdic").open_scan(pair_dir / "ref.zarr")
    except Exception:  # noqa: BLE001 - anything missing means "synthesize again"
        return False
    return (meta.get("field") == field.to_json() and scan.shape(0) == (n, n, n)
            and scan.dtype(0).name == args.dtype
            and {k: meta.get("texture", {}).get(k) for k in ("seed", *_texture(args))}
            == {"seed": args.seed, **_texture(args)})


def _texture(args) -> dict:
    """Texture lengths of the benchmark's specimen (level-0 voxels)."""
    k = args.texture_scale
    return {"cell_size": 8.0 * k, "bead_size": 64.0 * k, "wall_width": 2.5 * k, "skin_width": 4.0 * k}


def _check_disk(workdir: Path, args, reuse: bool) -> None:
    import numpy as np

    from chunkdic.io.coarsen import pyramid_dtype

    size = args.size
    # level 0 of two scans uncompressed, plus the pyramids (levels 1.. in 4-byte sums: 1/2, 1/16...)
    scans = 0 if reuse else 2 * size**3 * (np.dtype(args.dtype).itemsize + 4 / 8 * 8 / 7)
    # the correlation's scratch on its finest level, at most the whole level: the float32
    # B-spline coefficients of g and the haloed copy of f (the level's dtype)
    scratch = (size >> args.level) ** 3 * (4 + pyramid_dtype(args.dtype, args.level).itemsize)
    need = scans + scratch
    free = shutil.disk_usage(workdir).free
    print(f"# disk: up to {_fmt_bytes(need)} needed (uncompressed estimate: scans {_fmt_bytes(scans)}, "
          f"scratch {_fmt_bytes(scratch)}), {_fmt_bytes(free)} free in {workdir}")
    if need > 0.9 * free and not args.force:
        sys.exit(f"not enough free disk in {workdir} for a {size}^3 pair: pass --workdir elsewhere or --force")


# --------------------------------------------------------------------------- main


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=512, help="scan edge, voxels (512, 1024, 2048)")
    p.add_argument("--dtype", default="uint16", choices=("uint8", "uint16"))
    p.add_argument("--level", type=int, default=2, help="pyramid level correlated (2 = the paper's 4^3)")
    p.add_argument("--element-size", type=int, default=8, help="ell, voxels of --level")
    p.add_argument("--interpolation", default="cubic", choices=("cubic", "linear"))
    p.add_argument("--workers", type=int, default=2, help="LocalCluster worker processes (1 thread each)")
    p.add_argument("--worker-memory", default="auto", help="memory limit per worker (dask syntax, e.g. 4GiB)")
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--texture-scale", type=float, default=None,
                   help="multiply every length of the default foam texture (cells 8, beads 64, walls 2.5, "
                        "skins 4 voxels) by this; default 2^--level")
    p.add_argument("--workdir", default="/tmp/chunkdic-scale", help="where the scans go (needs disk)")
    p.add_argument("--keep", action="store_true", help="keep the scans and result")
    p.add_argument("--force", action="store_true", help="run even if the disk looks too small")
    p.add_argument("--reuse", action="store_true",
                   help="reuse the pair of an earlier --keep run with the same size, dtype and seed")
    p.add_argument("--iterations-only", action="store_true",
                   help="time --iterations Gauss-Newton passes per level and extrapolate a full run")
    p.add_argument("--iterations", type=int, default=3, help="Gauss-Newton iterations per level with --iterations-only")
    p.add_argument("--assume-iterations", type=int, default=8,
                   help="Gauss-Newton passes assumed by the extrapolation of --iterations-only")
    args = p.parse_args(argv)
    # The texture must look on the correlated level as the default texture looks on level 0:
    # after the 4^3 sums of level 2 the default 8-voxel cells are 2 voxels across and their
    # 2.5-voxel walls 0.6 voxel thick, which cubic interpolation cannot follow (nodal RMS
    # error 0.08 level-2 voxels where level 0 gives 0.01, and the run does not converge).
    if args.texture_scale is None:
        args.texture_scale = float(2**args.level)

    from distributed import Client, LocalCluster

    import chunkdic
    from chunkdic.synth import synthetic

    n = args.size
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    run_dir = workdir / f"scale{n}"
    pair_dir, result_path, report_dir = run_dir / "pair", run_dir / "result.zarr", run_dir / "report"
    c = (n - 1) / 2.0
    field = synthetic.Band(center_z=c, width=n / 4.0, strain=-0.05, lateral=0.3, center_y=c, center_x=c)
    reuse = args.reuse and _same_pair(pair_dir, field, n, args)
    _check_disk(workdir, args, reuse)
    if run_dir.exists():
        for q in ([result_path, report_dir] if reuse else [run_dir]):
            shutil.rmtree(q, ignore_errors=True)
    run_dir.mkdir(parents=True, exist_ok=True)
    top = args.level + 3
    while top > args.level and n // 2**top < 16:
        top -= 1
    record = {"args": vars(args), "field": field.to_json(), "host_cpus": os.cpu_count(),
              "host_memory": __import__("psutil").virtual_memory().total}

    cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address="127.0.0.1:0", memory_limit=args.worker_memory)
    client = Client(cluster)
    print(f"# LocalCluster: {args.workers} workers x 1 thread, dashboard {client.dashboard_link}", flush=True)
    mon = Monitor(client)
    t_total = time.perf_counter()
    try:
        if reuse:
            print(f"# reusing the pair in {pair_dir} (--reuse): no synthesize stage", flush=True)
            paths = {k: str(pair_dir / f) for k, f in (("reference", "ref.zarr"), ("deformed", "def.zarr"))}
        else:
            with mon.stage("synthesize", voxels=2 * n**3) as row:
                paths = synthetic.synthesize(pair_dir, (n,) * 3, field=field, seed=args.seed, dtype=args.dtype,
                                             levels=0, overwrite=True, progress=_fraction_printer("synthesize"),
                                             **_texture(args))
                row["disk"] = _du(pair_dir)
        with mon.stage("pyramid", voxels=2 * n**3, levels=top) as row:
            for key in ("reference", "deformed"):
                chunkdic.build_pyramid(paths[key], top, progress=_fraction_printer(f"pyramid {key}"))
            row["disk"] = _du(pair_dir)
        events: list[dict] = []

        def progress(event):
            events.append(event)
            _print_event(event)

        kw = dict(element_size=args.element_size, level=args.level, interpolation=args.interpolation,
                  scheduler=client, progress=progress)
        if args.iterations_only:
            kw.update(tolerance=0.0, max_iterations=args.iterations)
        else:
            kw.update(output=result_path, overwrite=True)
        with mon.stage("correlate") as row:
            result = chunkdic.correlate(paths["reference"], paths["deformed"], **kw)
            row["voxels"], row["levels"] = _voxel_passes(events)
            row["nodes"] = list(result.displacement.shape[1:])
            row["status"] = result.info["status"]
            row["final_gap"] = result.info["final_gap"]
        record["error"] = _error(result, field, args.level)
        if args.iterations_only:
            record["extrapolation"] = _extrapolate(events, args)
        else:
            with mon.stage("strain") as row:
                from chunkdic.results.strain import mean_strain, strain_summary

                s = strain_summary(result)
                # The mean of dUz/dZ over the inner box only depends on Uz at its faces, and
                # the band's Uz depends on Z alone: the same average of the exact nodal field
                # is the exact mean strain of the prescribed field over that box.
                t = mean_strain(_truth(result, field, args.level), result.info["element_size"])
                row["eps_zz"], row["eps_zz_corrected"] = s.eps_zz, s.eps_zz_corrected
                row["volume_change"], row["eps_zz_true"], row["volume_change_true"] = (
                    s.volume_change, t.eps_zz, t.volume_change)
                print(f"   mean strain (inner elements): eps_zz {s.eps_zz:+.5f} (true {t.eps_zz:+.5f}), "
                      f"corrected {s.eps_zz_corrected:+.5f}, tr {s.volume_change:+.5f} (true {t.volume_change:+.5f})",
                      flush=True)
            with mon.stage("report") as row:
                from chunkdic.plot.report import report

                figures = report(result, report_dir, progress=lambda msg: print("   " + msg, flush=True))
                row["figures"] = sorted(figures)
        record["total_seconds"] = time.perf_counter() - t_total
    finally:
        mon.close()
        client.close()
        cluster.close()
    record["stages"] = mon.stages
    _print_table(record, args)
    out_json = workdir / f"bench_scale_{n}{'_iter' if args.iterations_only else ''}_L{args.level}.json"
    out_json.write_text(json.dumps(record, indent=1, default=str))
    print(f"# record: {out_json}")
    if not args.keep:
        shutil.rmtree(run_dir, ignore_errors=True)
        print(f"# removed {run_dir}")
    return record


def _extrapolate(events: list[dict], args) -> dict:
    """Full-run estimate from the timed passes on ``--level`` (coarser levels as measured)."""
    import statistics

    lv = args.level
    m = [e for e in events if e["stage"] == "matrix" and e["level"] == lv][-1]
    its = [e for e in events if e["stage"] == "iteration" and e["level"] == lv and e.get("assemble_seconds") is not None]
    it_s = statistics.median(e["seconds"] for e in its) if its else math.nan
    coarse = sum(e["seconds"] for e in events if e["stage"] == "level" and e["level"] != lv)
    level_s = [e for e in events if e["stage"] == "level" and e["level"] == lv][-1]["seconds"]
    # measured on --level: M, prefilter, 2 gap passes and --iterations + 1 b passes; a full run
    # with N iterations makes N - --iterations more passes
    one = level_s + max(0, args.assume_iterations - args.iterations) * it_s
    out = {"matrix_seconds": m["seconds"], "iteration_seconds": it_s, "voxels": m["voxels"], "level_seconds": level_s,
           "coarse_levels_seconds": coarse, "b_voxels_per_second": m["voxels"] / it_s if its else math.nan,
           "estimate_seconds": {f"{args.size}": coarse + one, f"{2 * args.size}": 8 * (coarse + one),
                                f"{4 * args.size}": 64 * (coarse + one)}}
    print(f"# level {lv}: M {m['seconds']:.1f} s, {it_s:.1f} s per Gauss-Newton pass "
          f"({m['voxels'] / it_s / 1e6:.1f} Mvoxel/s), coarser levels {coarse:.1f} s; full run with "
          f"{args.assume_iterations} passes: "
          + ", ".join(f"{k}^3 ~ {v / 60:.1f} min" for k, v in out["estimate_seconds"].items()), flush=True)
    return out


def _print_table(record: dict, args) -> None:
    n = args.size
    print()
    print(f"## {n}^3 {args.dtype} pair, level {args.level}, ell {args.element_size}, "
          f"texture x{args.texture_scale:g}, {args.workers} workers, total {record.get('total_seconds', float('nan')):.0f} s")
    print()
    print("| stage | wall (s) | voxels/s | peak RSS client (MiB) | peak RSS workers (MiB) | read | written | on disk |")
    print("|---|---|---|---|---|---|---|---|")
    for row in record["stages"]:
        rate = row.get("voxels", 0) / max(row["seconds"], 1e-9)
        workers = " / ".join(f"{r / MiB:.0f}" for r in row["worker_peak_rss"].values())
        disk = _fmt_bytes(row["disk"]) if "disk" in row else ""
        print(f"| {row['stage']} | {row['seconds']:.1f} | {_fmt_rate(rate) if rate else '-'} | "
              f"{row['client_peak_rss'] / MiB:.0f} | {workers} | {_fmt_bytes(row['bytes_read'])} | "
              f"{_fmt_bytes(row['bytes_written'])} | {disk} |")
    corr = next((r for r in record["stages"] if r["stage"] == "correlate"), None)
    if corr:
        print()
        print("| level | ROI voxels | passes | GN iterations | status | s |")
        print("|---|---|---|---|---|---|")
        for s, d in sorted(corr["levels"].items(), reverse=True):
            print(f"| {s} | {d['voxels']} | {d['passes']} | {d['iterations']} | {d.get('status', '')} | "
                  f"{d['seconds']:.1f} |")
    e = record["error"]
    print()
    print(f"displacement error vs the known field, voxels of level {args.level} (Uz, Uy, Ux): "
          f"RMS {', '.join(f'{v:.4f}' for v in e['rms'])}; max {', '.join(f'{v:.4f}' for v in e['max'])}; "
          f"|u| RMS {e['rms_vector']:.4f} (= {e['rms_vector_level0']:.3f} level-0 voxels), max {e['max_vector']:.4f} "
          f"(= {e['max_vector_level0']:.3f}); true field spans {', '.join(f'{v:.2f}' for v in e['truth_range'])}")
    peak = max([r["client_peak_rss"] for r in record["stages"]]
               + [v for r in record["stages"] for v in r["worker_peak_rss"].values()])
    print(f"largest peak RSS of any process, any stage: {peak / GiB:.2f} GiB")


if __name__ == "__main__":
    main()
