"""Large strain, large rotation and small-displacement accuracy of chunkdic's defaults.

Cases on the CT-like specimens (``grains``, ``concrete``; independent noise 0.02 in each
scan), each correlated with ``chunkdic.correlate(ref, def, element_size=ell)`` and its
defaults, scored between the nodes (:func:`chunkdic.analysis.scoring.score_between_nodes`:
the field trilinear on the node grid at every voxel at least ``ell`` from the faces, RMS
of the vector error):

- ``comp10`` / ``comp20``: homogeneous axial compression of 10 / 20 % along z with 3 / 6 %
  lateral expansion, about the volume's centre;
- ``rot10``: a rotation of 10° about z through the volume's centre;
- ``bigband``: a large, non-affine deformation: a compression band of −20 % over 48 voxels
  (tanh edges of 12 voxels, lateral factor 0.3): ``u_z`` drops by 9.6 voxels across it,
  ``u_y, u_x`` reach ±3 voxels (the nodal truth alone, trilinear between the nodes, scores
  0.037 / 0.021 voxel RMS at ℓ = 8 / 6: the basis's floor);
- ``shift``: translation (0.5, 0.5, 0.5) (the standard ``shift`` case);
- ``band``: the standard compression band (−8 %, 6 voxels).

``--scales`` coarsens the texture: every size of the specimen (grain radii; aggregate and
pore radii and the matrix's value-noise spacing) is multiplied by the factor
(:func:`scaled_specimen`; synth's defaults unchanged), and the reference's autocorrelation
length per axis (1/e of its unbiased autocorrelation, by FFT: :func:`autocorrelation_length`)
is measured and printed with each pair. Factor 1: about 6 voxels; 2.25: about 12; 4.5:
about 24.

Usage::

    python validation/scripts/bench_large_strain.py --size 100 --cases comp10 comp20 rot10 --spacings 8 6
    python validation/scripts/bench_large_strain.py --size 100 --cases shift band --spacings 16 12 8 --record NAME
    python validation/scripts/bench_large_strain.py --size 128 --scales 1 2.25 4.5 --aldvc --record NAME

docs/engine.md, "ROI and meshes", records what it measured.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RECORDS = Path(__file__).parent / "records"


def large_field(case: str, n: int):
    """The analytic field of a large-deformation case on an ``n``³ volume."""
    from chunkdic.synth.fields import Affine, Band

    c = ((n - 1) / 2,) * 3
    if case == "bigband":  # -20 % over a 48-voxel band, lateral 0.3: u_z drops 9.6 voxels across it
        return Band(center_z=c[0], width=48.0, edge=12.0, strain=-0.20, lateral=0.3, center_y=c[1], center_x=c[2])
    if case in ("comp10", "comp20"):
        e = 0.10 if case == "comp10" else 0.20
        return Affine(matrix=((-e, 0, 0), (0, 0.3 * e, 0), (0, 0, 0.3 * e)), center=c)
    if case == "rot10":
        t = math.radians(10.0)
        cs, sn = math.cos(t), math.sin(t)
        return Affine(matrix=((0, 0, 0), (0, cs - 1, -sn), (0, sn, cs - 1)), center=c)
    raise ValueError(case)


def scaled_specimen(specimen: str, factor: float) -> dict:
    """The specimen parameters that multiply every size of its texture by ``factor`` (voxels):
    grain radii (``grains``); aggregate and pore radii and the matrix's value-noise spacing
    (``concrete``). ``{}`` at factor 1 (the defaults)."""
    from chunkdic.synth.microstructure import SPECIMENS

    if factor == 1:
        return {}
    sizes = {"grains": ("radius_median", "radius_min", "radius_max"),
             "concrete": ("aggregate_median", "aggregate_min", "aggregate_max", "pore_median", "pore_min",
                          "pore_max", "texture_size")}[specimen]
    defaults = SPECIMENS[specimen]()
    return {name: getattr(defaults, name) * factor for name in sizes}


def autocorrelation_length(volume: np.ndarray) -> list[float]:
    """Lag (voxels) where the normalised autocorrelation of ``volume`` (3-D) first falls to 1/e,
    per axis ``(z, y, x)``, linearly interpolated between lags. Unbiased: the autocorrelation
    (by FFT, zero-padded to twice the shape) is divided by the number of voxel pairs at each lag."""
    v = volume.astype(np.float64)
    v -= v.mean()
    shape, axes = [2 * n for n in v.shape], (0, 1, 2)

    def power(a):
        return np.fft.irfftn(np.abs(np.fft.rfftn(a, s=shape, axes=axes)) ** 2, s=shape, axes=axes)

    ac = power(v) / np.maximum(power(np.ones_like(v)), 1.0)
    ac /= ac[0, 0, 0]
    out = []
    for a in range(3):
        line = ac[tuple(slice(0, v.shape[a] // 2) if b == a else 0 for b in range(3))]
        j = int(np.argmax(line < 1 / np.e))
        out.append(float(j - 1 + (line[j - 1] - 1 / np.e) / (line[j - 1] - line[j])) if j > 0 else math.nan)
    return out


def make_pair(root: Path, specimen: str, case: str, n: int, seed: int = 0, scale: float = 1.0) -> dict:
    from chunkdic.synth import synthetic

    out = root / f"{specimen}-{case}-{n}-{seed}-x{scale:g}"
    params = scaled_specimen(specimen, scale)
    if case in ("shift", "band"):
        return synthetic.standard_case(out, case, n, specimen=specimen, noise=0.02, seed=seed, overwrite=True,
                                       **params)
    return synthetic.synthesize(out, n, field=large_field(case, n), specimen=specimen, noise=0.02, seed=seed,
                                overwrite=True, **params)


def reference_acl(pair: dict) -> list[float]:
    """The autocorrelation length per axis of the pair's reference (read whole: benchmark sizes)."""
    from chunkdic.io.scan import open_scan

    return autocorrelation_length(np.asarray(open_scan(pair["reference"]).refs([0])[0].open()[:]))


