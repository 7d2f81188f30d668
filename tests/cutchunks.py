"""Chunk files cut short, read the way one was read when a resumed synth kept it.

The Blosc 1 decoder trusts the frame header's length (``cbytes``), not the buffer's, and
reads past the end of a cut-short chunk: whether the chunk then decodes depends on the
bytes that follow it in memory. In the failing runs those were, for the most part, the
rest of the same chunk (freed memory of an earlier read of the whole file), and the cut
chunk decoded (docs/safety.md, "Resuming a synthetic pair"). :func:`stale_tail_reads`
makes that memory layout happen on every read instead of by chance.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def cut_in_half(path: Path) -> bytes:
    """Cut the file ``path`` to half its length; returns its whole former content."""
    whole = path.read_bytes()
    path.write_bytes(whole[: len(whole) // 2])
    return whole


def stale_tail_reads(monkeypatch, whole: dict[Path, bytes]) -> None:
    """Make every Zarr read of a file of ``whole`` (path -> its former content) that is now
    shorter return a buffer of the file's length followed in memory by the rest of the
    former content, as the heap held it (measured on the failing resumes)."""
    from zarr.core.buffer import default_buffer_prototype
    from zarr.storage import LocalStore

    get = LocalStore.get
    former = {str(Path(p).resolve()): b for p, b in whole.items()}

    async def get_with_stale_tail(self, key, prototype=None, byte_range=None):
        buf = await get(self, key, prototype, byte_range)
        old = former.get(str((Path(self.root) / key).resolve()))
        if buf is None or old is None or byte_range is not None:
            return buf
        data = buf.to_bytes()
        if len(data) >= len(old):
            return buf  # rewritten whole since
        backing = np.frombuffer(bytearray(data + old[len(data):]), np.uint8)
        return (prototype or default_buffer_prototype()).buffer.from_array_like(backing[: len(data)])

    monkeypatch.setattr(LocalStore, "get", get_with_stale_tail)
