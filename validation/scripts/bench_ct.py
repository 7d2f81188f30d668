"""Speed of the CT-like specimens: phantom, projector, FBP and ``synthesize`` pairs.

Usage::

    python validation/scripts/bench_ct.py [--sizes 128 300] [--specimens grains concrete]
                                  [--repeat 1] [--dir DIR] [--skimage]

Prints, per slice size, the CPU time of one slice for the phase map (reference and
band-deformed), the Joseph projector and the FBP (one thread), optionally the same for
scikit-image's ``radon``/``iradon`` (``--skimage``, when installed); then for each size
and specimen, ``synthesize`` of a pair with a compression band (Dask threads, all cores):
wall time, CPU time, Mvoxel/s of wall time (both scans counted, ``2 N^3``) and peak RSS.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import tempfile
import time


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def slice_costs(n: int, skimage: bool) -> dict:
    import numpy as np

    from chunkdic.synth import ctsim as C
    from chunkdic.synth import microstructure as M
    from chunkdic.synth.ctpair import standard_field

    P = M.GrainsParams()
    fld, _ = standard_field("band", (n, n, n))
    M.render_phantom(P, (1, 8, 8), field=fld)
    g = C.Geometry.of(n, n)
    out = {"angles": g.angles, "detector": g.ndet}

    def best(fn, k=3):
        ts = []
        for _ in range(k):
            t = time.process_time()
            r = fn()
            ts.append(time.process_time() - t)
        return min(ts), r

    out["phantom_ref_ms"] = 1e3 * best(lambda: M.render_phantom(P, (1, n, n), origin=(n // 2, 0, 0)))[0]
    out["phantom_def_ms"] = 1e3 * best(lambda: M.render_phantom(P, (1, n, n), origin=(n // 2, 0, 0), field=fld))[0]
    mu = M.render_phantom(P, (1, n, n), origin=(n // 2, 0, 0))[0].astype(np.float64)
    C.fbp(C.radon(mu, g), g)
    out["radon_ms"], sino = best(lambda: C.radon(mu, g))
    out["radon_ms"] *= 1e3
    out["fbp_ms"] = 1e3 * best(lambda: C.fbp(sino, g))[0]
    if skimage:
        try:
            from skimage.transform import iradon, radon
        except ImportError:
            return out
        th = np.degrees(g.theta)
        out["skimage_radon_ms"], s2 = best(lambda: radon(mu, th, circle=False), 1)
        out["skimage_radon_ms"] *= 1e3
        out["skimage_iradon_ms"] = 1e3 * best(
            lambda: iradon(s2, th, circle=False, filter_name="ramp", output_size=n), 1)[0]
    return out


def pair_time(n: int, specimen: str, root: str) -> dict:
    from chunkdic.synth import synthetic as S
    from chunkdic.synth.ctpair import standard_field

    fld, _ = standard_field("band", (n, n, n))
    out = os.path.join(root, f"{specimen}{n}")
    c0, t0 = _cpu(), time.perf_counter()
    S.synthesize(out, n, specimen=specimen, field=fld, noise=0.02, overwrite=True)
    wall, cpu = time.perf_counter() - t0, _cpu() - c0
    shutil.rmtree(out, ignore_errors=True)
    return {"wall_s": wall, "cpu_s": cpu, "Mvox_per_s": 2 * n ** 3 / wall / 1e6,
            "Mvox_per_cpu_s": 2 * n ** 3 / cpu / 1e6}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 300])
    ap.add_argument("--specimens", nargs="+", default=["grains", "concrete"])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--dir", default=None)
    ap.add_argument("--skimage", action="store_true")
    a = ap.parse_args()
    for n in a.sizes:
        c = slice_costs(n, a.skimage)
        print(f"slice {n}^2: " + ", ".join(f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}"
                                           for k, v in c.items()), flush=True)
    root = a.dir or tempfile.mkdtemp(prefix="bench_ct_")
    from chunkdic.synth import synthetic as S

    S.synthesize(os.path.join(root, "warm"), 16, specimen="grains", overwrite=True)
    for n in a.sizes:
        for sp in a.specimens:
            runs = [pair_time(n, sp, root) for _ in range(a.repeat)]
            med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
            print(f"pair {sp} {n}^3 (band, noise 0.02, uint16): wall {med['wall_s']:.1f} s, "
                  f"cpu {med['cpu_s']:.1f} s, {med['Mvox_per_s']:.2f} Mvoxel/s wall, "
                  f"{med['Mvox_per_cpu_s']:.2f} Mvoxel/s per CPU s, peak RSS "
                  f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB", flush=True)
    if a.dir is None:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
