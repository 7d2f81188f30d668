"""Who owns a path: process identities, one-writer locks, and stale leftovers of dead runs.

Every file or directory that a chunkdic run leaves behind while it works (a lock file, a
half-written output, a scratch directory) records its owner: host name, process id and
the process's start time. The start time tells a live owner from a dead one whose pid was
reused. A leftover is reclaimed only when its owner is known dead: same host, and no
process with that pid and start time. A leftover of another host is never touched (that
host may be alive and share the file system).

Only paths that carry chunkdic's own names and owner records are ever removed here:
``.NAME.chunkdic-lock`` (a lock), ``.NAME.chunkdic-partial-HOST-PID-XXXX`` (a staged
output, see :mod:`chunkdic.io.outputs`) and ``chunkdic-*`` scratch directories holding
``SCRATCH_MARKER``.

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

import hashlib
import json
import logging
import os
import re
import shutil
import socket
import tempfile
import time
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path

from .. import config
from ..errors import InputError

log = logging.getLogger(__name__)

__all__ = ["Owner", "OutputLock", "make_scratch", "reclaim_stale_scratch", "partial_name", "final_name",
           "reclaim_stale_partials", "reclaim_stale_locks", "name_limits", "LOCK_SUFFIX", "SCRATCH_MARKER",
           "adopt_scratch", "interrupted_run_of", "reclaimable_scratch_bytes", "directory_bytes", "leave_scratch",
           "kept_scratch"]

LOCK_SUFFIX = ".chunkdic-lock"
PARTIAL_TAG = ".chunkdic-partial-"
SCRATCH_PREFIX = "chunkdic-"
SCRATCH_MARKER = ".chunkdic-scratch.json"
#: a dead run's scratch directory being removed (renamed first: one reclaimer wins)
RECLAIMED_TAG = ".chunkdic-reclaimed-"
#: a dead run's scratch directory being adopted by a live run (``…HOST-PID-XXXXXXXX``)
ADOPTING_TAG = ".chunkdic-adopting-"


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


def _hidden_sibling(final: Path, stem: str, tail: str) -> Path:
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
        return cls(str(d["host"]), int(d["pid"]), d.get("start"))

    def is_dead(self) -> bool:
        """True only when this owner is known dead (same host, no such live process)."""
        if self.host != socket.gethostname():
            return False
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


# --------------------------------------------------------------------------- locks


class OutputLock:
    """One writer per output: an exclusive lock file next to it (``.NAME.chunkdic-lock``).

    The file is created atomically (``O_EXCL``) and holds the owner (JSON). A lock whose
    owner is dead (killed with SIGKILL, machine rebooted) is taken over; a live owner's
    lock is refused with one line naming it. Released (removed) on exit.
    """

    def __init__(self, output):
        out = Path(output)
        self.output = out
        self.path = _hidden_sibling(out, out.name, LOCK_SUFFIX)
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
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                self._take_over_if_stale()
                continue
            except OSError as exc:
                raise InputError(f"cannot create the lock {self.path}: {exc.strerror}") from None
            try:
                with os.fdopen(fd, "w") as fh:
                    fh.write(record)
            except OSError as exc:  # a full disk: the empty lock file would outlive the refusal
                self.path.unlink(missing_ok=True)
                raise InputError(f"cannot write the lock {self.path}: {exc.strerror}") from None
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
            info = json.loads(self.path.read_text())
            owner = Owner.from_dict(info)
        except (OSError, ValueError, KeyError, TypeError):
            return None
        return None if owner.is_dead() else f"{owner.describe()} since {info.get('since', '?')}"

    def _take_over_if_stale(self) -> None:
        try:
            info = json.loads(self.path.read_text())
            owner = Owner.from_dict(info)
        except FileNotFoundError:
            return  # released meanwhile: try again
        except (OSError, ValueError, KeyError, TypeError):
            age = time.time() - _mtime(self.path)
            if age < 10:  # being written right now by its owner
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
        grave.unlink(missing_ok=True)
        log.info("took over the stale lock of %s (%s is dead)", self.output, owner.describe())

    def release(self) -> None:
        if self.held:
            _HELD.discard(_lock_key(self.path))
            self.path.unlink(missing_ok=True)
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


# --------------------------------------------------------------------------- staged outputs


def partial_name(final: Path) -> Path:
    """Name of a staged (half-written) version of ``final``: a hidden sibling that names
    its owner and keeps the suffix (writers such as meshio choose the format by it)."""
    me = Owner.me()
    host = re.sub(r"[^A-Za-z0-9_]", "_", me.host)
    return _hidden_sibling(final, final.stem, f"{PARTIAL_TAG}{host}-{me.pid}-{uuid.uuid4().hex[:6]}{final.suffix}")


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
    host = re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname())
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
            _remove(entry)
            removed.append(entry)
            log.info("removed %s, left by a dead run", entry)
    return removed


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
            owner = Owner.from_dict(json.loads(entry.read_text()))
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if owner.is_dead():
            entry.unlink(missing_ok=True)
            removed.append(entry)
            log.info("removed the lock %s of a dead run (%s)", entry, owner.describe())
    return removed


# --------------------------------------------------------------------------- scratch


def scratch_root() -> Path:

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
            _remove(path)
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
        meta = json.loads((Path(output) / "zarr.json").read_text())
        attrs = meta["attributes"]["chunkdic"]
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
        info = json.loads((entry / SCRATCH_MARKER).read_text())
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
    host = re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname())
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
            _remove(claimed)
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
    host = re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname())
    release = None if release is None else _resolved(release)
    claim = re.compile(re.escape(f"{ADOPTING_TAG}{host}-") + r"(\d+)-[0-9a-f]{8}$")
    for entry in entries:
        if entry.name.startswith(RECLAIMED_TAG):
            if _own_directory(entry):
                _remove(entry)  # only a reclaimer names so: one died while removing it (or removes it now)
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
        _remove(grave)
        removed.append(entry)
        log.info("reclaimed the scratch directory %s of a dead run", entry)
    return removed


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)
