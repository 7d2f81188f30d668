"""The hidden siblings chunkdic names after an output: its lock and its staged copies.

An output ``NAME`` has a one-writer lock ``.NAME.chunkdic-lock`` (:mod:`chunkdic.io.locks`)
and, while it is written, a staged copy ``.NAME.chunkdic-partial-HOST-PID-XXXXXX[.suffix]``
renamed into place at the end (:mod:`chunkdic.io.outputs`). This module derives those names
(shortened to fit the file system) and reclaims the staged copies of dead runs. Only entries
that carry these names, of this host, whose owner pid is dead, are ever removed here.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import socket
import uuid
from pathlib import Path

from .owners import Owner, host_tag
from .owntree import remove

log = logging.getLogger(__name__)

__all__ = ["LOCK_SUFFIX", "PARTIAL_TAG", "name_limits", "hidden_sibling", "partial_name", "final_name",
           "reclaim_stale_partials"]

LOCK_SUFFIX = ".chunkdic-lock"
PARTIAL_TAG = ".chunkdic-partial-"

#: bytes kept free in a derived name for the longest suffix added to it later (the
#: ``.stale-XXXXXXXX`` of a lock taken over)
_SPARE = 16


def name_limits(directory) -> tuple[int, int]:
    """``(NAME_MAX, PATH_MAX)`` in bytes for ``directory``'s file system (255, 4096 where unknown)."""
    limits = []
    for key, default in (("PC_NAME_MAX", 255), ("PC_PATH_MAX", 4096)):
        try:
            limits.append(int(os.pathconf(directory, key)))
        except (OSError, ValueError):
            limits.append(default)
    return limits[0], limits[1]


def hidden_sibling(final: Path, stem: str, tail: str) -> Path:
    """``final.parent / ("." + stem + tail)``, or, when that name would be longer than the
    file system allows (a valid output name of 240 bytes plus ``.chunkdic-partial-HOST-…``),
    the same with the middle of ``stem`` replaced by a digest of the whole output name
    (``.aaaa~1f2e3d4c5b6aaaaa.chunkdic-lock``). Deterministic: two runs on one output derive
    the same lock name, and different outputs never share one. The end of ``stem`` is kept:
    the lock of a staged copy (``export --fields`` stages inside a staged copy) keeps the
    copy's ``…chunkdic-partial-HOST-PID-XXXXXX`` so that it is reclaimed with it."""
    name = f".{stem}{tail}"
    name_max = name_limits(final.parent if final.parent.is_dir() else ".")[0]
    budget = name_max - _SPARE
    if len(os.fsencode(name)) <= budget:
        return final.parent / name
    digest = "~" + hashlib.sha256(os.fsencode(final.name)).hexdigest()[:12] + "~"
    room = budget - len(os.fsencode(f".{digest}{tail}"))
    front, back = stem[:-96], stem[-96:]  # the end (a staged copy's owner) is cut last
    while len(os.fsencode(front + back)) > room:  # by characters: never a broken UTF-8 sequence
        if len(front) > 16 or not back:
            front = front[:-1]
        else:
            back = back[1:]
    return final.parent / f".{front}{digest}{back}{tail}"



def partial_name(final: Path) -> Path:
    """Name of a staged (half-written) version of ``final``: a hidden sibling that names
    its owner and keeps the suffix (writers such as meshio choose the format by it)."""
    return hidden_sibling(final, final.stem,
                          f"{PARTIAL_TAG}{host_tag()}-{os.getpid()}-{uuid.uuid4().hex[:6]}{final.suffix}")


def final_name(path) -> str:
    """The name a staged output will have once in place (``.x.chunkdic-partial-HOST-PID-XXXXXX.zarr``
    -> ``x.zarr``); other names unchanged. Metadata that records the store's own name uses it."""
    name = Path(path).name
    m = re.fullmatch(r"\.(.*)" + re.escape(PARTIAL_TAG) + r"[A-Za-z0-9_]+-\d+-[0-9a-f]{6}(\.[^.]*)?", name)
    return name if m is None else m.group(1) + (m.group(2) or "")


def reclaim_stale_partials(final: Path) -> list[Path]:
    """Remove the staged outputs of dead runs (this host) in the directory of ``final``:
    of ``final`` and of any other output there (a killed ``export --fields`` leaves one
    beside its output, which the next run of any command writing there reclaims). Only
    entries named as chunkdic's staged outputs whose owner pid is dead; returns them."""
    host = host_tag()
    # a staged copy, or the lock of one (an output staged inside a staged copy, as export
    # --fields does, locks that copy: its lock is orphaned with it)
    pattern = re.compile(r"\..+" + re.escape(f"{PARTIAL_TAG}{host}-") + r"(\d+)-[0-9a-f]{6}(\.[^.]*)?"
                         + f"({re.escape(LOCK_SUFFIX)})?$")
    removed = []
    try:
        entries = list(final.parent.iterdir())
    except OSError:
        return removed
    for entry in entries:
        m = pattern.match(entry.name)
        if m is None:
            continue
        pid = int(m.group(1))
        # no start time in a name: a live pid counts as the owner (never remove a live run's work)
        if Owner(socket.gethostname(), pid).is_dead():
            remove(entry)
            removed.append(entry)
            log.info("removed %s, left by a dead run", entry)
    return removed

