"""The star table: noise, l10 % and MEI of chunkdic and al-dvc, side by side.

For each CT-like specimen and each node spacing ``ell`` both tools correlate, in this
session and on the same scans:

- a **star** pair (:class:`chunkdic.synth.fields.Star`, ``Ux = 0.5 sin(2π (z − z_c) / λ(y))``,
  ``λ`` rising linearly from ``2 ell`` to ``20 ell`` over the rows read, ``ell`` from the y
  faces, as ``chunkdic resolution`` builds it), rendered from the specimen's geometry with
  independent CT noise ``--noise`` in each scan (the same rendering as every case of
  ``bench_vs_aldvc.py``);
- a **translated** pair ((0.5, 0.5, 0.5) voxel, rendered, independent noise in each scan),
  correlated **at the setting of the star run**: chunkdic with the regularisation length
  its automatic rule chose on the star (as ``chunkdic resolution`` does), al-dvc with the
  ``beta`` its L-curve auto-tuned on the star (``--set beta=...``; the rest of its
  defaults, ``--winsize 2ell --step ell``). Left to themselves both would pick a much
  smoother setting on a translation, whose small noise says nothing about the resolution
  read on the star.

Scores, both tools alike (``chunkdic.analysis``): ``l10 %`` read between each tool's points
(:func:`chunkdic.analysis.resolution.star_ratios_nodes`, trilinear between the points,
rows at least ``ell`` from the faces and inside the tool's hull; DIC Challenge 2.0 rule:
the period at which the smooth fit of measured/imposed amplitude first rises through 0.9);
the noise ``n`` = σ pooled over the components of the translated pair between the nodes
(:func:`chunkdic.analysis.scoring.score_between_nodes`), over the tool's own voxels (at
least ``ell`` from the faces, inside its hull: the voxels its ``l10 %`` is read on) and
over the voxels common to both tools (``n common``); ``MEI = n · l10 %`` and the 3-D form
``n · l10 %^1.5``; ``ratio`` = al-dvc's MEI / chunkdic's (target: ≥ 1.5 at
ell = 8).

chunkdic runs once per ``--regularizations`` kind (default Tikhonov and the equilibrium
gap, both with the automatic length); ``--solo-spacings`` run chunkdic alone (ell = 6).
Each run is a fresh process with ``--threads`` cores, as in ``bench_vs_aldvc.py``.

Usage::

    nice python validation/scripts/bench_star_vs_aldvc.py --specimen grains concrete \
        --spacings 16 12 8 --solo-spacings 6 --threads 2 --workdir /tmp/star
    nice python validation/scripts/bench_star_vs_aldvc.py --seed 2 --spacings 8 --threads 2 \
        --workdir /tmp/star --record validation/scripts/records/bench_star_vs_aldvc_seed2.json
    nice python validation/scripts/bench_star_vs_aldvc.py --specimen concrete --texture-scales 1 2 4 \
        --spacings 8 --regularizations tikhonov --threads 2 --workdir /tmp/star   # MEI per texture scale

The run prints one line per tool and setting as it goes, then a Markdown table; the JSON
record (``validation/scripts/records/bench_star_vs_aldvc.json`` unless ``--record``) is rewritten
after every spacing.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import aldvc as peer  # noqa: E402
from bench_vs_aldvc import (  # noqa: E402
    RECORDS,
    Case,
    _between,
    _commit,
    _fmt,
    _star,
    between_common,
    npy_copies,
    run_chunkdic,
    set_options,
    warm_up,
)

SHIFT = (0.5, 0.5, 0.5)
AMPLITUDE = 0.5


def _error(msg: str) -> None:
    print(f"bench_star_vs_aldvc: error: {msg}", file=sys.stderr)
    sys.exit(2)


def star_field(shape, ell: int):
    """The star of ``chunkdic resolution`` for ``ell``: periods ``2 ell … 20 ell`` over the rows
    at least ``ell`` from the y faces, zero phase at mid-height."""
    from chunkdic.synth.fields import Star

    return Star(amplitude=AMPLITUDE, period_min=2.0 * ell, period_max=20.0 * ell, y0=ell - 0.5,
                y1=shape[1] - 0.5 - ell, center_z=(shape[0] - 1) / 2.0)


def specimen_label(specimen: str, scale: float) -> str:
    """``concrete`` at texture scale 1, ``concrete-ts2`` at 2 (as ``bench_vs_aldvc.py`` names them)."""
    return specimen if scale == 1.0 else f"{specimen}-ts{scale:g}"


def make_pair(workdir: Path, name: str, shape, specimen: str, field, args, scale: float = 1.0) -> Case:
    """Render a pair (kept under ``workdir`` between runs: same seed, same scans); ``scale``: the
    specimen's texture scale (``texture_scale`` of :func:`chunkdic.synth.synthetic.synthesize`)."""
    from chunkdic.synth import synthetic

    label = specimen_label(specimen, scale)
    tag = f"{name}-{'x'.join(map(str, shape))}-{label}-n{args.noise:g}-s{args.seed}"
    out = workdir / tag
    if not (out / "field.json").exists():
        t0 = time.perf_counter()
        extra = {"texture_scale": scale} if scale != 1.0 else {}
        synthetic.synthesize(out, shape, field=field, specimen=specimen, seed=args.seed, dtype="uint16",
                             noise=args.noise, overwrite=True, **extra)
        print(f"# synthesized {tag} in {time.perf_counter() - t0:.1f} s", flush=True)
    return Case(f"{name}/{label}", str(out / "ref.zarr"), str(out / "def.zarr"), field, tuple(shape))


