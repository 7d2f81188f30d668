"""The band and the slip at ℓ = 8: what a different penalty could gain.

Usage::

    python validation/scripts/bench_band_penalty.py capture --workdir DIR [--pairs PAIRDIR]
    python validation/scripts/bench_band_penalty.py evaluate --workdir DIR [--cases band-grains ...] [--json PATH]
    python validation/scripts/bench_band_penalty.py full --pairs PAIRDIR --cases band slip \
        --options '{"smoothing": 1.5, "roi": "2:98,2:98,2:98"}'
    python validation/scripts/bench_band_penalty.py noise-free --workdir DIR [--pairs PAIRDIR] [--json PATH]

``capture`` correlates the pairs of ``bench_vs_aldvc.py`` (100³, seed 1, the
``--workdir`` of that script: ``PAIRDIR/<case>-100-<specimen>-uint16-n0.02-s1``, with
``--offset N`` the ``--feature-offset N`` pairs, suffix ``-offN``) with the
defaults at ℓ = 8 up to the automatic length choice and stores what the choice sees:
the half stencil of ``M``, the field ``a``, ``b``, ``κ σ_r²``, the chosen length and
weight, the node axes (level 0) and the true field.

``evaluate`` then solves, on the client, the linearised regularised problem
``(M + λ R_w) x = M a + b`` (the first regularised Gauss–Newton step: within 1 % of the
engine's converged field, docs/engine.md) for variants of the curvature penalty
``R_w = Σ_terms w_t d_tᵀ d_t`` (``d_t`` the second and mixed differences of the
Tikhonov Hessian penalty of :mod:`chunkdic.solve.regularizer`, each component apart)
and scores ``x`` between the nodes on the voxels ``bench_vs_aldvc.py``'s table scores at
ℓ = 8 (13 … 85 along each axis: ≥ ℓ from the faces and inside al-dvc's node hull):

``base``
    ``w = 1``, the engine's length (the default engine, linearised).
``floor``
    The best trilinear field on chunkdic's node grid (least squares over the same voxels,
    per component; the band's and slip's fields are separable): no field on this grid
    scores lower.
``oracle``
    Knowing where the feature is: the ``z`` curvature terms (``zz``, ``zy``, ``zx``, or
    ``zz`` alone) within ``h`` voxels of the feature's plane set to ``w = 0``, the weight
    ``λ`` elsewhere ``m`` times the engine's; the best over ``h ∈ {6, 10, 14}``,
    ``m ∈ {16, 64, 256}``: the most any spatially weighted curvature penalty of this form
    could give.
``irls-k``
    Data-driven, one reweighting (iteratively reweighted least squares, a hard-threshold
    robust penalty): from the base field, each term whose difference exceeds ``k`` robust
    standard deviations (1.4826 × the median absolute difference of its kind and component)
    gets ``w = 0``, then the length is chosen again by the engine's rule (Morozov's
    discrepancy, the same bisection over ``ℓ · 2^(k/2)``; at 13³ nodes the engine's one
    region is the whole mesh) with the weighted penalty.
``irls-k-x2``
    The same reweighted once more from the ``irls-k`` field.

``noise-free`` renders the band, the slip and the translation again without noise (same
seed and texture; ``shift``: the reference Fourier-shifted) and runs the whole engine on them
(and on the noisy pairs of ``--pairs`` beside them): the defaults, no penalty, the plain
penalty at its best fixed length: how much of the error at ℓ = 8 the noise makes at all.

``full`` runs the whole engine at ℓ = 8 with other settings (``--options``, keywords of
:func:`chunkdic.correlate`) on the same pairs and scores it the same way. A setting that
changes the ROI's margin (the low-pass width does) moves the node grid: hold the default
ROI (``"roi": "2:98,2:98,2:98"`` at 100³, ℓ = 8) to compare like with like.

Scans and results stay in ``--workdir``; nothing is written into the pair directories.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # validation/scripts/_capture.py, next to this file

CASES = ("band", "slip", "wave32", "wave48", "noise")
SPECIMENS = ("grains", "concrete")
ELL = 8
#: the voxels scored at ℓ = 8 on 100³: ≥ ℓ from the faces and inside al-dvc's node hull
SCORED = (13, 85)


def capture(args) -> None:
    import chunkdic
    from _capture import capture_choice

    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    for case in args.cases:
        for specimen in SPECIMENS:
            tag = f"-off{args.offset:g}" if args.offset else ""
            pair = Path(args.pairs) / f"{case}-100-{specimen}-uint16-n0.02-s1{tag}"
            out = work / f"{case}-{specimen}{tag}.npz"
            if out.exists():
                continue

            def save(problem, penalty, pair=pair, out=out):
                np.savez(out, **problem, length=penalty.length, weight=penalty.weight,
                         field=(pair / "field.json").read_text())

            seconds = capture_choice(lambda pair=pair: chunkdic.correlate(str(pair / "ref.zarr"), str(pair / "def.zarr"),
                                                                           element_size=ELL),
                                     save, engine_choice=True)  # the engine's own length beside the problem
            print(f"{case} {specimen}: " + ("no choice made" if seconds is None else f"captured in {seconds:.1f} s"),
                  flush=True)


def sparse_matrix(H: np.ndarray):
    """``M`` (3 N × 3 N, CSR, unknowns ordered (node, component)) from the half stencil ``H``."""
    import scipy.sparse as sp

    nz, ny, nx = H.shape[:3]
    idx = np.arange(nz * ny * nx).reshape(nz, ny, nx)
    rows, cols, vals = [], [], []
    for h in range(14):
        k = h + 13
        off = (k // 9 - 1, (k // 3) % 3 - 1, k % 3 - 1)
        src = tuple(slice(max(0, -d), n - max(0, d)) for d, n in zip(off, (nz, ny, nx)))
        dst = tuple(slice(max(0, d), n - max(0, -d)) for d, n in zip(off, (nz, ny, nx)))
        n1, n2, S = idx[src].ravel(), idx[dst].ravel(), H[src + (h,)].reshape(-1, 3, 3)
        for i in range(3):
            for j in range(3):
                rows.append(3 * n1 + i), cols.append(3 * n2 + j), vals.append(S[:, i, j])
                if h:  # the transposed entry of the neighbour
                    rows.append(3 * n2 + j), cols.append(3 * n1 + i), vals.append(S[:, i, j])
    N = 3 * nz * ny * nx
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(N, N))


def hessian_terms(shape):
    """The scalar rows ``d_t`` of the Tikhonov penalty (``Σ_t d_tᵀ d_t`` = second differences
    along every grid line + 2 × the mixed differences of every 2×2 square), their kinds
    (0–2: ``zz``, ``yy``, ``xx``; 3–5: ``zy``, ``zx``, ``yx``) and centres (node units)."""
    import scipy.sparse as sp

    idx = np.arange(int(np.prod(shape))).reshape(shape)
    R, C, V, kinds, centres, r = [], [], [], [], [], 0

    def part(ax, lo, n):
        s = [slice(None)] * 3
        s[ax] = slice(lo, shape[ax] - n + lo)
        return s

    for ax in range(3):
        i0, i1, i2 = (idx[tuple(part(ax, lo, 2))].ravel() for lo in (0, 1, 2))
        rr = r + np.arange(i0.size)
        R += [rr] * 3
        C += [i0, i1, i2]
        V += [np.ones(i0.size), -2.0 * np.ones(i0.size), np.ones(i0.size)]
        kinds.append(np.full(i0.size, ax))
        centres.append(np.stack(np.unravel_index(i1, shape), 1).astype(float))
        r += i0.size
    for kind, (p, q) in enumerate(((0, 1), (0, 2), (1, 2)), start=3):
        def corner(dp, dq, p=p, q=q):
            s = [slice(None)] * 3
            s[p], s[q] = slice(dp, shape[p] - 1 + dp), slice(dq, shape[q] - 1 + dq)
            return idx[tuple(s)].ravel()

        i00, i10, i01, i11 = corner(0, 0), corner(1, 0), corner(0, 1), corner(1, 1)
        rr = r + np.arange(i00.size)
        s2 = np.sqrt(2.0) * np.ones(i00.size)
        R += [rr] * 4
        C += [i00, i10, i01, i11]
        V += [s2, -s2, -s2, s2]
        kinds.append(np.full(i00.size, kind))
        c = np.stack(np.unravel_index(i00, shape), 1).astype(float)
        c[:, p] += 0.5
        c[:, q] += 0.5
        centres.append(c)
        r += i00.size
    D = sp.csr_matrix((np.concatenate(V), (np.concatenate(R), np.concatenate(C))), shape=(r, idx.size))
    return D, np.concatenate(kinds), np.concatenate(centres)


class Captured:
    """One captured case: the linearised problem, the weighted penalty and the scoring."""

    def __init__(self, path: Path):
        from chunkdic.solve.regularizer import Regularizer, plane_wave_weight
        from chunkdic.solve.stencil import stencil_matvec
        from chunkdic.synth.fields import Field, true_displacement

        importlib.import_module("chunkdic.synth.shear")  # registers the wave and slip fields
        d = np.load(path)
        self.name = path.stem
        self.H, self.a, self.b = d["half"], d["a"], d["b"]
        self.ell, self.scale = float(d["ell"]), float(d["scale"])
        self.length, self.weight, self.noise_variance = float(d["length"]), float(d["weight"]), float(d["noise_variance"])
        self.axes = [d["az"], d["ay"], d["ax"]]
        self.field = Field.from_json(json.loads(str(d["field"]))["field"])
        self.shape = self.H.shape[:3]
        self.M = sparse_matrix(self.H)
        self.D, self.kinds, self.centres = hessian_terms(self.shape)
        self.rhs = self.M @ self.a.reshape(-1) + self.b.reshape(-1)
        self.unit = plane_wave_weight(Regularizer("tikhonov", self.shape, self.ell),
                                      lambda v: stencil_matvec(self.H, v), 1.0)
        p = np.arange(SCORED[0], SCORED[1] + 1, dtype=float)
        self.positions = [p] * 3
        self.truth = true_displacement(self.field, p[:, None, None], p[None, :, None], p[None, None, :])

    def penalty(self, w=None):
        """``R_w`` (3 N × 3 N); ``w`` (terms, 3) per term and component, None: the engine's ``R``."""
        import scipy.sparse as sp

        if w is None:
            return sp.kron(self.D.T @ self.D, sp.eye(3), format="csr")
        out = None
        for c in range(3):
            pick = sp.csr_matrix(([1.0], ([c], [c])), shape=(3, 3))
            t = sp.kron(self.D.T @ sp.diags(w[:, c]) @ self.D, pick, format="csr")
            out = t if out is None else out + t
        return out

    def solve(self, lam: float, R) -> np.ndarray:
        import scipy.sparse.linalg as spl

        return spl.spsolve((self.M + lam * R).tocsc(), self.rhs).reshape(self.shape + (3,))

    def score(self, x: np.ndarray) -> float:
        """RMS vector error between the nodes on the scored voxels (σ pooled for the translation)."""
        from chunkdic.analysis.scoring import _grid_interpolate

        v = _grid_interpolate(self.axes, np.moveaxis(x, -1, 0) * self.scale, self.positions)
        e = (v - self.truth).reshape(3, -1)
        if self.name.startswith("noise"):
            return float(np.sqrt(np.mean(np.var(e, axis=1))))
        return float(np.sqrt(np.mean(np.sum(e**2, axis=0))))

    def discrepancy(self, R) -> tuple[float, np.ndarray]:
        """The engine's rule with penalty ``R``: the longest ``ℓ · 2^(k/2)`` whose misfit increase
        stays within ``κ σ_r² N`` (bisection as in :func:`chunkdic.solve.regchoice.choose_length`)."""
        from chunkdic.solve.regchoice import CANDIDATES, _longest_within

        lengths = np.array([k * self.ell for k in CANDIDATES])
        a, b = self.a.reshape(-1), self.b.reshape(-1)
        budget, cache = self.noise_variance * a.size, {}

        def misfit(i):
            if i not in cache:
                x = self.solve(self.unit * lengths[i] ** 4, R)
                d = x.reshape(-1) - a
                cache[i] = (float(-2.0 * b @ d + d @ (self.M @ d)), x)
            return cache[i][0]

        base = misfit(0)
        i = _longest_within(lambda i: misfit(i) - base <= budget, len(lengths), len(lengths) // 2)
        return float(lengths[i] * self.scale), cache[i][1]

    def robust_weights(self, x: np.ndarray, k: float) -> np.ndarray:
        """``w = 0`` for the terms beyond ``k`` robust σ of their kind and component, 1 elsewhere."""
        t = self.D @ x.reshape(-1, 3)
        w = np.ones_like(t)
        for c in range(3):
            for kind in range(6):
                sel = self.kinds == kind
                s = 1.4826 * np.median(np.abs(t[sel, c])) + 1e-30
                w[sel, c] = np.where(np.abs(t[sel, c]) > k * s, 0.0, 1.0)
        return w

    def floor(self) -> float | None:
        """Least-squares trilinear fit on the node grid over the scored voxels (separable fields: per
        component, a 1-D fit along z of the profile, times the component's exact linear factor)."""
        z = self.positions[0]
        az = self.axes[0]
        k = np.clip(np.searchsorted(az, z, side="right") - 1, 0, az.size - 2)
        w = (z - az[k]) / (az[k + 1] - az[k])
        B = np.zeros((z.size, az.size))
        B[np.arange(z.size), k], B[np.arange(z.size), k + 1] = 1 - w, w
        err2 = 0.0
        for c in range(3):
            t = self.truth[c]
            if c == 0 or self.field.kind != "band":  # functions of z alone (uz of the band, ux of the slip)
                prof = t[:, 0, 0]
                coef = np.linalg.lstsq(B, prof, rcond=None)[0]
                err2 += np.mean((B @ coef - prof) ** 2)
            else:  # the band's lateral components: p(z) times (y - c) or (x - c)
                lin = (self.positions[c] - (self.field.center_y if c == 1 else self.field.center_x))
                j = int(np.argmax(np.abs(lin)))
                prof = (t[:, j, 0] if c == 1 else t[:, 0, j]) / lin[j]
                coef = np.linalg.lstsq(B, prof, rcond=None)[0]
                err2 += np.mean((B @ coef - prof) ** 2) * np.mean(lin**2)
        return float(np.sqrt(err2))

    def oracle(self) -> tuple[float, dict]:
        """The best weighted penalty knowing the feature's plane (see the module docstring)."""
        plane = getattr(self.field, "center_z", getattr(self.field, "center", None))
        z = self.centres[:, 0] * self.ell * self.scale + self.axes[0][0]
        best = (np.inf, {})
        for h in (6, 10, 14):
            for m in (16, 64, 256):
                for kinds in ((0, 3, 4), (0,)):
                    w = np.ones((self.D.shape[0], 3))
                    w[(np.abs(z - plane) < h) & np.isin(self.kinds, kinds)] = 0.0
                    s = self.score(self.solve(m * self.weight, self.penalty(w)))
                    if s < best[0]:
                        best = (s, {"h": h, "m": m, "kinds": list(kinds)})
        return best


def evaluate_one(path: Path, variants) -> dict:
    c = Captured(path)
    R = c.penalty()
    row = {"case": c.name, "engine_length": c.length * c.scale}
    length, x0 = c.discrepancy(R)
    row["base"], row["base_length"] = c.score(x0), length
    if c.field is not None and c.field.kind in ("band", "slip"):
        row["floor"] = c.floor()
        if "oracle" in variants:
            row["oracle"], row["oracle_setting"] = c.oracle()
    for k in (4.0, 6.0):
        if f"irls-{k:g}" not in variants:
            continue
        length, x1 = c.discrepancy(c.penalty(c.robust_weights(x0, k)))
        row[f"irls-{k:g}"], row[f"irls-{k:g}_length"] = c.score(x1), length
        length, x2 = c.discrepancy(c.penalty(c.robust_weights(x1, k)))
        row[f"irls-{k:g}-x2"], row[f"irls-{k:g}-x2_length"] = c.score(x2), length
    return row


def evaluate(args) -> None:
    rows = []
    names = args.cases or sorted(p.stem for p in Path(args.workdir).glob("*.npz"))
    for name in names:
        row = evaluate_one(Path(args.workdir) / f"{name}.npz", args.variants)
        rows.append(row)
        print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}), flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1))


