"""
A whole specimen at level 2
===========================

From raw files to strain: two raw uint16 files (standing in for a beamline's output) are
ingested into Zarr scan groups, given a pyramid of 2×2×2 sums, and correlated on level 2,
where each voxel is the sum of 4³ (the paper's compression). ``workflows/whole_specimen.py``
is the same as a script for real files.
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
n, c = 128, 127 / 2
field = synthetic.Affine(matrix=((-0.02, 0.0, 0.0), (0.0, 0.006, 0.0), (0.0, 0.0, 0.006)), center=(c, c, c),
                         translation=(2.0, -1.0, 0.5))

# %%
# Two raw files, rendered from a foam whose cells are 16 voxels across (4 at level 2)
for which in ("reference", "deformed"):
    volume = foam.render((n, n, n), field=field, which=which, dtype="uint16", seed=7, cell_size=16.0,
                         bead_size=128.0)
    volume.astype("<u2").tofile(work / f"{which}.raw")

# %%
# Ingest, pyramid, correlate on level 2
# -------------------------------------
for name, which in (("ref", "reference"), ("def", "deformed")):
    chunkdic.ingest(work / f"{which}.raw", work / f"{name}.zarr", shape=(n, n, n), dtype="uint16",
                    voxel_size=5.0, unit="um")
    chunkdic.build_pyramid(work / f"{name}.zarr", 3)
res = chunkdic.correlate(work / "ref.zarr", work / "def.zarr", element_size=6, level=2, output=work / "whole.zarr")
print(res.info["status"], "| final gap", f"{100 * res.info['final_gap']:.2f} %")
strain = res.strain_summary()
print(f"mean strain: eps_zz {strain.eps_zz:+.4f} (true -0.0200)")

# %%
# The field is in voxels of level 2; ``info["scale"]`` (4) converts to level 0
f = res.info["scale"]
level0 = f * res.node_coords + (f - 1) / 2
truth = field.displacement(*level0) / f
z = level0[0][:, 2, 2]
fig, ax = plt.subplots(figsize=(5, 3.2), layout="constrained")
ax.plot(z, f * truth[0][:, 2, 2], "k-", label="truth")
ax.plot(z, f * res.displacement[0][:, 2, 2], "o", label="level 2, ℓ = 6 (24 level-0 voxels)")
ax.set(xlabel="z (level-0 voxels)", ylabel="$U_z$ (level-0 voxels)", title="Axial displacement, whole specimen")
ax.legend()
plt.show()

# %%
# The scans and results were written to a temporary folder; remove it.
shutil.rmtree(work)
