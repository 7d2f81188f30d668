"""
On a local cluster, and on SLURM
================================

A ``LocalCluster`` of two worker processes on the loopback interface, its ``Client``
handed to :func:`chunkdic.correlate`. The tasks read their blocks from the Zarr stores
themselves; the client sends paths and nodal fields, never voxels. The result does not
depend on the scheduler beyond round-off. ``workflows/local_cluster.py`` and
``workflows/slurm.py`` (the same with dask-jobqueue) are the scripts to start from.
"""

# %%
import shutil
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from distributed import Client, LocalCluster

import chunkdic
from chunkdic.synth import synthetic

work = Path(tempfile.mkdtemp(prefix="chunkdic-gallery-"))
n, c = 48, 47 / 2
field = synthetic.Affine(matrix=((-0.01, 0.0, 0.0), (0.0, 0.003, 0.0), (0.0, 0.0, 0.003)), center=(c, c, c),
                         translation=(0.8, -0.4, 0.3))
synthetic.synthesize(work / "pair", (n, n, n), field=field, seed=2)
ref, deformed = work / "pair" / "ref.zarr", work / "pair" / "def.zarr"

# %%
# The same correlation on the embedded thread pool and on the cluster
embedded = chunkdic.correlate(ref, deformed, element_size=8, output=work / "embedded.zarr")
with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                  dashboard_address=None) as cluster, Client(cluster) as client:
    clustered = chunkdic.correlate(ref, deformed, element_size=8, output=work / "cluster.zarr", scheduler=client)

difference = np.abs(clustered.displacement - embedded.displacement).max()
print(f"largest difference between the two fields: {difference:.2e} voxel")

# %%
# The measured lateral displacement against the truth, on a mid-plane
truth = field.displacement(*clustered.node_coords)
fig, axes = plt.subplots(1, 2, figsize=(6.4, 3), layout="constrained", sharey=True)
for ax, data, title in zip(axes, (clustered.displacement[2][:, 3, :], truth[2][:, 3, :]), ("cluster", "truth")):
    im = ax.imshow(data, origin="lower", vmin=truth[2].min(), vmax=truth[2].max())
    ax.set(title=f"$U_x$, {title}", xlabel="x node")
axes[0].set_ylabel("z node")
fig.colorbar(im, ax=axes, label="voxels")
plt.show()

# %%
# On a SLURM cluster
# ------------------
# There the workers come from dask-jobqueue and the ``Client`` is made the same way. This is
# the batch script it submits for each job (nothing is submitted here: the cluster is only
# created to render it). ``workflows/slurm.py`` runs the whole recipe.
from dask_jobqueue import SLURMCluster

with SLURMCluster(cores=8, processes=1, memory="32GiB", walltime="04:00:00", account="proj",
                  scheduler_options={"host": "127.0.0.1", "dashboard_address": "127.0.0.1:0"}) as slurm:
    print(slurm.job_script())

# %%
# The scans and results were written to a temporary folder; remove it.
shutil.rmtree(work)
