"""How a level's scratch stores are kept: the fast layout, or the compact one when the disk is short.

A level-0 run keeps two scratch stores of the size of the scan (the haloed low-passed
``f`` and the prepared ``g``, :mod:`chunkdic.passes.haloed`, :mod:`chunkdic.passes.prefilter`).
Both are on a 16-bit grid of the scan's range: one grey level per step for 16-bit scans,
about 1/200 of the noise left after the low-pass of a CT scan. On such a grid the
low-passed noise fills every bit, and no lossless codec of numcodecs gains more than 6-11 %
(measured on the grains pair, docs/engine.md "Scratch disk"), so the fast layout keeps
them uncompressed (the prepared ``g`` a memory-mapped ``.npy`` when every task is local).

The **compact** layout (``chunkdic.scratch-layout``: ``"auto"``, the default, lets the plan
choose it when the fast one does not fit the free disk; ``"fast"``, ``"compact"`` force
one) stores both on a grid :data:`COMPACT_STEP` times coarser (16 grey levels per step
for 16-bit scans: 4 096 steps over the dtype's range, a rounding of σ 4.6 grey levels) and
compresses them (:data:`COMPACT_CODECS`): the rounding error, 1/45 of the low-passed noise
of the grains pair, stays far below the measurement noise, and the cleared low bits let
the codecs find the redundancy the noise hid. Measured: 0.55 (``f``) and 0.74 (``g``) of
the uncompressed bytes, ``b`` passes slower by the decoding.
Only 1- and 2-byte integer scan levels are stored so (float levels stay float32: at
level ≥ 1 a 16-bit scan's sums are 1/8 of level 0 or less).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from .. import config

#: steps of the 16-bit scratch grid merged into one by the compact layout
COMPACT_STEP = 16
#: the compact layout's codecs (blosc). The haloed ``f``: zstd level 1 with byte shuffle
#: (0.55 of the fast store on the grains pair); each block reads its own one chunk. The
#: prepared ``g``: lz4 with bit shuffle (0.74): a block's window spans 27-64 of its 64³
#: chunks, and zstd's decoding made that read 3.4x slower than lz4's (137 against 40 ms
#: for a 136³ window; 1.5 ms from the fast layout's memory-mapped file)
COMPACT_CODECS = {"f": {"cname": "zstd", "clevel": 1, "shuffle": "shuffle"},
                  "g": {"cname": "lz4", "clevel": 5, "shuffle": "bitshuffle"}}
#: planned bytes of each compact store per byte of its fast one (measured 0.55 and 0.74 on
#: the grains pair, docs/engine.md "Scratch disk"; kept above: noisier scans compress less)
COMPACT_RATIO = {"f": 0.60, "g": 0.78}
#: the work of a level whose stores are compact, per unit of the fast layout's (measured
#: on the 256³ grains pair, CPU seconds: ``M`` pass 1.14x, each ``b`` pass 1.20x;
#: docs/engine.md "Scratch disk")
COMPACT_WORK = 1.2
LAYOUTS = ("auto", "fast", "compact")


def layout() -> str:
    """``chunkdic.scratch-layout`` checked: ``"auto"``, ``"fast"`` or ``"compact"``."""
    from ..errors import InputError

    value = str(config.get("scratch-layout") or "auto").lower()
    if value not in LAYOUTS:
        raise InputError(f"chunkdic.scratch-layout={value!r}: use auto, fast or compact")
    return value


def compact() -> bool:
    """Scratch stores written now use the compact layout (the run's plan sets ``"compact"``
    for its duration when it chose it)."""
    return layout() == "compact"


def step_factor() -> int:
    """Factor of the 16-bit grid's step in the current layout."""
    return COMPACT_STEP if compact() else 1


def compressors(store: str, itemsize: int):
    """Zarr compressors of scratch store ``store`` (``"f"``: haloed ``f``, ``"g"``: prepared ``g``)
    in the current layout (``None``: uncompressed)."""
    if not compact():
        return None
    from zarr.codecs import BloscCodec

    return (BloscCodec(typesize=int(itemsize), **COMPACT_CODECS[store]),)


