"""Lengths given in physical units on the command line, converted to voxels of a scan; and
the check that scans compared voxel to voxel have the same voxel size.

``--element-size 60um`` and ``--roi 0:500,0:500,0:500 --roi-unit um`` (or a unit suffix on
the ROI) are converted with the reference scan's voxel size (OME-NGFF metadata,
:mod:`chunkdic.io.ngff`). Voxel ``i`` of level 0 has its centre at ``i * voxel_size``
(DESIGN.md), so a physical coordinate ``p`` is voxel coordinate ``p / voxel_size``.
"""

from __future__ import annotations

import math
import re

from ..errors import InputError
from .ngff import normalize_unit
from .scan import open_scan

#: metres per unit, for the units a scan's metadata and a user are likely to use
METERS = {"angstrom": 1e-10, "picometer": 1e-12, "nanometer": 1e-9, "micrometer": 1e-6,
          "millimeter": 1e-3, "centimeter": 1e-2, "decimeter": 1e-1, "meter": 1.0}

_NUMBER_UNIT = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([^\d\s.:,+-][^\s:,]*)?\s*$")


def parse_length(text, what: str = "--element-size") -> tuple[float, str | None]:
    """``"60um"`` -> ``(60.0, "micrometer")``; ``"12"`` -> ``(12.0, None)`` (voxels)."""
    m = _NUMBER_UNIT.match(str(text))
    if m is None:
        raise InputError(f"{what} {text!r}: expected a number, optionally with a length unit (12, 60um, 0.06mm)")
    unit = m.group(2)
    if unit is not None and unit.lower() in ("vx", "voxel", "voxels"):
        unit = None
    value = float(m.group(1))
    if not math.isfinite(value) or value <= 0:  # 1e999 overflows to inf; -160um is no length
        raise InputError(f"{what} {text!r}: a length must be a positive finite number")
    return value, normalize_unit(unit)


def factor(unit: str, scan_unit: str | None) -> float:
    """How many ``scan_unit`` make one ``unit`` (refuses units it cannot relate)."""
    scan_unit = normalize_unit(scan_unit) if scan_unit else None
    if scan_unit is None or unit == scan_unit:
        return 1.0
    if unit not in METERS or scan_unit not in METERS:
        raise InputError(f"cannot convert {unit} to the scan's unit {scan_unit}")
    return METERS[unit] / METERS[scan_unit]


def _voxel(scan, what: str):
    vs = getattr(scan, "voxel_size", None)
    if not vs:
        raise InputError(f"{what} is given in a physical unit but the reference scan has no voxel size: give "
                         "it in voxels, or ingest the scan with --voxel-size and --unit")
    return tuple(float(v) for v in vs), getattr(scan, "unit", None)


def element_size_voxels(text, scan, level: int = 0) -> tuple[int, str | None]:
    """``--element-size`` in voxels of ``level``: ``(ell, note)``.

    A physical size is divided by the level's voxel (``voxel_size * 2**level``, which must
    be the same along the three axes: C8 elements are cubes of voxels) and rounded to the
    nearest whole voxel; ``note`` says so (``None`` for a size given in voxels).
    """
    value, unit = parse_length(text)
    if unit is None:
        if value != int(value):
            raise InputError(f"--element-size {text!r}: a size in voxels must be a whole number")
        return int(value), None
    vs, scan_unit = _voxel(scan, "--element-size")
    if max(vs) - min(vs) > 1e-9 * max(vs):
        raise InputError(f"--element-size {text!r}: the voxel size {vs} is not the same along z, y, x; give the "
                         "element size in voxels")
    voxel = vs[0] * 2**level
    exact = value * factor(unit, scan_unit) / voxel
    if not exact >= 1.5:  # the value given, not the whole voxels it rounds to (1e-300um is not "1")
        raise InputError(f"--element-size {text!r} is {exact:.3g} voxels of level {level} ({voxel:g} "
                         f"{scan_unit or unit} each): an element needs at least 2 voxels per side")
    if not math.isfinite(exact):
        raise InputError(f"--element-size {text!r} is more voxels than any scan holds")
    ell = round(exact)
    return ell, (f"--element-size {text} = {exact:.3f} voxels of level {level}: using {ell} "
                 f"({ell * voxel:.4g} {scan_unit or unit})")


