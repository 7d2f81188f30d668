"""Is the residual noise? Elements whose deformed scan does not match the reference.

The iterations stop when the increments fall to the noise level (docs/engine.md,
"Iterations and stopping"), which says nothing of whether the field found *matches* the
scans: a deformed scan with half of its blocks replaced by noise converges there too, with
nodal errors of several voxels, and so do two unrelated images. What tells them apart is
the residual itself, element by element. A matched element leaves the scans' noise, a
small part of the reference's own variation wherever it is textured; an element whose
deformed scan is unrelated to the reference leaves its whole variation, whatever the field.

Per element the ``b`` pass sums (:func:`chunkdic.engine.greylevel.residual_rows`):
``Σ w r²`` with the element's own best gain and offset (so that no brightness change and
no brightness model counts as a mismatch) and ``Σ w (f - f̄)²``. Their ratio, the share of
the reference's variation the deformed scan leaves unexplained, is compared with the noise
model of the pass (``σ_r²``): an element is *mismatched* when

- it is textured, ``Σ (f - f̄)² / n > TEXTURE · σ_r²`` (an element of pure noise, air around
  a specimen, cannot be judged: its residual is its noise whatever the field), and
- its residual explains less than ``1 - UNEXPLAINED`` of that variation.

``σ_r²`` here is a robust one, the median over elements of their own ``Σ w r² / n``: the
pass's mean (:attr:`chunkdic.engine.level.Pass.noise_variance`) is raised by the very
elements under test. Two unrelated scans leave every element's residual at its own
variation: no element is textured above that residual, so the rule counts every element
as mismatched when none is textured above the residual of the others (:func:`mismatched`).

A node is flagged :data:`~chunkdic.results.result.FLAG_MISMATCH` when half or more of its
elements with data are mismatched, and a converged run whose flagged nodes exceed
``chunkdic.max-mismatch-fraction`` of the measured nodes ends ``mismatch``, not
``converged`` (:func:`residual_status`). The thresholds come from the honest pairs of the
test suite (docs/engine.md, "A residual that is not noise").
"""

from __future__ import annotations

import logging

import numpy as np

from .. import config
from ..results.result import FLAG_MASKED, FLAG_MISMATCH, FLAG_NO_DATA

log = logging.getLogger(__name__)

__all__ = ["UNEXPLAINED", "TEXTURE", "mismatched", "node_share", "residual_status"]

#: an element leaving more than this share of the reference's own variation unexplained
#: is not matched (honest pairs: at most 0.3 on textured elements; unrelated: 0.9-1)
UNEXPLAINED = 0.6
#: an element is textured when its own variation exceeds this many times the noise
TEXTURE = 4.0


def mismatched(residual: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Elements whose residual is not noise, bool, shape (ez, ey, ex) (or (ey, ex) in 2-D).

    Parameters
    ----------
    residual : ndarray, shape (2, *elements), float64, grey levels²
        Per element ``Σ w r²`` with the element's own gain and offset, and ``Σ w (f - f̄)²``
        (:func:`chunkdic.engine.greylevel.residual_rows`).
    valid : ndarray, shape elements, float64
        ``Σ w`` per element (voxels used).
    """
    ssr, own = residual
    used = valid > 0
    out = np.zeros(valid.shape, bool)
    if not used.any():
        return out
    n = np.where(used, valid, 1.0)
    noise = float(np.median(ssr[used] / n[used]))
    unexplained = ssr > UNEXPLAINED * own
    textured = own / n > TEXTURE * noise
    if noise > 0 and not textured[used].any():
        # nothing stands out of the residual: every element leaves its own variation
        # (two unrelated scans), or the scans hold no texture at all (weak nodes say so)
        return used & unexplained
    return used & textured & unexplained


def node_share(bad: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Nodes (shape: elements + 1 per axis, bool) at least half of whose elements with data
    are in ``bad`` (bool, elements shape)."""
    pad = [(1, 1)] * bad.ndim
    b, v = np.pad(bad & (valid > 0), pad), np.pad(valid > 0, pad)
    corners = [tuple(slice(d, d + n + 1) for d, n in zip(offset, bad.shape))
               for offset in np.ndindex(*(2,) * bad.ndim)]
    nb = sum(b[c].astype(np.int32) for c in corners)
    nv = sum(v[c].astype(np.int32) for c in corners)
    return (nv > 0) & (2 * nb >= nv)


def residual_status(status: str, flags: np.ndarray, elements: np.ndarray | None, progress=None) -> str:
    """The run's status once its residual is judged; sets ``FLAG_MISMATCH`` in ``flags``.

    Parameters
    ----------
    status : str
        The finest level's status (only ``converged`` can change, to ``mismatch``).
    flags : ndarray, shape (nz, ny, nx), uint8
        The result's node flags, updated in place.
    elements : ndarray, shape (8, ez, ey, ex), float64, optional
        The last pass's element fields (:func:`chunkdic.engine.gauss_newton.element_fields`:
        row 2 the voxels used, rows 6-7 the residual rows); a checkpoint of an older layout
        (6 rows) or None leaves everything as it is.
    progress : callable, optional
        Receives a ``mismatch`` event when nodes are flagged.
    """
    if elements is None or elements.shape[0] < 8 or not np.isfinite(elements[6:]).all():
        return status
    bad = node_share(mismatched(elements[6:8], elements[2]), elements[2])
    measured = (flags & (FLAG_NO_DATA | FLAG_MASKED)) == 0
    bad &= measured
    flags[bad] |= FLAG_MISMATCH
    share = int(bad.sum()) / max(int(measured.sum()), 1)
    if bad.any():
        log.info("%d of %d measured nodes leave a residual that is not noise (%.0f %%)", int(bad.sum()),
                 int(measured.sum()), 100 * share)
        if progress is not None:
            progress(dict(stage="mismatch", nodes=int(bad.sum()), measured=int(measured.sum())))
    if status == "converged" and share > config.get("max-mismatch-fraction"):
        return "mismatch"
    return status
