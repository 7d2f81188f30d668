"""Reading the small JSON files chunkdic finds on disk, whoever wrote them.

Metadata (``zarr.json``), folder markers, lock files and scratch owner records are read
before chunkdic knows whether it wrote them. Any of them may be another program's, cut
short, or crafted: a list where an object belongs, numbers such as ``1e400`` (infinity),
nesting a million levels deep (Python's parser then raises ``RecursionError``, not a
``ValueError``), a FIFO that would block a reader for ever, or a file of gigabytes. Every
reader here answers such a file with ``ValueError`` (or ``OSError``), the two errors its
callers already handle, and hands back only what it promises (an object, an integer).
"""

from __future__ import annotations

import json
import math
import os
import stat

__all__ = ["MAX_JSON_BYTES", "read_json", "read_json_object", "json_int", "json_dict"]

#: larger than any metadata chunkdic writes (a result's ``zarr.json`` with its history: ~100 kB)
MAX_JSON_BYTES = 64 << 20


def read_json(path, *, max_bytes: int = MAX_JSON_BYTES):
    """The JSON document in file ``path``.

    Raises
    ------
    OSError
        The file cannot be read (missing, permissions).
    ValueError
        Not a regular file (a FIFO, a device: never opened), larger than ``max_bytes``, not
        UTF-8, not JSON, or nested too deeply to parse.
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO opened for reading must not wait for a writer
    with os.fdopen(fd, "rb") as fh:
        st = os.fstat(fh.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise ValueError(f"{os.fspath(path)} is not a regular file")
        if st.st_size > max_bytes:
            raise ValueError(f"{os.fspath(path)} holds {st.st_size} bytes, more than any metadata file")
        data = fh.read(st.st_size + 1)  # its size, not the bound: read(n) allocates n bytes first
    return loads(data)


def loads(data: bytes | str):
    """``json.loads`` whose every failure is a ``ValueError`` (a document nested too deeply included)."""
    try:
        return json.loads(data)
    except RecursionError:
        raise ValueError("JSON nested too deeply") from None
    except (UnicodeDecodeError, TypeError) as exc:
        raise ValueError(str(exc)) from None


def read_json_object(path, *, max_bytes: int = MAX_JSON_BYTES) -> dict:
    """:func:`read_json` of a document that must be an object (``ValueError`` otherwise)."""
    return json_dict(read_json(path, max_bytes=max_bytes), os.fspath(path))


def json_dict(value, what: str = "value") -> dict:
    """``value`` if it is a JSON object, else ``ValueError``."""
    if not isinstance(value, dict):
        raise ValueError(f"{what} is not a JSON object")
    return value


def json_int(value, what: str = "value") -> int:
    """``value`` as an int if it is a finite integral JSON number (not a bool), else ``ValueError``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{what} is not a number")
    if isinstance(value, float) and not (math.isfinite(value) and value.is_integer()):
        raise ValueError(f"{what} is not an integer")
    return int(value)