def roi_voxels(roi: str, scan, unit: str | None = None) -> tuple[str, str | None]:
    """A ROI ``"z0:z1,y0:y1,x0:x1"`` in ``unit`` (or with a unit suffix, ``"0:500,0:500,0:500um"``)
    as the same string in level-0 voxels (bounds rounded to the nearest voxel), and a note."""
    text = str(roi).strip()
    m = re.match(r"^(.*?\d)\s*([^\d\s.:,+-][^\s:,]*)$", text)
    if m is not None:
        text, unit = m.group(1), m.group(2)
    unit = None if unit is None or unit.lower() in ("vx", "voxel", "voxels") else normalize_unit(unit)
    if unit is None:
        return text, None
    vs, scan_unit = _voxel(scan, "--roi")
    f = factor(unit, scan_unit)
    try:
        pairs = [tuple(float(v) for v in part.split(":")) for part in text.split(",")]
    except ValueError:
        raise InputError(f"ROI {roi!r}: expected z0:z1,y0:y1,x0:x1 in {unit}") from None
    if len(pairs) != 3 or any(len(p) != 2 for p in pairs):
        raise InputError(f"ROI {roi!r}: expected three ranges z0:z1,y0:y1,x0:x1")
    if not all(math.isfinite(v) for p in pairs for v in p):
        raise InputError(f"ROI {roi!r}: every bound must be a finite number")
    out = ",".join(f"{round(a * f / v)}:{round(b * f / v)}" for (a, b), v in zip(pairs, vs))
    return out, f"--roi {roi} ({unit}) = {out} in level-0 voxels"


def resample_size(text, voxel_size, unit: str | None) -> tuple[float, float, float]:
    """``--resample`` (``"20um"``, ``"20,20,25um"``, a number or three, in the scan's own unit)
    as a voxel size (z, y, x) in the scan's unit ``unit``; ``voxel_size`` the scan's (needed)."""
    if not voxel_size:
        raise InputError("--resample needs the scan's voxel size: give --voxel-size (and --unit)")
    if isinstance(text, (int, float)) or (isinstance(text, (list, tuple)) and len(text) == 3):
        values, given = [float(v) for v in (text if isinstance(text, (list, tuple)) else [text] * 3)], None
    else:
        m = re.match(r"^(.*?\d\.?)\s*([^\d\s.:,+-][^\s:,]*)?$", str(text).strip())
        parts = (m.group(1) if m else str(text)).split(",")
        given = normalize_unit(m.group(2)) if m and m.group(2) else None
        try:
            values = [float(v) for v in parts]
        except ValueError:
            raise InputError(f"--resample {text!r}: expected a voxel size such as 20um or 20,20,25um") from None
        values = values * 3 if len(values) == 1 else values
    if len(values) != 3 or not all(math.isfinite(v) and v > 0 for v in values):
        raise InputError(f"--resample {text!r}: a voxel size is one or three positive finite numbers")
    f = 1.0 if given is None else factor(given, unit)
    return tuple(float(f"{v * f:.12g}") for v in values)  # 0.02mm in um: 20, not 20.000000000000004


def has_unit(element_size=None, roi=None, roi_unit: str | None = None) -> bool:
    """Whether an element size or a ROI is given in a physical unit (so the reference's voxel
    size is needed): ``"60um"``, ``roi_unit="um"`` or a ROI with a unit suffix."""
    if roi_unit is not None and str(roi_unit).lower() not in ("vx", "voxel", "voxels"):
        return True
    if isinstance(element_size, str) and parse_length(element_size)[1] is not None:
        return True
    return isinstance(roi, str) and bool(roi.strip()) and not roi.strip()[-1:].isdigit()


