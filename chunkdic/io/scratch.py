"""Scratch directories: made with an owner record, kept for a resume, adopted or reclaimed.

Inputs that are not on disk, missing pyramid levels and a correlation's prepared scans go
into a scratch directory ``chunkdic-XXXX`` under ``chunkdic.scratch-directory``, which
records its owner (:data:`SCRATCH_MARKER`: host, pid, start time; :mod:`chunkdic.io.owners`).
Only ``chunkdic-*`` directories holding that record are ever removed or adopted here, so
nothing else in a shared temporary directory is touched.

A dead run's scratch directory is either reclaimed (removed) or, by a run that resumes the
very same run (:func:`adopt_scratch`: the identity recorded in its marker), adopted. Both
begin with a rename of the directory, so of a reclaimer and an adopter (or two of either)
exactly one gets it: the reclaimer renames it to ``.chunkdic-reclaimed-…`` before removing
it, the adopter to ``.chunkdic-adopting-HOST-PID-…`` (a name that tells its live owner) before
writing its own owner into the marker and giving it a ``chunkdic-*`` name again.

A correlation's scratch also records the output and run it serves (``resume``): while that
output holds the run's checkpoint, marked incomplete (the same command resumes it), the
directory is *kept for the resume* and no other run reclaims it; only the run that writes
that output (resuming, or starting it over) adopts or releases it. Once the output is
complete, removed or replaced by another run's, the next run reclaims it as any other.
"""

from __future__ import annotations

import json
import logging
import os
import re
import socket
import tempfile
import uuid
from dataclasses import asdict
from pathlib import Path

from .. import config
from ..errors import InputError
from .jsonfile import json_dict, read_json_object
from .owners import Owner, host_tag
from .owntree import remove

log = logging.getLogger(__name__)

__all__ = ["SCRATCH_MARKER", "scratch_root", "make_scratch", "adopt_scratch", "leave_scratch", "reclaim_stale_scratch",
           "interrupted_run_of", "reclaimable_scratch_bytes", "kept_scratch", "directory_bytes"]

SCRATCH_PREFIX = "chunkdic-"
SCRATCH_MARKER = ".chunkdic-scratch.json"
#: a dead run's scratch directory being removed (renamed first: one reclaimer wins)
RECLAIMED_TAG = ".chunkdic-reclaimed-"
#: a dead run's scratch directory being adopted by a live run (``…HOST-PID-XXXXXXXX``)
ADOPTING_TAG = ".chunkdic-adopting-"


def scratch_root() -> Path:
    """The root under which scratch directories are made (``chunkdic.scratch-directory``)."""
    return Path(config.get("scratch-directory") or tempfile.gettempdir())


def make_scratch(prefix: str = SCRATCH_PREFIX, *, run: str | None = None,
                 resume: tuple[str, str] | None = None) -> Path:
    """A new scratch directory under ``chunkdic.scratch-directory`` that records its owner.

    Stale scratch of dead runs in the same root is reclaimed first (not what is kept for
    another output's resume; this run's own output's is released: :func:`reclaim_stale_scratch`).
    ``run``: an identity of what the directory will hold (a correlation's output, fingerprint
    and scratch layout), recorded in the marker so that a run resuming the same correlation
    after this process dies can adopt it (:func:`adopt_scratch`). ``resume``: ``(output,
    fingerprint)`` of that correlation; while ``output`` holds that run's interrupted
    checkpoint the directory is kept for its resume (:func:`interrupted_run_of`). Raises
    InputError if the root cannot be written.
    """
    root = scratch_root()
    if not root.is_dir():
        raise InputError(f"scratch directory {root} does not exist (chunkdic.scratch-directory)")
    reclaim_stale_scratch(root, release=None if resume is None else resume[0])
    path = None
    try:
        path = Path(tempfile.mkdtemp(prefix=prefix, dir=root))
        _write_marker(path, run, resume)
    except OSError as exc:
        if path is not None:  # made, but its owner record could not be written (a full disk)
            remove(path)
        raise _unwritable(root, exc) from None
    return path


def _unwritable(root: Path, exc: OSError) -> InputError:
    return InputError(f"cannot write in the scratch directory {root}: {exc.strerror} "
                      "(set chunkdic.scratch-directory, e.g. DASK_CHUNKDIC__SCRATCH_DIRECTORY)")


def _write_marker(path: Path, run: str | None, resume=None) -> None:
    """The owner record of scratch directory ``path``: this process (and ``run``, and the
    ``(output, fingerprint)`` it is kept for while interrupted), replaced atomically."""
    record = asdict(Owner.me())
    if run is not None:
        record["run"] = run
    if resume is not None:
        record["resume"] = {"output": _resolved(resume[0]), "fingerprint": str(resume[1])}
    tmp = path / f"{SCRATCH_MARKER}.{uuid.uuid4().hex[:8]}"
    tmp.write_text(json.dumps(record))
    os.replace(tmp, path / SCRATCH_MARKER)


