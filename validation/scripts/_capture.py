"""The engine's linearised problem at its regularisation-length choice, captured for benchmarks.

``bench_reg_criteria.py`` and ``bench_band_penalty.py`` study the choice of the
regularisation length on the client, away from the engine: both run
:func:`chunkdic.correlate` up to the point where the engine chooses the length (the finest
level converged to the coarse tolerance, unregularised on that level), keep what the
choice sees, and stop the run there. :func:`capture_choice` does that once for both: it
replaces the :func:`chunkdic.method.length.choose_regularization` that
:func:`chunkdic.method.level_solve.solve_level` calls for the length of one call (restored
whatever happens), hands :func:`linearised_problem` to the caller's ``save`` and ends the
correlation with :class:`ChoiceCaptured`.

With it, ``(M + λ R) x = M a + b`` (the first regularised Gauss–Newton step) is solved
for any length ``λ`` and penalty ``R`` without a scan in memory: ``M`` is the half
stencil, ``a`` the converged unregularised field, ``b`` the residual's right-hand side.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np


class ChoiceCaptured(Exception):
    """Raised by the capturing hook once the problem is saved: ends the correlation there."""


def linearised_problem(op, state, p, settings, level: int, mesh) -> dict[str, object]:
    """What the engine's length choice sees on ``level`` at ``state``.

    Parameters
    ----------
    op : chunkdic.method.operator.Operator
        The level's ``M``.
    state : chunkdic.method.stopping.State
    p : chunkdic.method.protocol.Pass
        The pass the choice linearises around.
    settings : chunkdic.method.settings.Settings
    level : int
    mesh : chunkdic.mesh.Mesh

    Returns
    -------
    dict
        ``half`` (nz, ny, nx, 14, 3, 3), the half stencil of ``M``; ``a`` (nz, ny, nx, 3), the
        field, voxels of the level; ``b`` (nz, ny, nx, 3); ``noise_variance`` = ``κ σ_r²``
        and ``kappa``; ``ell`` (element edge, level voxels); ``scale`` (``2^s``); ``kind``
        (the regularisation); ``az``, ``ay``, ``ax``, the node axes in level-0 voxels.
    """
    scale = 2.0**level
    axes = [scale * x + (scale - 1) / 2 for x in mesh.node_axes()]  # level s -> level 0 (DESIGN.md)
    return {"half": op.solver.matrix, "a": np.moveaxis(state.u, 0, -1).copy(), "b": p.b,
            "noise_variance": p.kappa * p.noise_variance, "kappa": p.kappa, "ell": mesh.element_size,
            "scale": scale, "kind": settings.regularization, "az": axes[0], "ay": axes[1], "ax": axes[2]}


def capture_choice(run: Callable[[], object], save: Callable[[dict, object], None], *,
                   engine_choice: bool = False) -> float | None:
    """Run ``run()`` (a :func:`chunkdic.correlate` call) up to the engine's length choice,
    call ``save(problem, penalty)`` there and stop the run.

    Parameters
    ----------
    run : callable
        Starts the correlation.
    save : callable
        ``save(problem, penalty)``: ``problem`` from :func:`linearised_problem`, taken before
        any choice; ``penalty`` the :class:`chunkdic.method.length.Penalty` the solver holds
        (the engine's choice with ``engine_choice``).
    engine_choice : bool, keyword-only
        Let the engine make its own choice before ``save`` (to record it beside the problem).

    Returns
    -------
    float or None
        Seconds until the capture; None when the run ended without a choice (not
        converged before it, or no regularisation).
    """
    from chunkdic.method import level_solve

    original = level_solve.choose_regularization

    def hook(op, state, p, penalty, settings, level, mesh, progress=None, **kw):
        problem = linearised_problem(op, state, p, settings, level, mesh)
        if engine_choice:
            _, penalty = original(op, state, p, penalty, settings, level, mesh, progress, **kw)
        save(problem, penalty)
        raise ChoiceCaptured

    level_solve.choose_regularization = hook
    t0 = time.perf_counter()
    try:
        run()
    except ChoiceCaptured:
        return time.perf_counter() - t0
    finally:
        level_solve.choose_regularization = original
    return None
