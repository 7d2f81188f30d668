"""Who made a path: the process identity (host, pid, start time) chunkdic records, and
whether that process is still alive.

Every file or directory that a chunkdic run leaves behind while it works (a lock file
:mod:`chunkdic.io.locks`, a staged output :mod:`chunkdic.io.siblings`, a scratch directory
:mod:`chunkdic.io.scratch`) records its owner. The start time tells a live owner from a dead
one whose pid was reused. A leftover is reclaimed only when its owner is known dead: same
host, and no process with that pid and start time. A leftover of another host is never
touched (that host may be alive and share the file system).
"""

from __future__ import annotations

import os
import re
import socket
from dataclasses import dataclass

from .jsonfile import json_int

__all__ = ["Owner", "host_tag"]


def host_tag() -> str:
    """This host's name as it appears in chunkdic's file names (``[A-Za-z0-9_]`` only)."""
    return re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname())


def _stat_fields(path: str) -> list[str] | None:
    """The fields of a ``/proc/…/stat`` file after the command name (state first), else None."""
    try:
        with open(path) as fh:
            stat = fh.read()
    except OSError:
        return None
    # the command name (field 2) may hold spaces and parentheses: split after the last ')'
    return stat.rsplit(")", 1)[1].split()


def _start_time(pid: int) -> str | None:
    """Start time of process ``pid`` in clock ticks since boot (Linux), else None."""
    fields = _stat_fields(f"/proc/{pid}/stat")
    return None if fields is None else fields[19]


def _exited(pid: int) -> bool:
    """Whether process ``pid`` has exited but is not yet reaped by its parent (a zombie: every
    thread in state ``Z``/``X``, Linux). Such a process holds no file and writes nothing, but
    ``kill(pid, 0)`` still succeeds: a run killed by ``kill -9`` from a parent that has not
    waited for it yet (a notebook's ``Popen``, a batch script's background job) is dead."""
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        tasks = [str(pid)]
    states = [_stat_fields(f"/proc/{pid}/task/{t}/stat") for t in tasks] or [_stat_fields(f"/proc/{pid}/stat")]
    return all(f is not None and f[0] in ("Z", "X") for f in states)


#: the largest pid any kernel hands out (Linux: 2**22); a record naming a larger one is not an owner
_PID_MAX = 1 << 22


@dataclass(frozen=True)
class Owner:
    """A process: ``host``, ``pid`` and its ``start`` time (None where unknown)."""

    host: str
    pid: int
    start: str | None = None

    @classmethod
    def me(cls) -> "Owner":
        return cls(socket.gethostname(), os.getpid(), _start_time(os.getpid()))

    @classmethod
    def from_dict(cls, d: dict) -> "Owner":
        """The owner an owner record names; ``ValueError`` for a record that names none (not an
        object, a pid that is not a positive integer within the kernel's range, ``1e400``)."""
        if not isinstance(d, dict):
            raise ValueError("an owner record is a JSON object")
        pid = json_int(d.get("pid"), "pid")
        if not 0 < pid <= _PID_MAX:
            raise ValueError(f"pid {pid} is out of range")
        start = d.get("start")
        return cls(str(d["host"]), pid, None if start is None else str(start))

    def is_dead(self) -> bool:
        """True only when this owner is known dead (same host, no such live process)."""
        if self.host != socket.gethostname() or not 0 < self.pid <= _PID_MAX:
            return False  # another host's, or a name no process has (never judged dead)
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return True
        except PermissionError:  # alive, someone else's
            return False
        if _exited(self.pid):
            return True  # killed (or ended), not yet reaped by its parent: whoever it was, it is dead
        if self.start is not None:
            now = _start_time(self.pid)
            return now is not None and now != self.start  # the pid was reused
        return False

    def describe(self) -> str:
        return f"pid {self.pid} on {self.host}"
