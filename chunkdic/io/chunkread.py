"""Reading a region of a Zarr v3 array from its chunk files, each crossed chunk decoded once.

The level-0 ``M`` pass and the prefilter of ``g`` read every block with the halo of the
low-pass (5 voxels for ``f``, 16 for ``g``), so a block's region crosses 8 of the scan's
128³ chunks, sometimes 27, and zarr-python decodes each of them for that region alone:
every chunk of the scan was decoded 5-16 times per pass (measured on the 512³ scan: 27 ms
of CPU for a 138³ region over 8 chunks, 3.3 ms for one aligned chunk). Decoding (and the
page faults of each new buffer) is most of that cost, so what pays is decoding each chunk
once: this module keeps the decoded chunks in a bounded per-process LRU
(:func:`chunk_cache`), and those passes run their blocks in :func:`z_order_key` order so
that neighbours, which share chunks, run close in time. At 512³: the ``M`` pass's CPU
−17 %, the prefilter's −41 %, each chunk decoded 1.4 and 3-3.6 times (docs/distributed.md,
"Reading the scans' chunks").

The fast path takes the arrays whose layout it knows exactly: Zarr v3, a regular chunk
grid, the default chunk keys, the ``bytes`` codec followed by at most one of ``blosc``,
``zstd`` (what :func:`chunkdic.io.store.compressors` writes), ``gzip`` or ``zlib``; and
Zarr v2 arrays in C order with one of those compressors (or none) and no filters. Anything
else (sharding, filters, other codecs, transformers) is read by zarr-python as before:
:func:`layout_of` returns None for it. The voxels are the same bytes either way.

Every chunk decodes into at most its own size (a *decompression bomb*, a few kB that
declare gigabytes, is refused before it is expanded; zarr-python decodes the whole
frame first, once per thread): a Blosc chunk is checked against its frame header (the
decoder trusts the header's length, docs/safety.md), a zstd frame against the content size
its header declares and decoded into a buffer of the chunk's size, a gzip/zlib stream
decoded with the chunk's size as the bound. A damaged chunk gives the same one-line error
as a read through zarr.
"""

from __future__ import annotations

import functools
import itertools
import math
import os
import threading
import zlib
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .jsonfile import read_json_object

#: the codecs after ``bytes`` this reader decodes itself, by their Zarr v3 and v2 names
_COMPRESSORS = {"blosc": "blosc", "zstd": "zstd", "gzip": "zlib", "zlib": "zlib", "numcodecs.zlib": "zlib",
                "numcodecs.gzip": "zlib"}


class ChunkDamaged(ValueError):
    """A chunk file that is not a whole frame of its array's codec (``index``, ``file``)."""

    def __init__(self, index, file, reason: str):
        super().__init__(reason)
        self.index, self.file = tuple(int(i) for i in index), str(file)


@dataclass(frozen=True)
class ChunkLayout:
    """Where and how a Zarr v3 array keeps its chunks.

    Attributes
    ----------
    directory : str
        The array's directory (holding ``zarr.json`` and ``c/...``).
    shape, chunks : tuple of int
        Array and chunk shapes (voxels).
    dtype : numpy.dtype
        Stored dtype, with the ``bytes`` codec's byte order.
    compressor : {"", "blosc", "zstd", "zlib"}
        The one bytes-to-bytes codec ("": none; "zlib" for a zlib or gzip stream).
    separator : str
        Chunk key separator (``"/"`` or ``"."``).
    fill : float or int
        Value of a chunk with no file.
    prefix : tuple of str
        Key components before the chunk index (``("c",)`` in Zarr v3, none in v2).
    """

    directory: str
    shape: tuple[int, ...]
    chunks: tuple[int, ...]
    dtype: np.dtype
    compressor: str
    separator: str
    fill: float | int
    prefix: tuple[str, ...] = ("c",)

    @property
    def chunk_bytes(self) -> int:
        return int(np.prod(self.chunks)) * self.dtype.itemsize

    def chunk_file(self, index) -> Path:
        return Path(self.directory, self.separator.join([*self.prefix, *map(str, index)]))


