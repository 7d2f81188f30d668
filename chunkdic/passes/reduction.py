"""A ``b`` pass on the client: the blocks' partials added up, then the pass they give.

Each block task returns its share of a pass (:class:`chunkdic.method.brightness.Partials`:
nodal rows over its own nodes, scalars, per-element rows); shared face nodes add up.
:class:`PassSums` holds the sums while the blocks come in; :meth:`PassSums.result` turns them
into the :class:`~chunkdic.method.protocol.Pass` (``b``, the brightness fit, the gap, the noise
correlation), dropping the nodal rows before the element rows are fitted: at 128³ nodes the
nodal rows of the drift model are 240 MB, and they never coexist with the fit's arrays.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..kernels.blocks import LAGS
from ..mesh import Mesh
from ..method.brightness import element_fit, misfit, nodal_rhs
from ..method.noise import correlation_factor
from ..method.operator import Operator
from ..method.protocol import Pass


class PassSums:
    """The sums of one pass's block partials over a level's mesh, and those of its probes."""

    def __init__(self, mesh: Mesh, probes: int = 0):
        self.mesh = mesh
        self.nodal = self.scalars = self.elements = None
        self.n_excluded = 0
        self.lags = np.zeros((6, LAGS + 1))
        self.probe_scalars = [None] * probes

    def add(self, block, part, probe_parts=()) -> None:
        """Add one block's partials (a :class:`~chunkdic.mesh.Block`'s share) and its probes' scalars."""
        mesh = self.mesh
        if self.nodal is None:
            self.nodal = np.zeros((part.nodal.shape[0],) + mesh.nodes_shape + (3,))
            self.scalars = np.zeros_like(part.scalars)
            self.elements = np.zeros((part.elements.shape[0],) + tuple(mesh.shape))
        self.nodal[(slice(None), *block.node_slices)] += part.nodal
        self.scalars += part.scalars
        self.elements[(slice(None), *(slice(e0, e1) for e0, e1 in block.elements))] = part.elements
        self.n_excluded += part.n_excluded
        self.lags += part.lags
        for k, (sc, _) in enumerate(probe_parts):
            self.probe_scalars[k] = sc.copy() if self.probe_scalars[k] is None else self.probe_scalars[k] + sc

    def result(self, grey: str, op: Operator, names=(), started: float | None = None) -> Pass:
        """The pass these sums give for the brightness model ``grey`` and the operator ``op``
        (its centring, range and sensitivity lags); ``names``: the probes'; ``started``: the
        pass's start (``time.perf_counter()``), for its wall time. The sums are consumed."""
        # b first, then the nodal rows go (5 per node with the drift model, 240 MB at 128³ nodes)
        # before the element rows are fitted: they never coexist with the fit's arrays
        b = nodal_rhs(grey, self.nodal, self.scalars)
        self.nodal = None
        fit = element_fit(grey, b, self.scalars, self.elements, op.center, self.mesh.element_size)
        self.elements = b = None
        gap = matching_gap(fit.ssr, fit.weight, op)
        kappa = correlation_factor(self.lags, op.sensitivity_lags, float(np.median(fit.gain)),
                                   fit.ssr / fit.weight if fit.weight > 0 else None)
        probe_gaps = {name: matching_gap(*misfit(grey, sc), op) for name, sc in zip(names, self.probe_scalars)}
        n_excluded = self.n_excluded
        seconds = 0.0 if started is None else time.perf_counter() - started
        return Pass(fit, gap, self.mesh.n_voxels - n_excluded, n_excluded, kappa, probe_gaps, seconds)


def matching_gap(ssr: float, weight: float, op: Operator) -> float:
    """The matching gap ``rms(r) / (max f - min f)`` of a pass's misfit (paper section 5.1)."""
    return math.sqrt(ssr / weight) / op.dynamic_range if weight > 0 else math.inf
