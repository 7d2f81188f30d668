"""An earlier result to start from (``correlate(..., init=RESULT)``, ``--init``): opened, checked, identified.

Besides no motion and the rigid translation found on the coarsest level, a correlation may
start from the displacement field of an earlier result, when that field's gap is the lowest
of the three (:func:`chunkdic.method.start.best_start`): the previous step of a loading series,
a coarser or finer element size, another ROI or another pyramid level. The earlier C8 field
is evaluated at the new mesh's nodes by :func:`chunkdic.method.start.init_field` (its own
shape functions, positions and values converted between levels with the half-voxel offset
of shared/DESIGN.md, :func:`chunkdic.mesh.carry_field`).

Choices (docs/analysis.md, "Starting from an earlier result"):

- **Outside the earlier ROI** the field takes the linear extension of the nearest
  element up to one element beyond the earlier mesh, and beyond that the value at that
  limit (``carry_field(..., clamp=True)``, the policy of :func:`chunkdic.analysis.loadseries.compose`
  too): a start field that keeps growing far from the data would only make the first
  iterations worse.
- **Nodes the earlier run did not measure** (NaN: no data, masked) take the mean of the
  measured nodes, per component, before evaluation.
- With ``init`` the run starts on the finest level (``coarsest = level``) unless
  ``coarsest`` is given: the earlier field already holds the large displacements the
  coarse levels exist to find, and a coarse mesh could not hold its detail.

The earlier result is an input: it is checked before any output is created (one line,
:class:`chunkdic.InputError`) and identified in the resume fingerprint and the new
result's ``info["init"]`` by its path, its own fingerprint and a SHA-256 of its
displacement array (mesh-sized, cheap).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..inputs import check_shape_for_result
from ..io.kinds import kind_of
from ..results.result import Result, open_result

__all__ = ["open_init", "init_identity"]


def open_init(init, ref_shape) -> Result:
    """The earlier result ``init`` (path or :class:`Result`), checked against the reference.

    Parameters
    ----------
    init : str, Path or Result
    ref_shape : tuple of 3 int
        Level-0 shape of the new run's reference scan.

    Raises
    ------
    InputError
        A missing path, something that is not a complete chunkdic result (a scan, a
        folder, an interrupted run), a result computed on a reference of another shape,
        or one without a single measured node.
    """
    if isinstance(init, Result):
        res = init
    else:
        path = Path(os.fspath(init))
        if not path.exists():
            raise InputError(f"--init {path} does not exist")

        kind, _ = kind_of(path)
        if kind is not None and kind != "result":
            raise InputError(f"--init {path} is a chunkdic {kind}, not a result: pass a correlation result")
        try:
            res = open_result(path)
        except InputError as exc:
            raise InputError(f"--init: {exc}") from None
    try:  # the shape it was computed on (older results: its ROI must lie in this reference)
        check_shape_for_result(res.info, ref_shape, "reference", what="this reference",
                               hint="pass a result of this specimen's scans")
    except InputError as exc:
        raise InputError(f"--init {res.path}: {exc}") from None
    if not np.isfinite(res.displacement).all(axis=0).any():
        raise InputError(f"--init {res.path}: the result has no measured node (all displacements NaN)")
    return res


def init_identity(res: Result) -> dict:
    """What identifies the earlier result for resuming and in ``info["init"]``: its path,
    its own fingerprint and creation time, and the SHA-256 of its displacement."""
    u = np.ascontiguousarray(res.displacement, dtype=np.float64)
    return {"path": None if res.path is None else str(Path(res.path).resolve()),
            "fingerprint": res.info.get("fingerprint"), "created": res.info.get("created"),
            "displacement_sha256": hashlib.sha256(u.tobytes()).hexdigest()[:32],
            "element_size": res.info.get("element_size"), "level": res.level}