def _resolved(output) -> str:
    """``output``'s absolute path, links resolved where they can be: a path under a loop of
    symbolic links stays as given (absolute), for the output checks to refuse in one line."""
    try:
        return str(Path(output).resolve())
    except (OSError, RuntimeError):  # RuntimeError: Python 3.11's "Symlink loop"
        return os.path.abspath(output)


def interrupted_run_of(output, fingerprint: str) -> bool:
    """Whether ``output`` holds the checkpoint of the correlation ``fingerprint``, marked
    incomplete: the run that the same command resumes. Read from the group's metadata
    (``zarr.json``, attribute ``chunkdic``: ``complete`` false, the same ``fingerprint``);
    anything unreadable answers False."""
    try:
        meta = read_json_object(Path(output) / "zarr.json")
        attrs = json_dict(json_dict(meta.get("attributes"))["chunkdic"])
        return attrs.get("complete") is False and attrs.get("fingerprint") == fingerprint
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return False


def _gone(info: dict) -> bool:
    """The run that made a scratch directory (owner record ``info``) is over: its process is
    dead (:meth:`Owner.is_dead`), or it ended and left the directory for a resume
    (:func:`leave_scratch`: ``released``; an interrupted call in a process that goes on)."""
    return info.get("released") is True or Owner.from_dict(info).is_dead()


def leave_scratch(path: Path) -> None:
    """Mark scratch directory ``path``, of this process's run that has just ended interrupted
    (Ctrl-C, a lost cluster), as left for the resume: its owner record says ``released``, so
    the run that resumes adopts it even in this very process (a notebook's second call), and
    other runs keep it while its output holds the interrupted checkpoint (:func:`_kept_for_resume`).
    The caller has stopped every task that could write into it."""
    info = _read_marker(Path(path))
    if info is None:
        return
    tmp = Path(path) / f"{SCRATCH_MARKER}.{uuid.uuid4().hex[:8]}"
    tmp.write_text(json.dumps({**info, "released": True}))
    os.replace(tmp, Path(path) / SCRATCH_MARKER)


def _left_for(info: dict, output: str | None) -> bool:
    """A scratch directory another host's run made for ``output`` (resolved path; None: no).
    The owner check cannot see another host's processes, but the caller holds the lock of
    ``output`` (one writer per output): the run that made it is over (dead, or its lock was
    removed by a user who knew it was), so the caller may adopt or remove it."""
    kept = info.get("resume")
    return (output is not None and isinstance(kept, dict) and kept.get("output") == output
            and str(info.get("host")) != socket.gethostname())


def _kept_for_resume(info: dict, release: str | None) -> bool:
    """A dead run's scratch (owner record ``info``) stays for the resume of its output: the
    output still holds that run's interrupted checkpoint, and the caller is not the run that
    writes that output (``release``: its resolved path), which adopts or releases it."""
    kept = info.get("resume")
    try:
        output, print_ = str(kept["output"]), str(kept["fingerprint"])
    except (KeyError, TypeError):
        return False
    return output != release and interrupted_run_of(output, print_)


def directory_bytes(path) -> int:
    """Bytes of the files under ``path`` (their sizes; links not followed; unreadable ones skipped)."""
    total = 0
    for parent, _, files in os.walk(path):
        for name in files:
            try:
                total += os.lstat(os.path.join(parent, name)).st_size
            except OSError:
                pass
    return total


def reclaimable_scratch_bytes(root: Path | None = None, *, release=None) -> int:
    """Bytes a run starting now frees or reuses in the scratch root: the ``chunkdic-*``
    directories of dead runs that it reclaims (:func:`reclaim_stale_scratch` with the same
    ``release``) or adopts. The plan counts them as free disk: on a resume, the interrupted
    run's scratch fills the disk it needs (35 GB of 37 at 2048³), yet it is that very data."""
    root = scratch_root() if root is None else Path(root)
    release = None if release is None else _resolved(release)
    try:
        entries = [e for e in root.iterdir() if e.name.startswith(SCRATCH_PREFIX)]
    except OSError:
        return 0
    total = 0
    for entry in entries:
        info = _read_marker(entry)
        if info is not None and (_gone(info) or _left_for(info, release)) and not _kept_for_resume(info, release):
            total += directory_bytes(entry)
    return total


def kept_scratch(root: Path | None = None) -> list[tuple[Path, str, int]]:
    """The scratch directories under ``root`` kept for the resume of their outputs
    (:func:`_kept_for_resume`): ``(directory, output, bytes)``, largest first. A run refused
    for lack of disk names them: resuming or removing those outputs frees them."""
    root = scratch_root() if root is None else Path(root)
    try:
        entries = [e for e in root.iterdir() if e.name.startswith(SCRATCH_PREFIX)]
    except OSError:
        return []
    kept = []
    for entry in entries:
        info = _read_marker(entry)
        if info is not None and _gone(info) and _kept_for_resume(info, None):
            kept.append((entry, str(info["resume"]["output"]), directory_bytes(entry)))
    return sorted(kept, key=lambda k: -k[2])


