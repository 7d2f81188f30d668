"""Where outputs may go: the rules every output of a command is checked against before anything is written.

- An output is never an input, never inside one and never contains one (symbolic links
  resolved; a Zarr input counts as its whole store, so ``def.zarr/1`` is inside the input
  ``def.zarr/0``). It is never the current directory or one of its parents, never inside
  a Zarr store, never under a regular file, and its directory must exist and be writable
  (``ingest`` may create missing parent directories: ``parents=True``). A path the file
  system cannot take (a loop of links, a name or path too long) is refused in one line.
- An existing output is refused unless ``overwrite``. Even then only something chunkdic
  wrote, of the same kind, is replaced: stores carry ``attrs["chunkdic"]["kind"]``,
  folders a marker file (:data:`chunkdic.io.kinds.MARKER`), files are recognised by their header. A user's
  folder, a file of another format, an input: refused, with one line saying why. A
  complete output this very command made (:mod:`chunkdic.io.madeof`) is ``done``.

:class:`chunkdic.io.outputs.Outputs` declares a command's outputs through :func:`check_output`
and then writes them.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import os
import tempfile
from pathlib import Path

from ..errors import InputError
from .kinds import KINDS, Kind, kind_of
from .locks import OutputLock
from .madeof import recorded
from .owntree import check_own_tree
from .siblings import name_limits

__all__ = ["check_output", "check_writable", "input_roots", "inside", "real_path", "missing_parents", "say_path",
           "CWD_GONE"]

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


def say_path(path) -> str:
    """A path as given, for an error line."""
    return os.fspath(path)


def real_path(path: Path) -> Path:
    """Absolute path with every directory component resolved (the last one kept as is).

    A directory that is a loop of symbolic links (``ln -s a b; ln -s b a``, then ``-o
    a/o.zarr``) cannot be resolved: refused in one line (pathlib raises RuntimeError on
    Python 3.11, OSError ELOOP on later versions).
    """
    a = Path(os.path.abspath(path))
    try:
        return a.parent.resolve() / a.name
    except (RuntimeError, OSError):
        raise InputError(f"output {say_path(path)} lies under a loop of symbolic links ({os.strerror(errno.ELOOP)}): "
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
        raise InputError(f"output {say_path(p)} is the current directory or contains it: choose a new path")
    if not p.name or p.name in (".", ".."):
        raise InputError(f"output {say_path(p)} is not a usable name: choose a new path")


def _check_location(p: Path, real: Path, kind: Kind, parents: bool = False) -> None:
    if kind.suffixes and real.suffix.lower() not in kind.suffixes:
        raise InputError(f"{kind.label} {say_path(p)}: unknown extension {real.suffix or '(none)'!r}, "
                         f"use {' or '.join(kind.suffixes)}")
    anc = _existing_ancestor(p)
    if anc.exists() and not anc.is_dir():
        raise InputError(f"output {say_path(p)} lies under the file {anc}, which is not a directory")
    if not real.parent.is_dir() and not parents:
        raise InputError(f"output directory {real.parent} does not exist")
    for parent in real.parents:
        if _in_container(parent):
            continue  # the container this process writes (inside())
        if (parent / "zarr.json").is_file() or (parent / ".zgroup").is_file() or (parent / ".zarray").is_file():
            raise InputError(f"output {say_path(p)} lies inside the Zarr store {parent}: choose a path outside it")


def _existing_ancestor(p: Path) -> Path:
    """The nearest ancestor of ``p`` that exists (maybe a file: refused by the caller)."""
    anc = Path(os.path.abspath(p)).parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    return anc


def missing_parents(p: Path) -> list[Path]:
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
            raise InputError(f"output {say_path(p)} is the input {r}: choose another path")
        if r in real.parents:
            raise InputError(f"output {say_path(p)} lies inside the input {r}: choose a path outside it")
        if real in r.parents:
            raise InputError(f"output {say_path(p)} contains the input {r}: choose another path")


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
        raise InputError(f"output {say_path(p)} is a symbolic link: refusing to write through it; choose another path")
    if not real.exists():
        return "absent"
    if kind.form == "folder" and real.is_dir() and not any(real.iterdir()):
        return "empty-folder"
    holder = OutputLock(real).live_owner()
    if holder is not None:  # not interrupted nor foreign: another run is writing it now (two writers racing)
        raise InputError(f"output {say_path(p)} is being written by another chunkdic run ({holder}): wait for it "
                         "to finish or choose another path")
    found, complete = kind_of(real)
    if found == kind.name and not complete and resumable and not overwrite:
        check_own_tree(real, what=kind.label)  # written into again: never through a link out of it
        return "resume"
    if not overwrite:
        if found == kind.name and complete and made is not None and recorded(real) == made:
            return "done"
        if found == kind.name and complete:
            raise InputError(f"output {say_path(p)} is a complete {kind.label}: choose another path or pass --overwrite")
        if found == kind.name:
            raise InputError(f"output {say_path(p)} holds an interrupted {kind.label}: pass --overwrite to replace it")
        raise InputError(f"output {say_path(p)} exists: choose another path or pass --overwrite")
    if found is None:
        what = "a folder" if real.is_dir() else "a file"
        raise InputError(f"output {say_path(p)} is {what} chunkdic did not write: refusing to replace it "
                         "(remove it yourself or choose another path)")
    if found != kind.name:
        label = KINDS[found].label if found in KINDS else found
        raise InputError(f"output {say_path(p)} holds a chunkdic {label}, not a {kind.label}: refusing to replace it; "
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
    real = real_path(p)
    _check_name_lengths(p, real)
    _check_cwd(p, real)
    _check_inputs(p, real, input_roots(inputs))
    _check_location(p, real, k, parents)
    state = _check_existing(p, real, k, overwrite, resumable, made_of)
    check_writable(real.parent if real.parent.is_dir() else _existing_ancestor(p), f" (for output {say_path(p)})")
    return state