@functools.lru_cache(maxsize=64)
def layout_of(path: str, key: str) -> ChunkLayout | None:
    """The :class:`ChunkLayout` of the Zarr array ``path``/``key``; None when this module
    does not read it itself (then zarr-python does). Cached per process, forgotten with the
    open handles (:func:`chunkdic.io.handles.forget_open_arrays`)."""
    directory = Path(path, key) if key else Path(path)
    for name, read in (("zarr.json", _layout), (".zarray", _layout_v2)):
        try:
            meta = read_json_object(directory / name)
        except (OSError, ValueError):
            continue
        try:
            return read(str(directory), meta)
        except (KeyError, TypeError, ValueError, AttributeError, IndexError):
            return None
    return None


def _layout(directory: str, meta: dict) -> ChunkLayout | None:
    if meta.get("zarr_format") != 3 or meta.get("node_type") != "array" or meta.get("storage_transformers"):
        return None
    grid, keys = meta["chunk_grid"], meta["chunk_key_encoding"]
    if grid["name"] != "regular" or keys["name"] != "default":
        return None
    codecs = meta["codecs"]
    if not codecs or codecs[0]["name"] != "bytes" or len(codecs) > 2:
        return None
    compressor = codecs[1]["name"] if len(codecs) == 2 else ""
    if compressor and compressor not in _COMPRESSORS:
        return None
    compressor = _COMPRESSORS.get(compressor, "")
    dtype = np.dtype(meta["data_type"])
    if dtype.kind not in "biuf":
        return None
    endian = (codecs[0].get("configuration") or {}).get("endian", "little")
    dtype = dtype.newbyteorder("<" if endian == "little" else ">")
    fill = _fill(meta.get("fill_value", 0), dtype)
    separator = (keys.get("configuration") or {}).get("separator", "/")
    return _checked(ChunkLayout(directory, tuple(meta["shape"]), tuple(grid["configuration"]["chunk_shape"]), dtype,
                                compressor, separator, fill))


def _layout_v2(directory: str, meta: dict) -> ChunkLayout | None:
    """A Zarr v2 array (``.zarray``) in C order, no filters, one of the known compressors or none."""
    if meta.get("zarr_format") != 2 or meta.get("filters") or meta.get("order", "C") != "C":
        return None
    compressor = meta.get("compressor")
    name = "" if compressor is None else _COMPRESSORS.get(compressor["id"])
    if name is None:
        return None
    dtype = np.dtype(meta["dtype"])
    if dtype.kind not in "biuf":
        return None
    fill = 0 if meta.get("fill_value") is None else _fill(meta["fill_value"], dtype)
    return _checked(ChunkLayout(directory, tuple(meta["shape"]), tuple(meta["chunks"]), dtype, name,
                                meta.get("dimension_separator", "."), fill, ()))


def _fill(fill, dtype: np.dtype) -> float | int:
    """A fill value of the metadata as a number (``ValueError`` for one this reader does not read)."""
    if isinstance(fill, str):
        special = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}
        if fill not in special or dtype.kind != "f":
            raise ValueError(f"fill value {fill!r}")
        fill = special[fill]
    if isinstance(fill, bool):
        fill = int(fill)
    if not isinstance(fill, (int, float)):
        raise ValueError(f"fill value {fill!r}")
    return fill


def _checked(layout: ChunkLayout) -> ChunkLayout | None:
    ok = (len(layout.shape) == len(layout.chunks) and all(isinstance(n, int) and n >= 0 for n in layout.shape)
          and all(isinstance(c, int) and c > 0 for c in layout.chunks) and layout.separator in ("/", "."))
    return layout if ok else None


