"""Where the per-node uncertainty estimate holds and where it cannot.

For each case (``fourier-shift``: the paper's section 4.2 test, both scans share their
noise; ``shift``: the same translation with independent noise in each scan) and element
size, on a small CT-like pair (:func:`chunkdic.synth.synthetic.standard_case`, grains):

- ``measured``: σ of chunkdic's field (unregularised), pooled over components, at nodes
  at least ℓ from the faces (:func:`chunkdic.score_displacement`);
- ``predicted``: the same pooled over ``Result.uncertainty`` (``κ σ_r² M⁻¹``);
- ``linearised``: σ of ``δa = M⁻¹ b*`` on chunkdic's own node grid, ``b* = Σ N_a ∇f r*``
  with ``r* = f̃ - g̃(x + u_true)`` the residual at the *true* displacement (low-pass σ = 1,
  cubic B-spline, centred differences: the engine's defaults), assembled densely with
  scipy. When it equals ``measured`` the error is the linear image of ``r*``;
- ``eff / model``: ``mean(b*² / M_aa)`` (the variance per unit of ``M`` that the error
  actually comes from) against the model's ``κ σ_r²``.

Whole volumes in memory: an analysis for small pairs (≤ 100³), not a pipeline.

Usage::

    python validation/scripts/uncertainty_anatomy.py --size 80 --element-sizes 16 12 8
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
import scipy.sparse.linalg as spl

import chunkdic
from chunkdic.analysis.scoring import scored_region
from chunkdic.synth import synthetic


def load(path) -> np.ndarray:
    """Level 0 of a scan, float64 (small pairs only)."""
    return np.asarray(chunkdic.open_scan(path).level(0)[...], dtype=np.float64)


def trilinear_operator(axes) -> sp.csr_matrix:
    """``Φ`` (voxels × nodes): trilinear shape functions of the node grid ``axes`` (3 arrays of
    node positions, uniform spacing) at every voxel centre between the first and last node."""
    per_axis = []
    for pos in axes:
        vox = np.arange(int(np.ceil(pos[0])), int(np.floor(pos[-1])) + 1)
        t = (vox - pos[0]) / (pos[1] - pos[0])
        e = np.clip(np.floor(t).astype(int), 0, len(pos) - 2)
        xi = t - e
        rows = np.concatenate([np.arange(len(vox))] * 2)
        per_axis.append(sp.csr_matrix((np.concatenate([1 - xi, xi]), (rows, np.concatenate([e, e + 1]))),
                                      shape=(len(vox), len(pos))))
    return sp.kron(sp.kron(per_axis[0], per_axis[1]), per_axis[2]).tocsr()


def linearised(f, g, u_true, axes, smoothing=1.0):
    """``(σ of M⁻¹ b*, mean(b*²/M_aa))`` on the node grid ``axes`` (see module docstring)."""
    fp = ndi.gaussian_filter(f, smoothing, mode="mirror", truncate=4.0)
    gp = ndi.gaussian_filter(g, smoothing, mode="mirror", truncate=4.0)
    coords = np.indices(f.shape, dtype=np.float64) + np.asarray(u_true, dtype=np.float64)[:, None, None, None]
    r = fp - ndi.map_coordinates(gp, coords, order=3, mode="mirror")
    box = tuple(slice(int(np.ceil(a[0])), int(np.floor(a[-1])) + 1) for a in axes)
    grads = [0.5 * (np.roll(fp, -1, k) - np.roll(fp, 1, k))[box].ravel() for k in range(3)]
    phi = trilinear_operator(axes)
    M = sp.bmat([[phi.T @ sp.diags(grads[i] * grads[j]) @ phi for j in range(3)] for i in range(3)]).tocsc()
    b = np.concatenate([phi.T @ (grads[i] * r[box].ravel()) for i in range(3)])
    da = spl.spsolve(M, b).reshape((3,) + tuple(len(a) for a in axes))
    inner = (slice(None),) + (slice(1, -1),) * 3
    eff = float(np.mean((b.reshape(da.shape)[inner] ** 2) / M.diagonal().reshape(da.shape)[inner]))
    return da, eff


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=80)
    ap.add_argument("--element-sizes", type=int, nargs="+", default=[16, 12, 8])
    ap.add_argument("--cases", nargs="+", default=["fourier-shift", "shift"])
    args = ap.parse_args(argv)
    n = args.size
    print(f"{'case':14} {'ell':>3} {'measured':>9} {'predicted':>9} {'linearised':>10} "
          f"{'pred/meas':>9} {'eff':>10} {'model':>10}")
    with tempfile.TemporaryDirectory() as tmp:
        for case in args.cases:
            pair = synthetic.standard_case(Path(tmp) / case, case, n, specimen="grains", noise=0.02)
            f, g = load(pair["reference"]), load(pair["deformed"])
            for ell in args.element_sizes:
                res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=ell,
                                         regularization="none")
                c = res.node_coords
                truth = pair["field"].displacement(*c)
                score = chunkdic.score_displacement(c, res.displacement, truth, (n,) * 3, ell)
                keep = scored_region(c, (n,) * 3, ell)
                predicted = float(np.sqrt(np.mean(res.uncertainty.reshape(3, -1)[:, keep] ** 2)))
                axes = (c[0][:, 0, 0], c[1][0, :, 0], c[2][0, 0, :])
                u_true = truth.reshape(3, -1).mean(axis=1)  # a uniform translation in both cases
                da, eff = linearised(f, g, u_true, axes, res.info["settings"]["smoothing"])
                lin = float(np.sqrt(np.mean([da[k].reshape(-1)[keep.reshape(-1)].var() for k in range(3)])))
                noise = res.info["noise"]
                model = noise["kappa"] * noise["sigma_r"] ** 2
                print(f"{case:14} {ell:3d} {score.sigma:9.5f} {predicted:9.5f} {lin:10.5f} "
                      f"{predicted / score.sigma:9.2f} {eff:10.4g} {model:10.4g}", flush=True)


if __name__ == "__main__":
    main()
