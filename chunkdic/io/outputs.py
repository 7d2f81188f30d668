"""The one place that prepares outputs: what may be written where, and what may be replaced.

Every command that writes (correlate, ingest, synth, uncertainty, sweep, table, report,
export, demo) declares its outputs here, with their *kind*, before it writes anything.
The rules, checked for all outputs of a command before the first byte is written:

- An output is never an input, never inside one and never contains one (symbolic links
  resolved; a Zarr input counts as its whole store, so ``def.zarr/1`` is inside the input
  ``def.zarr/0``). It is never the current directory or one of its parents, never inside
  a Zarr store, never under a regular file, and its directory must exist and be writable
  (``ingest`` may create missing parent directories: ``parents=True``).
- An existing output is refused unless ``overwrite``. Even then only something chunkdic
  wrote, of the same kind, is replaced: stores carry ``attrs["chunkdic"]["kind"]``,
  folders a marker file (:data:`chunkdic.io.kinds.MARKER`), files are recognised by their header. A user's
  folder, a file of another format, an input: refused, with one line saying why.
- Two outputs of one command may not share a path (``export --vtk X --csv X``).

Writing then goes one of two ways, and a failed run leaves nothing of its own behind,
never removing what was there before:

- *staged* (stores and files): written into a hidden sibling
  ``.NAME.chunkdic-partial-HOST-PID-XXXX`` and renamed into place when the whole command
  succeeded, so an old output stays intact until the new one is complete. A staged copy
  left by a killed run is reclaimed by the next run on the same output once its owner is
  known dead (:mod:`chunkdic.io.siblings`).
- *in place* (folders whose files refer to each other, and the correlation result, which
  holds the checkpoint that a re-run resumes from): written where they belong; the folder
  marker says ``complete: false`` until the end; on failure what this run created is
  removed. With ``overwrite``, the old folder's chunkdic entries are removed first, and
  anything else in the folder (a user's notes) is left alone.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import logging
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError
from .kinds import KINDS, Kind, kind_of, mark_folder, ours_in_folder
from .locks import OutputLock
from .madeof import record, recorded
from .owntree import check_own_tree, remove
from .siblings import name_limits, partial_name, reclaim_stale_partials
from .store import drain_zarr_io

log = logging.getLogger(__name__)

__all__ = ["Outputs", "check_output", "check_writable", "input_roots", "inside", "CWD_GONE"]

#: the refusal of a run whose working directory was removed (``os.getcwd()`` fails)
CWD_GONE = ("the current directory no longer exists (it was removed): relative paths cannot be resolved; "
            "cd to an existing directory and run again")

#: the Zarr store (resolved path) of a container this process is writing, whose members
#: may be outputs (a loading series' step results) and inputs (the step that initialises
#: the next one); ``None``: no output may lie inside any Zarr store
_CONTAINER: contextvars.ContextVar[Path | None] = contextvars.ContextVar("chunkdic_container", default=None)


@contextlib.contextmanager
def inside(container):
    """Allow outputs inside the chunkdic store ``container`` while the block runs.

    Used by :func:`chunkdic.series` only, for the step results it writes into its own
    ``series`` store (checked by :class:`Outputs` as a whole first). Within it, a member
    group counts as an input on its own (not as the whole store), so one step may
    initialise the next. Every other rule still holds.
    """
    token = _CONTAINER.set(Path(os.path.abspath(container)).resolve())
    try:
        yield
    finally:
        _CONTAINER.reset(token)


def _in_container(path: Path) -> bool:
    box = _CONTAINER.get()
    return box is not None and (path == box or box in path.parents)


# --------------------------------------------------------------------------- inputs


def input_roots(inputs) -> list[Path]:
    """Resolved on-disk extent of each input: a file, a folder, or a whole Zarr store.

    ``inputs``: paths (``file.h5:/dataset`` counts as ``file.h5``), zarr arrays/groups on
    a local store, :class:`chunkdic.Scan` objects; in-memory inputs are skipped.
    """
    roots = []
    for src in inputs:
        path = _input_path(src)
        if path is None:
            continue
        p = Path(os.path.abspath(path))
        p = p.resolve() if p.exists() else p
        # a Zarr node: its whole store (the outermost directory of the hierarchy)
        top = p
        for parent in p.parents:
            if _in_container(parent):
                break  # a member of the container being written counts as itself (inside())
            if (parent / "zarr.json").is_file() or (parent / ".zgroup").is_file():
                top = parent
            else:
                break
        roots.append(top)
    return roots


def _input_path(src) -> str | None:
    if src is None:
        return None
    if isinstance(src, (str, os.PathLike)):
        s = os.fspath(src)
        if not os.path.exists(s) and ":" in s:  # file.h5:/path/to/dataset
            head = s.rsplit(":", 1)[0]
            if os.path.exists(head):
                return head
        return s
    path = getattr(src, "path", None)  # Scan
    if isinstance(path, str) and not hasattr(src, "store"):
        return path
    store = getattr(src, "store", None)  # zarr Array / Group
    root = getattr(store, "root", None)
    if root is not None:
        key = str(getattr(src, "path", "") or "").strip("/")
        return os.path.join(str(root), key) if key else str(root)
    return None


# --------------------------------------------------------------------------- checks


def _say(path) -> str:
    return os.fspath(path)


def _real(path: Path) -> Path:
    """Absolute path with every directory component resolved (the last one kept as is).

    A directory that is a loop of symbolic links (``ln -s a b; ln -s b a``, then ``-o
    a/o.zarr``) cannot be resolved: refused in one line (pathlib raises RuntimeError on
    Python 3.11, OSError ELOOP on later versions).
    """
    a = Path(os.path.abspath(path))
    try:
        return a.parent.resolve() / a.name
    except (RuntimeError, OSError):
        raise InputError(f"output {_say(path)} lies under a loop of symbolic links ({os.strerror(errno.ELOOP)}): "
                         "choose another path") from None


def _check_name_lengths(p: Path, real: Path) -> None:
    """Refuse a path the file system cannot hold before anything is written: a component
    longer than ``NAME_MAX`` bytes (255 on most file systems) or a whole path longer than
    ``PATH_MAX``. The sibling names derived from the output (``.NAME.chunkdic-lock``, the
    staged ``.NAME.chunkdic-partial-…``) are shortened by :mod:`chunkdic.io.siblings`
    when they would not fit, so any name that fits by itself is usable."""
    name_max, path_max = name_limits(_existing_ancestor(p))
    for part in real.parts:
        size = len(os.fsencode(part))
        if size > name_max:
            shown = part if len(part) <= 40 else part[:40] + "…"
            raise InputError(f"output {shown!s} ({size} bytes) is a name longer than the file system allows "
                             f"({name_max} bytes, ENAMETOOLONG: {os.strerror(errno.ENAMETOOLONG)}): choose a "
                             "shorter name")
    if len(os.fsencode(str(real))) >= path_max:
        raise InputError(f"output path ({len(os.fsencode(str(real)))} bytes) is longer than the file system allows "
                         f"({path_max} bytes, ENAMETOOLONG): choose a shorter path")


def _check_cwd(p: Path, real: Path) -> None:
    try:
        cwd = Path.cwd().resolve()
    except FileNotFoundError:  # removed under this process: no output can be it, but nothing relative resolves
        raise InputError(CWD_GONE) from None
    if real == cwd or real in cwd.parents:
        raise InputError(f"output {_say(p)} is the current directory or contains it: choose a new path")
    if not p.name or p.name in (".", ".."):
        raise InputError(f"output {_say(p)} is not a usable name: choose a new path")


def _check_location(p: Path, real: Path, kind: Kind, parents: bool = False) -> None:
    if kind.suffixes and real.suffix.lower() not in kind.suffixes:
        raise InputError(f"{kind.label} {_say(p)}: unknown extension {real.suffix or '(none)'!r}, "
                         f"use {' or '.join(kind.suffixes)}")
    anc = _existing_ancestor(p)
    if anc.exists() and not anc.is_dir():
        raise InputError(f"output {_say(p)} lies under the file {anc}, which is not a directory")
    if not real.parent.is_dir() and not parents:
        raise InputError(f"output directory {real.parent} does not exist")
    for parent in real.parents:
        if _in_container(parent):
            continue  # the container this process writes (inside())
        if (parent / "zarr.json").is_file() or (parent / ".zgroup").is_file() or (parent / ".zarray").is_file():
            raise InputError(f"output {_say(p)} lies inside the Zarr store {parent}: choose a path outside it")


def _existing_ancestor(p: Path) -> Path:
    """The nearest ancestor of ``p`` that exists (maybe a file: refused by the caller)."""
    anc = Path(os.path.abspath(p)).parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    return anc


def _missing_parents(p: Path) -> list[Path]:
    """The directories above ``p`` that do not exist yet, outermost first."""
    missing = []
    parent = Path(os.path.abspath(p)).parent
    while not parent.exists() and parent != parent.parent:
        missing.append(parent)
        parent = parent.parent
    return missing[::-1]


def _check_inputs(p: Path, real: Path, roots: list[Path]) -> None:
    for r in roots:
        if real == r:
            raise InputError(f"output {_say(p)} is the input {r}: choose another path")
        if r in real.parents:
            raise InputError(f"output {_say(p)} lies inside the input {r}: choose a path outside it")
        if real in r.parents:
            raise InputError(f"output {_say(p)} contains the input {r}: choose another path")


def check_writable(directory, what: str = "") -> None:
    """Refuse early (one line) a directory this run could not write in (read-only file
    system, permissions): a probe file is created and removed at once."""
    try:
        with tempfile.TemporaryFile(dir=directory, prefix=".chunkdic-probe-"):
            pass
    except OSError as exc:
        raise InputError(f"cannot write in {directory}{what}: {exc.strerror}") from None


def _check_existing(p: Path, real: Path, kind: Kind, overwrite: bool, resumable: bool,
                    made: str | None = None) -> str:
    """How to treat an existing ``real``: "absent", "empty-folder", "resume", "replace" or "done"
    (a complete output of this very command: it records ``made``, :mod:`chunkdic.io.madeof`)."""
    if real.is_symlink():
        raise InputError(f"output {_say(p)} is a symbolic link: refusing to write through it; choose another path")
    if not real.exists():
        return "absent"
    if kind.form == "folder" and real.is_dir() and not any(real.iterdir()):
        return "empty-folder"
    holder = OutputLock(real).live_owner()
    if holder is not None:  # not interrupted nor foreign: another run is writing it now (two writers racing)
        raise InputError(f"output {_say(p)} is being written by another chunkdic run ({holder}): wait for it "
                         "to finish or choose another path")
    found, complete = kind_of(real)
    if found == kind.name and not complete and resumable and not overwrite:
        check_own_tree(real, what=kind.label)  # written into again: never through a link out of it
        return "resume"
    if not overwrite:
        if found == kind.name and complete and made is not None and recorded(real) == made:
            return "done"
        if found == kind.name and complete:
            raise InputError(f"output {_say(p)} is a complete {kind.label}: choose another path or pass --overwrite")
        if found == kind.name:
            raise InputError(f"output {_say(p)} holds an interrupted {kind.label}: pass --overwrite to replace it")
        raise InputError(f"output {_say(p)} exists: choose another path or pass --overwrite")
    if found is None:
        what = "a folder" if real.is_dir() else "a file"
        raise InputError(f"output {_say(p)} is {what} chunkdic did not write: refusing to replace it "
                         "(remove it yourself or choose another path)")
    if found != kind.name:
        label = KINDS[found].label if found in KINDS else found
        raise InputError(f"output {_say(p)} holds a chunkdic {label}, not a {kind.label}: refusing to replace it; "
                         "choose another path")
    return "replace"


def check_output(path, kind: str, *, inputs=(), overwrite: bool = False, resumable: bool = False,
                 parents: bool = False, made_of: str | None = None) -> str:
    """Check one output against every rule (module docstring); no side effects.

    Parameters
    ----------
    path : str or Path
        The output.
    kind : str
        One of :data:`chunkdic.io.kinds.KINDS`.
    inputs : iterable
        The command's inputs (paths, zarr nodes, scans; in-memory arrays are ignored).
    overwrite : bool
        Allow replacing an existing output of the same kind that chunkdic wrote.
    resumable : bool
        An interrupted output of this kind may be continued (the correlation result).
    parents : bool
        Missing parent directories may be created (``ingest``); the nearest existing
        ancestor must then be a writable directory outside every Zarr store.
    made_of : str, optional
        What this command makes the output of (:func:`chunkdic.io.madeof.made_of`): a complete
        output recording the same is this command's own, and has nothing to do ("done").

    Returns
    -------
    str
        ``"absent"``, ``"empty-folder"``, ``"resume"``, ``"replace"`` or ``"done"``.

    Raises
    ------
    InputError
        One line saying what is wrong and what to do.
    """
    k = KINDS[kind]
    p = Path(path)
    real = _real(p)
    _check_name_lengths(p, real)
    _check_cwd(p, real)
    _check_inputs(p, real, input_roots(inputs))
    _check_location(p, real, k, parents)
    state = _check_existing(p, real, k, overwrite, resumable, made_of)
    check_writable(real.parent if real.parent.is_dir() else _existing_ancestor(p), f" (for output {_say(p)})")
    return state


# --------------------------------------------------------------------------- transaction


@dataclass
class Entry:
    """One declared output: ``final`` (as given), ``work`` (where to write now)."""

    final: Path
    kind: Kind
    staged: bool
    state: str
    work: Path = None  # type: ignore[assignment]
    created: bool = False
    keep: set = field(default_factory=set)
    parents: list = field(default_factory=list)  # missing directories to create, outermost first
    made: list = field(default_factory=list)  # the directories this run created
    lock: OutputLock | None = None  # the one-writer lock, held from _begin to commit or rollback
    begun: bool = False  # writing began (rollback undoes only such entries: never another run's output)
    made_of: str | None = None  # recorded in the output at the commit (chunkdic.io.madeof)


class Outputs:
    """All outputs of one command: checked together, written, then committed or rolled back.

    Examples
    --------
    >>> import tempfile, os
    >>> d = tempfile.mkdtemp()
    >>> out = Outputs(inputs=[], overwrite=False)
    >>> csv = out.add(os.path.join(d, "nodes.csv"), "csv")
    >>> with out:
    ...     _ = open(csv.work, "w").write("# positions and displacements in voxel\\n")
    >>> os.listdir(d)
    ['nodes.csv']
    """

    def __init__(self, *, inputs=(), overwrite: bool = False):
        self.inputs = list(inputs)
        self.overwrite = bool(overwrite)
        self.entries: list[Entry] = []
        self._open = False

    def add(self, path, kind: str, *, staged: bool | None = None, resumable: bool = False,
            parents: bool = False, made_of: str | None = None) -> Entry:
        """Declare and check one output; nothing is written yet.

        ``parents``: create missing parent directories when writing begins (removed again
        if the run fails). ``made_of``: what this command makes it of
        (:func:`chunkdic.io.madeof.made_of`), recorded in it at the commit; the same command
        on its own complete output finds it ``done`` (:attr:`done`).
        """
        if path is None or os.fspath(path) == "":
            raise InputError(f"empty path for the {KINDS[kind].label}")
        k = KINDS[kind]
        real = _real(Path(path))
        for e in self.entries:
            other = _real(e.final)
            if other == real:
                raise InputError(f"{_say(path)} is given for two outputs ({e.kind.label} and {k.label}): "
                                 "choose different paths")
            if other in real.parents or real in other.parents:
                raise InputError(f"outputs {_say(e.final)} and {_say(path)} overlap: choose separate paths")
        state = check_output(path, kind, inputs=self.inputs, overwrite=self.overwrite, resumable=resumable,
                             parents=parents, made_of=made_of)
        if staged is None:
            staged = k.form != "folder" and not resumable
        entry = Entry(Path(path), k, staged, state, parents=_missing_parents(Path(path)) if parents else [],
                      made_of=made_of)
        entry.work = entry.final
        self.entries.append(entry)
        if self._open:
            self._begin(entry)
        return entry

    @property
    def done(self) -> bool:
        """Every output is already this command's own, complete: nothing to do, nothing to write."""
        return bool(self.entries) and all(e.state == "done" for e in self.entries)

    # -- side effects -----------------------------------------------------------------
    def _begin(self, e: Entry) -> None:
        if e.state == "done":  # some outputs done, others not: the done ones are as any complete one
            raise InputError(f"output {_say(e.final)} is a complete {e.kind.label}: choose another path or pass "
                             "--overwrite")
        for d in e.parents:
            if not d.exists():
                d.mkdir()
                e.made.append(d)
        # one writer per output, whatever the command (a no-op where this process holds it already)
        e.lock = OutputLock(e.final)
        e.lock.acquire()
        if e.state == "absent" and (e.final.exists() or e.final.is_symlink()):
            raise InputError(f"output {_say(e.final)} appeared while this run was starting: choose another path "
                             "or pass --overwrite")
        e.begun = True
        reclaim_stale_partials(e.final)
        if e.staged:
            e.work = partial_name(e.final)
            return
        if e.kind.form == "folder":
            if e.state == "replace":
                ours, others = ours_in_folder(e.final, e.kind)
                for entry in ours:
                    remove(entry)
                e.keep = {x.name for x in others}
            elif e.state == "absent":
                e.final.mkdir()
                e.created = True
            elif e.state == "resume":  # an interrupted folder continued: what it holds stays on failure
                e.keep = {x.name for x in e.final.iterdir()}
            mark_folder(e.final, e.kind.name, complete=False)
        elif e.state == "replace":
            remove(e.final)

    def __enter__(self) -> "Outputs":
        try:
            for e in self.entries:
                self._begin(e)
        except BaseException:
            self.rollback()
            raise
        self._open = True
        return self

    def _release(self) -> None:
        for e in self.entries:
            if e.lock is not None:
                e.lock.release()

    def __exit__(self, exc_type, exc, tb) -> bool:
        self._open = False
        if exc_type is None:
            self.commit()
        else:
            self.rollback()
        return False

    def commit(self) -> None:
        """Move staged outputs into place (replacing the old same-kind output) and mark
        folders complete; then release the locks."""
        try:
            # nothing moves unless every output may: one that appeared meanwhile refuses them all
            for e in self.entries:
                if e.staged and e.work.exists() and (e.final.exists() or e.final.is_symlink()):
                    found, _ = kind_of(e.final)
                    if found != e.kind.name or e.state == "absent":
                        raise InputError(f"output {_say(e.final)} appeared while this run was writing it: "
                                         "refusing to replace it")
            self._commit()
        except BaseException:
            self.rollback()
            raise
        self._release()

    def _commit(self) -> None:
        for e in self.entries:
            if e.staged and e.made_of is not None and e.work.exists():
                record(e.work, e.made_of)  # before the rename: the output is whole with it, or absent
            if e.staged:
                if not e.work.exists():
                    continue  # this output was not written (an optional step was skipped)
                if e.final.exists() or e.final.is_symlink():
                    if e.final.is_dir():
                        grave = partial_name(e.final)
                        os.rename(e.final, grave)
                        os.rename(e.work, e.final)
                        remove(grave)
                        continue
                os.replace(e.work, e.final)
            elif e.kind.form == "folder":
                mark_folder(e.final, e.kind.name, complete=True)
                if e.made_of is not None:
                    record(e.final, e.made_of)

    def rollback(self) -> None:
        """Remove what this run created; never what was there before."""
        drain_zarr_io()  # chunk writes still in flight would bring a removed store back
        for e in self.entries:
            try:
                if e.begun:
                    self._undo(e)
            except OSError as exc:  # a full or read-only disk must not hide the first error
                log.warning("could not remove %s: %s", e.work, exc)
        self._release()  # the lock files first: they lie in the directories made below
        for e in self.entries:
            for d in reversed(e.made):  # only if still empty: never what another process put there
                try:
                    d.rmdir()
                except OSError as exc:
                    log.warning("could not remove %s: %s", d, exc)

    @staticmethod
    def _undo(e: Entry) -> None:
        if e.staged:
            remove(e.work)
        elif e.kind.form == "folder":
            if e.created:
                remove(e.final)
            elif e.final.is_dir():
                for entry in e.final.iterdir():
                    if entry.name not in e.keep:
                        remove(entry)
        elif e.state in ("absent", "replace"):
            remove(e.final)