def _score_result(res, case: str, fld) -> float:
    """RMS vector error of ``res`` between its nodes on the scored voxels (σ pooled for a translation)."""
    from chunkdic.analysis.scoring import _grid_interpolate
    from chunkdic.mesh import level0_position
    from chunkdic.synth.fields import true_displacement

    p = np.arange(SCORED[0], SCORED[1] + 1, dtype=float)
    scale = 2.0**res.level
    axes = [level0_position(np.unique(a), scale) for a in res.node_coords.reshape(3, -1)]
    v = _grid_interpolate(axes, res.displacement * scale, [p] * 3)
    e = (v - true_displacement(fld, p[:, None, None], p[None, :, None], p[None, None, :])).reshape(3, -1)
    if case in ("noise", "shift"):
        return float(np.sqrt(np.mean(np.var(e, axis=1))))
    return float(np.sqrt(np.mean(np.sum(e**2, axis=0))))


def full(args) -> None:
    import chunkdic
    from chunkdic.mesh import level0_position
    from chunkdic.synth.fields import Field

    importlib.import_module("chunkdic.synth.shear")
    options = json.loads(args.options)
    for case in args.cases:
        for specimen in SPECIMENS:
            pair = Path(args.pairs) / f"{case}-100-{specimen}-uint16-n0.02-s1"
            fld = Field.from_json(json.loads((pair / "field.json").read_text())["field"])
            res = chunkdic.correlate(str(pair / "ref.zarr"), str(pair / "def.zarr"), element_size=ELL, **options)
            length = (res.info.get("regularization") or {}).get("length")
            print(json.dumps({"case": case, "specimen": specimen, "options": options,
                              "error": round(_score_result(res, case, fld), 4), "status": res.info.get("status"),
                              "length": length,
                              "first_node": float(level0_position(res.node_coords[0].min(), 2.0**res.level))}),
                  flush=True)