def _own_directory(entry: Path) -> bool:
    """``entry`` is a directory (not a link to one) of this process's user."""
    try:
        return not entry.is_symlink() and entry.is_dir() and entry.stat().st_uid == os.getuid()
    except OSError:
        return False


def _read_marker(entry: Path) -> dict | None:
    """The owner record of a directory chunkdic made (a real directory of this user), else None."""
    try:
        if not _own_directory(entry):
            return None
        info = read_json_object(entry / SCRATCH_MARKER)
        Owner.from_dict(info)
        return info
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def adopt_scratch(run: str, root: Path | None = None, *, resume: tuple[str, str] | None = None) -> Path | None:
    """Claim the scratch directory a dead run of the same ``run`` left under ``root``, or None.

    Only a ``chunkdic-*`` directory holding chunkdic's owner record, whose owner is known
    dead (:meth:`Owner.is_dead`: same host, no such process) and whose recorded ``run``
    equals ``run`` is adopted; its stores are then checked one by one by their users (a
    store is reused only when marked complete and every chunk file is whole). The
    directory is renamed first (one of several recovering runs wins), its marker made this
    process's, and it gets a new ``chunkdic-*`` name. Other dead runs' directories are
    left to :func:`reclaim_stale_scratch` (:func:`make_scratch` calls it). ``resume``:
    ``(output, fingerprint)`` of the caller, which holds the lock of that output: recorded in
    the new marker, as :func:`make_scratch` does (kept for the resume again should this run
    be interrupted too); and a directory another host's run made for that output is adopted
    too, though its owner cannot be checked from here (:func:`_left_for`: the lock says that
    run is over).
    """
    root = scratch_root() if root is None else Path(root)
    try:
        entries = sorted(e for e in root.iterdir() if e.name.startswith(SCRATCH_PREFIX))
    except OSError:
        return None
    host = host_tag()
    mine = None if resume is None else _resolved(resume[0])
    for entry in entries:
        info = _read_marker(entry)
        if info is None or info.get("run") != run or not (_gone(info) or _left_for(info, mine)):
            continue
        claimed = root / f"{ADOPTING_TAG}{host}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        try:
            os.rename(entry, claimed)  # fails when another run reclaimed or adopted it first
        except OSError:
            continue
        final = root / f"{SCRATCH_PREFIX}{uuid.uuid4().hex[:8]}"
        try:
            _write_marker(claimed, run, resume)
            os.rename(claimed, final)
        except OSError as exc:
            remove(claimed)
            raise _unwritable(root, exc) from None
        log.info("adopted the scratch directory %s of the interrupted run (%s %s) as %s", entry,
                 Owner.from_dict(info).describe(), "ended" if info.get("released") is True else "is dead", final)
        return final
    return None


def reclaim_stale_scratch(root: Path | None = None, *, release=None) -> list[Path]:
    """Remove ``chunkdic-*`` scratch directories under ``root`` whose owner is dead.

    Only directories holding chunkdic's owner record are considered, so nothing else in a
    shared temporary directory is ever touched. A directory kept for the resume of its
    output (that output holds the dead run's interrupted checkpoint) stays, unless its
    output is ``release``: the caller writes that output (it holds its lock), so it adopted
    that scratch already or starts the run over; such a directory goes even when another
    host's run made it (:func:`_left_for`). Each is renamed to ``.chunkdic-reclaimed-…``
    before it is removed (so that an adopter, :func:`adopt_scratch`, never gets a directory
    half removed); such leftovers of a reclaimer killed while removing, and directories a
    dead adopter had claimed (``.chunkdic-adopting-HOST-PID-…``), go too.
    """
    root = scratch_root() if root is None else Path(root)
    removed = []
    try:
        entries = list(root.iterdir())
    except OSError:
        return removed
    host = host_tag()
    release = None if release is None else _resolved(release)
    claim = re.compile(re.escape(f"{ADOPTING_TAG}{host}-") + r"(\d+)-[0-9a-f]{8}$")
    for entry in entries:
        if entry.name.startswith(RECLAIMED_TAG):
            if _own_directory(entry):
                remove(entry)  # only a reclaimer names so: one died while removing it (or removes it now)
            continue
        m = claim.match(entry.name)
        if m is not None:
            dead = Owner(socket.gethostname(), int(m.group(1))).is_dead()  # the claimant, named
        elif entry.name.startswith(SCRATCH_PREFIX):
            info = _read_marker(entry)
            dead = info is not None and (_gone(info) or _left_for(info, release))
            if dead and _kept_for_resume(info, release):
                log.info("kept the scratch directory %s of the interrupted run of %s (for its resume)", entry,
                         info["resume"]["output"])
                continue
        else:
            continue
        if not dead:
            continue
        grave = root / f"{RECLAIMED_TAG}{uuid.uuid4().hex[:8]}"
        try:
            os.rename(entry, grave)  # of two reclaimers (or a reclaimer and an adopter) one wins
        except OSError:
            continue
        remove(grave)
        removed.append(entry)
        log.info("reclaimed the scratch directory %s of a dead run", entry)
    return removed
