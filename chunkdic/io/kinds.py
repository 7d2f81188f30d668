"""What chunkdic wrote: the kinds of its outputs and how each is recognised on disk.

Stores carry ``attrs["chunkdic"]["kind"]`` in their ``zarr.json`` (results and scans
written before the attribute existed are recognised by their other attributes); folders
carry a marker file (:data:`MARKER`, JSON ``{"kind": ..., "complete": ...}``); files are
recognised by their header (a node table by its column line, its JSON sidecar by its
``kind``). :mod:`chunkdic.io.outputs` replaces (``--overwrite``) only what
:func:`kind_of` recognises as the same kind.
"""

from __future__ import annotations

import fnmatch
import json
import os
from dataclasses import dataclass
from pathlib import Path

__all__ = ["VTU_MARK", "VTK_TITLE", "MARKER", "Kind", "KINDS", "kind_of", "store_kind", "ours_in_folder", "mark_folder"]

#: marker file of the folders chunkdic writes: JSON ``{"kind": ..., "complete": ...}``
MARKER = ".chunkdic.json"


@dataclass(frozen=True)
class Kind:
    """What an output is: a Zarr ``store``, a ``folder`` of files, or one ``file``."""

    name: str
    form: str
    label: str
    entries: tuple[str, ...] = ()   # folder: glob patterns of the entries it writes
    suffixes: tuple[str, ...] = ()  # file: required suffixes (empty: any)


_SYNTH = ("ref.zarr", "def.zarr", "field.json", "field.json.tmp", "def.fourier.tmp.zarr")
KINDS: dict[str, Kind] = {k.name: k for k in (
    Kind("result", "store", "result"),
    Kind("scan", "store", "scan"),
    Kind("corrected", "store", "corrected-image group"),
    Kind("fields", "store", "fields image"),
    Kind("mask", "store", "mask labels image"),
    Kind("series", "store", "loading series"),
    Kind("figures", "folder", "figures folder",
         ("cut_x.png", "cut_y.png", "cut_z.png", "residual.png", "uz_map.png", "epszz_map.png", "gap.png")),
    Kind("table", "folder", "table folder", ("zoi_table.md", "zoi_table.csv")),
    Kind("cutcheck", "folder", "cut-check folder", ("cutcheck.png", "cutcheck.pdf", "cutcheck.svg", "cutcheck.json")),
    Kind("uncertainty", "folder", "uncertainty folder",
         ("uncertainty.csv", "uncertainty.md", "uncertainty.png", "shifted.zarr", "shifted.zarr.passes",
          "result-ell*.zarr", "scan-*.zarr")),
    Kind("resolution", "folder", "resolution folder",
         ("resolution.csv", "resolution.json", "resolution.md", "reference.zarr", "shifted.zarr", "shifted.zarr.passes",
          "translated.zarr", "star-ell*.zarr", "star-ell*.csv", "result-translated-ell*.zarr",
          "result-star-ell*.zarr", "scan-*.zarr")),
    Kind("sweep", "folder", "sweep folder", ("result-ell*.zarr", "zoi_table.md", "zoi_table.csv", "uncertainty")),
    Kind("gauge", "folder", "gauge folder", ("gauge.csv", "gauge.json", "gauge.png", "gauge.pdf", "gauge.svg")),
    Kind("cracks", "folder", "cracks folder", ("cracks.vtu", "cracks.csv", "cracks.json", "cracks-labels.zarr")),
    Kind("displacements", "store", "OME-NGFF displacement field"),
    Kind("pvd", "folder", "ParaView series folder", ("series.pvd", "step-*.vtu")),
    Kind("synth", "folder", "synthetic pair folder", _SYNTH),
    Kind("demo", "folder", "demo folder", _SYNTH + ("result.zarr",)),
    Kind("vtk", "file", "VTK file", suffixes=(".vtu", ".vtk")),
    Kind("csv", "file", "node table"),
    Kind("csv-meta", "file", "node table sidecar", suffixes=(".json",)),
)}

#: first line of a node table (``chunkdic.export.meshfiles.CSV_COLUMNS``); tables written before the
#: JSON sidecar began with a comment line ``# positions …``
CSV_HEADER = b"iz,iy,ix,z,y,x,Uz,Uy,Ux,"

#: chunkdic's own mark in the VTK files it writes (``chunkdic.export.meshfiles.write_vtk``): an
#: XML comment right after meshio's in a ``.vtu``, the title line (line 2) of a legacy
#: ``.vtk``. meshio's own signature is not enough: any meshio user's file carries it.
VTU_MARK = b"<!--This file was written by chunkdic (export, VTK)-->"
VTK_TITLE = b"written by chunkdic (export, VTK)"


