"""Grid floors for the issue-20 records (the node grids do not depend on specimen or seed)."""
import json
import sys

import numpy as np

sys.path.insert(0, 'benchmarks')
import bench_vs_aldvc as b

from chunkdic.synth.fields import true_displacement


class A:
    band_lateral = None; seed = 1; dtype = "uint16"; noise = 0.02

n = 100
out = {}
for name in ["wave24", "wave32", "wave48", "wave64", "slip", "band", "comp10", "comp20", "rot10", "noise"]:
    case = b.build_case(name, n, "grains", __import__("pathlib").Path("/work/scratch/bench7/w100"), A)
    for ell in (8, 12, 16):
        d = f"/work/scratch/bench7/runs_seed1/{name}/grains-100-ell{ell}-r0"
        pc = np.load(d + "/chunkdic.npz")["points"]
        pa = np.load(d + "/aldvc/aldvc.npz")["coordinates"][:, ::-1].T.astype(float)
        f = case.field
        r = b.between_common({"chunkdic": (pc, true_displacement(f, *pc)), "al-dvc": (pa, true_displacement(f, *pa))}, case, ell)
        out[f"{name}/{ell}"] = {"chunkdic": r["chunkdic"]["floor_common"], "al-dvc": r["al-dvc"]["floor_common"],
                                "common_hull": r["chunkdic"]["common_hull"]}
        print(name, ell, round(out[f"{name}/{ell}"]["chunkdic"], 4), round(out[f"{name}/{ell}"]["al-dvc"], 4))
json.dump({"what": "grid floor per case/ell: the exact field at each tool's nodes, trilinear between them, RMS over the common voxels "
           "(>= ell from the faces, inside both node hulls); 100^3, the same node grids on grains and concrete and for every seed; "
           "computed with bench_vs_aldvc.between_common from the seed-1 runs' node positions",
           "floors": out}, open("benchmarks/records/bench_vs_aldvc_100_issue20_floors.json", "w"), indent=1)

# the best trilinear field on each grid (L2 fit over the same voxels) for the 1-D shear fields (Ux(z) only)
rec = json.load(open("benchmarks/records/bench_vs_aldvc_100_issue20_floors.json"))
for name in ["wave24", "wave32", "wave48", "wave64", "slip"]:
    case = b.build_case(name, n, "grains", __import__("pathlib").Path("/work/scratch/bench7/w100"), A)
    for ell in (8, 12, 16):
        lo, hi = rec["floors"][f"{name}/{ell}"]["common_hull"][0]
        z = np.arange(n, dtype=float)
        z = z[(z + 0.5 >= ell) & (n - 0.5 - z >= ell) & (z >= lo) & (z <= hi)]
        h = case.field._h(z)
        d = f"/work/scratch/bench7/runs_seed1/{name}/grains-100-ell{ell}-r0"
        best = {}
        for tool, ax in (("chunkdic", np.unique(np.load(d + "/chunkdic.npz")["points"][0].round(6))),
                         ("al-dvc", np.unique(np.load(d + "/aldvc/aldvc.npz")["coordinates"][:, 2].astype(float)))):
            M = np.zeros((z.size, ax.size))
            k = np.clip(np.searchsorted(ax, z, side="right") - 1, 0, ax.size - 2)
            w = (z - ax[k]) / (ax[k + 1] - ax[k])
            M[np.arange(z.size), k] = 1 - w
            M[np.arange(z.size), k + 1] = w
            coef, *_ = np.linalg.lstsq(M, h, rcond=None)
            best[tool] = float(np.sqrt(np.mean((M @ coef - h) ** 2)))
        rec["floors"][f"{name}/{ell}"]["l2_best"] = best
rec["what_l2_best"] = ("shear waves and slip (Ux(z) only): RMS of the best trilinear field on each tool's grid, "
                       "least squares over the same voxels: below it no tool on that grid can go")
json.dump(rec, open("benchmarks/records/bench_vs_aldvc_100_issue20_floors.json", "w"), indent=1)