def _row(tool: str, star: dict, trans: dict, common: dict | None, setting) -> dict:
    """One tool at one setting: l10 % from the star, n from the translated pair, MEI."""
    l10 = star.get("l10")
    n_own, n_common = trans.get("sigma"), (common or {}).get("sigma_common")
    out = {"tool": tool, "setting": setting, "l10": l10, "l10_bound": star.get("l10_bound"),
           "n": n_own, "n_common": n_common,
           "status_star": star.get("status"), "status_translated": trans.get("status"),
           "wall_star": star.get("wall"), "wall_translated": trans.get("wall")}
    for key, n in (("", n_own), ("_common", n_common)):
        ok = l10 is not None and n is not None and math.isfinite(n)
        out[f"mei{key}"] = n * l10 if ok else None
        out[f"mei3d{key}"] = n * l10 ** 1.5 if ok else None
    return out


def chunkdic_setting(star: Case, trans: Case, ell: int, reg: str, args, runs: Path) -> tuple[dict, dict, tuple]:
    """chunkdic on the star (automatic length), then the translated pair at that length."""
    opts = {**args.options, "regularization": reg}
    s = run_chunkdic(star, ell, args.threads, runs / f"chunkdic-{reg}-star", args.timeout, opts)
    pts, u = s.pop("points", None), s.pop("u", None)
    s.update(_star(pts, u, None, star, ell))
    same = dict(opts)
    if s.get("reg_length") is not None and reg != "none":
        same["regularization_length"] = float(s["reg_length"])
    t = run_chunkdic(trans, ell, args.threads, runs / f"chunkdic-{reg}-translated", args.timeout, same)
    tp, tu = t.pop("points", None), t.pop("u", None)
    t.update(_between(tp, tu, trans, ell))
    return s, t, (tp, tu)


def aldvc_setting(exe, star: Case, trans: Case, ell: int, args, workdir: Path, runs: Path):
    """al-dvc on the star (its defaults, beta auto-tuned), then the translated pair at that beta."""
    a = peer.run_aldvc(exe, *npy_copies(star, workdir), runs / "aldvc-star", winsize=2 * ell, step=ell,
                       threads=args.threads, timeout=args.timeout)
    s = {"status": a.status, "wall": a.pipeline_seconds, "beta": a.info.get("beta"),
         "n_flagged": a.info.get("n_flagged"), **_star(a.points, a.u, a.valid, star, ell)}
    settings = {"beta": s["beta"]} if s["beta"] is not None else None
    b = peer.run_aldvc(exe, *npy_copies(trans, workdir), runs / "aldvc-translated", winsize=2 * ell, step=ell,
                       threads=args.threads, timeout=args.timeout, settings=settings)
    t = {"status": b.status, "wall": b.pipeline_seconds, "beta": b.info.get("beta"),
         "n_flagged": b.info.get("n_flagged"), **_between(b.points, b.u, trans, ell)}
    return s, t, (b.points, b.u)


