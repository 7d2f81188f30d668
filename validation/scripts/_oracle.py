"""The oracle of the regularisation length: every candidate length's field, for benchmarks.

``bench_vs_aldvc.py --oracle`` compares the engine's automatic length with the best fixed
one. A fixed length per candidate would cost a whole correlation each (11 per case and
element size); instead the child that runs the defaults also keeps the linearised problem
the engine's length choice sees (:func:`_capture.linearised_problem`, taken when the
choice starts, the run then continuing as usual), and after the run solves
``(M + λ(L) R) x = M a + b`` on the whole mesh for every candidate ``L = ℓ · 2^(k/2)``,
``k = 0 … 10`` (the plain Tikhonov penalty, no reweighting: what ``--regularization-length
L`` runs): the first regularised Gauss–Newton step, within 1 % of the engine's converged
field on the 100³ cases of ``bench_vs_aldvc.py`` (docs/engine.md). The parent scores each
candidate's field as it scores the tool's own, and the least error is the oracle's;
``--oracle-full`` runs the whole engine at the oracle's length to check the linearisation.
The child also saves the problem (``…-problem.npz`` beside its result) for
``bench_length_texture.py``.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np


@contextmanager
def keep_choice_problem():
    """While the block runs, every :func:`chunkdic.correlate` keeps the linearised problem
    of its first length choice in the yielded dict (key ``"problem"``); the run goes on."""
    from _capture import linearised_problem

    from chunkdic.method import level_solve

    original = level_solve.choose_regularization
    box: dict = {}

    def hook(op, state, p, penalty, settings, level, mesh, progress=None, **kw):
        if "problem" not in box:
            box["problem"] = linearised_problem(op, state, p, settings, level, mesh)
        return original(op, state, p, penalty, settings, level, mesh, progress, **kw)

    level_solve.choose_regularization = hook
    try:
        yield box
    finally:
        level_solve.choose_regularization = original


def candidate_fields(problem: dict) -> tuple[np.ndarray, np.ndarray]:
    """Every candidate length's linearised field.

    Returns
    -------
    lengths : ndarray, shape (K,), level-0 voxels
    fields : ndarray, shape (K, 3, nz, ny, nx), float64, level-0 voxels
    """
    from chunkdic.solve.cg import StencilSolver
    from chunkdic.solve.regchoice import CANDIDATES
    from chunkdic.solve.regularizer import Regularizer, plane_wave_unit
    from chunkdic.solve.stencil import stencil_matvec

    half, a, b = problem["half"], problem["a"], problem["b"]
    ell, scale, kind = float(problem["ell"]), float(problem["scale"]), str(problem["kind"])
    solver = StencilSolver(np.array(half, copy=True), rtol=1e-6)
    reg = Regularizer(kind, half.shape[:3], ell)
    unit = plane_wave_unit(reg, lambda v: stencil_matvec(solver.matrix, v))
    rhs = solver.data_matvec(a) + b
    lengths, fields = [], []
    for factor in CANDIDATES:
        length = factor * ell
        solver.regularize(reg, unit * length**reg.order)
        x = solver.solve(rhs.copy())[0]
        lengths.append(length * scale)
        fields.append(np.moveaxis(x, -1, 0) * scale)
    return np.array(lengths), np.stack(fields)
