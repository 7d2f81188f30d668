"""The engine's linearised problem at its regularisation-length choice, captured for benchmarks.

``bench_reg_criteria.py`` and ``bench_band_penalty.py`` study the choice of the
regularisation length on the client, away from the engine: both run
:func:`chunkdic.correlate` up to the point where the engine chooses the length (the finest
level converged to the coarse tolerance, unregularised on that level), keep what the
choice sees, and stop the run there. :func:`capture_choice` does that once for both: it
replaces :func:`chunkdic.method.length.choose_regularization` for the length of one call
(restored whatever happens), hands :func:`linearised_problem` to the caller's ``save``
and ends the correlation with :class:`ChoiceCaptured`.

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


def linearised_problem(lvl, state) -> dict[str, object]:
    """What the engine's length choice sees on level ``lvl`` at ``state``.

    Parameters
    ----------
    lvl : chunkdic.passes.level.Level
    state : chunkdic.method.gauss_newton.State

    Returns
    -------
    dict
        ``half`` (nz, ny, nx, 14, 3, 3), the half stencil of ``M``; ``a`` (nz, ny, nx, 3), the
        field, voxels of the level; ``b`` (nz, ny, nx, 3); ``noise_variance`` = ``κ σ_r²``
        and ``kappa``; ``ell`` (element edge, level voxels); ``scale`` (``2^s``); ``kind``
        (the regularisation); ``az``, ``ay``, ``ax``, the node axes in level-0 voxels.
    """
    from chunkdic.engine.checkpoint import resumed_pass

    p = resumed_pass(lvl, state)  # the pass the engine's own choice uses
    scale = 2.0**lvl.s
    axes = [scale * x + (scale - 1) / 2 for x in lvl.mesh.node_axes()]  # level s -> level 0 (DESIGN.md)
    return {"half": lvl.solver.matrix, "a": np.moveaxis(state.u, 0, -1).copy(), "b": p.b,
            "noise_variance": p.kappa * p.noise_variance, "kappa": p.kappa, "ell": lvl.mesh.element_size,
            "scale": scale, "kind": lvl.settings.regularization, "az": axes[0], "ay": axes[1], "ax": axes[2]}


def capture_choice(run: Callable[[], object], save: Callable[[dict, object], None], *,
                   engine_choice: bool = False) -> float | None:
    """Run ``run()`` (a :func:`chunkdic.correlate` call) up to the engine's length choice,
    call ``save(problem, lvl)`` there and stop the run.

    Parameters
    ----------
    run : callable
        Starts the correlation.
    save : callable
        ``save(problem, lvl)``: ``problem`` from :func:`linearised_problem`, taken before
        any choice; ``lvl`` the level (its ``regularization_length`` / ``_weight`` hold the
        engine's choice with ``engine_choice``).
    engine_choice : bool, keyword-only
        Let the engine make its own choice before ``save`` (to record it beside the problem).

    Returns
    -------
    float or None
        Seconds until the capture; None when the run ended without a choice (not
        converged before it, or no regularisation).
    """
    from chunkdic.method import length as steps

    original = steps.choose_regularization

    def hook(lvl, state, progress):
        problem = linearised_problem(lvl, state)
        if engine_choice:
            original(lvl, state, progress)
        save(problem, lvl)
        raise ChoiceCaptured

    steps.choose_regularization = hook
    t0 = time.perf_counter()
    try:
        run()
    except ChoiceCaptured:
        return time.perf_counter() - t0
    finally:
        steps.choose_regularization = original
    return None
