"""The method on the dense passes equals the method on the out-of-core block passes.

The oracle of the machinery around the kernels (dask-image's test of its Dask filters
against SciPy's): the same 24³ pair correlated by :func:`chunkdic.correlate` (block tasks,
Zarr scratch stores and their 16-bit grids, the client's sums of block partials, a
checkpointed run's state) and by the method alone, :func:`chunkdic.method.level_solve.run_level`,
on :class:`chunkdic.passes.dense.DensePasses` (whole in-memory arrays, one call of the
kernels' NumPy twins per pass, no task, no store). Measured: the fields agree to 5e-15
voxel (the twins' round-off; 0 with the numba kernels), the dense run takes 0.4-1.5 s on a
loaded 2-core machine.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import chunkdic
from chunkdic.engine.meshes import plan_meshes
from chunkdic.method.level_solve import run_level
from chunkdic.method.runstate import RunState
from chunkdic.method.settings import Settings
from chunkdic.passes.dense import DensePasses
from chunkdic.passes.prefilter import face_margin
from chunkdic.synth import foam, synthetic

FIELDS = {
    "translation": synthetic.Translation((0.4, -0.3, 0.2)),
    "affine": synthetic.Affine(matrix=((-0.02, 0, 0.01), (0, 0.01, 0), (0, 0, 0)), center=(12, 12, 12),
                               translation=(0.6, -0.4, 0.3)),
}


def _pair(name: str):
    f = foam.render((24, 24, 24), seed=5)
    return f, foam.render((24, 24, 24), seed=5, field=FIELDS[name], which="deformed")


def _method_on_dense_passes(f, g, settings: Settings):
    """The whole method on one level (the correlated one) of in-memory scans."""
    meshes = plan_meshes(f.shape, element_size=settings.element_size, level=0, coarsest=0,
                         min_margin=face_margin(settings.smoothing))
    passes = DensePasses(f, g, meshes[0], settings)
    run, _ = run_level(passes, RunState(), None, meshes=meshes, levels=[0], settings=settings)
    return run, meshes[0]


@pytest.mark.parametrize("field,grey", [("translation", "drift"), ("affine", "drift"), ("affine", "element")])
def test_the_method_on_dense_passes_equals_it_on_block_passes(field, grey):
    f, g = _pair(field)
    settings = Settings(element_size=6, coarsest=0, grey=grey, grey_cell=0)
    run, mesh = _method_on_dense_passes(f, g, settings)
    res = chunkdic.correlate(f, g, settings)
    assert res.info["status"] == run.gn.status == "converged"
    np.testing.assert_array_equal(res.node_coords, mesh.node_coords())
    np.testing.assert_allclose(run.gn.u, res.displacement, rtol=0, atol=1e-10)
    assert run.gn.gap == pytest.approx(res.info["final_gap"], rel=1e-9)
    assert len(run.history.rows["gap"]) == len(res.history["gap"])
    # and the known field, to the method's accuracy on a noise-free texture
    truth = FIELDS[field].displacement(*mesh.node_coords())
    assert np.abs(run.gn.u - truth).max() < 0.02


def test_the_method_loads_neither_the_passes_nor_io():
    """The method's modules reach the voxels only through the passes' protocol: importing the
    whole method package loads no module of ``chunkdic.passes`` or ``chunkdic.io`` (the
    import-linter contract checks the imports; this, what loading them does)."""
    code = ("import sys, pkgutil, importlib, chunkdic.method as m\n"
            "for info in pkgutil.iter_modules(m.__path__): importlib.import_module('chunkdic.method.' + info.name)\n"
            "print(sorted(k for k in sys.modules if k.startswith(('chunkdic.passes', 'chunkdic.io'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
