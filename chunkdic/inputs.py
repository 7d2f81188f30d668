"""The one place that checks inputs and options before any output is created.

Each check raises :class:`InputError` with one line that names the offending input or
option and says what to change; the CLI prints it and exits with status 2. Commands call
these first, then declare their outputs (:mod:`chunkdic.io.outputs`), then compute.

- :func:`number`: numeric options (finite, in range, integer where needed).
- :func:`check_finite` / :func:`non_finite_error`: NaN and infinite voxels, with one
  wording for every command (ingest, the Fourier shift of ``uncertainty``, and the
  correlation passes, which see every voxel of ``f`` anyway).
- :func:`check_scan_for_result` / :func:`check_shape_for_result`: a scan given to
  ``export``/``report`` for a result, or the reference of a run started from a result
  (``--init``), must be the shape the result was computed on (or at least hold its ROI).

A result read back is checked by :meth:`chunkdic.Result.check_displacement` before strains
or exports are derived from it.
"""

from __future__ import annotations

import math

import numpy as np

from . import config
from .errors import InputError

__all__ = ["number", "check_finite", "non_finite_error", "check_scan_for_result", "check_shape_for_result"]


def number(value, name: str, *, minimum: float | None = None, maximum: float | None = None,
           above: float | None = None, integer: bool = False):
    """A finite number within bounds, else InputError naming the option.

    Parameters
    ----------
    value : number or str
    name : str
        How the user wrote the option (``"--noise"``).
    minimum, maximum : float, optional
        Inclusive bounds.
    above : float, optional
        Exclusive lower bound.
    integer : bool
        Require an integer (returned as ``int``).

    Examples
    --------
    >>> number("0.5", "--noise", minimum=0)
    0.5
    >>> number(-1, "--noise", minimum=0)
    Traceback (most recent call last):
    ...
    chunkdic.errors.InputError: --noise must be >= 0, got -1
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise InputError(f"{name} must be a finite number, got {value!r}")
    if integer:
        if v != int(v):
            raise InputError(f"{name} must be an integer, got {value!r}")
        v = int(v)
    if minimum is not None and v < minimum:
        raise InputError(f"{name} must be >= {minimum:g}, got {value!r}")
    if above is not None and v <= above:
        raise InputError(f"{name} must be > {above:g}, got {value!r}")
    if maximum is not None and v > maximum:
        raise InputError(f"{name} must be <= {maximum:g}, got {value!r}")
    return v


def non_finite_error(label: str, voxel, value, where: str = "") -> InputError:
    """The one wording of a NaN/inf voxel: ``label`` names the input, ``voxel`` is the
    (z, y, x) index in the input's level, ``where`` adds e.g. the slice file."""
    z, y, x = (int(v) for v in voxel)
    extra = f", {where}" if where else ""
    return InputError(f"{label}: {float(value)} value at voxel (z, y, x) = ({z}, {y}, {x}){extra}: "
                      "voxels must be finite (replace NaN/inf first)")


def check_finite(block: np.ndarray, origin, label: str, where=None) -> None:
    """Raise :func:`non_finite_error` for the first NaN/inf voxel of ``block``.

    Parameters
    ----------
    block : ndarray, shape (nz, ny, nx)
        Voxels just read (integer blocks pass at no cost).
    origin : tuple of 3 int
        Index of ``block[0, 0, 0]`` in the input.
    label : str
        The input (path).
    where : callable(z) -> str, optional
        Extra location text for the absolute slice ``z`` (e.g. the TIFF file).
    """
    if block.dtype.kind != "f" or np.isfinite(block).all():
        return
    local = np.argwhere(~np.isfinite(block))[0]
    voxel = tuple(int(a) + int(o) for a, o in zip(local, origin))
    raise non_finite_error(label, voxel, block[tuple(local)], where(voxel[0]) if where else "")


def check_scan_for_result(info: dict, scan, role: str, given: bool) -> None:
    """Refuse a scan that cannot be the one a result was computed on.

    Parameters
    ----------
    info : dict
        The result's ``info`` (``roi`` and ``level``; ``input_shapes`` when recorded).
    scan : chunkdic.Scan
    role : {"reference", "deformed"}
    given : bool
        The user passed the scan (``--ref``/``--deformed``) rather than the recorded path.
    """
    opt = "--ref" if role == "reference" else "--deformed"
    check_shape_for_result(info, scan.shape(0), role, what=f"the {role} scan" + (f" ({opt})" if given else ""))


def check_shape_for_result(info: dict, shape0, role: str, *, what: str,
                           hint: str = "pass the scans of this result") -> None:
    """Refuse a level-0 shape that cannot be the one of the ``role`` scan of a result:
    another shape than the one recorded (``input_shapes``), or, for older results that
    did not record it, a reference too small for the result's ROI.

    Parameters
    ----------
    info : dict
        The result's ``info``.
    shape0 : tuple of 3 int
        The level-0 shape of the scan offered.
    role : {"reference", "deformed"}
    what : str, keyword-only
        How the message names that scan (``"the reference scan (--ref)"``).
    hint : str, keyword-only
        What the message tells the user to do.
    """
    level = int(info.get("level", 0))
    recorded = (info.get("input_shapes") or {}).get(role)
    shape0 = tuple(int(n) for n in shape0)
    if recorded is not None and tuple(int(n) for n in recorded) != shape0:
        raise InputError(f"{what} has shape {shape0} but the result was computed on one of shape "
                         f"{tuple(int(n) for n in recorded)}: {hint}")
    if role == "reference":
        shape = tuple(n // 2**level for n in shape0)  # the pyramid's level shape (odd voxels trimmed)
        for axis, ((a, b), n) in enumerate(zip(info["roi"], shape)):
            if a < 0 or b > n:
                raise InputError(f"{what} has shape {shape} at level {level}, too small for the result's ROI "
                                 f"{a}:{b} on axis {'zyx'[axis]}: {hint}")




def parse_memory(value) -> int | None:
    """Bytes from ``"2GiB"``, ``"1.5 GB"``, ``2e9`` or ``None``; refuse anything else."""
    if value is None or value == "":
        return None
    from dask.utils import parse_bytes

    try:
        out = int(parse_bytes(value)) if isinstance(value, str) else int(value)
    except (TypeError, ValueError):
        raise InputError(f"memory target {value!r}: expected a size such as 2GiB or 1500MB") from None
    if out <= 0:
        raise InputError(f"memory target {value!r} must be positive")
    return out


def memory_target_of(value=None) -> int | None:
    """``value``, else ``chunkdic.memory-target`` from dask.config, as bytes (or ``None``)."""
    return parse_memory(value if value is not None else config.get("memory-target"))
