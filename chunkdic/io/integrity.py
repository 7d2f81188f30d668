"""Damaged inputs and input identity: the narrow places where stored bytes are trusted.

- A chunk that does not decode (truncated, overwritten, bit rot) raises, inside whatever
  task read it, one :class:`InputError` naming the array, the chunk and its file
  (:func:`damaged_read_error`). It costs nothing on the hot path: the reader only calls it
  from its ``except`` branch, and only then are the chunks of the failed region probed
  one by one.
- A chunk *file* missing from a stored level: Zarr reads it as the fill value without a
  word. chunkdic writes every chunk of every level (``write_empty_chunks``), so in a scan
  that chunkdic wrote a missing chunk can only be damage: :func:`check_chunks_present`
  refuses it when the scan is opened (one directory listing per level). In a Zarr array
  written by another tool, absent chunks are a legitimate way to store empty regions:
  there it is a warning.
- A chunk file *cut short* (a copy, a disk): a Blosc 1 frame carries its length in its
  header, and the decoder trusts the header rather than the buffer and reads past the end
  of a cut file (numcodecs issue #228), so the chunk may decode, to its former voxels or a
  few wrong ones, without an error. :func:`check_blosc_frames` compares every chunk file's
  header with its size when the scan is opened (16 bytes read per file, threaded) and
  refuses the scan, naming the file, whoever wrote it. Other codecs need no check: zstd
  takes the buffer's length, an uncompressed chunk fails zarr's size check, a sharded
  array's default index carries a checksum (docs/safety.md, "Damaged and unusual inputs").
- :func:`content_identity`: a cheap, out-of-core identity of an on-disk array for the
  resume fingerprint: the array metadata, the list of chunk files with their sizes, and
  hashes of a fixed sample of chunk files (a ``.npy``: its size and sampled byte ranges).
  Modification times are part of it: a rewritten chunk changes it even when its size
  does not, and a scan copied without its times counts as changed (the safe side: the
  re-run is refused, never resumed on other data). Reading it costs a listing and at
  most ``SAMPLE_FILES`` partial file reads, never the scan.
"""

from __future__ import annotations

import concurrent.futures
import hashlib
import itertools
import logging
import math
import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..warn import warn_user
from .store import blosc_frame_bytes, blosc_frame_fault

log = logging.getLogger(__name__)

__all__ = ["damaged_read_error", "check_chunks_present", "check_no_empty_chunks", "check_blosc_frames",
           "content_identity", "MissingChunksWarning"]

#: chunk files hashed per array for the content identity
SAMPLE_FILES = 8
#: bytes hashed per sampled file: whole files up to this size, else head, middle and tail
SAMPLE_BYTES = 1 << 20
#: chunk keys visited to name the first missing chunks (the grid's first ones only)
NAMED_KEYS = 100_000
#: threads reading chunk frame headers (I/O-bound: one open and 16 bytes per file)
HEADER_THREADS = 8


class MissingChunksWarning(UserWarning):
    """Chunks absent from a Zarr array that chunkdic did not write (read as the fill value)."""


def _array_dir(path: str, key: str) -> Path:
    return Path(path) / key if key else Path(path)


def _chunk_file(arr, coords) -> str:
    try:
        return arr.metadata.encode_chunk_key(tuple(int(c) for c in coords))
    except Exception:  # noqa: BLE001 - v2 or exotic encodings: name the index only
        return "/".join(str(int(c)) for c in coords)