def run(pair: dict, n: int, ell: int, **settings) -> dict:
    import chunkdic
    from chunkdic.analysis.scoring import score_between_nodes

    t0 = time.perf_counter()
    res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=ell, **settings)
    wall = time.perf_counter() - t0
    s = score_between_nodes(res.mesh.node_axes(), res.displacement, pair["field"], (n,) * 3, ell)
    return {"status": res.info["status"], "rms": s.rms, "max": s.max_error, "wall": wall,
            "levels": res.info["levels"], "level_status": res.info["level_status"],
            "reg_length": res.info["regularization"]["length"]}


def run_peer(pair: dict, n: int, ell: int, workdir: Path, threads: int) -> dict:
    """al-dvc (``--winsize 2ell --step ell``, its defaults) on the same pair, scored the same way
    (its nodes as they come out, inpainted ones included; ``flagged`` counts those it flags)."""
    sys.path.insert(0, str(Path(__file__).parent))
    import aldvc as peer

    from chunkdic.analysis.scoring import score_between_nodes
    from chunkdic.io.scan import open_scan

    npys = []
    for which in ("reference", "deformed"):
        arr = open_scan(pair[which]).refs([0])[0].open()
        npys.append(peer.write_npy(arr, workdir / f"{Path(pair[which]).parent.name}-{which}.npy"))
    r = peer.run_aldvc(peer.ensure_venv(), npys[0], npys[1], workdir / "aldvc", winsize=2 * ell, step=ell,
                       threads=threads)
    if r.points is None:
        return {"status": r.status, "rms": math.nan, "max": math.nan, "wall": r.wall}
    axes = [np.unique(r.points[a]) for a in range(3)]
    u = r.u.reshape((3,) + tuple(a.size for a in axes))
    s = score_between_nodes(axes, u, pair["field"], (n,) * 3, ell)
    return {"status": r.status, "rms": s.rms, "max": s.max_error, "wall": r.wall,
            "flagged": int((~r.valid).sum())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=100)
    ap.add_argument("--specimens", nargs="+", default=["grains", "concrete"])
    ap.add_argument("--cases", nargs="+", default=["comp10", "comp20", "rot10"])
    ap.add_argument("--spacings", nargs="+", type=int, default=[8, 6])
    ap.add_argument("--scales", nargs="+", type=float, default=[1.0],
                    help="texture scale factors (every size of the specimen multiplied: scaled_specimen)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a chunkdic setting (value parsed as JSON when it can be)")
    ap.add_argument("--coarse-min-element", type=int,
                    help="override chunkdic.engine.meshes.COARSE_MIN_ELEMENT (measuring the schedule)")
    ap.add_argument("--aldvc", action="store_true", help="also run al-dvc on each pair (benchmarks/aldvc.py)")
    ap.add_argument("--aldvc-only", action="store_true", help="run al-dvc alone on each pair, not chunkdic")
    ap.add_argument("--threads", type=int, default=2, help="al-dvc's threads")
    ap.add_argument("--record", help="write benchmarks/records/bench_large_strain_NAME.json")
    args = ap.parse_args(argv)
    settings = {}
    for kv in args.set:
        k, v = kv.split("=", 1)
        try:
            settings[k] = json.loads(v)
        except json.JSONDecodeError:
            settings[k] = v
    if args.coarse_min_element is not None:
        from chunkdic.engine import meshes as planning

        planning.COARSE_MIN_ELEMENT = args.coarse_min_element
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for specimen, scale, case in itertools.product(args.specimens, args.scales, args.cases):
            pair = make_pair(Path(tmp), specimen, case, args.size, scale=scale)
            acl = reference_acl(pair)
            print(f"{specimen} x{scale:g} {case}: autocorrelation length {' '.join(f'{v:.1f}' for v in acl)}",
                  flush=True)
            tag = dict(specimen=specimen, scale=scale, acl=acl, case=case)
            for ell in args.spacings:
                if not args.aldvc_only:
                    r = run(pair, args.size, ell, **settings)
                    r.update(tag, ell=ell)
                    rows.append(r)
                    print(f"{specimen:9s} x{scale:<4g} {case:7s} ell={ell:3d} {r['status']:15s} rms={r['rms']:.4f} "
                          f"max={r['max']:.3f} wall={r['wall']:.1f}s reg={r['reg_length']} levels={r['levels']}",
                          flush=True)
                if args.aldvc or args.aldvc_only:
                    a = run_peer(pair, args.size, ell, Path(tmp), args.threads)
                    a.update(tag, ell=ell, tool="al-dvc")
                    rows.append(a)
                    print(f"{'':9s} {'':5s} {'al-dvc':7s} ell={ell:3d} {a['status']:15s} rms={a['rms']:.4f} "
                          f"max={a['max']:.3f} wall={a['wall']:.1f}s flagged={a.get('flagged')}", flush=True)
    if args.record:
        RECORDS.mkdir(exist_ok=True)
        path = RECORDS / f"bench_large_strain_{args.record}.json"
        path.write_text(json.dumps({"argv": sys.argv[1:], "settings": settings, "rows": rows}, indent=1))
        print(f"record: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