class ChunkCache:
    """Decoded chunks kept for the next reads of this process: an LRU of at most ``capacity``
    bytes, shared by the process's threads.

    A chunk is keyed by its file's identity (path, inode, size, modification time), so a
    rewritten chunk or another scan is never served from an old entry, and a chunk two
    threads want at once is decoded by one while the other waits (neighbouring blocks run
    side by side and share the chunks between them). Entries are read-only arrays.
    """

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self.held = 0
        self.hits = self.decoded = 0
        self._entries: OrderedDict = OrderedDict()
        self._pending: dict = {}
        self._lock = threading.Lock()

    def get(self, key, decode) -> np.ndarray:
        """The chunk ``key`` from the cache, else ``decode()``'s (kept when it fits)."""
        while True:
            with self._lock:
                chunk = self._entries.get(key)
                if chunk is not None:
                    self._entries.move_to_end(key)
                    self.hits += 1
                    return chunk
                waiting = self._pending.get(key)
                if waiting is None:
                    self._pending[key] = threading.Event()
                    break
            waiting.wait()  # another thread decodes it: then read it from the cache (or decode, if evicted)
        try:
            chunk = decode()
            chunk.setflags(write=False)
            with self._lock:
                self.decoded += 1
                self._put(key, chunk)
            return chunk
        finally:
            with self._lock:
                self._pending.pop(key).set()

    def _put(self, key, chunk: np.ndarray) -> None:
        if chunk.nbytes > self.capacity:
            return
        self._entries[key] = chunk
        self.held += chunk.nbytes
        while self.held > self.capacity:
            _, old = self._entries.popitem(last=False)
            self.held -= old.nbytes

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
            self.held = 0


_cache: ChunkCache | None = None
_cache_lock = threading.Lock()


def chunk_cache() -> ChunkCache | None:
    """This process's :class:`ChunkCache` (``chunkdic.chunk-cache`` bytes; None when 0)."""
    global _cache
    from .. import config

    capacity = int(config.get("chunk-cache") or 0)
    with _cache_lock:
        if _cache is None or _cache.capacity != capacity:
            _cache = ChunkCache(capacity) if capacity > 0 else None
        return _cache


def forget_chunks() -> None:
    """Empty this process's chunk cache (the end of a level: its memory back)."""
    with _cache_lock:
        if _cache is not None:
            _cache.clear()


def cached_chunk(layout: ChunkLayout, index, cache: ChunkCache | None) -> np.ndarray:
    """Chunk ``index`` of the array, through ``cache`` when there is one (:func:`decode_chunk`)."""
    if cache is None:
        return decode_chunk(layout, index)
    file = layout.chunk_file(index)
    try:
        st = os.stat(file)
    except FileNotFoundError:
        return decode_chunk(layout, index)  # the fill value: nothing to keep
    return cache.get((str(file), st.st_ino, st.st_size, st.st_mtime_ns), lambda: decode_chunk(layout, index))


def decode_chunk(layout: ChunkLayout, index) -> np.ndarray:
    """Chunk ``index`` of the array, decoded (shape ``layout.chunks``, native byte order).

    A chunk with no file is the fill value (as zarr reads it). Raises ValueError for a
    chunk whose bytes are not a whole frame of the array's codec (:class:`ChunkDamaged`).
    """
    file = layout.chunk_file(index)
    try:
        data = file.read_bytes()
    except FileNotFoundError:
        return np.full(layout.chunks, layout.fill, layout.dtype.newbyteorder("="))
    try:
        raw = _decompress(layout, data)
    except Exception as exc:  # noqa: BLE001 - the decoder's own error, named with the chunk
        raise ChunkDamaged(index, file, f"{type(exc).__name__}: {exc}".splitlines()[0][:200]) from None
    if len(raw) != layout.chunk_bytes:
        raise ChunkDamaged(index, file, f"decodes to {len(raw)} bytes, not the chunk's {layout.chunk_bytes}")
    chunk = np.frombuffer(raw, layout.dtype).reshape(layout.chunks)
    return chunk if layout.dtype.isnative else chunk.astype(layout.dtype.newbyteorder("="))


