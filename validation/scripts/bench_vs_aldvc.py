"""chunkdic side by side with the peer code pyALDVC (al-dvc) on the same scans.

For each case (a reference scan, a deformed scan and, when known, the true displacement
field) and each node spacing ``ell``, both tools run on the same data in this session:

- chunkdic: ``chunkdic.correlate(ref, def, element_size=ell)`` with its defaults, in a
  fresh Python process, reading the Zarr scans (its nodes ``result.node_coords``,
  ``result.displacement``, in level-0 voxels);
- al-dvc: ``al-dvc run --volumes REF.npy DEF.npy --winsize 2ell --step ell`` with its
  defaults, from its own virtual environment (created on first use, outside the
  repository; see ``benchmarks/aldvc.py``), reading ``.npy`` copies of the same scans.

With a known field both are scored **between the nodes** (the project's scoring rule,
:func:`chunkdic.analysis.scoring.score_between_nodes`): the field trilinear on the tool's
own node grid, as a viewer shows it, against the truth at every voxel at least ``ell``
from the faces and inside the grid's hull; ``rms`` = RMS of the vector error, ``sigma``
pooled over the three components (``sqrt(mean of the three variances)``, the figure for
translations). al-dvc's grid starts about ``2 ell`` from the faces (its first node at
``winsize - 1``), so its hull is smaller than chunkdic's: ``rms_common`` /
``sigma_common`` score both tools on the same voxels (every voxel ``>= ell`` from the faces
inside both hulls; the fields are cropped exactly, a trilinear cell cut by a plane staying
trilinear), and the summary table compares those. al-dvc's field is scored as it comes out
(its flagged nodes hold inpainted values); ``failed`` counts the nodes it flags. The
nodal scores of :func:`chunkdic.score_displacement` (at the points, flagged points left
out) stay in the record as ``nodal_*``. The table gives medians over ``--repeats`` runs;
``wall`` is the tool's own correlation time (chunkdic: the ``correlate`` call, its modules
imported before; al-dvc: its "Done in" time, input reading included, printed after its
imports), ``proc`` the whole process (interpreter start and imports included),
``cpu s`` (``proc_cpu`` in the record) the whole process's CPU seconds, user + system,
every thread (chunkdic's ``correlate`` call alone: ``cpu``): on a machine shared with other
work the comparable figure, where wall times move with the load,
``x`` = al-dvc wall / chunkdic wall. Both tools get ``--threads`` cores (default: all):
chunkdic's embedded pool (``DASK_CHUNKDIC__NUM_THREADS``), al-dvc's ``n_threads``, and
``NUMBA_NUM_THREADS`` / ``OMP_NUM_THREADS`` / BLAS of both children. A warm-up run of
each tool on a 48³ pair comes first, so that neither pays for Numba compilation.

Cases, on each ``--specimen`` (default: the CT-like ``grains`` and ``concrete`` of
:mod:`chunkdic.synth.microstructure` imaged by :mod:`chunkdic.synth.ctsim`, with independent noise
``--noise`` in each scan; ``foam`` for the smooth synthetic foam):

- ``shift``: the reference, Fourier-shifted by (0.5, 0.5, 0.5) voxel (the paper's section
  4.2 test: both scans share the reference's noise);
- ``noise``: a (0.5, 0.5, 0.5) translation rendered from the geometry, independent noise
  in each scan;
- ``band``: the standard compression band (:func:`chunkdic.synth.ctpair.standard_field`: −8 %
  peak strain, 6-voxel width, lateral factor 0.05 unless ``--band-lateral``), independent
  noise in each scan. The C8 basis alone cannot follow so sharp a band: at 100³ the L2
  projection of this field on chunkdic's meshes leaves 0.029 / 0.026 voxel RMS at the
  scored nodes for ell = 12 / 8 (0.13 / 0.06 with a lateral factor of 0.3, which would
  measure the basis rather than the tools);
- ``band-grey``: ``band`` with the deformed scan's grey levels changed (gain 1.1, +5 %
  offset, 3 % drift along z; CT specimens only);
- ``wave24`` … ``wave64`` (group ``heterogeneous`` with ``slip`` and ``band``): shear waves
  ``Ux = 0.5 sin(2π (z − c) / T)`` of period ``T`` = 24, 32, 48, 64 voxels
  (:class:`chunkdic.synth.shear.Wave`), independent noise in each scan;
- ``slip``: a shear slip ``Ux = 0.5 tanh((z − c) / 3)`` (:class:`chunkdic.synth.shear.Slip`,
  1 voxel across about 6), independent noise in each scan;
- ``comp10`` / ``comp20`` / ``rot10`` (group ``large``): 10 / 20 % axial compression along z
  with 3 / 6 % lateral expansion, and a 10° rotation about z, about the volume's centre
  (the fields of ``bench_large_strain.py``), independent noise in each scan;
- ``crack-comp10`` / ``slip-comp10`` (group ``composed``): the crack or the slip, then
  ``comp10`` (:class:`chunkdic.synth.fields.Composed`): a feature under a large deformation;
- ``star``: the 3-D star, ``Ux = 0.5 sin(2π (z − z_c) / λ(y))`` with ``λ`` from 10 to
  100 voxels across y, rendered from the geometry, independent noise in each scan; besides
  the scores, each tool's spatial resolution ``l10 %`` read between its points
  (:func:`chunkdic.analysis.resolution.star_ratios_nodes`: chunkdic's C8 nodes, al-dvc's
  grid of step ``ell``, both trilinear between points). ``chunkdic resolution`` measures the
  same on a scan's own texture, with the noise of the same setting;
  ``bench_star_vs_aldvc.py`` makes the star table (star ``2ell … 20ell``, each tool's
  noise at the setting of its star run, MEI and the ratios).

``--set KEY=VALUE`` passes settings to chunkdic (e.g. ``--set smoothing=0 --set grey=none``
for the paper's plain C8).

Usage::

    python validation/scripts/bench_vs_aldvc.py --selfcheck            # verify the adapter's conventions
    python validation/scripts/bench_vs_aldvc.py --sizes 128 --spacings 16 12 8 --repeats 1
    python validation/scripts/bench_vs_aldvc.py --sizes 300 --cases shift --spacings 12 --repeats 3
    python validation/scripts/bench_vs_aldvc.py --pair /data/specimen   # a synthesized pair directory
    python validation/scripts/bench_vs_aldvc.py --sizes 128 --cases star --specimen grains --spacings 16 12 8
    python validation/scripts/bench_vs_aldvc.py --sizes 100 --cases heterogeneous large noise \
        --spacings 16 12 8 --solo-spacings 6 --repeats 1          # docs/validation/vs-aldvc.md

The run ends with a Markdown table (:func:`summary_table`): per case and ``ell`` both
tools' between-node error on the common voxels (RMS; sigma for the translations), the ratio
chunkdic / al-dvc, chunkdic's error over all its voxels, status, regularisation length and
wall times. The record is rewritten after each case and spacing (``"complete": false``
until the end), so an interrupted run keeps what completed.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import itertools
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import aldvc as peer  # noqa: E402  (benchmarks/aldvc.py, next to this file)
from _oracle import candidate_fields, keep_choice_problem  # noqa: E402

RECORDS = Path(__file__).resolve().parent / "records"
#: heterogeneous fields (independent noise in each scan): shear waves, a shear slip
WAVES = ("wave24", "wave32", "wave48", "wave64")
HETEROGENEOUS = WAVES + ("slip", "band", "crack")
#: large deformations (bench_large_strain.py's fields): 10 / 20 % compression, 10 degree rotation
LARGE = ("comp10", "comp20", "rot10")
#: a feature under a large deformation: the crack or the slip, then 10 % compression
#: (:class:`chunkdic.synth.fields.Composed`)
COMPOSED = ("crack-comp10", "slip-comp10")
CASE_NAMES = ("shift", "noise", "band", "band-grey", "star", *WAVES, "slip", "crack", *LARGE, *COMPOSED)
#: the default case list (the band, its grey-level variant and the star, plus the two translations)
DEFAULT_CASES = ("shift", "noise", "band", "band-grey", "star")
CASE_GROUPS = {"heterogeneous": HETEROGENEOUS, "large": LARGE, "composed": COMPOSED, "all": CASE_NAMES}
#: the star: Ux = 0.5 sin(2 pi (z - zc) / period(y)), period 10 -> 100 voxels across y
STAR = {"amplitude": 0.5, "period_min": 10.0, "period_max": 100.0}
SHIFT = (0.5, 0.5, 0.5)
#: the crack: a sliding jump Ux = ±0.3 voxel across the plane z = c (a slip whose edge is far below a voxel)
CRACK = {"jump": 0.6, "edge": 0.01}


def _error(msg: str) -> None:
    print(f"bench_vs_aldvc: error: {msg}", file=sys.stderr)
    sys.exit(2)


# --------------------------------------------------------------------------- cases


@dataclasses.dataclass
class Case:
    """One pair of scans. ``reference``/``deformed``: what chunkdic reads (Zarr);
    ``field``: the true displacement (a :class:`chunkdic.synth.fields.Field`) or None."""

    name: str
    reference: str
    deformed: str
    field: object | None
    shape: tuple[int, int, int]
    note: str = ""
    offset: float = 0.0  # voxels along z the feature moved from the volume's centre (--feature-offset)


GREY_CHANGE = {"gain": 1.1, "offset": 0.05, "drift": 0.03}


def _band(n: int, lateral: float | None):
    from chunkdic.synth.ctpair import standard_field

    kw = {} if lateral is None else {"lateral": lateral}
    return standard_field("band", (n,) * 3, **kw)[0]


def _pair(out: Path, n: int, args, specimen: str, *, field, **extra) -> dict:
    from chunkdic.synth import synthetic

    if (out / "field.json").exists():
        return {"reference": str(out / "ref.zarr"), "deformed": str(out / "def.zarr")}
    t0 = time.perf_counter()
    kw = {"seed": args.seed, "dtype": args.dtype, "overwrite": True, "noise": args.noise}
    if specimen != "foam":
        kw["specimen"] = specimen
        if getattr(args, "scale", 1.0) != 1.0:
            kw["texture_scale"] = args.scale
    paths = synthetic.synthesize(out, (n,) * 3, field=field, **kw, **extra)
    print(f"# synthesized {out.name} ({n}^3) in {time.perf_counter() - t0:.1f} s", flush=True)
    return paths


def offset_moves(name: str) -> bool:
    """Whether ``--feature-offset`` moves case ``name`` (a plane feature or a wave's phase)."""
    return name in WAVES or name in ("slip", "crack") or name.startswith("band")


def build_case(name: str, n: int, specimen: str, workdir: Path, args) -> Case | None:
    """Write the scans of case ``name`` at ``n``³ under ``workdir`` (kept between runs);
    ``args.scale``: the specimen's texture scale (``texture_scale`` of
    :func:`chunkdic.synth.synthetic.synthesize`), ``args.feature_offset`` the feature's offset
    (:attr:`Case.offset`)."""
    offset = (getattr(args, "feature_offset", 0.0) or 0.0) if offset_moves(name) else 0.0
    case = _write_case(name, n, specimen, workdir, args, offset)
    return None if case is None else dataclasses.replace(case, offset=offset)


def _write_case(name: str, n: int, specimen: str, workdir: Path, args, offset: float) -> Case | None:
    from chunkdic.synth.fields import Translation

    scale = getattr(args, "scale", 1.0)
    tag = f"{name}-{n}-{specimen}-{args.dtype}-n{args.noise:g}-s{args.seed}"
    if scale != 1.0 and specimen != "foam":
        tag += f"-ts{scale:g}"
        specimen_label = f"{specimen}-ts{scale:g}"
    else:
        specimen_label = specimen
    if name.startswith("band") and args.band_lateral is not None:
        tag += f"-lat{args.band_lateral:g}"
    if offset:
        tag += f"-off{offset:g}"
    out = workdir / tag
    label = f"{name}/{specimen_label}"
    if name == "shift":
        if specimen == "foam":
            from chunkdic.io.scan import open_scan
            from chunkdic.synth.fourier_shift import fourier_shift_scan

            paths = _pair(out, n, args, specimen, field=None)
            shifted = out / "shifted.zarr"
            if not shifted.exists():
                src = open_scan(paths["reference"]).refs([0])[0]
                fourier_shift_scan(src, shifted, SHIFT, overwrite=True)
            return Case(label, paths["reference"], str(shifted), Translation(SHIFT), (n,) * 3,
                        "Fourier shift of the reference")
        paths = _pair(out, n, args, specimen, field=Translation(SHIFT), fourier_shift=True)
        return Case(label, paths["reference"], paths["deformed"], Translation(SHIFT), (n,) * 3,
                    "Fourier shift of the reference")
    if name == "noise":
        paths = _pair(out, n, args, specimen, field=Translation(SHIFT))
        return Case(label, paths["reference"], paths["deformed"], Translation(SHIFT), (n,) * 3,
                    f"translation, independent noise {args.noise:g}")
    if name == "star":
        from chunkdic.synth.fields import Star

        field = Star(**STAR, y0=0.0, y1=n - 1.0, center_z=(n - 1) / 2.0)
        paths = _pair(out, n, args, specimen, field=field)
        return Case(label, paths["reference"], paths["deformed"], field, (n,) * 3,
                    f"star, period 10-100 across y, independent noise {args.noise:g}")
    if name in WAVES or name in ("slip", "crack") or name in COMPOSED:
        from chunkdic.synth.fields import Composed
        from chunkdic.synth.shear import Slip, Wave

        c = (n - 1) / 2.0 + offset
        feature, _, large = name.partition("-")
        if feature == "slip":  # Ux = 0.5 tanh((z - c) / 3): a 1-voxel slip across ~6 voxels
            field, note = Slip(center=c, jump=1.0, edge=3.0), "shear slip 1 voxel, edge 3"
        elif feature == "crack":  # Ux = ±0.3 on either side of z = c: a sliding crack
            field, note = Slip(center=c, **CRACK), "sliding crack, Ux = ±0.3 voxel"
        else:  # Ux = 0.5 sin(2 pi (z - c) / period)
            field = Wave(period=float(name[4:]), amplitude=0.5, phase=c)
            note = f"shear wave period {name[4:]}, amplitude 0.5"
        if large:
            from bench_large_strain import large_field

            field, note = Composed(field, large_field(large, n)), f"{note}, then {large}"
        paths = _pair(out, n, args, specimen, field=field)
        return Case(label, paths["reference"], paths["deformed"], field, (n,) * 3,
                    f"{note}, independent noise {args.noise:g}")
    if name in LARGE:
        from bench_large_strain import large_field

        field = large_field(name, n)
        note = {"comp10": "compression 10 %, lateral +3 %", "comp20": "compression 20 %, lateral +6 %",
                "rot10": "rotation 10 deg about z"}[name]
        paths = _pair(out, n, args, specimen, field=field)
        return Case(label, paths["reference"], paths["deformed"], field, (n,) * 3,
                    f"{note}, independent noise {args.noise:g}")
    field = _band(n, args.band_lateral)
    if offset:
        field = dataclasses.replace(field, center_z=field.center_z + offset)
    if name == "band":
        paths = _pair(out, n, args, specimen, field=field)
        return Case(label, paths["reference"], paths["deformed"], field, (n,) * 3, "band -8 %, width 6")
    if name == "band-grey":
        if specimen == "foam":
            print("# band-grey skipped on the foam (grey-level changes are a CT-specimen option)", flush=True)
            return None
        paths = _pair(out, n, args, specimen, field=field, **GREY_CHANGE)
        return Case(label, paths["reference"], paths["deformed"], field, (n,) * 3,
                    "band, deformed x1.1 +5 % drift 3 %")
    raise ValueError(name)


def pair_case(path: str) -> Case:
    """A synthesized pair directory (``ref.zarr``, ``def.zarr``, ``field.json``)."""
    from chunkdic.io.scan import open_scan
    from chunkdic.synth import synthetic

    d = Path(path)
    ref, dfm = d / "ref.zarr", d / "def.zarr"
    if not (ref.exists() and dfm.exists()):
        _error(f"--pair {path}: expected {ref} and {dfm}")
    field = synthetic.load_field(d) if (d / "field.json").exists() else None
    shape = tuple(int(s) for s in open_scan(str(ref)).shape(0))
    return Case(d.name, str(ref), str(dfm), field, shape, "pair directory")


def npy_copies(case: Case, workdir: Path) -> tuple[Path, Path]:
    """``.npy`` copies of a case's level-0 scans for al-dvc (slab by slab)."""
    from chunkdic.io.scan import open_scan

    out = []
    for src in (case.reference, case.deformed):
        arr = open_scan(src).refs([0])[0].open()
        src = Path(src).resolve()
        target = workdir / "npy" / f"{src.parent.name}-{src.stem}.npy"  # never beside a user's scans
        target.parent.mkdir(parents=True, exist_ok=True)
        out.append(peer.write_npy(arr, target))
    return out[0], out[1]


# --------------------------------------------------------------------------- chunkdic child


def _chunkdic_child(args) -> None:
    """One chunkdic run in this (fresh) process; writes points/u (.npz) and a JSON summary."""
    import zarr  # noqa: F401

    import chunkdic
    import chunkdic.engine.driver  # noqa: F401  (the correlation's modules: imported before the clock
    # starts, as al-dvc's "Done in" time starts after its imports; `proc` counts both. zarr too:
    # chunkdic imports it on the first scan it opens, 0.18 s that would count inside the call)

    options = json.loads(args.options or "{}")
    oracle = options.pop("__oracle", False)
    with contextlib.ExitStack() as stack:
        kept = stack.enter_context(keep_choice_problem()) if oracle else {}
        t0, c0 = time.perf_counter(), time.process_time()
        res = chunkdic.correlate(args.ref, args.deformed, element_size=args.element_size, **options)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    scale = float(res.info.get("scale", 1))
    # level-s voxels -> level-0 voxels (shared/DESIGN.md: centre offset (2^s - 1) / 2)
    points = res.node_coords.reshape(3, -1) * scale + (scale - 1) / 2
    u = res.displacement.reshape(3, -1) * scale
    extra = {}
    if "problem" in kept:  # every candidate length's linearised field (validation/scripts/_oracle.py)
        lengths, fields = candidate_fields(kept["problem"])
        extra = {"oracle_lengths": lengths, "oracle_u": fields.reshape(len(lengths), 3, -1)}
        # the problem itself, for studies of the choice away from the engine (bench_length_texture.py)
        np.savez(args.out + "-problem.npz", **kept["problem"], reference=args.ref)
    np.savez(args.out + ".npz", points=points, u=u, **extra)
    hist = res.history
    summary = {
        "wall": wall, "cpu": cpu, "status": res.info.get("status"), "converged": res.converged,
        "final_gap": res.info.get("final_gap"), "level": res.info.get("level"), "scale": scale,
        "iterations": int(np.sum(np.asarray(hist["level"]) == res.info.get("level"))),
        "nodes": int(points.shape[1]), "roi": res.info.get("roi_level0"),
        "reg_length": (res.info.get("regularization") or {}).get("length"),
    }
    with open(args.out + ".json", "w") as fh:
        json.dump(summary, fh)


def run_chunkdic(case: Case, ell: int, threads: int, out: Path, timeout: float, options: dict | None = None) -> dict:
    out.parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, __file__, "--child", "--ref", case.reference, "--deformed", case.deformed,
           "--element-size", str(ell), "--out", str(out), "--options", json.dumps(options or {})]
    env = peer.child_env(threads)
    env["DASK_CHUNKDIC__NUM_THREADS"] = str(threads)
    t0 = time.perf_counter()
    with open(str(out) + ".log", "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                env=env, start_new_session=True)
        rc, peak, proc_cpu = peer.wait_with_peak(proc, timeout)
    proc_wall = time.perf_counter() - t0
    if rc is None:
        return {"status": "timeout", "proc": proc_wall, "proc_cpu": proc_cpu, "peak_rss_mb": peak}
    if rc != 0:
        tail = Path(str(out) + ".log").read_text(errors="replace").strip().splitlines()[-3:]
        return {"status": f"failed (exit {rc})", "proc": proc_wall, "proc_cpu": proc_cpu, "peak_rss_mb": peak,
                "tail": tail}
    summary = json.loads(Path(str(out) + ".json").read_text())
    with np.load(str(out) + ".npz") as d:
        summary["points"], summary["u"] = d["points"], d["u"]
        if "oracle_u" in d:
            summary["oracle_lengths"], summary["oracle_u"] = d["oracle_lengths"], d["oracle_u"]
    summary.update(proc=proc_wall, proc_cpu=proc_cpu, peak_rss_mb=peak)
    return summary


# --------------------------------------------------------------------------- scoring and table


def _score(points, u, valid, case: Case, ell: int) -> dict:
    from chunkdic import score_displacement
    from chunkdic.synth.fields import true_displacement

    if points is None:
        return {}
    if case.field is None:
        return {"n_points": int(points.shape[1]), "no_truth": True}
    truth = true_displacement(case.field, points[0], points[1], points[2])
    return score_displacement(points, u, truth, case.shape, ell, valid=valid).as_dict()


def _to_grid(points, u, valid=None):
    """A field given at the points of a regular grid (either tool), as node axes ``(z, y, x)``
    and a nodal array ``(3, nz, ny, nx)``; points flagged ``valid=False`` become NaN."""
    axes = [np.unique(np.round(c, 6)) for c in points]
    grid = np.full((3, *(a.size for a in axes)), np.nan)
    idx = [np.searchsorted(a, np.round(c, 6)) for a, c in zip(axes, points)]
    uu = np.array(u, np.float64)
    if valid is not None:
        uu[:, ~np.asarray(valid, bool)] = np.nan
    grid[:, idx[0], idx[1], idx[2]] = uu
    return axes, grid


def _between(points, u, case: Case, ell: int, sample: int | None = None) -> dict:
    """The field between the points (the project's scoring rule, the same for both tools):
    trilinear on the tool's node grid at every voxel at least ``ell`` from the faces
    (:func:`chunkdic.analysis.scoring.score_between_nodes`); RMS of the vector error, sigma
    pooled over the components. al-dvc's field is scored as it comes out (the nodes it
    flags hold its inpainted values: what a viewer shows); ``failed`` counts them."""
    from chunkdic.analysis.scoring import score_between_nodes

    if points is None or case.field is None:
        return {}
    axes, grid = _to_grid(points, u)
    if grid.size != np.asarray(u).size:  # not a full regular grid: no between-node score
        return {"between_error": "points are not a full regular grid"}
    s = score_between_nodes(axes, grid, case.field, case.shape, ell, sample=sample)
    return {"rms": s.rms, "sigma": s.sigma, "bias": list(s.bias), "max_error": s.max_error,
            "n_points": s.n_points, "n_voxels_outside_hull": s.n_outside}


def _crop_grid(axes, grid, hull):
    """The same trilinear field on a node grid cropped to the box ``hull`` (per axis (lo, hi)):
    nodes outside dropped, nodes added on the box's faces with the field's trilinear value there.
    Inside the box the field is unchanged (a trilinear cell cut by a plane stays trilinear), so
    :func:`score_between_nodes` on the cropped grid scores exactly the voxels inside the box."""
    from scipy.interpolate import RegularGridInterpolator

    new = []
    for a, (lo, hi) in zip(axes, hull):
        inner = a[(a > lo + 1e-9) & (a < hi - 1e-9)]
        new.append(np.concatenate([[lo], inner, [hi]]))
    pts = np.stack(np.meshgrid(*new, indexing="ij"), axis=-1)
    out = np.stack([RegularGridInterpolator(axes, g, method="linear")(pts) for g in grid])
    return new, out


def between_common(fields: dict, case: Case, ell: int, sample: int | None = None) -> dict:
    """Each tool's field between its nodes on the *same* voxels: every voxel at least ``ell``
    from the faces and inside every tool's node hull (al-dvc's first and last nodes sit about
    ``2 ell`` from the faces, chunkdic's half a voxel outside its ROI). ``fields``: tool ->
    (points, u); returns tool -> score dict (keys suffixed ``_common``). ``floor_common``: the
    same score of the exact field sampled at the tool's nodes, trilinear between them: what
    the node grid alone costs (a slip or band centred on a node costs more than one between
    two nodes, whatever the tool; a least-squares fit on the same grid can go somewhat below)."""
    from chunkdic.analysis.scoring import score_between_nodes

    grids = {t: _to_grid(p, u) for t, (p, u) in fields.items() if p is not None}
    if case.field is None or len(grids) < 2 or any(g.size != np.asarray(fields[t][1]).size
                                                   for t, (_, g) in grids.items()):
        return {}
    hull = [(max(ax[i][0] for ax, _ in grids.values()), min(ax[i][-1] for ax, _ in grids.values()))
            for i in range(3)]
    from chunkdic.synth.fields import true_displacement

    out = {}
    for t, (axes, grid) in grids.items():
        s = score_between_nodes(*_crop_grid(axes, grid, hull), case.field, case.shape, ell, sample=sample)
        # the grid's own floor: the exact field at this tool's nodes, trilinear between them
        pts = fields[t][0]
        exact = _to_grid(pts, true_displacement(case.field, pts[0], pts[1], pts[2]))
        f = score_between_nodes(*_crop_grid(*exact, hull), case.field, case.shape, ell, sample=sample)
        out[t] = {"rms_common": s.rms, "sigma_common": s.sigma, "max_error_common": s.max_error,
                  "n_points_common": s.n_points, "common_hull": [list(h) for h in hull],
                  "floor_common": f.rms}
    return out


def _nodal(score: dict) -> dict:
    """The nodal score (``score_displacement`` at the points), kept beside the between-node one."""
    return {f"nodal_{k}": v for k, v in score.items() if k in ("rms", "sigma", "max_error", "n_points", "n_failed")}


def _star(points, u, valid, case: Case, ell: int) -> dict:
    """l10 % of a field on a regular grid of points (either tool), read between the points."""
    from chunkdic.analysis.resolution import l10, star_ratios_nodes
    from chunkdic.synth.fields import Star

    if points is None or not isinstance(case.field, Star):
        return {}
    axes, grid = _to_grid(points, u, valid)
    try:
        per, rat = star_ratios_nodes(axes, grid, case.field, case.shape, ell)
        v, bound = l10(per, rat)
    except Exception as exc:  # a grid that is not regular, too few rows: say so in the record
        return {"l10_error": str(exc)}
    return {"l10": v, "l10_bound": bound}


def _median(values):
    v = [x for x in values if x is not None and not (isinstance(x, float) and math.isnan(x))]
    return statistics.median(v) if v else float("nan")


def _summarise(runs: list[dict]) -> dict:
    """Median of the numeric fields over repeats; status of the first run that was not ok."""
    first = runs[0]
    out = {k: v for k, v in first.items() if not isinstance(v, (int, float)) or isinstance(v, bool)}
    for k, v in first.items():
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            out[k] = _median([r.get(k) for r in runs])
    bad = [r["status"] for r in runs if r["status"] not in ("ok", "converged")]
    out["status"] = bad[0] if bad else first["status"]
    out["statuses"] = [r["status"] for r in runs]
    return out


HEADER = (f"{'size':>4} {'case':<18} {'ell':>3} {'tool':<8} {'sigma':>8} {'|bias|':>8} {'RMS':>8} "
          f"{'max':>7} {'points':>6} {'failed':>6} {'status':<14} {'wall s':>7} {'proc s':>7} "
          f"{'cpu s':>7} {'MB':>6} {'x':>5}")


def _fmt(v, spec):
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def row(size, case, ell, tool, m: dict, ratio=None) -> str:
    bias = m.get("bias")
    bnorm = float(np.linalg.norm(bias)) if bias and all(np.isfinite(bias)) else None
    return (f"{size:>4} {case:<18} {ell:>3} {tool:<8} {_fmt(m.get('sigma'), '8.4f')} {_fmt(bnorm, '8.4f')} "
            f"{_fmt(m.get('rms'), '8.4f')} {_fmt(m.get('max_error'), '7.3f')} "
            f"{_fmt(m.get('n_points'), '6.0f')} {_fmt(m.get('n_failed'), '6.0f')} {m.get('status', '-'):<14} "
            f"{_fmt(m.get('wall'), '7.1f')} {_fmt(m.get('proc'), '7.1f')} {_fmt(m.get('proc_cpu'), '7.1f')} "
            f"{_fmt(m.get('peak_rss_mb'), '6.0f')} "
            f"{_fmt(ratio, '5.1f')}")


# --------------------------------------------------------------------------- runs


def compare(case: Case, ell: int, args, exe: Path, workdir: Path, npys, *, peer_too: bool = True) -> dict:
    """Both tools (chunkdic alone when not ``peer_too``) on one case at one spacing,
    ``--repeats`` times; scored medians.

    With a known field the main scores (``rms``, ``sigma``, ``bias``, ``max_error``,
    ``n_points``) are between the nodes (:func:`_between`, both tools alike); the nodal
    scores of :func:`chunkdic.score_displacement` stay in the record as ``nodal_*``.
    """
    runs = {"chunkdic": []} | ({"al-dvc": []} if peer_too else {})
    options = dict(args.options) | ({"__oracle": True} if args.oracle else {})
    for rep in range(args.repeats):
        base = workdir / "runs" / f"{case.name}-{case.shape[0]}-ell{ell}-r{rep}"
        c = run_chunkdic(case, ell, args.threads, base / "chunkdic", args.timeout, options)
        pts, uc = c.pop("points", None), c.pop("u", None)
        candidates = (c.pop("oracle_lengths", None), c.pop("oracle_u", None))
        score = _score(pts, uc, None, case, ell)
        runs["chunkdic"].append({**c, **score, **_nodal(score), **_between(pts, uc, case, ell, args.points),
                                 **_star(pts, uc, None, case, ell)})
        if not peer_too:
            runs["chunkdic"][-1].update(oracle_scores(candidates, pts, case, ell, None, args.points))
            continue
        a = peer.load_run(base / "aldvc") if args.reuse_peer else None
        if a is None:
            a = peer.run_aldvc(exe, npys[0], npys[1], base / "aldvc", winsize=2 * ell, step=ell,
                               threads=args.threads, timeout=args.timeout)
        score = _score(a.points, a.u, a.valid, case, ell)
        # the same field scored with every node al-dvc returns, flagged ones included
        every = _score(a.points, a.u, None, case, ell) if a.points is not None else {}
        info = {k: v for k, v in a.info.items() if k not in ("para", "command")}
        runs["al-dvc"].append({"status": a.status, "wall": a.pipeline_seconds, "proc": a.wall, "proc_cpu": a.cpu_seconds,
                               "peak_rss_mb": a.peak_rss_mb, **score, **_nodal(score),
                               **_between(a.points, a.u, case, ell, args.points), **_star(a.points, a.u, a.valid, case, ell),
                               "rms_all_nodes": every.get("rms"), "sigma_all_nodes": every.get("sigma"),
                               "info": info})
        common = between_common({"chunkdic": (pts, uc), "al-dvc": (a.points, a.u)}, case, ell, args.points)
        for tool, extra in common.items():
            runs[tool][-1].update(extra)
        runs["chunkdic"][-1].update(oracle_scores(candidates, pts, case, ell, (a.points, a.u), args.points))
    if args.oracle_full and runs["chunkdic"][-1].get("oracle_length"):
        # the whole engine at the oracle's length (the plain penalty): checks the linearisation
        L = runs["chunkdic"][-1]["oracle_length"]
        c = run_chunkdic(case, ell, args.threads, workdir / "runs" / f"{case.name}-{case.shape[0]}-ell{ell}-full",
                         args.timeout, dict(args.options) | {"regularization_length": L})
        pts, uc = c.pop("points", None), c.pop("u", None)
        full = _between(pts, uc, case, ell, args.points)
        if peer_too and a.points is not None:
            full.update(between_common({"chunkdic": (pts, uc), "al-dvc": (a.points, a.u)}, case, ell,
                                       args.points).get("chunkdic", {}))
        runs["chunkdic"][-1].update({f"oracle_full_{k}": v for k, v in full.items()
                                     if k in ("rms", "sigma", "rms_common", "sigma_common")})
    return {tool: _summarise(r) | {"runs": r} for tool, r in runs.items()}


def oracle_scores(candidates, pts, case: Case, ell: int, peer_field, sample) -> dict:
    """Each candidate length's linearised field (validation/scripts/_oracle.py) scored as the tool's own:
    between the nodes over all voxels ≥ ``ell`` from the faces and, with al-dvc's field, on the
    voxels both tools score; ``oracle_*`` the least error (σ for the translations) and its length."""
    lengths, fields = candidates
    if lengths is None or case.field is None:
        return {}
    key = "sigma" if case.name.split("/")[0] in ("shift", "noise") else "rms"
    out = {"oracle_lengths": [float(v) for v in lengths], f"oracle_{key}_all": [], f"oracle_{key}_common_all": []}
    for u in fields:
        out[f"oracle_{key}_all"].append(_between(pts, u, case, ell, sample).get(key))
        if peer_field is not None and peer_field[0] is not None:
            common = between_common({"chunkdic": (pts, u), "al-dvc": peer_field}, case, ell, sample)
            out[f"oracle_{key}_common_all"].append(common.get("chunkdic", {}).get(f"{key}_common"))
    pick = out[f"oracle_{key}_common_all"] or out[f"oracle_{key}_all"]
    best = int(np.nanargmin(np.array(pick, dtype=float)))
    out.update({"oracle_length": float(lengths[best]), f"oracle_{key}": out[f"oracle_{key}_all"][best]})
    if out[f"oracle_{key}_common_all"]:
        out[f"oracle_{key}_common"] = out[f"oracle_{key}_common_all"][best]
    return out


def warm_up(exe: Path, args, workdir: Path) -> None:
    """One untimed run of each tool on a 48³ pair: Numba caches loaded or compiled."""
    from chunkdic.synth.fields import Translation

    class A:  # the synthesis settings of a tiny pair
        seed, dtype, noise = 0, "uint8", 0.0

    paths = _pair(workdir / "warmup-48", 48, A, "foam", field=Translation((0.3, 0.2, 0.1)))
    case = Case("warmup", paths["reference"], paths["deformed"], None, (48,) * 3)
    t0 = time.perf_counter()
    c = run_chunkdic(case, 8, args.threads, workdir / "runs" / "warmup" / "chunkdic", args.timeout,
                     args.options)
    ref, dfm = npy_copies(case, workdir)
    a = peer.run_aldvc(exe, ref, dfm, workdir / "runs" / "warmup" / "aldvc", winsize=16, step=8,
                       threads=args.threads, timeout=args.timeout)
    print(f"# warm-up: chunkdic {c['status']}, al-dvc {a.status} ({time.perf_counter() - t0:.0f} s)",
          flush=True)


# --------------------------------------------------------------------------- self-check


def _affine_fit(points, u):
    """Least-squares affine fit ``u = M q + b`` of ``u`` (3, N) at ``q`` (3, N); returns ``M``, ``b``."""
    P = np.vstack([points, np.ones(points.shape[1])]).T
    coef, *_ = np.linalg.lstsq(P, u.T, rcond=None)
    return coef[:3].T, coef[3]


def selfcheck(exe: Path, args, workdir: Path) -> int:
    """al-dvc on known fields: integer translation (2, -1, 3) voxel and an affine field.

    Prints al-dvc's raw output next to the converted one and the truth, and the error of
    the adapter's conventions against the errors of plausible mistakes (axes not reversed,
    sign flipped, node positions off by one voxel). For the affine field it also fits an
    affine map to al-dvc's nodal field: the fitted gradient must match the true one, and
    the fitted displacement at the field's centre the true translation, which pins the
    node positions down to a fraction of a voxel. Exit status 1 when a check fails.
    """
    from chunkdic import score_displacement
    from chunkdic.synth.fields import Affine, Translation, true_displacement

    class A:
        seed, dtype, specimen, noise = 3, "float32", None, 0.0

    n, ell, c = 80, 12, 39.5
    matrix = ((-0.04, 0.01, 0.0), (0.0, 0.03, -0.01), (0.008, 0.0, 0.035))
    fields = {
        "translation": Translation((2.0, -1.0, 3.0)),
        "affine": Affine(matrix=matrix, center=(c, c, c), translation=(0.3, -0.2, 0.7)),
    }
    ok = True
    record = {}
    for name, field in fields.items():
        paths = _pair(workdir / f"selfcheck-{name}", n, A, "foam", field=field)  # noise-free foam (A.noise)
        case = Case(name, paths["reference"], paths["deformed"], field, (n,) * 3)
        ref, dfm = npy_copies(case, workdir)
        a = peer.run_aldvc(exe, ref, dfm, workdir / "runs" / f"selfcheck-{name}",
                           winsize=2 * ell, step=ell, threads=args.threads, timeout=args.timeout)
        if a.status != "ok":
            print(f"{name}: al-dvc {a.status}; see {a.info.get('log')}")
            return 1
        with np.load(Path(a.info["log"]).with_name("aldvc.npz")) as d:
            raw_c, raw_u = d["coordinates"], d["U_1"]
        print(f"\n{name} {field.to_json()}\n  al-dvc --winsize {2 * ell} --step {ell} on {n}^3: grid "
              f"{a.info['grid_shape_zyx']} (z, y, x), first node coordinates [x, y, z] = {raw_c[0].tolist()}, "
              f"{a.info['n_flagged']} flagged")
        t = true_displacement(field, *a.points)
        print(f"  raw U_1 [u, v, w], mean over nodes: {np.round(raw_u.mean(axis=0), 4).tolist()}")
        print(f"  converted (Uz, Uy, Ux), mean:       {np.round(a.u.mean(axis=1), 4).tolist()}")
        print(f"  truth (Uz, Uy, Ux), mean:           {np.round(t.mean(axis=1), 4).tolist()}")
        # each variant: a measured field (positions, u) scored against the truth at those positions
        variants = {
            "adapter (axes reversed, same sign)": (a.points, a.u),
            "axes not reversed": (a.points, a.u[::-1]),
            "sign flipped": (a.points, -a.u),
        }
        if name == "affine":
            variants["node positions +1 voxel"] = (a.points + 1.0, a.u)
            variants["node positions -1 voxel"] = (a.points - 1.0, a.u)
        errs = {}
        for label, (p, u) in variants.items():
            s = score_displacement(p, u, true_displacement(field, *p), case.shape, ell, valid=a.valid)
            errs[label] = s.rms
            print(f"  {label:<36} RMS error {s.rms:.5f} voxel, max {s.max_error:.5f} "
                  f"({s.n_points} points, {s.n_failed} failed)")
        good = errs.pop("adapter (axes reversed, same sign)")
        passed = all(v > 3 * good for v in errs.values())
        rec = {"errors": {"adapter": good, **errs}, "raw_mean_U_xyz": raw_u.mean(axis=0).tolist(),
               "converted_mean_u_zyx": a.u.mean(axis=1).tolist(), "wall": a.pipeline_seconds}
        if name == "translation":
            passed &= good < 0.01
        else:
            m, b = _affine_fit(a.points[:, a.valid] - c, a.u[:, a.valid])
            # measured u = A (X_true - c) + t with X_true = X_reported + offset, so the fit's
            # value at the centre is b = t + A offset
            offset = np.linalg.solve(np.asarray(matrix), b - np.asarray(field.translation))
            print("  fitted gradient (rows Uz, Uy, Ux; columns d/dz, d/dy, d/dx):\n"
                  + "\n".join("    " + " ".join(f"{v:+.5f}" for v in r) for r in m)
                  + "\n  true gradient:\n" + "\n".join("    " + " ".join(f"{v:+.5f}" for v in r) for r in matrix))
            print(f"  fitted u at the centre {np.round(b, 4).tolist()}, true {list(field.translation)}: "
                  f"node positions consistent to {np.round(offset, 3).tolist()} voxel (z, y, x)")
            passed &= bool(np.abs(m - np.asarray(matrix)).max() < 0.002 and np.abs(offset).max() < 0.25)
            rec.update(fitted_gradient=m.tolist(), fitted_centre=b.tolist(), position_offset=offset.tolist())
        print(f"  -> {'PASS' if passed else 'FAIL'}")
        rec["passed"] = bool(passed)
        record[name] = rec
        ok &= passed
    _write_record(args, {"selfcheck": record})
    return 0 if ok else 1


# --------------------------------------------------------------------------- main


def _write_record(args, payload: dict, quiet: bool = False) -> None:
    path = Path(args.record) if args.record else RECORDS / (
        "bench_vs_aldvc_selfcheck.json" if args.selfcheck else
        f"bench_vs_aldvc_{'-'.join(str(s) for s in args.sizes)}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"date": time.strftime("%Y-%m-%d %H:%M:%S"), "host": platform.node(), "cores": os.cpu_count(),
            "machine": f"{platform.machine()} {platform.processor() or platform.platform()}", "commit": _commit(),
            "threads": args.threads, "aldvc_version": peer.VERSION, "aldvc_settings": peer.FIXED_SETTINGS,
            "argv": sys.argv[1:]}
    with open(path, "w") as fh:
        json.dump({"meta": meta, **payload}, fh, indent=1, default=_json_default)
    if not quiet:
        print(f"# record: {path}")


def _commit() -> str:
    """The checkout's commit (with ``+dirty`` when the tree has changes), or ``"unknown"``."""
    here = Path(__file__).resolve().parent
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain"], cwd=here, capture_output=True, text=True).stdout.strip()
    except OSError:
        return "unknown"
    return (sha or "unknown") + ("+dirty" if dirty else "")


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", nargs="+", default=list(DEFAULT_CASES), choices=CASE_NAMES + tuple(CASE_GROUPS),
                   help="built-in cases, or a group: heterogeneous (waves, slip, band), large (comp10, "
                        f"comp20, rot10), composed (crack-comp10, slip-comp10), all (default: {' '.join(DEFAULT_CASES)})")
    p.add_argument("--pair", action="append", default=[], metavar="DIR",
                   help="also run a synthesized pair directory (ref.zarr, def.zarr, field.json); repeatable")
    p.add_argument("--sizes", type=int, nargs="*", default=[128],
                   help="scan edges of the built-in cases (none: only the --pair directories)")
    p.add_argument("--spacings", type=int, nargs="*", default=[16, 12, 8],
                   help="ell: chunkdic element size, al-dvc --step ell --winsize 2ell (none, with "
                        "--solo-spacings: chunkdic alone)")
    p.add_argument("--solo-spacings", type=int, nargs="+", default=[], metavar="ELL",
                   help="further spacings run with chunkdic alone (e.g. 6: al-dvc is not run there)")
    p.add_argument("--repeats", type=int, default=3, help="runs per case and spacing (medians)")
    p.add_argument("--points", type=int, default=None,
                   help="score the field between the nodes at this many random voxels (the same for "
                        "both tools) instead of every voxel: 1024³ is 10⁹ voxels, ~10 min per score")
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="cores given to each tool")
    p.add_argument("--noise", type=float, default=0.02,
                   help="acquisition noise std, texture units (grey range ~1); independent per scan")
    p.add_argument("--band-lateral", type=float, default=None,
                   help="lateral expansion factor of the band cases (default: the standard case's 0.05)")
    p.add_argument("--feature-offset", type=float, nargs="+", default=[0.0], metavar="VOXELS",
                   dest="feature_offsets",
                   help="move the centre of the slip, crack and band cases (and the waves' phase) along z by "
                        "this much from the volume's centre, one set of cases per value: the score of a sharp "
                        "feature depends on where it falls between each tool's nodes (default 0)")
    p.add_argument("--dtype", default="uint16", choices=["uint8", "uint16", "float32"])
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--specimen", nargs="+", default=["grains", "concrete"], choices=["grains", "concrete", "foam"],
                   help="specimens of the built-in cases (default: the CT-like grains and concrete)")
    p.add_argument("--texture-scales", type=float, nargs="+", default=[1.0], metavar="FACTOR",
                   help="texture scales of the CT specimens (synth texture_scale: 1, 2, 4 give autocorrelation "
                        "lengths of about 6, 12 and 24 voxels; default 1)")
    p.add_argument("--oracle", action="store_true",
                   help="also score every candidate length's linearised field (validation/scripts/_oracle.py): the best "
                        "fixed length beside the automatic one")
    p.add_argument("--oracle-full", action="store_true",
                   help="with --oracle: run the whole engine at the oracle's length too (one more run per case)")
    p.add_argument("--reuse-peer", action="store_true",
                   help="score al-dvc's result an earlier run left in --workdir instead of running it again "
                        "(same scans and settings: its field is deterministic; its wall time is not kept)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a chunkdic setting for every run, e.g. --set regularization=none (repeatable)")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds per tool run")
    p.add_argument("--workdir", default=None, help="scans and runs (default: a new temporary directory)")
    p.add_argument("--venv", default=str(peer.DEFAULT_VENV), help="al-dvc's virtual environment")
    p.add_argument("--record", default=None, help="JSON record path (default: benchmarks/records/...)")
    p.add_argument("--no-warmup", action="store_true", help="skip the untimed warm-up runs")
    p.add_argument("--selfcheck", action="store_true",
                   help="only verify the adapter's conventions on known fields, then exit")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    for name in ("--ref", "--deformed", "--out", "--options"):
        p.add_argument(name, help=argparse.SUPPRESS)
    p.add_argument("--element-size", type=int, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return args
    if not args.spacings + args.solo_spacings:
        _error("give --spacings or --solo-spacings (--spacings with no value and --solo-spacings: chunkdic alone)")
    if any(s < 4 for s in args.spacings + args.solo_spacings):
        _error("--spacings and --solo-spacings must be >= 4")
    cases = []
    for c in args.cases:
        for name in CASE_GROUPS.get(c, (c,)):
            if name not in cases:
                cases.append(name)
    args.cases = cases
    if any(s < 32 for s in args.sizes):
        _error("--sizes must be >= 32")
    if args.repeats < 1 or args.threads < 1 or args.timeout <= 0:
        _error("--repeats, --threads and --timeout must be positive")
    args.options = set_options(args.set)
    return args


def set_options(items) -> dict:
    """``--set KEY=VALUE`` items as chunkdic settings (values read as JSON where they parse)."""
    options = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            _error(f"--set {item!r}: expected KEY=VALUE")
        try:
            options[key.replace("-", "_")] = json.loads(value)
        except json.JSONDecodeError:
            options[key.replace("-", "_")] = value
    return options


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.child:
        _chunkdic_child(args)
        return 0
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="chunkdic-vs-aldvc-")).resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    exe = peer.ensure_venv(Path(args.venv))
    print(f"# al-dvc {peer.VERSION} from {exe}; settings {peer.FIXED_SETTINGS}, n_threads {args.threads}; "
          f"chunkdic {args.threads} threads; {os.cpu_count()} cores; workdir {workdir}", flush=True)
    if args.selfcheck:
        return selfcheck(exe, args, workdir)
    if not args.no_warmup:
        warm_up(exe, args, workdir)
    cases = []
    for args.scale, n, specimen, args.feature_offset, name in itertools.product(
            args.texture_scales, args.sizes, args.specimen, args.feature_offsets, args.cases):
        if args.feature_offset != args.feature_offsets[0] and not offset_moves(name):
            continue  # a case the offset does not move (noise, large strain): once
        c = build_case(name, n, specimen, workdir, args)
        if c is not None:
            cases.append(c)
    cases += [pair_case(p) for p in args.pair]
    print(f"# medians of {args.repeats} run(s); with a known field: between the nodes (trilinear on each "
          f"tool's node grid, every voxel >= ell from the faces), sigma pooled, RMS vector error; "
          f"x = al-dvc wall / chunkdic wall\n" + HEADER, flush=True)
    results = []
    spacings = [(ell, True) for ell in args.spacings] + [(ell, False) for ell in args.solo_spacings
                                                         if ell not in args.spacings]
    for case in cases:
        npys = npy_copies(case, workdir)
        for ell, peer_too in spacings:
            if min(case.shape) < 3 * ell + 11:  # al-dvc needs two nodes per axis
                print(f"# {case.name} {case.shape[0]}^3: ell {ell} too large for this size, skipped")
                continue
            r = compare(case, ell, args, exe, workdir, npys, peer_too=peer_too)
            c, a = r["chunkdic"], r.get("al-dvc", {})
            ratio = a["wall"] / c["wall"] if c.get("wall") and a.get("wall") else None
            label = case.name + (f"@{case.offset:g}" if case.offset else "")
            print(row(case.shape[0], label, ell, "chunkdic", c), flush=True)
            if peer_too:
                print(row(case.shape[0], label, ell, "al-dvc", a, ratio), flush=True)
            for tool, m in (("chunkdic", c), ("al-dvc", a)):
                if "l10" in m:  # the star: spatial resolution read between the points (analysis/resolution.py)
                    print(f"{'':>4} {case.name:<18} {ell:>3} {tool:<8} l10 % {m.get('l10_bound', '')}"
                          f" {m['l10']:.1f} voxels", flush=True)
            results.append({"case": case.name, "note": case.note, "shape": case.shape, "ell": ell,
                            "offset": case.offset,
                            "field": None if case.field is None else case.field.to_json(),
                            "chunkdic": c, "al-dvc": a or None, "wall_ratio": ratio})
            _write_record(args, {"results": results, "complete": False}, quiet=True)  # what completed so far
    print(summary_table(results))
    _write_record(args, {"results": results, "complete": True})
    return 0


