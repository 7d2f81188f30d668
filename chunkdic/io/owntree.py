"""An output's own tree: removing a path, and writing only inside it.

chunkdic removes what it wrote (a staged copy, a level being rebuilt, a dead run's scratch)
and writes into stores it owns (a scan's pyramid levels, a resumed result's checkpoint).
A symbolic link in such a tree leads elsewhere: a user's folder, another scan. Neither a
removal nor a write ever goes through one:

- :func:`remove` removes a file, a link (the link itself, never what it points to) or a
  directory tree whose links are removed as links (``shutil.rmtree`` does not descend into
  them). It is the one way chunkdic removes a path.
- :func:`check_own_tree` refuses, in one line, a tree whose entries lead out of it through
  a symbolic link, before anything is written into it.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from pathlib import Path

from ..errors import InputError

log = logging.getLogger(__name__)

__all__ = ["remove", "check_own_tree", "link_out_of"]


def remove(path) -> None:
    """Remove ``path`` if it exists, following no symbolic link.

    A link is unlinked itself (whatever it points to, a directory included); a directory is
    removed with everything in it, the links within removed as links; a missing path is no
    error. A directory that is not gone at once is tried again half a second later (a task
    on a remote worker may still be finishing a write into it). Errors are logged, not
    raised: a removal cleans up, and must not hide the error that called for it.
    """
    p = Path(path)
    try:
        if p.is_symlink() or not p.is_dir():
            p.unlink(missing_ok=True)
            return
    except OSError as exc:
        log.warning("could not remove %s: %s", p, exc.strerror)
        return
    shutil.rmtree(p, ignore_errors=True)
    if p.exists():
        time.sleep(0.5)
        shutil.rmtree(p, ignore_errors=True)


def link_out_of(root, entries=None) -> tuple[Path, str] | None:
    """The first symbolic link under ``root`` that leads out of it, as ``(link, target)``, or None.

    ``entries``: the paths under ``root`` that will be written or replaced (only they and
    the directories between ``root`` and them are looked at); default: the whole tree,
    walked without following links. A link that stays inside ``root`` (or a dangling one
    whose target would lie inside) is harmless: a write through it stays in the tree, and
    :func:`remove` unlinks it.
    """
    base = Path(os.path.realpath(root))

    def leaves(link: Path) -> str | None:
        target = os.path.realpath(link)
        return None if target == str(base) or target.startswith(str(base) + os.sep) else target

    if entries is not None:
        for entry in entries:
            rel = Path(os.path.abspath(entry)).relative_to(os.path.abspath(root))
            p = Path(root)
            for part in rel.parts:
                p = p / part
                if p.is_symlink() and (target := leaves(p)) is not None:
                    return p, target
        return None
    for parent, dirs, files in os.walk(root):  # links to directories are listed, never entered
        for name in dirs + files:
            p = Path(parent) / name
            if p.is_symlink() and (target := leaves(p)) is not None:
                return p, target
    return None


def check_own_tree(root, entries=None, *, what: str = "output") -> None:
    """Refuse, in one line, to write into ``root`` when a symbolic link leads out of it
    (:func:`link_out_of`: the whole tree, or only ``entries`` and the directories above them).

    Raises
    ------
    InputError
        Naming the link and where it leads.
    """
    found = link_out_of(root, entries)
    if found is not None:
        link, target = found
        raise InputError(f"{what} {root}: {link} is a symbolic link to {target}, outside it; chunkdic writes "
                         "only inside an output's own tree (remove the link, or copy what it points to in)")