def read_chunk(path: str, index, shape, dtype, compressed: bool) -> np.ndarray:
    """Chunk ``index`` of a scratch Zarr v3 array this module's layouts wrote, read from its file.

    The stores are chunkdic's own (default chunk keys ``c/i/j/k``, little-endian bytes,
    then blosc when ``compressed``), so a task reads a chunk's file and decodes it itself:
    through zarr-python a 130³ chunk took 18 ms and a block's window of the prepared ``g``
    over 27 compressed chunks 60 ms, against 34 ms read so (a quarter of a ``b`` pass's
    time per block under load). A chunk never written (zarr skips chunks equal to the fill
    value) reads as zeros.
    """
    file = Path(path, "c", *map(str, index))
    try:
        data = file.read_bytes()
    except FileNotFoundError:
        return np.zeros(shape, dtype)
    if compressed:
        from numcodecs import blosc

        data = blosc.decompress(data)
    return np.frombuffer(data, np.dtype(dtype).newbyteorder("<")).reshape(shape)


def read_window(path: str, window, chunk: int, dtype, compressed: bool) -> np.ndarray:
    """``window`` (slices, array indices) of a 3-D scratch array of ``chunk``³ chunks,
    assembled from the chunks' files (:func:`read_chunk`)."""
    out = np.empty([w.stop - w.start for w in window], dtype)
    first = [w.start // chunk for w in window]
    last = [(w.stop - 1) // chunk for w in window]
    for i in range(first[0], last[0] + 1):
        for j in range(first[1], last[1] + 1):
            for k in range(first[2], last[2] + 1):
                c = read_chunk(path, (i, j, k), (chunk,) * 3, dtype, compressed)
                lo = [max(w.start, n * chunk) for w, n in zip(window, (i, j, k))]
                hi = [min(w.stop, (n + 1) * chunk) for w, n in zip(window, (i, j, k))]
                src = tuple(slice(a - n * chunk, b - n * chunk) for a, b, n in zip(lo, hi, (i, j, k)))
                dst = tuple(slice(a - w.start, b - w.start) for a, b, w in zip(lo, hi, window))
                out[dst] = c[src]
    return out


def f_store(scratch, level: int) -> Path:
    """The haloed ``f`` of a level in the run's scratch directory (:mod:`chunkdic.passes.haloed`)."""
    return Path(scratch) / f"f-level{int(level)}.zarr"


def g_store(scratch, level: int, build: int) -> Path:
    """The ``build``-th prepared ``g`` of a level in the run's scratch directory (:mod:`chunkdic.passes.prefilter`)."""
    return Path(scratch) / f"g-level{int(level)}-{int(build)}.zarr"


def prune_adopted(scratch: Path, level: int | None) -> None:
    """Remove from an adopted scratch directory (:func:`chunkdic.io.ownership.adopt_scratch`) the
    level stores no level of this run will adopt: those of levels coarser than ``level`` (the
    level of the interrupted run's checkpoint, done or under way; None: keep every level's),
    a prepared ``g`` left without its completion record or superseded by a later build, and
    the mask's levels (prepared again: :func:`chunkdic.passes.masks.prepare_mask` writes a new
    group)."""
    scratch = Path(scratch)
    latest: dict[int, int] = {}
    for rec in scratch.glob("g-level*-*.prepared.json"):
        name = rec.name[len("g-level"):].split(".")[0]
        try:
            s, k = (int(v) for v in name.split("-"))
        except ValueError:
            continue
        latest[s] = max(latest.get(s, -1), k)
    doomed = [scratch / "mask"]
    for entry in scratch.iterdir():
        name = entry.name
        if not (name.startswith("f-level") or name.startswith("g-level")):
            continue
        try:
            if name.startswith("f-level"):
                s, k = int(name[len("f-level"):].split(".")[0]), None
            else:
                s, k = (int(v) for v in name[len("g-level"):].split(".")[0].split("-"))
        except ValueError:
            doomed.append(entry)
            continue
        if (level is not None and s > level) or (k is not None and k != latest.get(s)):
            doomed.append(entry)
    for path in doomed:
        shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)
