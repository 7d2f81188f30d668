"""One writer per output: the lock file ``.NAME.chunkdic-lock`` next to it.

The lock is created atomically (``O_EXCL``) and holds its owner's record
(:class:`chunkdic.io.owners.Owner`, JSON). A lock whose owner is dead (killed with SIGKILL,
machine rebooted) is taken over; a live owner's lock is refused with one line naming it. A
lock file that is not a lock (malformed JSON, a pid no process can have) is never taken
over: the run is refused, naming it.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import time
import uuid
from dataclasses import asdict
from pathlib import Path

from ..errors import DiskSpaceError, InputError
from .diskspace import DISK_ERRNOS
from .jsonfile import read_json
from .owners import Owner
from .owntree import remove
from .siblings import LOCK_SUFFIX, hidden_sibling

log = logging.getLogger(__name__)

#: a lock file younger than this that holds no record yet is being written by its owner, seconds
WRITING_SECONDS = 10.0

__all__ = ["OutputLock", "reclaim_stale_locks"]


class OutputLock:
    """One writer per output: an exclusive lock file next to it (``.NAME.chunkdic-lock``).

    The file is created atomically (``O_EXCL``) and holds the owner (JSON). A lock whose
    owner is dead (killed with SIGKILL, machine rebooted) is taken over; a live owner's
    lock is refused with one line naming it. Released (removed) on exit.
    """

    def __init__(self, output):
        out = Path(output)
        self.output = out
        self.path = hidden_sibling(out, out.name, LOCK_SUFFIX)
        self.held = False

    def acquire(self) -> "OutputLock":
        """Take the lock. Re-entrant within a process: when this process already holds the
        lock of the same output (``correlate`` holds it while ``Result.save`` stages the
        result), this handle does not own it and its :meth:`release` does nothing."""
        key = _lock_key(self.path)
        if key in _HELD:
            return self
        me = Owner.me()
        record = json.dumps({**asdict(me), "since": time.strftime("%Y-%m-%d %H:%M:%S"),
                             "output": str(self.output)})
        # a lock whose owner is still writing it (created, not yet holding its record) is waited
        # for: on a loaded machine the owner may be descheduled between the two steps
        deadline = time.monotonic() + WRITING_SECONDS + 5.0
        while time.monotonic() < deadline:
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                self._take_over_if_stale()
                continue
            except OSError as exc:
                raise _lock_error("create", self.path, exc) from None
            try:
                with os.fdopen(fd, "w") as fh:
                    fh.write(record)
            except OSError as exc:  # a full disk: the empty lock file would outlive the refusal
                remove(self.path)
                raise _lock_error("write", self.path, exc) from None
            self.held = True
            _HELD.add(key)
            return self
        raise InputError(f"output {self.output} is locked by {self.path} and the lock could not be taken")

    def live_owner(self) -> str | None:
        """Who holds this lock, if a live process (or one on another host) does: ``"pid 12 on
        host since …"``; None when the lock is free, stale, unreadable or held by this process.
        No side effects."""
        if _lock_key(self.path) in _HELD:
            return None
        try:
            info = read_json(self.path)
            owner = Owner.from_dict(info)
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            return None
        return None if owner.is_dead() else f"{owner.describe()} since {info.get('since', '?')}"

    def _take_over_if_stale(self) -> None:
        try:
            info = read_json(self.path)
            owner = Owner.from_dict(info)
        except FileNotFoundError:
            return  # released meanwhile: try again
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            age = time.time() - _mtime(self.path)
            if age < WRITING_SECONDS:  # being written right now by its owner
                time.sleep(0.2)
                return
            raise InputError(f"output {self.output} has an unreadable lock {self.path}: remove it if no "
                             "chunkdic run is writing this output") from None
        if not owner.is_dead():
            hint = "" if owner.host == socket.gethostname() else \
                f" (if that run is dead, remove {self.path})"
            raise InputError(f"output {self.output} is being written by another chunkdic run "
                             f"({owner.describe()} since {info.get('since', '?')}): wait for it to finish or "
                             f"stop it{hint}")
        # Rename first: of two runs recovering the same stale lock, only one rename succeeds.
        grave = self.path.with_name(self.path.name + f".stale-{uuid.uuid4().hex[:8]}")
        try:
            os.rename(self.path, grave)
        except FileNotFoundError:
            return
        remove(grave)
        log.info("took over the stale lock of %s (%s is dead)", self.output, owner.describe())

    def release(self) -> None:
        if self.held:
            _HELD.discard(_lock_key(self.path))
            remove(self.path)
            self.held = False

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


#: the lock files this process holds (resolved paths): :meth:`OutputLock.acquire` is re-entrant
_HELD: set[str] = set()


def _lock_key(path: Path) -> str:
    return os.path.join(os.path.realpath(path.parent), path.name)


def _mtime(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return time.time()



def reclaim_stale_locks(directory: Path) -> list[Path]:
    """Remove the locks in ``directory`` whose owner is dead (this host). A lock is taken over
    by the next run on its output; this is for the outputs no run will write again, such as
    a loading series' step that a killed run had just completed (the re-run skips it). The
    caller holds the lock of what contains ``directory``, so no live run can be taking one
    of them over meanwhile."""
    removed = []
    try:
        entries = [e for e in Path(directory).iterdir() if e.name.endswith(LOCK_SUFFIX)]
    except OSError:
        return removed
    for entry in entries:
        try:
            owner = Owner.from_dict(read_json(entry))
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            continue
        if owner.is_dead():
            remove(entry)
            removed.append(entry)
            log.info("removed the lock %s of a dead run (%s)", entry, owner.describe())
    return removed


def _lock_error(verb: str, path: Path, exc: OSError) -> InputError:
    """The one line for a lock that cannot be made; a disk error (a full disk) is a
    :class:`~chunkdic.errors.DiskSpaceError` with its cause, so that a command that keeps
    what it wrote on a full disk (``series``) says so here too."""
    message = f"cannot {verb} the lock {path}: {exc.strerror}"
    if exc.errno in DISK_ERRNOS:
        return DiskSpaceError(message, cause=f"{exc.strerror} ({path})")
    return InputError(message)

