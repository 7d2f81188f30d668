"""Free disk before writing: how much a file system holds, and a refusal when an output cannot fit.

One idea: a command that knows how many bytes it will write compares them with the free
space of the file system that will hold them, *before* the first byte, and refuses in one
line (:class:`~chunkdic.errors.DiskSpaceError`, exit 2) naming the need, the free space and
what makes it fit. Used by the correlation's plan (:mod:`chunkdic.engine.costs`: scratch
and result) and by the image exports (:mod:`chunkdic.export.fields_image`,
:mod:`chunkdic.export.corrected_image`); it sits in ``io`` so every layer above may use it.
"""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

from ..errors import DiskSpaceError

__all__ = ["DISK_MARGIN", "DISK_ERRNOS", "disk_cause", "existing_parent", "free_bytes", "same_device", "format_bytes",
           "check_disk"]

GiB, MiB = 2**30, 2**20

#: free disk kept beyond an estimate (file-system metadata, other writers)
DISK_MARGIN = 1.05
#: disk errors (full, quota, read-only, I/O, file too large): the run cannot write, its inputs are fine
DISK_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO, errno.EFBIG})


def disk_cause(exc: BaseException) -> str | None:
    """The disk error behind ``exc`` in one phrase naming the path, or None (another failure):
    a :class:`~chunkdic.errors.DiskSpaceError`'s cause, or an ``OSError`` of :data:`DISK_ERRNOS`."""
    if isinstance(exc, DiskSpaceError):
        return exc.cause
    if isinstance(exc, OSError) and exc.errno in DISK_ERRNOS:
        return f"{exc.strerror or exc} ({exc.filename})" if exc.filename else f"{exc.strerror or exc}"
    return None


def existing_parent(path) -> Path:
    """``path`` itself if it exists, else its nearest existing ancestor (absolute)."""
    path = Path(path).absolute()
    while not path.exists() and path.parent != path:
        path = path.parent
    return path


def free_bytes(path) -> int:
    """Free bytes for this user on the file system holding ``path`` (or its nearest parent)."""
    return int(shutil.disk_usage(existing_parent(path)).free)


def same_device(a, b) -> bool:
    """Whether two paths (or their nearest existing parents) lie on one file system."""
    return os.stat(existing_parent(a)).st_dev == os.stat(existing_parent(b)).st_dev


def format_bytes(n: float) -> str:
    """``n`` bytes for a person: GiB with two decimals from 1 GiB up, whole MiB from 10 MiB,
    MiB with one decimal from 1 MiB, else whole KiB.

    Examples
    --------
    >>> format_bytes(3 * 2**30), format_bytes(50 * 2**20), format_bytes(3532032), format_bytes(48384)
    ('3.00 GiB', '50 MiB', '3.4 MiB', '47 KiB')
    """
    if n >= GiB:
        return f"{n / GiB:.2f} GiB"
    if n >= MiB:
        return f"{n / MiB:.0f} MiB" if n >= 10 * MiB else f"{n / MiB:.1f} MiB"
    return f"{n / 1024:.0f} KiB"


def check_disk(need: int, where, what: str, hint: str) -> int:
    """Refuse (one line) ``need`` bytes that the file system of ``where`` cannot hold.

    Parameters
    ----------
    need : int
        Bytes the output will take at most (bytes)
    where : path
        The output (it need not exist: its nearest existing parent decides the file system).
    what : str
        What is written, for the message (``"the fields image"``).
    hint : str
        What makes it fit (``"--fields-level 2 needs 1.2 GiB"``), ends the message.

    Returns
    -------
    int
        The free bytes found.

    Raises
    ------
    DiskSpaceError
        When ``need * DISK_MARGIN`` exceeds the free bytes.
    """
    room = int(free_bytes(where))
    if need * DISK_MARGIN > room:
        raise DiskSpaceError(f"not enough disk: {what} needs up to {format_bytes(need)} in "
                             f"{existing_parent(Path(where).absolute().parent)}, {format_bytes(room)} free; {hint}")
    return room
