"""Adapter for the peer code pyALDVC (``pip install al-dvc``), for side-by-side benchmarks.

al-dvc is **not** a dependency of chunkdic: :func:`ensure_venv` installs it into a virtual
environment of its own, outside the repository (default
``~/.cache/chunkdic-bench/aldvc-<version>``), and :func:`run_aldvc` runs its command line
``al-dvc run --volumes REF DEF --winsize 2L --step L`` in a subprocess.

What al-dvc 1.2.1 does (read from its installed source, ``al_dvc/core/config.py``,
``core/pipeline.py``, ``mesh/grid_mesh.py``, ``export/export_npz.py``; checked by
``bench_vs_aldvc.py --selfcheck``):

- Input: one file per volume (TIFF stack, ``.npy``, ``.npz``, ``.mat``, HDF5, NIfTI,
  NRRD, or a folder of slices), read whole into memory, array order ``(z, y, x)``. Each
  volume is normalised to zero mean and unit std over the VOI (so a global gain/offset
  between scans does not matter to it).
- Grid: nodes on a regular grid of step ``winstepsize`` placed so that every subset (a
  cube of ``winsize + 1`` voxels centred on the node) stays ``3 + 2`` voxels inside the
  volume, centred in the available span; node coordinates are voxel indices (voxel ``i``
  centred at ``i``, as in chunkdic).
- Pipeline: global phase-correlation shift, coarse-to-fine NCC initial guess, local
  12-DOF IC-GN (ZNCC, Keys cubic interpolation, 7-point gradients), then the augmented
  Lagrangian (ADMM) global step: an FE smoothness term weighted by ``mu = 1e-3`` and a
  ``beta`` auto-tuned per reference by an L-curve over 5 candidates, at most 4 ADMM steps
  (``admm_tol`` 1e-2 voxel). Nodes that fail or that a median test (threshold 2) rejects
  are replaced by inpainting; their ``status`` / ``outlier`` say so. No post-smoothing
  (``disp_smoothing = 0``) and no prefilter (``prefilter_sigma = 0``) by default.
- Output (``--export npz``): ``coordinates`` (N, 3) columns ``[x, y, z]``, ``U_1`` (N, 3)
  columns ``[u, v, w] = [Ux, Uy, Uz]`` of the first pair, ``status_1`` (0 = converged),
  ``outlier_1``, ``node_valid``, ``zncc_1``; nodes ordered ``n = iz*ny*nx + iy*nx + ix``.
- Sign: ``U`` maps the reference to the deformed scan at the reference nodes
  (Lagrangian), i.e. chunkdic's ``f(X) = g(X + u(X))``: only the axis order differs.
- Threads: Numba ``prange`` kernels on ``n_threads`` cores (0 = all); the GPU backend is
  chosen automatically when numba-cuda finds a GPU.

:func:`run_aldvc` returns chunkdic's convention: points ``(3, N)`` ``(z, y, x)`` and
``u (3, N)`` ``(Uz, Uy, Ux)`` in voxels of the reference, plus a per-node ``valid`` flag.
This module is benchmark code, not part of the package; it imports nothing from al-dvc.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

VERSION = "1.2.1"
DEFAULT_VENV = Path.home() / ".cache" / "chunkdic-bench" / f"aldvc-{VERSION}"

#: al-dvc settings the benchmark sets (everything else stays at al-dvc's defaults)
FIXED_SETTINGS = {
    "backend": "numba",  # CPU, like chunkdic; "auto" picks CUDA only when a GPU is there
}

# thread pools of the child: one count for Numba, OpenMP and BLAS
_THREAD_VARS = ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


class AldvcError(RuntimeError):
    """al-dvc could not be installed or did not produce a result."""


@dataclass
class AldvcRun:
    """Outcome of one al-dvc run, in chunkdic's conventions.

    Attributes
    ----------
    points : ndarray, shape (3, N), float64, voxels
        Node positions ``(z, y, x)`` in the reference scan.
    u : ndarray, shape (3, N), float64, voxels
        Displacement ``(Uz, Uy, Ux)`` with ``f(X) = g(X + u(X))``.
    valid : ndarray, shape (N,), bool
        False where al-dvc flags the node: outside the mask, not converged in its last
        local pass, or rejected by its median test and replaced by inpainting.
    status : str
        ``"ok"``, ``"failed (exit N)"`` or ``"timeout"``.
    wall : float, s
        Wall time of the whole process (start-up and input reading included).
    pipeline_seconds : float, s
        al-dvc's own "Done in" time (reading, normalisation and correlation).
    peak_rss_mb : float
        Peak resident memory of the al-dvc process.
    info : dict
        Node status counts, ADMM steps, beta, grid shape, settings.
    cpu_seconds : float, s
        CPU time of the whole process (user + system, every thread; start-up included): on
        a shared machine the figure that wall times cannot give.
    """

    points: np.ndarray | None
    u: np.ndarray | None
    valid: np.ndarray | None
    status: str
    wall: float
    pipeline_seconds: float = float("nan")
    peak_rss_mb: float = float("nan")
    info: dict = field(default_factory=dict)
    cpu_seconds: float = float("nan")


def executable(venv: Path) -> Path:
    return Path(venv) / "bin" / "al-dvc"


def installed_version(venv: Path) -> str | None:
    """Version of al-dvc in ``venv``, or None."""
    py = Path(venv) / "bin" / "python"
    if not py.exists() or not executable(venv).exists():
        return None
    out = subprocess.run([str(py), "-c", "import importlib.metadata as m; print(m.version('al-dvc'))"],
                         capture_output=True, text=True)
    return out.stdout.strip() if out.returncode == 0 else None


def ensure_venv(venv: Path = DEFAULT_VENV, *, version: str = VERSION, log=print) -> Path:
    """Create ``venv`` with ``al-dvc==version`` unless it is there already; return ``al-dvc``.

    Uses the standard ``venv`` module and pip (PyPI, as configured on the machine). The
    environment lives outside the repository; chunkdic never imports from it.
    """
    venv = Path(venv).expanduser()
    have = installed_version(venv)
    if have == version:
        return executable(venv)
    if have is not None:
        log(f"# {venv} has al-dvc {have}; installing {version}")
    else:
        log(f"# creating {venv} and installing al-dvc=={version} (a few minutes)")
        venv.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    pip = subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q", f"al-dvc=={version}"],
                         capture_output=True, text=True)
    if pip.returncode != 0 or installed_version(venv) != version:
        raise AldvcError(f"could not install al-dvc=={version} into {venv}:\n{pip.stderr[-2000:]}")
    return executable(venv)


def write_npy(volume, path: Path, *, slab: int = 16) -> Path:
    """Write a scan as ``.npy`` (a format al-dvc reads), slab by slab along z.

    ``volume`` is anything with ``shape``, ``dtype`` and slicing (a Zarr array, a NumPy
    memmap, an ``ArrayRef``'s array): memory stays one slab. Kept if already there with the
    same shape and dtype.
    """
    path = Path(path)
    shape, dtype = tuple(int(s) for s in volume.shape), np.dtype(volume.dtype)
    if path.exists():
        old = np.load(path, mmap_mode="r")
        if old.shape == shape and old.dtype == dtype:
            return path
    tmp = path.with_name(path.name + ".tmp.npy")
    out = np.lib.format.open_memmap(tmp, mode="w+", dtype=dtype, shape=shape)
    for z in range(0, shape[0], slab):
        out[z:z + slab] = np.asarray(volume[z:z + slab])
    out.flush()
    del out
    os.replace(tmp, path)
    return path


def child_env(threads: int) -> dict:
    """Environment of a benchmarked child: every thread pool sized to ``threads``."""
    env = dict(os.environ)
    for name in _THREAD_VARS:
        env[name] = str(threads)
    env["MPLBACKEND"] = "Agg"
    env["QT_QPA_PLATFORM"] = "offscreen"
    return env


def _vm_hwm_mb(pid: int) -> float | None:
    """Peak resident memory of ``pid``'s own address space (``VmHWM``), MB; None if unknown."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def wait_with_peak(proc: subprocess.Popen, timeout: float):
    """Wait for ``proc``, tracking its peak memory; kill its process group on timeout.

    The peak is ``VmHWM`` of ``/proc/PID/status``, polled every 50 ms (it is a running
    maximum, so only a peak in the last 50 ms can be missed). ``ru_maxrss`` from ``wait4``
    is not used where ``/proc`` exists: on Linux it starts from the RSS of the forked copy
    of the parent, so every child would report at least the benchmark's own memory.

    Returns ``(exit code or None on timeout, peak MB, CPU seconds)``, the CPU time being the
    child's user + system time from ``wait4`` (every thread of the process). ``proc`` must
    have been started with ``start_new_session=True``.
    """
    t_end = time.monotonic() + timeout
    peak = None
    while True:
        hwm = _vm_hwm_mb(proc.pid)
        if hwm is not None:
            peak = hwm if peak is None else max(peak, hwm)
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid == proc.pid:
            proc.returncode = os.waitstatus_to_exitcode(status)
            return (proc.returncode, peak if peak is not None else usage.ru_maxrss / 1024.0,
                    usage.ru_utime + usage.ru_stime)
        if time.monotonic() > t_end:
            os.killpg(proc.pid, signal.SIGKILL)
            _, status, usage = os.wait4(proc.pid, 0)
            proc.returncode = None
            return None, peak if peak is not None else usage.ru_maxrss / 1024.0, usage.ru_utime + usage.ru_stime
        time.sleep(0.05)


def command(exe: Path, ref: Path, deformed: Path, out_dir: Path, *, winsize: int, step: int,
            threads: int, settings: dict | None = None) -> list[str]:
    """The ``al-dvc run`` command line the adapter runs."""
    sets = {**FIXED_SETTINGS, "n_threads": int(threads), **(settings or {})}
    return [str(exe), "run", "--volumes", str(ref), str(deformed), "--winsize", str(winsize),
            "--step", str(step), "-o", str(out_dir), "--export", "npz", "--no-strain",
            "--set", *[f"{k}={json.dumps(v)}" for k, v in sets.items()]]


def run_aldvc(exe: Path, ref: Path, deformed: Path, out_dir: Path, *, winsize: int, step: int,
              threads: int, timeout: float = 3600.0, settings: dict | None = None) -> AldvcRun:
    """Run ``al-dvc run`` on a pair and read its result in chunkdic's conventions.

    Parameters
    ----------
    exe : Path
        The ``al-dvc`` executable (:func:`ensure_venv`).
    ref, deformed : Path
        Reference and deformed scans in a format al-dvc reads (``.npy``: :func:`write_npy`).
    out_dir : Path
        Where al-dvc writes ``aldvc.npz`` and where its log goes (``aldvc.log``).
    winsize, step : int, voxels
        al-dvc's subset size (``winsize + 1`` voxels a side) and node spacing.
    threads : int
        al-dvc's ``n_threads`` and the child's Numba/OpenMP/BLAS thread counts.
    timeout : float, s
    settings : dict, optional
        More ``--set KEY=JSON`` overrides of al-dvc's parameters.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    npz = out_dir / "aldvc.npz"
    if npz.exists():
        npz.unlink()
    cmd = command(exe, ref, deformed, out_dir, winsize=winsize, step=step, threads=threads,
                  settings=settings)
    log_path = out_dir / "aldvc.log"
    t0 = time.perf_counter()
    with open(log_path, "w") as log:
        log.write(" ".join(cmd) + "\n")
        log.flush()
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                env=child_env(threads), start_new_session=True)
        rc, peak, cpu = wait_with_peak(proc, timeout)
    wall = time.perf_counter() - t0
    text = log_path.read_text(errors="replace")
    done = re.search(r"Done in ([0-9.]+)s", text)
    pipeline = float(done.group(1)) if done else float("nan")
    if rc is None:
        return AldvcRun(None, None, None, "timeout", wall, pipeline, peak, {"log": str(log_path)}, cpu)
    if rc != 0 or not npz.exists():
        tail = text.strip().splitlines()[-3:]
        return AldvcRun(None, None, None, f"failed (exit {rc})", wall, pipeline, peak,
                        {"log": str(log_path), "tail": tail}, cpu)
    points, u, valid, info = read_result(npz)
    info.update(parse_log(text))
    info["log"] = str(log_path)
    info["command"] = cmd
    return AldvcRun(points, u, valid, "ok", wall, pipeline, peak, info, cpu)


def load_run(out_dir: Path) -> AldvcRun | None:
    """An earlier :func:`run_aldvc` result left in ``out_dir`` (its ``aldvc.npz`` and log), or
    None: al-dvc's fields are deterministic for the same scans and settings, so a benchmark
    that changes only chunkdic may score them again instead of running al-dvc again. Wall,
    CPU and peak memory of the earlier process are not kept (NaN); its "Done in" time is."""
    out_dir = Path(out_dir)
    npz, log_path = out_dir / "aldvc.npz", out_dir / "aldvc.log"
    if not (npz.exists() and log_path.exists()):
        return None
    text = log_path.read_text(errors="replace")
    done = re.search(r"Done in ([0-9.]+)s", text)
    points, u, valid, info = read_result(npz)
    info.update(parse_log(text))
    info["log"], info["reused"] = str(log_path), True
    nan = float("nan")
    return AldvcRun(points, u, valid, "ok", nan, float(done.group(1)) if done else nan, nan, info, nan)


def parse_log(text: str) -> dict:
    """Diagnostics that the ``.npz`` does not keep: beta, ADMM steps, local pass summary."""
    out: dict = {}
    beta = re.search(r"Auto-tuned beta = ([0-9.eE+-]+)", text)
    if beta:
        out["beta"] = float(beta.group(1))
    steps = re.findall(r"ADMM step (\d+):", text)
    out["admm_steps"] = int(steps[-1]) if steps else 1
    local = re.findall(r"(?:Local IC-GN|Subpb1 \(3-DOF\)): (\d+)/(\d+) converged, (\d+) bad", text)
    if local:
        out["last_local_pass"] = {"converged": int(local[-1][0]), "nodes": int(local[-1][1]),
                                  "bad": int(local[-1][2])}
    shift = re.search(r"Global phase-correlation shift \(dx, dy, dz\) = \[([^\]]*)\]", text)
    if shift:
        out["global_shift_xyz"] = [float(v) for v in shift.group(1).split()]
    return out


def read_result(npz: Path, frame: int = 1):
    """Read al-dvc's ``.npz`` export and convert it to chunkdic's conventions.

    Returns
    -------
    points : ndarray, shape (3, N), float64, voxels, ``(z, y, x)``
    u : ndarray, shape (3, N), float64, voxels, ``(Uz, Uy, Ux)``
    valid : ndarray, shape (N,), bool
    info : dict
    """
    with np.load(npz, allow_pickle=False) as d:
        coords = np.asarray(d["coordinates"], dtype=np.float64)  # (N, 3) columns x, y, z
        U = np.asarray(d[f"U_{frame}"], dtype=np.float64)  # (N, 3) columns Ux, Uy, Uz
        status = np.asarray(d[f"status_{frame}"]) if f"status_{frame}" in d else np.zeros(len(U), np.int8)
        outlier = np.asarray(d[f"outlier_{frame}"], dtype=bool) if f"outlier_{frame}" in d \
            else np.zeros(len(U), bool)
        node_valid = np.asarray(d["node_valid"], dtype=bool)
        grid = [int(v) for v in d["grid_shape"]]
        para = json.loads(str(d["para_json"]))
    points = coords[:, ::-1].T.copy()
    u = U[:, ::-1].T.copy()
    valid = node_valid & (status == 0) & ~outlier
    codes, counts = np.unique(status, return_counts=True)
    info = {
        "grid_shape_zyx": grid,
        "n_nodes": int(len(U)),
        "status_counts": {int(c): int(n) for c, n in zip(codes, counts)},
        "n_outlier": int(outlier.sum()),
        "n_flagged": int((~valid).sum()),
        "winsize_xyz": para.get("winsize"),
        "winstepsize_xyz": para.get("winstepsize"),
        "para": para,
    }
    return points, u, valid, info
