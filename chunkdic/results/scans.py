"""The scans and inputs of a correlation result, for the commands that read it back.

One idea: from a :class:`~chunkdic.results.result.Result` to the reference and deformed scans it was
computed from (the recorded paths, or the ones the user passes instead, checked against
the result), the list of on-disk inputs for the output checks of :mod:`chunkdic.io.outputs`,
the interpolation it used, and :func:`level_refs`, the result's pyramid level of both
scans as :class:`~chunkdic.io.handles.ArrayRef` (missing levels written to scratch, removed on
exit). Used by :mod:`chunkdic.export.corrected_image`, :mod:`chunkdic.export.meshfiles`, :mod:`chunkdic.plot.report`,
:mod:`chunkdic.analysis.crosscheck` and the CLI.
"""

from __future__ import annotations

import contextlib
import shutil
from pathlib import Path

from ..errors import InputError
from ..inputs import check_scan_for_result
from ..io.ownership import make_scratch
from ..io.scan import open_scan
from .result import Result, open_result

__all__ = ["as_result", "input_scan", "input_scans", "input_paths", "level_refs", "interpolation_of"]


def as_result(result) -> Result:
    """``result`` itself, or the result stored at that path (:func:`~chunkdic.results.result.open_result`)."""
    return result if isinstance(result, Result) else open_result(result)


def input_scan(result: Result, role: str, given=None, *, optional: bool = False):
    """The ``role`` scan (``"reference"`` or ``"deformed"``) of a result, opened and checked.

    ``given`` (a path or an array) overrides the path recorded in ``result.info["inputs"]``
    (needed when the result was computed from in-memory arrays, or the scans moved); it is
    checked against the result (:func:`chunkdic.inputs.check_scan_for_result`).
    ``optional``: None instead of a refusal when nothing is given and the recorded scan is
    not on disk (in memory, moved).
    """

    src = given if given is not None else (result.info.get("inputs") or {}).get(role)
    missing = src is None or (isinstance(src, str) and src.startswith("<in-memory"))
    if optional and given is None and (missing or not Path(src).exists()):
        return None
    if missing:
        raise InputError(
            f"the {role} scan of this result is not on disk ({src or 'unknown'}): pass it explicitly "
            f"(--{'ref' if role == 'reference' else 'deformed'} PATH)"
        )
    scan = open_scan(src)
    check_scan_for_result(result.info, scan, role, given is not None)
    return scan


def input_scans(result: Result, ref=None, deformed=None) -> tuple:
    """The reference and deformed :class:`~chunkdic.Scan` of a result (:func:`input_scan`)."""
    return input_scan(result, "reference", ref), input_scan(result, "deformed", deformed)


def input_paths(result: Result, ref=None, deformed=None) -> list:
    """Every on-disk input of a command that reads ``result`` and its scans (for the
    output checks of :mod:`chunkdic.io.outputs`)."""
    recorded = result.info.get("inputs") or {}
    paths = [result.path]
    for given, key in ((ref, "reference"), (deformed, "deformed")):
        src = given if given is not None else recorded.get(key)
        if isinstance(src, str) and src.startswith("<in-memory"):
            src = None
        paths.append(src)
    return [p for p in paths if p is not None]


@contextlib.contextmanager
def level_refs(result: Result, ref=None, deformed=None, *, scans=None):
    """``(f_ref, g_ref)`` ArrayRefs of the result's level; scratch levels removed on exit.

    ``scans``: the ``(reference, deformed)`` scans already opened and checked by
    :func:`input_scans` (then ``ref`` and ``deformed`` are not used); default: opened here.
    """
    f_scan, g_scan = scans if scans is not None else input_scans(result, ref, deformed)
    s = result.level
    scratch = make_scratch("chunkdic-export-")
    try:
        f_ref = f_scan.refs([s], scratch / "ref")[s]
        g_ref = g_scan.refs([s], scratch / "def")[s]
        yield f_ref, g_ref
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def interpolation_of(result: Result) -> str:
    """The interpolation of ``g`` the result was computed with (``"cubic"`` when not recorded)."""
    return str((result.info.get("settings") or {}).get("interpolation", "cubic"))
