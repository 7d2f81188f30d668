"""A whole-specimen workflow as a user runs it, stage by stage: time, memory, bytes, error.

Runs the CLI (the embedded default scheduler unless ``--scheduler``) on an existing
synthetic pair (``chunkdic synth``: its ``field.json`` holds the known field) and prints,
per stage — ``correlate --plan``, ``correlate``, ``strain``, ``report``, ``export``
(VTU, node CSV, OME-NGFF fields) — the wall time, the peak resident memory of the stage's
process (``ru_maxrss`` from ``wait4``: the largest of the process and its waited
children), what it asked of the file system (``read_chars`` / ``write_chars``, page-cache
hits included, sampled every 0.5 s by psutil) and what reached the disk (``ru_inblock`` /
``ru_oublock`` × 512 B), and where the peak was set (the progress line when the
process's high-water mark last rose, sampled every 0.2 s), and with ``--scheduler local:N``
the peak of each process apart (the client, the nanny and the workers; RSS sampled every
0.5 s). After the correlation: the
end-to-end rate in Mvoxel of ROI per second per core, the rate per Gauss–Newton pass on
the finest level (from the run's event log), and the field's error against the truth by the project's scoring rule (the
field trilinear between the nodes, as a viewer shows it, RMS of the vector error over
voxels at least ``ell`` from the faces), evaluated at ``--points`` random voxel centres
of that region, since every voxel of a 2048³ scan would be 8.6 G evaluations.

Usage (the 2048³ end-to-end run of docs/distributed.md)::

    chunkdic synth /big/grains2048 --shape 2048 --specimen grains --imaging local \\
        --field band --strain -0.05 --noise 0.02 --dtype uint16
    python validation/scale/bench_stages.py /big/grains2048 -l 16 --level 0 --workdir /big/run \\
        --fields-level 2 --record validation/scale/records/bench_stages_2048.json

Small elements on a whole specimen, every process under a memory target, on a LocalCluster
(run the same command again after a kill: the correlation resumes from its checkpoint, and
the earlier stage logs are kept as ``correlate.1.log`` …)::

    chunkdic synth /big/grains2048u8 --shape 2048 --specimen grains --imaging local \
        --field band --strain -0.05 --noise 0.02 --dtype uint8
    python validation/scale/bench_stages.py /big/grains2048u8 -l 8 --level 0 --workdir /big/run8 \
        --scheduler local:2 --memory-target 4GiB --skip report export --record /big/run8.json

The pair is read, never written; outputs go to ``--workdir`` (kept).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

GiB = 1024**3


class IoSampler:
    """Peak of ``read_chars``/``write_chars`` and RSS over a process tree, every ``interval`` s."""

    def __init__(self, pid: int, interval: float = 0.5):
        import psutil

        self.proc = psutil.Process(pid)
        self.interval = interval
        self.io: dict[int, tuple[int, int]] = {}
        self.peak_rss: dict[int, int] = {}  # each process's largest sampled RSS
        self.peak_tree_rss = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        import psutil

        while not self._stop.is_set():
            try:
                procs = [self.proc, *self.proc.children(recursive=True)]
            except psutil.Error:
                return
            rss = 0
            for p in procs:
                try:
                    c = p.io_counters()
                    self.io[p.pid] = (c.read_chars, c.write_chars)
                    one = p.memory_info().rss
                    rss += one
                    self.peak_rss[p.pid] = max(self.peak_rss.get(p.pid, 0), one)
                except psutil.Error:
                    pass
            self.peak_tree_rss = max(self.peak_tree_rss, rss)
            self._stop.wait(self.interval)

    def stop(self) -> dict:
        self._stop.set()
        self._thread.join()
        return {"read_chars": sum(r for r, _ in self.io.values()),
                "write_chars": sum(w for _, w in self.io.values()),
                "peak_tree_rss": self.peak_tree_rss,
                # the stage's process first, then its descendants (a LocalCluster's nanny and workers)
                "peak_rss_each": [self.peak_rss[p] for p in sorted(self.peak_rss, key=lambda q: (q != self.proc.pid, q))]}


class PeakTracer:
    """Where a process's peak resident memory was set: every ``interval`` s its ``VmHWM``
    (the kernel's high-water mark, so no peak between two samples is missed) and, when it
    rose, the last progress line of its log (the stage it was in). Linux only."""

    def __init__(self, pid: int, log: Path, interval: float = 0.2):
        self.status, self.log, self.interval = Path(f"/proc/{pid}/status"), log, interval
        self.rises: list[tuple[float, int, str]] = []
        self._stop = threading.Event()
        self._t0 = time.perf_counter()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _last_line(self) -> str:
        try:
            with open(self.log, "rb") as fh:
                fh.seek(max(0, fh.seek(0, 2) - 400))
                lines = [x.strip() for x in re.split(r"[\r\n]", fh.read().decode(errors="replace")) if x.strip()]
        except OSError:
            return ""
        return lines[-1] if lines else ""

    def _loop(self) -> None:
        last = 0
        while not self._stop.is_set():
            try:
                hwm = [int(x.split()[1]) * 1024 for x in self.status.read_text().splitlines() if x.startswith("VmHWM")]
            except OSError:
                return
            if hwm and hwm[0] > last:
                last = hwm[0]
                self.rises.append((round(time.perf_counter() - self._t0, 1), last, self._last_line()[:160]))
            self._stop.wait(self.interval)

    def stop(self) -> list:
        self._stop.set()
        self._thread.join()
        return self.rises


def run_stage(name: str, args: list[str], log: Path) -> dict:
    """Run ``python -m chunkdic ARGS``; stderr to ``log``; its figures."""
    cmd = [sys.executable, "-m", "chunkdic", *args]
    print(f"## {name}: {' '.join(args)}", flush=True)
    if log.exists():  # a re-run (the correlation resuming an interrupted one) keeps the earlier log
        k = 1
        while log.with_suffix(f".{k}{log.suffix}").exists():
            k += 1
        log.rename(log.with_suffix(f".{k}{log.suffix}"))
    t0 = time.perf_counter()
    with open(log, "w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True)
        sampler = IoSampler(proc.pid)
        tracer = PeakTracer(proc.pid, log) if sys.platform.startswith("linux") else None
        _, status, ru = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        io = sampler.stop()
        rises = tracer.stop() if tracer else []
        out = proc.stdout.read()
        proc.returncode = os.waitstatus_to_exitcode(status)
    row = {"stage": name, "args": args, "exit": proc.returncode, "wall_s": wall,
           "peak_rss_gib": ru.ru_maxrss * 1024 / GiB, "peak_tree_rss_gib": io["peak_tree_rss"] / GiB,
           "peak_rss_each_gib": [b / GiB for b in io["peak_rss_each"]],
           "read_chars_gb": io["read_chars"] / 1e9, "write_chars_gb": io["write_chars"] / 1e9,
           "disk_read_gb": ru.ru_inblock * 512 / 1e9, "disk_write_gb": ru.ru_oublock * 512 / 1e9,
           "user_s": ru.ru_utime, "sys_s": ru.ru_stime, "stdout": out.strip()[-2000:], "log": str(log),
           "peak_rises": rises[-12:]}
    print(f"   exit {row['exit']}  {wall:8.1f} s  peak {row['peak_rss_gib']:.2f} GiB  "
          f"read {row['read_chars_gb']:.1f} GB ({row['disk_read_gb']:.1f} from disk)  "
          f"written {row['write_chars_gb']:.1f} GB ({row['disk_write_gb']:.1f} to disk)  "
          f"cpu {ru.ru_utime + ru.ru_stime:.0f} s", flush=True)
    if len(row["peak_rss_each_gib"]) > 1:
        print("   peak of each process (sampled every 0.5 s; the stage's first): "
              + ", ".join(f"{g:.2f}" for g in row["peak_rss_each_gib"]) + " GiB", flush=True)
    # the last rises of the high-water mark: in which stage of the run the peak was set
    # (within 10 % of it; the last rise in each distinct progress line)
    last: dict[str, tuple] = {}
    for t, hwm, line in rises:
        if rises and hwm >= 0.9 * rises[-1][1]:
            last.pop(line, None)
            last[line] = (t, hwm)
    for line, (t, hwm) in list(last.items())[-4:]:
        print(f"   peak rose to {hwm / GiB:.2f} GiB at {t:.0f} s: {line or '(no progress line)'}", flush=True)
    return row


def pass_seconds(log: Path, level: int) -> list[float]:
    """Seconds of each Gauss–Newton pass of ``level``, as the run's progress lines print them."""
    pat = re.compile(rf"^level {level} iter\s+\d+: .*\((\d+(?:\.\d+)?) s\)")
    return [float(m.group(1)) for m in map(pat.match, log.read_text().splitlines()) if m]


def field_error(result_path: Path, pair: Path, ell: float, n_points: int, seed: int = 0) -> dict:
    """Between-node error (trilinear on the node grid) at random voxel centres ≥ ell from the faces
    (:func:`chunkdic.analysis.scoring.score_between_nodes` on a sample of its region)."""
    import numpy as np

    import chunkdic
    from chunkdic.analysis.scoring import score_between_nodes
    from chunkdic.synth.synthetic import load_field, load_metadata

    res = chunkdic.open_result(result_path)
    field = load_field(pair)
    shape = tuple(load_metadata(pair)["shape"])
    f = 2.0**res.level
    axes = [np.unique(f * res.node_coords[i] + (f - 1) / 2) for i in range(3)]  # level-0 voxels
    s = score_between_nodes(axes, f * res.displacement, field, shape, ell, sample=n_points, seed=seed)
    out = s.as_dict()
    out["points_drawn"] = n_points
    truth = field.displacement(*np.meshgrid(*axes, indexing="ij"))  # the truth's span over the nodes
    out["truth_range"] = [float(np.ptp(t)) for t in truth]
    return out


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("pair", type=Path, help="synthetic pair directory (ref.zarr, def.zarr, field.json)")
    p.add_argument("-l", "--element-size", type=int, default=16)
    p.add_argument("--level", type=int, default=0)
    p.add_argument("--workdir", type=Path, required=True)
    p.add_argument("--scheduler", default=None)
    p.add_argument("--memory-target", default=None, help="passed to correlate (e.g. 4GiB)")
    p.add_argument("--fields-level", type=int, default=0,
                   help="grid level of the exported fields image (export --fields-level; 2 at 2048³)")
    p.add_argument("--points", type=int, default=2_000_000, help="voxels drawn for the field error")
    p.add_argument("--skip", nargs="*", default=[], choices=["plan", "strain", "report", "export"])
    p.add_argument("--record", type=Path)
    a = p.parse_args(argv)

    import psutil

    a.workdir.mkdir(parents=True, exist_ok=True)
    res = a.workdir / f"result_l{a.element_size}_level{a.level}.zarr"
    sched = ["--scheduler", a.scheduler] if a.scheduler else []
    target = ["--memory-target", a.memory_target] if a.memory_target else []
    corr = ["correlate", str(a.pair / "ref.zarr"), str(a.pair / "def.zarr"), "-o", str(res),
            "-l", str(a.element_size), "--level", str(a.level), *sched, *target]
    git = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                         cwd=Path(__file__).parent).stdout.strip()
    record = {"meta": {"date": time.strftime("%Y-%m-%d %H:%M:%S"), "commit": git, "cores": os.cpu_count(),
                       "ram_gib": psutil.virtual_memory().total / GiB, "argv": sys.argv[1:],
                       "load_start": os.getloadavg()}, "stages": []}
    if "plan" not in a.skip:
        record["stages"].append(run_stage("plan", [*corr, "--plan"], a.workdir / "plan.log"))
        print(record["stages"][-1]["stdout"] or (a.workdir / "plan.log").read_text()[-3000:])
    record["stages"].append(run_stage("correlate", corr, a.workdir / "correlate.log"))
    if "strain" not in a.skip:
        record["stages"].append(run_stage("strain", ["strain", str(res)], a.workdir / "strain.log"))
    if "report" not in a.skip:
        record["stages"].append(run_stage("report", ["report", str(res), "-o", str(a.workdir / "report"),
                                                     "--overwrite"], a.workdir / "report.log"))
    if "export" not in a.skip:
        record["stages"].append(run_stage("export", [
            "export", str(res), "--vtk", str(a.workdir / "field.vtu"), "--csv", str(a.workdir / "nodes.csv"),
            "--fields", str(a.workdir / f"fields_level{a.fields_level}.zarr"), "--fields-level", str(a.fields_level),
            "--overwrite", *sched], a.workdir / "export.log"))
    record["meta"]["load_end"] = os.getloadavg()

    import chunkdic

    r = chunkdic.open_result(res)
    roi = r.info.get("roi_level0")
    roi_voxels = math.prod(b - a for a, b in roi) if roi else None

    def mvoxel_per_s_per_core(seconds: float) -> float:
        return roi_voxels / seconds / (os.cpu_count() or 1) / 1e6

    c = next(s for s in record["stages"] if s["stage"] == "correlate")
    record["correlate"] = {"status": r.info.get("status"), "converged": r.converged, "roi_level0": roi,
                           "nodes": int(r.displacement[0].size), "regularization": r.info.get("regularization"),
                           "iterations": {int(lv): int((r.history["level"] == lv).sum()) for lv in set(r.history["level"])},
                           "mvoxel_per_s_per_core": mvoxel_per_s_per_core(c["wall_s"]) if roi_voxels else None}
    passes = pass_seconds(a.workdir / "correlate.log", a.level)
    med = statistics.median_high(passes) if passes else 0.0
    if roi_voxels and med > 0:  # a tiny run prints its passes as "0.0 s"
        record["correlate"].update(pass_seconds=passes, pass_median_s=med,
                                   pass_mvoxel_per_s_per_core=mvoxel_per_s_per_core(med))
    record["error"] = field_error(res, a.pair, a.element_size * 2**a.level, a.points)
    print(json.dumps({"correlate": record["correlate"], "error": record["error"]}, indent=1, default=str))
    if a.record:
        a.record.write_text(json.dumps(record, indent=1, default=str))
        print(f"record: {a.record}")
    return record


if __name__ == "__main__":
    main()
