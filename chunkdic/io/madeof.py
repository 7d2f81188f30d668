"""What an output was made of: one digest of a command's inputs and options, recorded in it.

A command run again on its own complete output (a batch job re-queued after a kill that
landed just after the commit, a script run twice) has nothing to do, as ``make``: it says so
and exits 0, writing nothing. To know that the output *is* its own, every output records a
digest of what made it (:func:`made_of`: the command, each input's identity and the options
that shape the output); :func:`already_made` compares. A correlation, a series and a
pyramid have their own fingerprints (:mod:`chunkdic.engine.checkpoint`); this is the same
for the others: ``ingest``, ``export`` and ``cutcheck`` name what shapes their outputs; for
the other commands the CLI digests its command line (:mod:`chunkdic.cli.rerun`) and declares
it for the output it names (:func:`making`), which :class:`~chunkdic.io.outputs.Outputs`
records there.

Where the digest lies, by the output's form (:mod:`chunkdic.io.kinds`): a store's
``attrs["chunkdic"]["made_of"]`` (its ``zarr.json``), a folder's marker, a JSON file's own
``made_of`` key (the node table's sidecar, which speaks for its table), a VTK file's header
(a comment line after chunkdic's mark in a ``.vtu``, the title line of a legacy ``.vtk``).
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import json
import os
import re
from pathlib import Path

from .jsonfile import json_dict, read_json_object
from .kinds import MARKER, VTK_TITLE, VTU_MARK, kind_of

__all__ = ["made_of", "path_identity", "recorded", "record", "already_made", "making", "made_here"]

_DIGEST = re.compile(rb"made_of=([0-9a-f]{32})")
#: the output being made and its digest, declared by the caller of an API function (:func:`making`)
_MAKING: contextvars.ContextVar[tuple[str, str] | None] = contextvars.ContextVar("chunkdic_making", default=None)


@contextlib.contextmanager
def making(path, digest: str):
    """Within: the output declared at ``path`` without a digest of its own records ``digest``
    (:func:`made_here`), so that the same command finds it its own next time."""
    token = _MAKING.set((os.path.realpath(path), digest))
    try:
        yield
    finally:
        _MAKING.reset(token)


def made_here(path) -> str | None:
    """The digest declared for ``path`` by an enclosing :func:`making`, or None."""
    current = _MAKING.get()
    return current[1] if current is not None and os.path.realpath(path) == current[0] else None


def path_identity(path) -> dict:
    """A cheap identity of an input on disk: its resolved path and, for every file under it,
    the size and modification time (a listing, nothing read). In-memory inputs: None."""
    if path is None or not isinstance(path, (str, os.PathLike)):
        return {"in-memory": True}
    p = Path(path)
    files = []
    if p.is_dir():
        for parent, _, names in os.walk(p):
            for name in names:
                try:
                    st = os.stat(os.path.join(parent, name))
                except OSError:
                    continue
                files.append((os.path.relpath(os.path.join(parent, name), p), st.st_size, st.st_mtime_ns))
    else:
        try:
            st = p.stat()
            files.append(("", st.st_size, st.st_mtime_ns))
        except OSError:
            pass
    return {"path": os.path.realpath(p), "files": sorted(files)}


def made_of(command: str, inputs, options: dict) -> str:
    """The digest (32 hex digits) of ``command`` run on ``inputs`` (paths) with ``options``
    (JSON-able: what shapes the output, not where it goes)."""
    doc = {"command": command, "inputs": [path_identity(p) for p in inputs], "options": options}
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()[:32]


def recorded(path) -> str | None:
    """The digest recorded in the output at ``path`` (None: none, or not readable)."""
    p = Path(path)
    try:
        if p.is_symlink() or not p.exists():
            return None
        if p.is_dir():
            meta = read_json_object(p / "zarr.json") if (p / "zarr.json").is_file() else \
                read_json_object(p / MARKER)
            holder = json_dict(json_dict(meta.get("attributes") or {}).get("chunkdic") or {}) \
                if (p / "zarr.json").is_file() else meta
            value = holder.get("made_of")
        elif p.suffix.lower() == ".json":
            value = read_json_object(p).get("made_of")
        elif p.suffix.lower() == ".csv":
            return recorded(p.with_name(p.name + ".json"))
        else:
            with open(p, "rb") as fh:
                m = _DIGEST.search(fh.read(4096))
            value = m.group(1).decode() if m else None
    except (OSError, ValueError):
        return None
    return value if isinstance(value, str) else None


def record(path, digest: str) -> None:
    """Write ``digest`` into the output at ``path`` (a store, a folder, a JSON file, a VTK file;
    a node table's digest goes into its sidecar, :func:`recorded`)."""
    p = Path(path)
    if p.is_dir():
        target = p / "zarr.json" if (p / "zarr.json").is_file() else p / MARKER
        doc = read_json_object(target)
        if target.name == "zarr.json":
            attrs = doc.setdefault("attributes", {})
            attrs["chunkdic"] = {**(attrs.get("chunkdic") or {}), "made_of": digest}
        else:
            doc["made_of"] = digest
        _replace(target, json.dumps(doc).encode())
    elif p.suffix.lower() == ".json":
        doc = read_json_object(p)
        _replace(p, json.dumps({**doc, "made_of": digest}).encode())
    elif p.suffix.lower() in (".vtu", ".vtk"):
        _replace(p, _vtk_with(p.read_bytes(), digest))


def _vtk_with(data: bytes, digest: str) -> bytes:
    """A VTK file's bytes with ``made_of=DIGEST`` in its header, after chunkdic's mark."""
    tag = f"made_of={digest}".encode()
    at = data.find(VTU_MARK)
    if at >= 0:  # XML: a comment line of its own after the mark's
        end = at + len(VTU_MARK)
        return data[:end] + b"\n<!--chunkdic " + tag + b"-->" + data[end:]
    at = data.find(VTK_TITLE)  # legacy: the title line (at most 256 characters)
    if at < 0:
        return data
    end = data.index(b"\n", at)
    line = (data[at:end][:256 - len(tag) - 1] + b" " + tag)
    return data[:at] + line + data[end:]


def _replace(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".made_of.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def already_made(path, kind: str, digest: str | None) -> bool:
    """Whether ``path`` holds a complete chunkdic output of ``kind`` recording ``digest``."""
    if digest is None:
        return False
    try:
        return kind_of(path) == (kind, True) and recorded(path) == digest
    except OSError:
        return False
