"""Local CT imaging (``--imaging local``) against the FBP imaging: spectra, blur, engine, speed.

Prints (docs/synthetic.md, "Local imaging"):

- ``spectra``: the radially averaged noise power spectrum (NPS, slices of pure noise) and
  transfer function of the noise-free phase map (cross spectrum / phantom spectrum) of both
  imagings at ``--n`` (default 128), and the noise std against the requested one;
- ``engine``: what ``chunkdic.correlate`` measures on pairs of both imagings at ``--n``:
  sigma of a (0.5, 0.5, 0.5) translation rendered with independent noise (case b) and the
  RMS error of the band case (c, no grey change) at the nodes at least ``ell`` from the
  faces, ``ell`` = 16 and 8; the translation also without regularisation (raw sigma);
- ``speed``: CPU time of a local pair (``synthesize``, band, uint16) at ``--sizes``,
  Mvoxel per CPU s (both scans counted) and the 2048³ pair extrapolated on 2 cores.

Usage: ``python validation/scale/bench_ct_local.py [spectra] [engine] [speed] [--n 128] [--sizes 128 256]``.
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time

import numpy as np


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _radial(power: np.ndarray, n: int, bins: np.ndarray) -> np.ndarray:
    f = np.fft.fftfreq(n)
    k = np.hypot(f[:, None], f[None, :]).ravel()
    idx = np.digitize(k, bins)
    return np.array([power.ravel()[idx == i].mean() for i in range(1, len(bins))])


def spectra(n: int, slices: int = 8) -> None:
    from chunkdic.synth.ctpair import render_ct

    bins = np.linspace(0.0, 0.70, 15)
    centres = 0.5 * (bins[1:] + bins[:-1])
    rows = {}
    for mode in ("fbp", "local"):
        kw = dict(specimen="grains", dtype="float32", imaging=mode, seed=0)
        shape = (slices, n, n)
        clean = render_ct(shape, noise=0.0, **kw).astype(np.float64)
        noisy = render_ct(shape, noise=0.02, **kw).astype(np.float64)
        noise = noisy - clean
        from chunkdic.synth import microstructure as M
        from chunkdic.synth.ctpair import CTSpecimen

        sp = CTSpecimen.build("grains", shape)
        mu = M.render_phantom(sp.params, shape).astype(np.float64)
        nps = cross = pp = 0.0
        for z in range(slices):
            F = np.fft.fft2(mu[z] - mu[z].mean())
            G = np.fft.fft2(clean[z] - clean[z].mean())
            cross = cross + (G * np.conj(F)).real
            pp = pp + np.abs(F) ** 2
            nps = nps + np.abs(np.fft.fft2(noise[z])) ** 2 / (n * n)
        edge = (mu > 0.02) & (mu < 0.98)
        rows[mode] = dict(nps=_radial(nps / slices, n, bins), mtf=_radial(cross, n, bins) / _radial(pp, n, bins),
                          std=float(noise.std()), edge_rms=float(np.sqrt(np.mean((clean - mu)[edge] ** 2))),
                          rms=float(np.sqrt(np.mean((clean - mu) ** 2))))
    print(f"# spectra at {n}^2, {slices} slices, noise 0.02 requested")
    for mode, r in rows.items():
        print(f"{mode:>5}: noise std {r['std']:.5f} ({r['std'] / 0.02:.3f} of requested), noise-free minus phase map: "
              f"RMS {r['rms']:.4f}, on partial-volume voxels {r['edge_rms']:.4f}")
    print(f"{'k':>6} {'NPS fbp':>10} {'NPS local':>10} {'ratio':>6} {'MTF fbp':>8} {'MTF local':>9}")
    for i, k in enumerate(centres):
        a, b = rows["fbp"], rows["local"]
        print(f"{k:6.3f} {a['nps'][i]:10.3e} {b['nps'][i]:10.3e} {b['nps'][i] / a['nps'][i]:6.2f} "
              f"{a['mtf'][i]:8.3f} {b['mtf'][i]:9.3f}")
    a, b = rows["fbp"]["nps"], rows["local"]["nps"]
    sel = (centres > 0.04) & (centres < 0.3)
    for mode, v in (("fbp", a), ("local", b)):
        slope = np.polyfit(np.log(centres[sel]), np.log(v[sel]), 1)[0]
        print(f"{mode:>5}: log-log slope of the NPS over 0.04 < k < 0.3: {slope:.2f}")


def engine(n: int, root: str, cases=("shift", "band")) -> None:
    import chunkdic
    from chunkdic import score_displacement
    from chunkdic.synth import synthetic as S
    from chunkdic.synth.fields import true_displacement

    print(f"# engine at {n}^3, grains, noise 0.02, uint16, CT defaults; nodes >= ell from the faces")
    print(f"{'imaging':>7} {'case':>12} {'ell':>4} {'sigma':>8} {'RMS':>8} {'status':>10} {'wall s':>7} reg. length")
    for mode in ("fbp", "local"):
        for case in cases:
            out = os.path.join(root, f"{mode}-{case}")
            res = S.standard_case(out, case, n, specimen="grains", noise=0.02, imaging=mode)
            fld = res["field"]
            runs = [(ell, {}) for ell in (16, 8)]
            if case == "shift":  # sigma of a translation without the regularisation, which hides it
                runs += [(ell, {"regularization": "none"}) for ell in (16, 8)]
            for ell, opts in runs:
                t0 = time.perf_counter()
                r = chunkdic.correlate(os.path.join(out, "ref.zarr"), os.path.join(out, "def.zarr"), element_size=ell,
                                       **opts)
                wall = time.perf_counter() - t0
                scale = float(r.info.get("scale", 1))
                pts = r.node_coords.reshape(3, -1) * scale + (scale - 1) / 2
                u = r.displacement.reshape(3, -1) * scale
                truth = true_displacement(fld, pts[0], pts[1], pts[2])
                s = score_displacement(pts, u, truth, (n, n, n), ell)
                name = case + (" noreg" if opts else "")
                print(f"{mode:>7} {name:>12} {ell:>4} {s.sigma:8.4f} {s.rms:8.4f} {str(r.info.get('status')):>10} "
                      f"{wall:7.1f} {(r.info.get('regularization') or {}).get('length')}", flush=True)


def speed(sizes, root: str) -> None:
    from chunkdic.synth import synthetic as S

    S.standard_case(os.path.join(root, "warm"), "band", 32, imaging="local")  # Numba caches loaded
    print("# local pair (band, grains, noise 0.02, uint16), synthesize, threads")
    rates = []
    for n in sizes:
        out = os.path.join(root, f"speed{n}")
        c0, t0 = _cpu(), time.perf_counter()
        S.standard_case(out, "band", n, imaging="local")
        cpu, wall = _cpu() - c0, time.perf_counter() - t0
        rate = 2 * n ** 3 / cpu / 1e6
        rates.append(rate)
        print(f"{n:>5}^3: CPU {cpu:.1f} s, wall {wall:.1f} s, {rate:.2f} Mvoxel per CPU s", flush=True)
    r = rates[-1]
    print(f"2048^3 pair at {r:.2f} Mvoxel per CPU s: {2 * 2048 ** 3 / r / 1e6 / 3600:.2f} CPU h, "
          f"{2 * 2048 ** 3 / r / 2e6 / 3600:.2f} h on 2 free cores")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("parts", nargs="*", default=["spectra", "engine", "speed"])
    ap.add_argument("--n", type=int, default=128)
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--dir", default=None)
    ap.add_argument("--cases", nargs="+", default=["shift", "band"])
    a = ap.parse_args()
    print(f"# load {open('/proc/loadavg').read().split()[:3]}")
    with tempfile.TemporaryDirectory(dir=a.dir) as root:
        if "spectra" in a.parts:
            spectra(a.n)
        if "engine" in a.parts:
            engine(a.n, root, a.cases)
        if "speed" in a.parts:
            speed(a.sizes, root)
    print(f"# load {open('/proc/loadavg').read().split()[:3]}")


if __name__ == "__main__":
    main()