def lengths_in_voxels(element_size, roi=None, *, roi_unit: str | None = None, reference=None,
                      level: int = 0) -> tuple[int | None, object, list[str]]:
    """The element size and ROI of a correlation in voxels, as :func:`chunkdic.correlate`,
    :func:`chunkdic.series` and the ``--element-size``/``--roi``/``--roi-unit`` options take them.

    Parameters
    ----------
    element_size : int, str or None
        Voxels of ``level`` (``16``, ``"16"``) or a physical length (``"80um"``, ``"0.08mm"``);
        ``None``: left as is (taken from a ``Settings``).
    roi : str, sequence or None
        ``"z0:z1,y0:y1,x0:x1"`` in level-0 voxels, in ``roi_unit``, or with a unit suffix
        (``"0:500,0:500,0:500um"``); a sequence of pairs is in voxels and left as is.
    roi_unit : str, optional
        Unit of a ROI string without suffix (``"um"``).
    reference : path or array, optional
        The reference scan; opened (:func:`chunkdic.io.scan.open_scan`) only when a length
        has a unit, for its voxel size and unit.
    level : int
        The pyramid level the element size is in.

    Returns
    -------
    element_size : int or None
    roi : str, sequence or None
        In level-0 voxels.
    notes : list of str
        One line per conversion made (``"--element-size 80um = 8.000 voxels of level 0: using 8 …"``).
    """
    if roi_unit is not None and roi is None:
        raise InputError(f"a ROI unit ({roi_unit}) without a ROI")
    if roi is not None and not isinstance(roi, str) and roi_unit is not None:
        raise InputError("roi_unit applies to a ROI given as a string 'z0:z1,y0:y1,x0:x1'")
    scan = None
    if has_unit(element_size, roi, roi_unit):

        scan = reference if hasattr(reference, "voxel_size") else open_scan(reference)
    notes = []
    if element_size is not None and not isinstance(element_size, bool) and isinstance(element_size, (str, int, float)):
        if isinstance(element_size, str):
            element_size, note = element_size_voxels(element_size, scan, level)
            if note:
                notes.append(note)
        elif float(element_size) == int(element_size):  # 16.0 -> 16; 16.5 left for Settings to refuse
            element_size = int(element_size)
    if isinstance(roi, str):
        roi, note = roi_voxels(roi, scan, roi_unit)
        if note:
            notes.append(note)
    return element_size, roi, notes


#: two voxel sizes are the same within this relative difference (the metadata's round-off)
SAME_SIZE = 1e-6


def _metres(scan) -> tuple[float, float, float] | None:
    """``scan``'s level-0 voxel size in metres (its unit unknown: in its own unit), or None."""
    vs = getattr(scan, "voxel_size", None)
    if not vs:
        return None
    unit = normalize_unit(getattr(scan, "unit", None)) if getattr(scan, "unit", None) else None
    scale = METERS.get(unit, 1.0) if unit else 1.0
    return tuple(float(v) * scale for v in vs)


def _shown(scan, sep: str = " x ", space: str = " ") -> str:
    """``scan``'s voxel size as text: ``20 micrometer``, ``20 x 21 x 20 micrometer``."""
    vs = tuple(float(v) for v in scan.voxel_size)
    size = f"{vs[0]:g}" if max(vs) - min(vs) <= SAME_SIZE * max(vs) else sep.join(f"{v:g}" for v in vs)
    return f"{size}{space}{getattr(scan, 'unit', None) or ''}".rstrip()


def check_voxel_sizes(scans: dict) -> None:
    """Refuse, in one line, scans to be compared voxel to voxel whose voxel sizes differ.

    A correlation reads a voxel of one scan against the voxel of the same index in the other:
    an unmoved specimen rescanned at 21 µm instead of 20 µm reads as a 4.7 % strain. Scans
    without a voxel size (a ``.npy``, an array) cannot be compared and pass; so does a scan
    whose unit is unknown against one whose unit is known when the numbers agree.

    Parameters
    ----------
    scans : dict
        ``{name: scan}`` in the order of the message (``"the reference"``, ``"the deformed
        scan"``, ``"series scan 3 (s3.zarr)"``); each scan has ``voxel_size`` (z, y, x) and
        ``unit``. The first one with a voxel size is the one the others must match.

    Raises
    ------
    InputError
        Naming both sizes and how to resample (``chunkdic ingest --resample``).
    """
    sized = [(name, scan, _metres(scan)) for name, scan in scans.items() if _metres(scan) is not None]
    if len(sized) < 2:
        return
    name0, scan0, size0 = sized[0]
    for name, scan, size in sized[1:]:
        units = (normalize_unit(scan0.unit) if scan0.unit else None, normalize_unit(scan.unit) if scan.unit else None)
        comparable = None not in units or units[0] == units[1]
        a, b = (size0, size) if comparable else (tuple(scan0.voxel_size), tuple(scan.voxel_size))
        if all(abs(x - y) <= SAME_SIZE * max(abs(x), abs(y)) for x, y in zip(a, b)):
            continue
        target = _shown(scan0, ",", "")
        raise InputError(f"{name} has voxel size {_shown(scan)}, {name0} {_shown(scan0)}: compared voxel to voxel, "
                         f"the difference would read as strain; resample it onto {name0}'s voxel size first "
                         f"(chunkdic ingest SCAN OUT --resample {target}), or, if a recorded voxel size is wrong, "
                         "ingest the scan again with the right --voxel-size")