def damaged_read_error(path: str, key: str, region, exc: BaseException) -> InputError:
    """One-line error for a failed read of ``region`` of the Zarr array ``path``/``key``.

    Probes the chunks (shards) the region overlaps, one at a time, to name the first that
    cannot be read; the caller raises the returned error.
    """
    import zarr

    where = str(_array_dir(path, key))
    first = f"{type(exc).__name__}: {exc}".splitlines()[0][:200]
    try:
        arr = zarr.open_array(store=path, path=key or None, mode="r")
        unit = tuple(arr.shards) if getattr(arr, "shards", None) else tuple(arr.chunks)
        ranges = []
        for s, u, n in zip(region, unit, arr.shape):
            a, b, _ = s.indices(n)
            ranges.append(range(a // u, max(a, b - 1) // u + 1))
        for coords in itertools.product(*ranges):
            box = tuple(slice(c * u, min((c + 1) * u, n)) for c, u, n in zip(coords, unit, arr.shape))
            try:
                arr[box]
            except Exception as inner:  # noqa: BLE001 - this is the damaged one
                reason = f"{type(inner).__name__}: {inner}".splitlines()[0][:200]
                return InputError(f"{where}: chunk {tuple(int(c) for c in coords)} (file "
                                  f"{_array_dir(path, key) / _chunk_file(arr, coords)}) cannot be read: {reason}; "
                                  "the store is damaged or truncated")
    except Exception:  # noqa: BLE001 - fall back to the original error
        pass
    return InputError(f"{where}: cannot read the region "
                      f"{tuple((s.start, s.stop) for s in region)}: {first}; the store is damaged or truncated")


#: metadata files of a Zarr array directory (v3 and v2); every other file in it is a chunk
_METADATA = ("zarr.json", ".zarray", ".zattrs", ".zgroup", ".zmetadata")


def _chunk_files(adir: Path) -> dict[str, tuple[int, int]]:
    """Relative path -> (size, mtime in ns) of every chunk file of a local Zarr array, whatever its
    chunk-key layout (v3 ``c/0/0/0`` or ``0.0.0``, v2 ``0.0.0`` or ``0/0/0``)."""
    out = {}
    for dirpath, _, files in os.walk(adir):
        for name in files:
            if dirpath == str(adir) and name in _METADATA:
                continue
            full = os.path.join(dirpath, name)
            try:
                st = os.stat(full)
            except OSError:
                continue
            out[os.path.relpath(full, adir)] = (st.st_size, st.st_mtime_ns)
    return out


def check_chunks_present(path: str, key: str, *, ours: bool) -> None:
    """Refuse (``ours``) or warn about (foreign array) chunk files missing from an array.

    Parameters
    ----------
    path, key : str
        Zarr store root and array path inside it.
    ours : bool
        True for a level that chunkdic wrote (every chunk is written): missing chunks are
        damage and raise :class:`InputError`. False: :class:`MissingChunksWarning`.
    """
    import zarr

    arr = zarr.open_array(store=path, path=key or None, mode="r")
    files = _chunk_files(_array_dir(path, key))  # one listing for the three checks
    check_no_empty_chunks(path, key, files=files)
    check_blosc_frames(path, key, arr=arr, files=files)
    # counted from the listing, never by visiting the grid: an array may declare 10⁹ chunks
    # (zarr's own count walks every key it declares: a hang at open)
    unit = tuple(arr.shards) if getattr(arr, "shards", None) else tuple(arr.chunks)
    grid = [range(-(-n // c)) for n, c in zip(arr.shape, unit)]
    expected, present = math.prod(len(g) for g in grid), len(files)
    if present >= expected:
        return
    missing_names = []
    for coords in itertools.islice(itertools.product(*grid), NAMED_KEYS):  # the first missing ones, if near
        name = _chunk_file(arr, coords)
        if name not in files:
            missing_names.append(name)
            if len(missing_names) == 3:
                break
    where = str(_array_dir(path, key))
    first = f" (first: {', '.join(missing_names)})" if missing_names else ""
    if ours:
        raise InputError(f"{where}: {expected - present} of {expected} chunk files are missing{first}; "
                         "the scan is damaged: write or ingest it again")
    warn_user(f"{where}: {expected - present} of {expected} chunks are absent{first} and read as the "
              f"fill value {arr.fill_value}", MissingChunksWarning)


def check_no_empty_chunks(path: str, key: str = "", *, files=None) -> None:
    """Refuse (one line) an array with a 0-byte chunk file: no codec writes one (an
    uncompressed chunk holds its voxels, a compressed one a frame header), so it can only be
    a truncated write or a damaged disk, whoever wrote the array. ``files``: the array's
    listing (:func:`_chunk_files`) when the caller has it."""
    adir = _array_dir(path, key)
    files = _chunk_files(adir) if files is None else files
    empty = sorted(name for name, (size, _) in files.items() if size == 0)
    if empty:
        more = f" and {len(empty) - 1} more" if len(empty) > 1 else ""
        raise InputError(f"{adir}: chunk file {empty[0]}{more} is empty (0 bytes); the store is damaged or "
                         "truncated")


def check_blosc_frames(path: str, key: str = "", *, arr=None, files=None) -> None:
    """Refuse (one line naming the file) an array with a chunk file that is not one whole
    Blosc frame of a chunk: cut short, or longer than its frame, or a frame of another size.

    Only arrays whose chunk files are Blosc 1 frames are checked
    (:func:`chunkdic.io.store.blosc_frame_bytes`; not sharded, not zstd). The Blosc decoder
    trusts the frame header's length and reads past the end of a cut-short file (numcodecs
    issue #228): such a chunk can decode without an error, to its former voxels or to a
    few wrong ones, so decoding is no check. Each file's 16-byte header is read (threaded:
    the cost is one open per file) and compared with the file's size and the chunk's
    decoded size, as the resume does (:func:`chunkdic.io.store.chunk_is_complete`).

    Parameters
    ----------
    path, key : str
        Zarr store root and array path inside it.
    arr : zarr.Array, optional
        The array, when the caller opened it.
    files : dict, optional
        The array's listing (:func:`_chunk_files`), when the caller has it.
    """
    if arr is None:
        import zarr

        arr = zarr.open_array(store=path, path=key or None, mode="r")
    nbytes = blosc_frame_bytes(arr)
    if nbytes is None:
        return
    adir = _array_dir(path, key)
    files = _chunk_files(adir) if files is None else files
    # chunk keys never start with "." (a file manager's .DS_Store is no chunk)
    names = sorted(n for n, (size, _) in files.items() if size and not os.path.basename(n).startswith("."))

    def faults(batch: list[str]) -> list[tuple[str, str]]:
        out = []
        for name in batch:
            try:
                why = blosc_frame_fault(os.path.join(adir, name), files[name][0], nbytes)
            except OSError as exc:  # removed or unreadable since the listing
                why = f"cannot be read ({exc.strerror or exc})"
            if why is not None:
                out.append((name, why))
        return out

    # one batch per thread, not one task per file: a task costs more than the open and read
    # of a file in the page cache (measured: 4096 files in 20-50 ms serially, 230-490 ms as
    # 4096 tasks of a pool, at load 9 on 2 cores); the threads overlap reads from the disk
    batches = [names[i::HEADER_THREADS] for i in range(HEADER_THREADS)]
    with concurrent.futures.ThreadPoolExecutor(HEADER_THREADS) as pool:
        bad = sorted(itertools.chain.from_iterable(pool.map(faults, batches)))
    if bad:
        more = f" ({len(bad) - 1} more chunk files too)" if len(bad) > 1 else ""
        raise InputError(f"{adir}: chunk file {bad[0][0]} {bad[0][1]}{more}; the store is damaged or truncated")


def _hash_file(h, path: str) -> None:
    size = os.path.getsize(path)
    h.update(str(size).encode())
    with open(path, "rb") as fh:
        if size <= SAMPLE_BYTES:
            h.update(fh.read())
            return
        part = SAMPLE_BYTES // 3
        for offset in (0, size // 2 - part // 2, size - part):
            fh.seek(offset)
            h.update(fh.read(part))


def content_identity(kind: str, path: str, key: str = "") -> str:
    """Cheap content hash of an on-disk array (module docstring); never reads it whole.

    Parameters
    ----------
    kind : {"zarr", "npy"}
    path, key : str
        As in :class:`chunkdic.io.handles.ArrayRef`.

    Returns
    -------
    str
        Hex digest; equal digests mean the same metadata, chunk list, chunk sizes and
        sampled bytes.
    """
    h = hashlib.sha256()
    if kind == "npy":
        _hash_npy(h, path)
        return h.hexdigest()[:32]
    adir = _array_dir(path, key)
    for name in ("zarr.json", ".zarray", ".zattrs"):  # v3 metadata, or v2 (any chunk-key layout)
        meta = adir / name
        if meta.is_file():
            h.update(meta.read_bytes())
    files = _chunk_files(adir)
    names = sorted(files)
    for name in names:
        h.update(f"{name}:{files[name][0]}:{files[name][1]};".encode())
    if names:
        picks = sorted({round(i * (len(names) - 1) / max(SAMPLE_FILES - 1, 1)) for i in range(SAMPLE_FILES)})
        for i in picks:
            _hash_file(h, str(adir / names[i]))
    return h.hexdigest()[:32]


def _hash_npy(h, path: str) -> None:
    st = os.stat(path)
    size = st.st_size
    h.update(f"{size}:{st.st_mtime_ns}".encode())
    window = 1 << 16
    with open(path, "rb") as fh:
        for i in range(SAMPLE_FILES * 2):
            offset = min(max(size - window, 0), round(i * max(size - window, 0) / (SAMPLE_FILES * 2 - 1)))
            fh.seek(offset)
            h.update(fh.read(window))
