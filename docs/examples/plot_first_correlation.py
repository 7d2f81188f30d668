"""
A first correlation
===================

Two small synthetic scans with a known affine field (−1 % along z, 0.5 % shear and a
translation), correlated on the embedded scheduler (threads in this process, no cluster),
then compared with the truth. ``workflows/laptop.py`` is the same workflow with options for
your own scans.
"""

# %%
# Write a synthetic pair
# ----------------------
# :func:`chunkdic.synth.synthetic.synthesize` writes a reference scan, a deformed scan
# and the field between them (``field.json``) into a folder. The deformed scan has no
# interpolation in it: it is rendered from the deformed texture directly.
import shutil
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import chunkdic
from chunkdic.synth import synthetic

work = Path(tempfile.mkdtemp(prefix="chunkdic-gallery-"))
n = 48
c = (n - 1) / 2
field = synthetic.Affine(matrix=((-0.01, 0.0, 0.005), (0.0, 0.0, 0.0), (0.005, 0.0, 0.0)),
                         center=(c, c, c), translation=(1.3, -0.7, 0.4))
synthetic.synthesize(work / "pair", (n, n, n), field=field, seed=1)

# %%
# Correlate
# ---------
# Element edge ℓ = 8 voxels; everything else is the default for CT scans (Gaussian
# low-pass σ = 1, brightness cells, curvature penalty with an automatic length).
res = chunkdic.correlate(work / "pair" / "ref.zarr", work / "pair" / "def.zarr", element_size=8,
                         output=work / "result.zarr")
print(res)
print("status:", res.info["status"], "| final gap:", f"{100 * res.info['final_gap']:.3f} %")

# %%
# Compare with the truth
# ----------------------
# ``res.node_coords`` are the nodes' positions (voxels of the correlated level, here level
# 0); the truth is evaluated there. Components are ordered (z, y, x).
truth = field.displacement(*res.node_coords)
error = res.displacement - truth
rms = np.sqrt((error**2).mean(axis=(1, 2, 3)))
print("RMS nodal error (Uz, Uy, Ux):", ", ".join(f"{v:.4f}" for v in rms), "voxel")
strain = res.strain_summary()
print(f"mean eps_zz {strain.eps_zz:+.5f} (true -0.01000)")

# %%
# A figure: Uz along z at the centre, measured and true
z = res.node_coords[0][:, 3, 3]
fig, ax = plt.subplots(figsize=(5, 3.2), layout="constrained")
ax.plot(z, truth[0][:, 3, 3], "k-", label="truth")
ax.plot(z, res.displacement[0][:, 3, 3], "o", label="chunkdic, ℓ = 8")
ax.set(xlabel="z (voxels)", ylabel="$U_z$ (voxels)", title="Axial displacement through the centre")
ax.legend()
plt.show()

# %%
# The scans and results were written to a temporary folder; remove it.
shutil.rmtree(work)
