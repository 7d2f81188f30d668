"""Is the residual noise? Elements whose deformed scan does not match the reference.

The iterations stop when the increments fall to the noise level (docs/engine.md,
"Iterations and stopping"), which says nothing of whether the field found *matches* the
scans: a deformed scan with half of its blocks replaced by noise converges there too, with
nodal errors of several voxels, and so do two unrelated images. What tells them apart is
the residual itself, element by element. A matched element leaves the scans' noise, a
small part of the reference's own variation wherever it is textured; an element whose
deformed scan is unrelated to the reference leaves its whole variation, whatever the field.

Per element the ``b`` pass sums (:func:`chunkdic.method.brightness.residual_rows`):
``Σ w r²`` with the element's own best gain and offset (so that no brightness change and
no brightness model counts as a mismatch) and ``Σ w (f - f̄)²``, the reference's own
variation. An element is *mismatched* (:func:`mismatched`) when

- its residual leaves more than :data:`UNEXPLAINED` of that variation unexplained, and
- it is textured: its own variation per voxel exceeds :data:`TEXTURE` times the noise (and a
  thousandth of the typical element's, :data:`FLAT_SHARE`, for scans without noise). An
  element of pure noise (air around a specimen) or a flat one cannot be judged: its residual
  is its noise whatever the field.

The noise is the residual per voxel of the best matched elements (:data:`NOISE_QUANTILE`
of it over the elements): the pass's ``σ_r²`` (:attr:`chunkdic.method.protocol.Pass.noise_variance`)
is the mean over every element, raised by the very elements under test (half of them, in a
half-noise scan), and so is a median. When no element is matched at all (two unrelated
scans), every element that leaves its variation unexplained is mismatched.

A node is flagged :data:`~chunkdic.results.layout.FLAG_MISMATCH` when half or more of its
elements with data are mismatched, and a converged run whose flagged nodes exceed
``chunkdic.max-mismatch-fraction`` of the measured nodes ends ``mismatch``, not
``converged`` (:func:`residual_status`). The thresholds come from the honest pairs of the
test suite (docs/engine.md, "A residual that is not noise").
"""

from __future__ import annotations

import logging

import numpy as np

from .. import config
from ..results.layout import FLAG_MASKED, FLAG_MISMATCH, FLAG_NO_DATA

log = logging.getLogger(__name__)

__all__ = ["UNEXPLAINED", "TEXTURE", "local_residual", "mismatched", "node_share", "mismatched_nodes", "judged",
           "residual_status"]

#: an element leaving more than this share of the reference's own variation unexplained
#: is not matched (the suite's honest pairs: 99 % of textured elements below 0.26, a few
#: up to 0.58 on a band at ℓ = 4; half-noise and unrelated elements: 0.5-1)
UNEXPLAINED = 0.4
#: an element is textured when its own variation exceeds this many times the noise
TEXTURE = 4.0
#: the noise is the residual per voxel of the best matched elements: this quantile of it over
#: the elements (a median is raised by the mismatched ones once they are half or more)
NOISE_QUANTILE = 0.1
#: an element whose own variation per voxel is below this share of the median element's is flat
FLAT_SHARE = 1e-3
#: an element whose ``Σ (g - ḡ)²`` is below this fraction of ``Σ g²`` fixes no gain (here and in
#: the ``element`` brightness model, :mod:`chunkdic.method.brightness`)
FLAT = 1e-12


