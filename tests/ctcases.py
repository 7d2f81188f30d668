"""CT-like test pairs written once per test session, and their correlations run once.

Shared by ``tests/engine/test_real_ct.py`` (issue 10) and ``tests/solve/test_regularization.py`` (issue 11): a
correlation asked for by several tests (the same pair, element size and settings) runs
once. Pairs are the standard cases of :func:`chunkdic.synth.synthetic.standard_case` (CT-like
``grains`` / ``concrete`` specimens, uint16, reconstruction noise 0.02 of the phase
contrast, independent in the two scans unless the case is a Fourier shift); a case name
``"band+grey-up"`` adds a grey-level change of the deformed scan (:data:`GREY`). Every
score is :func:`chunkdic.score_displacement` against the pair's known field, at the
result's nodes, with the element size as the border distance.
"""

from __future__ import annotations

from pathlib import Path

import chunkdic
from chunkdic.synth import synthetic

NOISE = 0.02
#: grey-level changes of the deformed scan (issue 10: gain 0.9-1.1, offset ±5 %, drift ±3 %)
GREY = {
    "grey-up": dict(gain=1.1, offset=0.05, drift=0.03),
    "grey-down": dict(gain=0.9, offset=-0.05, drift=-0.03),
}


class CTCases:
    """Pairs under ``root``, written on first use; correlations memoised by their arguments."""

    def __init__(self, root):
        self.root = Path(root)
        self._pairs: dict = {}
        self._runs: dict = {}

    def pair(self, specimen: str, case: str, size: int) -> dict:
        """The pair of :func:`chunkdic.synth.synthetic.standard_case` (``case`` optionally ``+grey``)."""
        key = (specimen, case, size)
        if key not in self._pairs:
            base, _, grey = case.partition("+")
            self._pairs[key] = synthetic.standard_case(
                self.root / f"{specimen}-{case}-{size}", base, size, specimen=specimen, noise=NOISE,
                **GREY.get(grey, {}))
        return self._pairs[key]

    def run(self, specimen: str, case: str, size: int, ell: int, **settings):
        """``(Result, Score)`` of ``correlate(ref, def, element_size=ell, **settings)`` on the pair."""
        key = (specimen, case, size, ell, tuple(sorted(settings.items())))
        if key not in self._runs:
            p = self.pair(specimen, case, size)
            res = chunkdic.correlate(p["reference"], p["deformed"], element_size=ell, **settings)
            truth = p["field"].displacement(*res.node_coords)
            score = chunkdic.score_displacement(res.node_coords, res.displacement, truth, (size,) * 3, ell)
            self._runs[key] = (res, score)
        return self._runs[key]