#: the settings compared without noise: the defaults, the C8 fit alone, and the plain penalty at
#: the best of these fixed lengths (voxels; band and slip only)
NOISE_FREE_SETTINGS = {"defaults": {}, "unregularised": {"regularization": "none"}, "best plain length": None}
FIXED_LENGTHS = (11.3, 16.0, 22.6, 32.0, 45.3, 64.0)
#: the translations' fixed length (an automatic one runs to 32 ℓ on a translation): the star's at ℓ = 8
TRANSLATION_LENGTH = 16.0


def noise_free(args) -> None:
    """The 100³ pairs rendered again without noise (same seed, same texture), at ℓ = 8: what
    the C8 fit and the penalty cost when no noise is left (band, slip: the defaults, no
    penalty, the plain penalty at the best of :data:`FIXED_LENGTHS`), and what the rendering alone costs a
    translation (``noise``: the deformed scan rendered from the moved geometry; ``shift``: the
    reference Fourier-shifted, the engine's own interpolation error). With ``--pairs`` the
    noisy pair of each case (``shift``: none) runs with the same settings beside it."""
    import types

    import chunkdic
    from bench_vs_aldvc import build_case

    work = Path(args.workdir)
    opts = types.SimpleNamespace(seed=1, dtype="uint16", noise=0.0, band_lateral=None, feature_offset=0.0)
    noisy = {r["case"]: r for r in json.loads(Path(args.noisy_record).read_text())["results"]
             if r.get("ell") == ELL} if args.noisy_record else {}
    rows = []
    for case in args.cases:
        for specimen in SPECIMENS:
            c = build_case(case, 100, specimen, work, opts)
            pairs = {"noise-free": (c.reference, c.deformed)}
            noisy_pair = Path(args.pairs or "") / f"{case}-100-{specimen}-uint16-n0.02-s1"
            if args.pairs and noisy_pair.is_dir():
                pairs["noise 0.02"] = (str(noisy_pair / "ref.zarr"), str(noisy_pair / "def.zarr"))
            ref = noisy.get(f"{case}/{specimen}") if case in ("band", "slip") else None
            peer = ref["al-dvc"]["rms_common"] if ref else None  # al-dvc's error with noise
            for name, setting in NOISE_FREE_SETTINGS.items():
                if setting is None and case not in ("band", "slip"):
                    continue
                candidates = ([dict(setting)] if setting is not None
                              else [{"regularization_length": L} for L in FIXED_LENGTHS])
                if case in ("noise", "shift") and name == "defaults":
                    candidates = [{"regularization_length": TRANSLATION_LENGTH}]
                errors = {}
                for label, (r, d) in pairs.items():
                    scored = []
                    for options in candidates:
                        res = chunkdic.correlate(r, d, element_size=ELL, **options)
                        scored.append((_score_result(res, case, c.field), options, res))
                    err, options, res = min(scored, key=lambda t: t[0])
                    errors[label] = err
                    rows.append({"case": case, "specimen": specimen, "setting": name, "options": options,
                                 "pair": label, "error": err, "status": res.info.get("status"),
                                 "length": (res.info.get("regularization") or {}).get("length"),
                                 "aldvc_noisy": peer})
                print(f"{case:6s} {specimen:9s} {name:18s} "
                      + "  ".join(f"{k} {v:.4f}" + (f" ({v / peer:.2f} of al-dvc's)" if peer else "")
                                  for k, v in errors.items()), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"argv": sys.argv[1:], "rows": rows}, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    c = sub.add_parser("capture")
    c.add_argument("--workdir", required=True)
    c.add_argument("--pairs", required=True, help="bench_vs_aldvc.py's workdir holding the 100^3 seed-1 pairs")
    c.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    c.add_argument("--offset", type=float, default=0.0,
                   help="the pairs of bench_vs_aldvc.py --feature-offset (directory suffix -offN)")
    e = sub.add_parser("evaluate")
    e.add_argument("--workdir", required=True)
    e.add_argument("--cases", nargs="+", default=None, help="e.g. band-grains slip-concrete (default: all captured)")
    e.add_argument("--variants", nargs="+", default=["oracle", "irls-4", "irls-6"],
                   choices=["oracle", "irls-4", "irls-6"])
    e.add_argument("--json", default=None)
    f = sub.add_parser("full")
    f.add_argument("--pairs", required=True)
    f.add_argument("--cases", nargs="+", default=["band", "slip"], choices=CASES)
    f.add_argument("--options", default="{}", help="JSON keywords of chunkdic.correlate")
    n = sub.add_parser("noise-free")
    n.add_argument("--workdir", required=True, help="where the noise-free pairs are rendered (kept)")
    n.add_argument("--pairs", default=None, help="bench_vs_aldvc.py's workdir of the noisy pairs (optional)")
    n.add_argument("--cases", nargs="+", default=["band", "slip", "noise", "shift"],
                   choices=["band", "slip", "noise", "shift"])
    n.add_argument("--noisy-record", default=str(Path(__file__).resolve().parent / "records"
                                                  / "bench_vs_aldvc_100_session30.json"),
                   help="bench_vs_aldvc.py record of the noisy pairs (al-dvc's errors for the ratios)")
    n.add_argument("--json", default=None)
    args = ap.parse_args()
    {"capture": capture, "evaluate": evaluate, "full": full, "noise-free": noise_free}[args.command](args)


if __name__ == "__main__":
    main()
