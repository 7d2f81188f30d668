"""
A loading series
================

Scans 0, 1 and 2 of one specimen under growing compression (−2 % per step, with a slow
rigid drift), correlated with :func:`chunkdic.series`: each scan against the previous one
(*incremental*) and against the first (*cumulative*, started from the previous cumulative
field composed with the new increment). ``workflows/loading_series.py`` is the same with
options for real scans.
"""

# %%
import shutil
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import chunkdic
from chunkdic.synth import foam, synthetic

work = Path(tempfile.mkdtemp(prefix="chunkdic-gallery-"))
n, c = 48, 47 / 2
fields = [synthetic.Affine(matrix=((e, 0.0, 0.0), (0.0, -0.3 * e, 0.0), (0.0, 0.0, -0.3 * e)), center=(c, c, c),
                           translation=(0.4 * k, -0.25 * k, 0.15 * k))
          for k, e in ((1, -0.02), (2, -0.04))]

# %%
# Scan 0 is the reference texture, scans 1 and 2 the same texture deformed by the known
# cumulative fields ``u_0→k``; each is written chunk by chunk.
scans = []
for k, field in enumerate([None, *fields]):
    lazy = foam.as_dask((n, n, n), chunks=64, field=field, seed=5,
                        which="reference" if field is None else "deformed", dtype="uint8")
    chunkdic.write_scan(work / f"scan{k}.zarr", lazy)
    scans.append(work / f"scan{k}.zarr")

# %%
# Correlate the series
# --------------------
s = chunkdic.series(scans, work / "series.zarr", element_size=8)
print(s.table())

# %%
# Cumulative fields against the truth
# -----------------------------------
# The cumulative result of step k is an ordinary result: nodes, displacement, strain.
errors = []
for k, field in enumerate(fields, start=1):
    res = s.cumulative[k]
    truth = field.displacement(*res.node_coords)
    errors.append(np.sqrt(((res.displacement - truth) ** 2).mean()))
    print(f"step {k}: mean eps_zz {res.strain_summary().eps_zz:+.4f} (true {-0.02 * k:+.4f}), "
          f"RMS error {errors[-1]:.4f} voxel")

fig, ax = plt.subplots(figsize=(5, 3.2), layout="constrained")
for k, field in enumerate(fields, start=1):
    res = s.cumulative[k]
    z = res.node_coords[0][:, 3, 3]
    ax.plot(z, field.displacement(*res.node_coords)[0][:, 3, 3], "k-", lw=0.8)
    ax.plot(z, res.displacement[0][:, 3, 3], "o", label=f"$u_{{0\\to{k}}}$")
ax.set(xlabel="z (voxels)", ylabel="$U_z$ (voxels)", title="Cumulative axial displacement (lines: truth)")
ax.legend()
plt.show()

# %%
# The scans and results were written to a temporary folder; remove it.
shutil.rmtree(work)