# --------------------------------------------------------------------------- what is there


def _zarr_attrs(path: Path) -> dict | None:
    """``attributes["chunkdic"]`` of the Zarr v3 node at ``path`` (None if not one of ours)."""
    try:
        meta = json.loads((path / "zarr.json").read_text())
    except (OSError, ValueError):
        return None
    ck = (meta.get("attributes") or {}).get("chunkdic")
    return dict(ck) if isinstance(ck, dict) else None


def store_kind(path: Path) -> tuple[str | None, bool]:
    """Kind and completeness of a chunkdic Zarr store (results written before the
    ``kind`` attribute existed are recognised by their attributes)."""
    ck = _zarr_attrs(path)
    if ck is None:
        return None, False
    kind = ck.get("kind")
    if kind is None:  # legacy stores
        if "fingerprint" in ck or "element_size" in ck:
            kind = "result"
        elif "description" in ck and (path / "corrected").is_dir():
            kind = "corrected"
        elif ck.get("scratch"):
            kind = "scratch"
        elif "voxel_size" in ck:
            kind = "scan"
        elif "fourier_shift" in ck:
            kind = "shifted"
    return kind, bool(ck.get("complete", True))


def _read_marker(path: Path) -> dict | None:
    try:
        d = json.loads((path / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) and "kind" in d else None


def ours_in_folder(path: Path, kind: Kind) -> tuple[list[Path], list[Path]]:
    """Entries of folder ``path`` that ``kind`` writes, and the others (marker excluded)."""
    ours, others = [], []
    for entry in sorted(path.iterdir()):
        if entry.name == MARKER:
            continue
        if any(fnmatch.fnmatchcase(entry.name, pat) for pat in kind.entries):
            # a store under one of our names must be one of ours too
            if entry.name.endswith(".zarr") and entry.is_dir() and store_kind(entry)[0] is None:
                others.append(entry)
            else:
                ours.append(entry)
        else:
            others.append(entry)
    return ours, others


def _file_kind(path: Path) -> str | None:
    try:
        with open(path, "rb") as fh:
            head = fh.read(1024)
    except OSError:
        return None
    if path.suffix.lower() in (".vtu", ".vtk") and _vtk_marked(head):
        return "vtk"
    if head.startswith(b"# positions"):  # tables written before the sidecar: chunkdic's own comment line
        return "csv"
    if head.startswith(CSV_HEADER) and _json_kind(path.with_name(path.name + ".json")) == "csv-meta":
        return "csv"  # the column line alone could be anyone's: its chunkdic sidecar proves it
    if path.suffix.lower() == ".json" and _json_kind(path) == "csv-meta":
        return "csv-meta"
    return None


def _vtk_marked(head: bytes) -> bool:
    """A VTK file chunkdic wrote: its mark in the header (:data:`VTU_MARK`, :data:`VTK_TITLE`)."""
    if head.startswith(b"<?xml"):
        lines = head.split(b"\n")[:4]
        return any(line.strip() == VTU_MARK for line in lines)
    lines = head.split(b"\n")
    return head.startswith(b"# vtk DataFile") and len(lines) > 1 and lines[1].startswith(VTK_TITLE)


def _json_kind(path: Path) -> str | None:
    """``kind`` of a small JSON object file (the node table's sidecar), else None."""
    try:
        if path.stat().st_size > 1 << 20:
            return None
        d = json.loads(path.read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    return d.get("kind") if isinstance(d, dict) and isinstance(d.get("kind"), str) else None


def kind_of(path) -> tuple[str | None, bool]:
    """What chunkdic wrote at ``path``: ``(kind, complete)``, ``(None, False)`` otherwise.

    A folder's kind comes from its marker (:data:`MARKER`); a store's from its
    ``chunkdic`` attributes; a file's from its header.
    """
    p = Path(path)
    if p.is_symlink() or not p.exists():
        return None, False
    if p.is_dir():
        if (p / "zarr.json").is_file():
            return store_kind(p)
        marker = _read_marker(p)
        if marker is not None:
            return str(marker["kind"]), bool(marker.get("complete", False))
        return None, False
    if not p.is_file():  # a FIFO, socket or device: never opened (reading a FIFO waits for ever)
        return None, False
    return _file_kind(p), True


def mark_folder(path, kind: str, *, complete: bool) -> None:
    """Write the folder marker (:data:`MARKER`) of ``kind``."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        v = version("chunkdic")
    except PackageNotFoundError:
        v = "unknown"
    tmp = Path(path) / (MARKER + ".tmp")
    tmp.write_text(json.dumps({"kind": kind, "complete": bool(complete), "chunkdic_version": v}))
    os.replace(tmp, Path(path) / MARKER)