def measure(exe, args, workdir: Path) -> list[dict]:
    from chunkdic.synth.fields import Translation

    shape = tuple(args.shape)
    rows = []
    spacings = [(e, True) for e in args.spacings] + [(e, False) for e in args.solo_spacings
                                                     if e not in args.spacings]
    for scale, base in ((s, b) for s in args.texture_scales for b in args.specimen):
        specimen = specimen_label(base, scale)
        trans = make_pair(workdir, "translated", shape, base, Translation(SHIFT), args, scale)
        for ell, peer_too in spacings:
            star = make_pair(workdir, f"star-ell{ell}", shape, base, star_field(shape, ell), args, scale)
            runs = workdir / "runs" / f"{specimen}-ell{ell}-s{args.seed}"
            grids = {}
            results = {}
            for reg in args.regularizations:
                s, t, grids[reg] = chunkdic_setting(star, trans, ell, reg, args, runs)
                results[reg] = (s, t)
            if peer_too:
                sa, ta, grids["al-dvc"] = aldvc_setting(exe, star, trans, ell, args, workdir, runs)
            for reg, (s, t) in results.items():
                common = between_common({"chunkdic": grids[reg], "al-dvc": grids["al-dvc"]}, trans, ell) \
                    if peer_too else {}
                r = _row(f"chunkdic {reg}", s, t, common.get("chunkdic"), s.get("reg_length"))
                rows.append({"specimen": specimen, "ell": ell, "seed": args.seed, **r,
                             "star_run": s, "translated_run": t})
                _print(rows[-1])
            if peer_too:
                # al-dvc's n on the voxels common with the first chunkdic setting's grid (the grids
                # of every chunkdic setting are the same mesh)
                first = args.regularizations[0]
                common = between_common({"chunkdic": grids[first], "al-dvc": grids["al-dvc"]}, trans, ell)
                r = _row("al-dvc", sa, ta, common.get("al-dvc"), sa.get("beta"))
                rows.append({"specimen": specimen, "ell": ell, "seed": args.seed, **r,
                             "star_run": sa, "translated_run": ta})
                _print(rows[-1])
            _write(args, rows, complete=False)
    return rows


def _print(r: dict) -> None:
    print(f"{r['specimen']:<9} ell {r['ell']:>2} {r['tool']:<26} setting {_fmt(r['setting'], '.3g'):>7} "
          f"n {_fmt(r['n'], '.4f')} (common {_fmt(r['n_common'], '.4f')}) l10 {r['l10_bound'] or ''}"
          f"{_fmt(r['l10'], '.1f')} MEI {_fmt(r['mei'], '.3f')} n*l10^1.5 {_fmt(r['mei3d'], '.2f')} "
          f"status {r['status_star']} / {r['status_translated']}", flush=True)