def _decompress(layout: ChunkLayout, data: bytes):
    if layout.compressor == "blosc":
        from numcodecs import blosc

        from .store import blosc_header_fault

        # the frame's own lengths first: the decoder reads cbytes bytes whatever the buffer
        # holds (numcodecs issue #228)
        fault = blosc_header_fault(data, len(data), layout.chunk_bytes)
        if fault is not None:
            raise ValueError(fault)
        return blosc.decompress(data)
    if layout.compressor == "zstd":
        from numcodecs import zstd

        declared = zstd_content_size(data)
        if declared is not None and declared != layout.chunk_bytes:
            raise ValueError(f"its zstd frame declares {declared} bytes, not the chunk's {layout.chunk_bytes}")
        out = bytearray(layout.chunk_bytes)  # the bound: a frame that needs more fails
        zstd.decompress(data, out)
        return out
    if layout.compressor == "zlib":
        stream = zlib.decompressobj(32 + zlib.MAX_WBITS)  # a zlib or a gzip header, recognised
        out = stream.decompress(data, layout.chunk_bytes + 1)
        if len(out) > layout.chunk_bytes or stream.unconsumed_tail:
            raise ValueError(f"its stream decodes to more than the chunk's {layout.chunk_bytes} bytes")
        return out + stream.flush()
    return data


def zstd_content_size(data: bytes) -> int | None:
    """The decoded size a zstd frame's header declares (RFC 8878, 3.1.1), or None when it
    declares none (or ``data`` is no zstd frame: its decoder says so)."""
    if len(data) < 6 or data[:4] != b"\x28\xb5\x2f\xfd":
        return None
    descriptor = data[4]
    single = (descriptor >> 5) & 1
    pos = 5 + (0 if single else 1) + (0, 1, 2, 4)[descriptor & 3]  # window descriptor, dictionary id
    size = (1 if single else 0, 2, 4, 8)[descriptor >> 6]
    if size == 0 or len(data) < pos + size:
        return None
    value = int.from_bytes(data[pos:pos + size], "little")
    return value + 256 if size == 2 else value


def read_region(layout: ChunkLayout, region) -> np.ndarray:
    """``region`` (slices within the array, step 1) of the array, assembled from its chunks.

    Each chunk the region crosses is taken from this process's :func:`chunk_cache` or read
    and decoded, and its overlap copied out. Returns a new C-ordered array of the array's
    dtype (native byte order).
    """
    cache = chunk_cache()
    bounds = [(s.start, s.stop) for s in region]
    out = np.empty([b - a for a, b in bounds], layout.dtype.newbyteorder("="))
    if out.size == 0:
        return out
    ranges = [range(a // c, (b - 1) // c + 1) for (a, b), c in zip(bounds, layout.chunks)]
    for index in itertools.product(*ranges):
        chunk = cached_chunk(layout, index, cache)
        src, dst = [], []
        for (a, b), i, c in zip(bounds, index, layout.chunks):
            lo, hi = max(a, i * c), min(b, (i + 1) * c)
            src.append(slice(lo - i * c, hi - i * c))
            dst.append(slice(lo - a, hi - a))
        out[tuple(dst)] = chunk[tuple(src)]
    return out


def read_whole(path: str, key: str = "") -> np.ndarray | None:
    """The whole Zarr array ``path``/``key`` from its chunk files (:func:`read_region`: every chunk
    decoded into at most its own size), or None when this module does not read its layout."""
    layout = layout_of(str(path), key)
    if layout is None:
        return None
    return read_region(layout, tuple(slice(0, n) for n in layout.shape))


def z_order_key(index) -> int:
    """Position of the grid cell ``index`` (3 non-negative ints) along the Z-order (Morton)
    curve: the bits of the three indices interleaved, z the most significant.

    Tasks run in this order read neighbouring regions close in time, so the chunks their
    halos share are still in the :func:`chunk_cache` (in row-major order a block's
    neighbour in the next plane comes a whole plane of blocks later). Simulated for the
    ``M`` pass of 1024³ (512 blocks, 128³ chunks, LRU of 24 chunks): each chunk decoded
    2.1 times in Z-order, 3.3 in row-major order, 6.6 without a cache.
    """
    key = 0
    for bit in range(21):
        for axis, i in enumerate(index):
            key |= ((int(i) >> bit) & 1) << (3 * bit + 2 - axis)
    return key