def local_residual(n, sd, sg, sdd, sdg, sgg) -> np.ndarray:
    """Per element, ``Σ w r²`` with the element's own least-squares gain and offset
    (``r = f - λ g(X+u) - μ``, whatever the brightness model: the least residual the element
    allows) and ``Σ w (f - f̄)²``, the reference's own variation: shape (2, *elements), grey levels².

    Parameters
    ----------
    n, sd, sg, sdd, sdg, sgg : ndarray, shape elements, float64
        Per element ``Σ w``, ``Σ w d``, ``Σ w g``, ``Σ w d²``, ``Σ w d g``, ``Σ w g²`` with
        ``d = f - g(X+u)`` and ``g = g(X+u)`` (minus any constant).
    """
    safe = np.where(n > 0, n, 1.0)
    cdd, cdg, cgg = sdd - sd * sd / safe, sdg - sd * sg / safe, sgg - sg * sg / safe  # within-element
    ok = cgg > FLAT * np.maximum(sgg, 1e-300)
    local = cdd - np.where(ok, cdg * cdg / np.where(ok, cgg, 1.0), 0.0)
    own = cdd + 2 * cdg + cgg
    return np.stack([np.maximum(local, 0.0), np.maximum(own, 0.0)])


def mismatched(residual: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Elements whose residual is not noise, bool, shape (ez, ey, ex) (or (ey, ex) in 2-D).

    Parameters
    ----------
    residual : ndarray, shape (2, *elements), float64, grey levels²
        Per element ``Σ w r²`` with the element's own gain and offset, and ``Σ w (f - f̄)²``
        (:func:`local_residual`).
    valid : ndarray, shape elements, float64
        ``Σ w`` per element (voxels used).
    """
    ssr, own = residual
    used = valid > 0
    unexplained = used & (ssr > UNEXPLAINED * own)
    explained = used & ~unexplained
    if not explained.any():  # nothing matched anywhere (two unrelated scans)
        return unexplained
    n = np.where(used, valid, 1.0)
    noise = float(np.quantile(ssr[used] / n[used], NOISE_QUANTILE))
    # and never below a thousandth of the typical element's own variation: a noise-free scan
    # has no noise to stand out of, but its flat parts are no texture either (as weak nodes)
    floor = max(noise, FLAT_SHARE * float(np.median(own[used] / n[used])))
    return unexplained & (own / n > TEXTURE * floor)


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


def mismatched_nodes(residual: np.ndarray, valid: np.ndarray, measured: np.ndarray | None = None) -> np.ndarray:
    """Nodes (bool, shape: elements + 1 per axis) whose residual is not noise: half or more of
    their elements with data are :func:`mismatched`; only ``measured`` nodes (bool) when given."""
    bad = node_share(mismatched(residual, valid), valid)
    return bad if measured is None else bad & measured


def judged(status: str, bad_nodes: int, measured_nodes: int) -> str:
    """``mismatch`` for a ``converged`` run whose nodes with a residual that is not noise exceed
    ``chunkdic.max-mismatch-fraction`` of its measured nodes; ``status`` otherwise."""
    share = bad_nodes / max(measured_nodes, 1)
    if bad_nodes:
        log.info("%d of %d measured nodes leave a residual that is not noise (%.0f %%)", bad_nodes, measured_nodes,
                 100 * share)
    return "mismatch" if status == "converged" and share > config.get("max-mismatch-fraction") else status


def residual_status(status: str, flags: np.ndarray, elements: np.ndarray | None) -> str:
    """The run's status once its residual is judged (:func:`judged`); sets ``FLAG_MISMATCH`` in ``flags``.

    Parameters
    ----------
    status : str
        The finest level's status (only ``converged`` can change, to ``mismatch``).
    flags : ndarray, shape (nz, ny, nx), uint8
        The result's node flags, updated in place.
    elements : ndarray, shape (8, ez, ey, ex), float64, optional
        The last pass's element fields (:func:`chunkdic.method.gauss_newton.element_fields`:
        row 2 the voxels used, rows 6-7 the residual rows); a checkpoint of an older layout
        (6 rows) or None leaves everything as it is.
    """
    if elements is None or elements.shape[0] < 8 or not np.isfinite(elements[6:8]).all():
        return status
    measured = (flags & (FLAG_NO_DATA | FLAG_MASKED)) == 0
    bad = mismatched_nodes(elements[6:8], elements[2], measured)
    flags[bad] |= FLAG_MISMATCH
    return judged(status, int(bad.sum()), int(measured.sum()))