def table(rows: list[dict]) -> str:
    """Markdown: per specimen, ell and tool/setting, the noise, l10 %, MEI and the ratios
    al-dvc / chunkdic (MEI with each tool's own n, and with n on the common voxels)."""
    peers = {(r["specimen"], r["ell"], r["seed"]): r for r in rows if r["tool"] == "al-dvc"}
    head = ("| specimen | ℓ | seed | tool | ℓ_reg (vox.) / β | n (vox.) | n common | l10 % (vox.) | MEI | "
            "n·l10 %^1.5 | al-dvc MEI / this | same, n common | al-dvc n·l10^1.5 / this | status star / translated |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        p = peers.get((r["specimen"], r["ell"], r["seed"]))

        def ratio(key, r=r, p=p):
            if p is None or r is p or not r.get(key) or p.get(key) is None:
                return None
            return p[key] / r[key]

        b = {"=": "", "<": "< ", ">": "> "}.get(r["l10_bound"] or "=", "")
        lines.append(
            f"| {r['specimen']} | {r['ell']} | {r['seed']} | {r['tool']} | {_fmt(r['setting'], '.3g')} | "
            f"{_fmt(r['n'], '.4f')} | {_fmt(r['n_common'], '.4f')} | {b}{_fmt(r['l10'], '.1f')} | "
            f"{_fmt(r['mei'], '.3f')} | {_fmt(r['mei3d'], '.2f')} | {_fmt(ratio('mei'), '.2f')} | "
            f"{_fmt(ratio('mei_common'), '.2f')} | {_fmt(ratio('mei3d'), '.2f')} | "
            f"{r['status_star']} / {r['status_translated']} |")
    return "\n".join(lines)


def _write(args, rows, complete: bool) -> None:
    path = Path(args.record) if args.record else RECORDS / "bench_star_vs_aldvc.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"date": time.strftime("%Y-%m-%d %H:%M:%S"), "commit": _commit(), "argv": sys.argv[1:],
            "threads": args.threads,
            "cores": os.cpu_count(), "aldvc_version": peer.VERSION, "aldvc_settings": peer.FIXED_SETTINGS,
            "loadavg_end": Path("/proc/loadavg").read_text().split()[:3] if Path("/proc/loadavg").exists() else None}
    with open(path, "w") as fh:
        json.dump({"meta": meta, "rows": rows, "complete": complete}, fh, indent=1, default=_json_default)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--specimen", nargs="+", default=["grains", "concrete"], choices=["grains", "concrete"])
    p.add_argument("--texture-scales", type=float, nargs="+", default=[1.0], metavar="FACTOR",
                   help="texture scales of the specimens (synth texture_scale: 1, 2, 4 give autocorrelation "
                        "lengths of about 6, 12 and 24 voxels; default 1)")
    p.add_argument("--shape", type=int, nargs=3, default=[96, 240, 96], metavar=("NZ", "NY", "NX"),
                   help="scan shape (default 96 240 96: the star's periods run along y)")
    p.add_argument("--spacings", type=int, nargs="*", default=[16, 12, 8], help="spacings run by both tools")
    p.add_argument("--solo-spacings", type=int, nargs="+", default=[], metavar="ELL",
                   help="spacings run by chunkdic alone (e.g. 6)")
    p.add_argument("--regularizations", nargs="+", default=["tikhonov", "equilibrium-gap"],
                   choices=["tikhonov", "equilibrium-gap", "none"], help="chunkdic's settings (automatic length)")
    p.add_argument("--noise", type=float, default=0.02, help="CT noise, fraction of the phase contrast, per scan")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    p.add_argument("--timeout", type=float, default=1800.0)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a chunkdic setting for every run")
    p.add_argument("--workdir", required=True, help="scans and runs (kept: a second run reuses the scans)")
    p.add_argument("--venv", default=str(peer.DEFAULT_VENV))
    p.add_argument("--record", default=None)
    p.add_argument("--no-warmup", action="store_true")
    args = p.parse_args(argv)
    if any(s < 4 for s in args.spacings + args.solo_spacings):
        _error("--spacings and --solo-spacings must be >= 4")
    if min(args.shape) < 3 * max(args.spacings + args.solo_spacings) + 11:
        _error("--shape too small for the largest spacing (al-dvc needs 3 ell + 11 voxels a side)")
    if args.threads < 1 or args.timeout <= 0:
        _error("--threads and --timeout must be positive")
    args.options = set_options(args.set)
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    workdir = Path(args.workdir).resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    exe = peer.ensure_venv(Path(args.venv))
    print(f"# al-dvc {peer.VERSION}, chunkdic and al-dvc on {args.threads} threads; load "
          f"{Path('/proc/loadavg').read_text().strip()}", flush=True)
    if not args.no_warmup:
        warm_up(exe, args, workdir)
    rows = measure(exe, args, workdir)
    print(table(rows))
    _write(args, rows, complete=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
