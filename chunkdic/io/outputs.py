"""The one place that writes outputs: declared and checked together, written, committed or rolled back.

Every command that writes (correlate, ingest, synth, uncertainty, sweep, table, report,
export, demo) declares its outputs here, with their *kind*, before it writes anything;
each is checked against the rules of :mod:`chunkdic.io.outputrules` (never an input,
``--overwrite`` only on chunkdic's own output of the same kind, ...). Two outputs of one
command may not share a path (``export --vtk X --csv X``).

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

Each output records what made it (:mod:`chunkdic.io.madeof`) at the commit.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError
from .kinds import KINDS, Kind, kind_of, mark_folder, ours_in_folder
from .locks import OutputLock
from .madeof import made_here, record
from .outputrules import check_output, missing_parents, real_path, say_path
from .owntree import remove
from .siblings import partial_name, reclaim_stale_partials
from .store import drain_zarr_io

log = logging.getLogger(__name__)

__all__ = ["Outputs", "Entry"]


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
        (:func:`chunkdic.io.madeof.made_of`; default: the one a caller declared for ``path``,
        :func:`chunkdic.io.madeof.making`), recorded in it at the commit; the same command on
        its own complete output finds it ``done`` (:attr:`done`).
        """
        if path is None or os.fspath(path) == "":
            raise InputError(f"empty path for the {KINDS[kind].label}")
        made_of = made_of if made_of is not None else made_here(path)
        k = KINDS[kind]
        real = real_path(Path(path))
        for e in self.entries:
            other = real_path(e.final)
            if other == real:
                raise InputError(f"{say_path(path)} is given for two outputs ({e.kind.label} and {k.label}): "
                                 "choose different paths")
            if other in real.parents or real in other.parents:
                raise InputError(f"outputs {say_path(e.final)} and {say_path(path)} overlap: choose separate paths")
        state = check_output(path, kind, inputs=self.inputs, overwrite=self.overwrite, resumable=resumable,
                             parents=parents, made_of=made_of)
        if staged is None:
            staged = k.form != "folder" and not resumable
        entry = Entry(Path(path), k, staged, state, parents=missing_parents(Path(path)) if parents else [],
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
            raise InputError(f"output {say_path(e.final)} is a complete {e.kind.label}: choose another path or pass "
                             "--overwrite")
        for d in e.parents:
            if not d.exists():
                d.mkdir()
                e.made.append(d)
        # one writer per output, whatever the command (a no-op where this process holds it already)
        e.lock = OutputLock(e.final)
        e.lock.acquire()
        if e.state == "absent" and (e.final.exists() or e.final.is_symlink()):
            raise InputError(f"output {say_path(e.final)} appeared while this run was starting: choose another path "
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
                        raise InputError(f"output {say_path(e.final)} appeared while this run was writing it: "
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
