"""Time from a restart to the first Gauss–Newton pass after a kill during level 0.

Runs ``python -m chunkdic correlate PAIR/ref.zarr PAIR/def.zarr -o OUT ARGS`` in a
subprocess (a session of its own) and SIGKILLs its whole process group when a progress line
starts with ``--kill-at`` (default ``level 0 iter  1``: the run has finished two level-0
passes and is in its third), as a batch job's end or ``kill -9 -- -PGID`` does: the client
and, with ``-- --scheduler local:2``, its cluster's processes. ``--meanwhile "ARGS"`` runs
``python -m chunkdic ARGS`` (``{pair}`` and ``{workdir}`` replaced) between the kill and the restart,
in the same scratch root, as another run of the machine may. Then runs the same command again and times, from its
start, the end of its first level-0 pass (its first ``level 0 iter`` line), and takes the
pass's own seconds from that line: ``setup`` = restart to first pass end − the pass, what
a kill costs beyond the interrupted pass. The restart's lines say what it built again
(``M built``, ``g prepared``) or reused (``M read``, ``reusing …``). The restart is killed
once its first pass is timed (the rest of the run is not what is measured).

``--pythonpath`` picks the chunkdic to run: a checkout before a change and one after it
give the before/after figures. Every process runs under ``nice -n 12``; the scratch
directory is ``WORKDIR/scratch`` (``chunkdic.scratch-directory``), the output
``WORKDIR/out.zarr``; both are removed before each repeat and at the end. The pair is
read, never written.

Usage::

    python validation/scale/bench_resume.py /big/grains512 --workdir /big/resume512 \\
        --pythonpath /path/to/checkout --repeats 2 -- -l 16 --level 0
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

PASS = re.compile(r"level 0 iter +\d+: .*\((\d+\.\d+) s\)")


def _spawn(cmd, env):
    # run from the checkout asked for: ``python -m`` puts the working directory first on sys.path;
    # a session of its own, so that a kill reaches the whole job (a LocalCluster's workers too)
    return subprocess.Popen(["nice", "-n", "12", *cmd], stderr=subprocess.PIPE, text=True, env=env,
                            cwd=env["PYTHONPATH"], start_new_session=True)


def _kill_job(proc) -> None:
    """SIGKILL the process group of ``proc`` and wait until every process of it is gone."""
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    for _ in range(600):
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.1)


def kill_at(cmd, env, at: str) -> list[str]:
    """Run ``cmd`` and SIGKILL it at its first stderr line starting with ``at``; its lines."""
    proc, lines = _spawn(cmd, env), []
    for line in proc.stderr:
        lines.append(line.rstrip())
        if line.startswith(at):
            _kill_job(proc)
            break
    proc.wait()
    if not lines or not lines[-1].startswith(at):
        raise SystemExit("the run ended before " + repr(at) + ":\n" + "\n".join(lines[-20:]))
    return lines


def restart(cmd, env) -> dict:
    """Run ``cmd`` again: seconds to its first level-0 pass line, that pass's seconds, its lines."""
    t0 = time.perf_counter()
    proc, lines, first = _spawn(cmd, env), [], None
    for line in proc.stderr:
        lines.append(line.rstrip())
        m = PASS.match(line)
        if m:
            first = (time.perf_counter() - t0, float(m.group(1)))
            _kill_job(proc)
            break
    proc.wait()
    if first is None:
        raise SystemExit("the restart printed no level-0 pass:\n" + "\n".join(lines[-20:]))
    return {"to_first_pass": first[0], "pass": first[1], "setup": first[0] - first[1],
            "rebuilt": [ln for ln in lines if "M built" in ln or "g prepared" in ln or "M read" in ln
                        or ln.startswith("resuming") or "low-passed again" in ln]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("pair", type=Path, help="folder of a synthetic pair (ref.zarr, def.zarr)")
    ap.add_argument("--workdir", type=Path, required=True, help="output and scratch go here (removed)")
    ap.add_argument("--pythonpath", default=str(Path(__file__).resolve().parents[2]),
                    help="the chunkdic checkout to run (default: this one)")
    ap.add_argument("--kill-at", default="level 0 iter  1")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--meanwhile", default=None,
                    help='chunkdic arguments run between the kill and the restart, e.g. "correlate {pair}/ref.zarr '
                         '{pair}/def.zarr -o {workdir}/other.zarr -l 8 --level 2 --coarsest 2"')
    argv = sys.argv[1:] if argv is None else list(argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []  # correlate's options, e.g. -- -l 16 --level 0
    a = ap.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    a.args = extra
    out, scratch = a.workdir / "out.zarr", a.workdir / "scratch"
    cmd = [sys.executable, "-m", "chunkdic", "correlate", str(a.pair / "ref.zarr"), str(a.pair / "def.zarr"),
           "-o", str(out), *a.args]
    env = dict(os.environ, PYTHONPATH=a.pythonpath, DASK_CHUNKDIC__SCRATCH_DIRECTORY=str(scratch))
    runs = []
    try:
        for _ in range(a.repeats):
            shutil.rmtree(a.workdir, ignore_errors=True)
            scratch.mkdir(parents=True)
            load = open("/proc/loadavg").read().split()[:3]
            killed = kill_at(cmd, env, a.kill_at)
            if a.meanwhile:
                args = a.meanwhile.replace("{pair}", str(a.pair)).replace("{workdir}", str(a.workdir)).split()
                other = [sys.executable, "-m", "chunkdic", *args]
                subprocess.run(["nice", "-n", "12", *other], env=env, cwd=env["PYTHONPATH"], check=True,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            again = restart(cmd, env)
            again.update(load=load, killed_after=[ln for ln in killed if "M built" in ln or "g prepared" in ln])
            runs.append(again)
            print(json.dumps(again), flush=True)
    finally:
        shutil.rmtree(a.workdir, ignore_errors=True)
    summary = {key: statistics.median(r[key] for r in runs) for key in ("to_first_pass", "pass", "setup")}
    print(json.dumps({"pythonpath": a.pythonpath, "args": a.args, "kill_at": a.kill_at, "meanwhile": a.meanwhile,
                      "repeats": a.repeats,
                      "median_seconds": summary}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