def summary_table(results: list[dict]) -> str:
    """Markdown: per case and ell, both tools' between-node error (sigma for translations),
    the ratio chunkdic / al-dvc, chunkdic's status and regularisation length, wall times, and
    each grid's floor (the exact field at its nodes, trilinear between them, same voxels)."""
    head = ("| case | ell | chunkdic | al-dvc | ratio | chunkdic, all voxels >= ell | chunkdic status "
            "| reg. length | oracle (length) | chunkdic / oracle | wall chunkdic / al-dvc (s) "
            "| grid floor chunkdic / al-dvc |")
    lines = [head, "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        c, a = r["chunkdic"], r.get("al-dvc") or {}
        name = r["case"].split("/")[0]
        key = "sigma" if name in ("shift", "noise") else "rms"
        ce, ae = (c.get(f"{key}_common"), a.get(f"{key}_common")) if a else (None, None)
        ratio = ce / ae if ce is not None and ae and math.isfinite(ce) and math.isfinite(ae) else None
        # the oracle on the same voxels as the tool's own figure: common ones beside al-dvc, else all
        mine, oracle = (ce, c.get(f"oracle_{key}_common")) if a else (c.get(key), c.get(f"oracle_{key}"))
        vs_oracle = mine / oracle if mine is not None and oracle else None
        at = f" @ {r['offset']:g}" if r.get("offset") else ""
        label = f"{r['case']}{at} ({'σ' if key == 'sigma' else 'RMS'})"
        lines.append(f"| {label} | {r['ell']} | {_fmt(ce, '.4f')} | {_fmt(ae, '.4f')} | {_fmt(ratio, '.2f')} | "
                     f"{_fmt(c.get(key), '.4f')} | {c.get('status', '-')} | {_fmt(c.get('reg_length'), '.0f')} | "
                     f"{_fmt(oracle, '.4f')} ({_fmt(c.get('oracle_length'), '.0f')}) | {_fmt(vs_oracle, '.2f')} | "
                     f"{_fmt(c.get('wall'), '.1f')} / {_fmt(a.get('wall'), '.1f')} | "
                     f"{_fmt(c.get('floor_common'), '.4f')} / {_fmt(a.get('floor_common'), '.4f')} |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
