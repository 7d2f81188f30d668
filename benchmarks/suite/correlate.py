"""``chunkdic.correlate`` on a 96³ pair with a known affine field, at ℓ = 16, 12 and 8."""

from __future__ import annotations

import numpy as np

from .common import ELLS, SIZE, affine_field, cache_dir, remove, workdir, write_pair


class Correlate:
    """The whole correlation with the defaults (embedded scheduler, CT defaults)."""

    params = (list(ELLS),)
    param_names = ["ell"]
    repeat = (1, 3, 60.0)
    number = 1
    timeout = 600

    def setup_cache(self):
        return write_pair(cache_dir("pair"))

    def setup(self, pair, ell):
        import chunkdic

        self.chunkdic = chunkdic
        self.out = workdir(f"correlate-{ell}")
        # the first call in a process loads (or compiles) the kernels: not part of the timing
        chunkdic.correlate(pair["ref"], pair["def"], element_size=16, output=self.out / "warm.zarr")
        self.runs = 0

    def teardown(self, pair, ell):
        remove(self.out)

    def _run(self, pair, ell):
        self.runs += 1
        return self.chunkdic.correlate(pair["ref"], pair["def"], element_size=ell,
                                       output=self.out / f"r{self.runs}.zarr")

    def time_correlate(self, pair, ell):
        self._run(pair, ell)

    def peakmem_correlate(self, pair, ell):
        self._run(pair, ell)

    def track_field_error(self, pair, ell):
        """RMS of the nodal error against the known field, voxels (pooled over z, y, x)."""
        res = self._run(pair, ell)
        truth = affine_field(pair["n"]).displacement(*res.node_coords)
        return float(np.sqrt(np.mean((res.displacement - truth) ** 2)))

    track_field_error.unit = "voxel"


class Solver:
    """Block-Jacobi CG on the M of a 96³ texture at ℓ = 8 (13³ nodes), plain and with the penalty."""

    params = ([False, True],)
    param_names = ["regularized"]
    repeat = (1, 5, 20.0)

    def setup(self, regularized):
        from chunkdic.kernels.m import m_block
        from chunkdic.solve.cg import StencilSolver, warmup
        from chunkdic.solve.regularizer import Regularizer
        from chunkdic.solve.stencil import half_stencil

        from .common import textured_volume

        warmup()
        f = textured_volume((SIZE + 2,) * 3)
        full = m_block(f, (1, 1, 1), (1, 1, 1), 8)[0]
        self.half = np.ascontiguousarray(half_stencil(full)).astype(np.float32)
        self.b = np.random.default_rng(1).standard_normal(self.half.shape[:3] + (3,))
        self.make = lambda: StencilSolver(self.half.copy())
        self.reg = Regularizer("tikhonov", self.half.shape[:3], 8) if regularized else None

    def time_solve(self, regularized):
        solver = self.make()
        if self.reg is not None:
            solver.regularize(self.reg, solver.scale)  # a penalty as strong as M's typical block
        solver.solve(self.b)
