"""The result of a run: the finest level's field, flags, uncertainty and the run's facts.

What :func:`chunkdic.correlate` returns (and saves): the displacement of the correlated
level with NaN where no node was measured, the node flags (:mod:`chunkdic.results.layout`),
the status (a converged run whose excluded voxels, weak nodes or nodes with a residual that
is not noise are too many is not called converged: :mod:`chunkdic.method.mismatch`), the
gaps, the brightness and noise found, the regularisation used and the settings.
"""

from __future__ import annotations

import time

import numpy as np

from .. import config
from ..method.length import freed_terms
from ..method.level_solve import LevelOutcome
from ..method.mismatch import residual_status
from ..method.stopping import State
from ..results.result import FLAG_MASKED, FLAG_NO_DATA, FLAG_WEAK, Result, node_flags
from ..solve.transfer import nominal_l10
from ..method.runstate import RunState


def assemble_result(ctx, run: RunState, final: State, outcome: LevelOutcome) -> Result:
    """The finest level's field, flags, uncertainty and the run's facts as a :class:`Result`.

    ``ctx``: the run's :class:`~chunkdic.engine.coarse_to_fine.RunContext`; ``final``: the
    finest level's last state; ``outcome``: what that level left (:func:`chunkdic.method.level_solve.level_outcome`).
    """
    settings, finest, coarsest = ctx.settings, ctx.finest, ctx.coarsest
    mesh = ctx.meshes[finest]
    # read back where a level in node blocks parked them (Passes.park); the final state is not reused
    final.elements = None if final.elements is None else np.asarray(final.elements)
    flags = node_flags(mesh, final.elements, outcome.weak, outcome.masked)
    missing = (flags & (FLAG_NO_DATA | FLAG_MASKED))[None] > 0
    u = np.where(missing, np.nan, final.u)
    sigma_u = None if outcome.sigma_u is None else np.where(missing, np.nan, outcome.sigma_u)
    statuses = dict(run.statuses)
    status = statuses[finest]
    excluded_fraction = final.excluded / max(final.excluded + final.n_valid, 1)
    if status == "converged" and excluded_fraction > config.get("max-excluded-fraction"):
        status = statuses[finest] = "excluded"
    measured = int(np.count_nonzero((flags & (FLAG_NO_DATA | FLAG_MASKED)) == 0))
    weak_fraction = int(np.count_nonzero(flags & FLAG_WEAK)) / max(measured, 1)
    if status == "converged" and weak_fraction > config.get("max-weak-fraction"):
        # a half-untextured scan "converged" with 2-3.5 voxel errors on its flat half: the
        # iterations converged, but so many nodes are the regularisation's guesses
        status = statuses[finest] = "weak-texture"
    status = statuses[finest] = residual_status(status, flags, final.elements)
    reg_length = outcome.reg_length
    info = {
        "element_size": settings.element_size,
        "roi": [[r.start, r.stop] for r in mesh.roi],
        "roi_level0": [[r.start * 2**finest, r.stop * 2**finest] for r in mesh.roi],
        "level": finest,
        "scale": 2**finest,
        "levels": ctx.levels,
        "level_status": {str(k): v for k, v in statuses.items()},
        "status": status,
        "converged": status == "converged",
        "initial_gap": run.initial_gap,
        "rigid_gap": run.rigid_gap,
        "final_gap": final.gap,
        "rigid_translation": (run.rigid_t * 2.0 ** (coarsest - finest)).tolist(),
        "excluded_voxels": int(final.excluded),
        "used_voxels": int(final.n_valid),
        "excluded_fraction": float(excluded_fraction),
        "nodes_without_data": int(np.count_nonzero(flags & FLAG_NO_DATA)),
        "masked_nodes": int(np.count_nonzero(flags & FLAG_MASKED)),
        "weak_nodes": int(np.count_nonzero(flags & FLAG_WEAK)),
        "grey_level": brightness_summary(settings.grey, final.elements),
        "noise": outcome.noise,
        "regularization": {"kind": settings.regularization,
                           "length": None if not np.isfinite(reg_length) else float(reg_length),
                           "automatic": settings.regularization_length is None,
                           # the robust reweighting: rounds asked, Tikhonov terms left out
                           "reweights": settings.reweights,
                           "freed_terms": freed_terms(final.freed),
                           # what l and the length let through of a sine, level-0 voxels (a lower
                           # bound of the spatial resolution; `chunkdic resolution` measures it)
                           "nominal_l10": nominal_l10(settings.element_size * 2**finest,
                                                      reg_length if np.isfinite(reg_length) else None)},
        "settings": settings.to_json(),
        **({} if outcome.split is None else {"crack": {"split_nodes": int(len(outcome.split)),
                                                        "cut_edges": int(outcome.crack_edges)}}),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "chunkdic_version": _version(),
    }
    brightness = None if final.elements is None else final.elements[:2]
    return Result(u, mesh.node_coords(), run.history.arrays(), info, flags=flags, brightness=brightness,
                  active=outcome.active, uncertainty=sigma_u, other_side=_other_side(outcome, final))


def brightness_summary(model: str, elements: np.ndarray | None) -> dict:
    """Median gain and offset, offset range and drift of the last pass (``info["grey_level"]``)."""
    out = {"model": model}
    if elements is not None:
        used = elements[2] > 0
        gain, offset = elements[0][used], elements[1][used]
        if gain.size:
            out.update(gain=float(np.median(gain)), offset=float(np.median(offset)),
                       offset_range=[float(offset.min()), float(offset.max())],
                       drift=[float(v) for v in elements[3:6, 0, 0, 0]])
    return out


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("chunkdic")
    except PackageNotFoundError:
        return "unknown"


def _other_side(outcome: LevelOutcome, final: State) -> np.ndarray | None:
    """The second copies of a known crack's split nodes on the node grid (NaN elsewhere), None without a crack."""
    if outcome.split is None:
        return None
    out = np.full(final.u.shape, np.nan)
    if final.u_other is not None and len(outcome.split):
        out[(slice(None), *outcome.split.T)] = np.asarray(final.u_other).T
    return out
