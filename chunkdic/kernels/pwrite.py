"""Rows of a 3-D region written into a raw file by ``pwrite``, without the GIL (numba).

The prefilter of ``g`` writes each task's region into a memory-mappable ``.npy`` store
(:func:`chunkdic.passes.prefilter.write_npy_region`) one row at a time (its rows are not
contiguous in the file): 21 600 ``pwrite`` calls for a 147³ task. From Python, each call
releases and retakes the GIL; with two such tasks and the client in one process on a busy
machine the threads queued for it (the convoy effect) and a task took 1-5 s instead of
0.05-0.2 s. Here the whole loop runs in one ``nogil`` call. ``pwrite`` is bound by name
(an external symbol of the C library, resolved when the kernel is compiled or loaded from
numba's cache), so the kernel caches like the others.
"""

from __future__ import annotations

from numba import types

from .interp import jit

#: ``ssize_t pwrite(int fd, const void *buf, size_t count, off_t offset)`` (POSIX; the
#: buffer's address passed as an integer of the pointer's size)
_PWRITE = types.ExternalFunction("pwrite", types.intp(types.int32, types.uintp, types.uintp, types.int64))


@jit
def write_rows(fd, data, offset, row, plane):
    """Write each x row of ``data`` (nz, ny, nx; its rows contiguous) at ``offset + z * plane
    + y * row`` bytes of the open file ``fd``; 0, or -1 if a write failed (disk full)."""
    nz, ny, nx = data.shape
    nbytes = nx * data.itemsize
    for z in range(nz):
        for y in range(ny):
            address = data[z, y].ctypes.data
            at = offset + z * plane + y * row
            done = 0
            while done < nbytes:  # a regular file may take fewer bytes at once
                n = _PWRITE(fd, address + done, nbytes - done, at + done)
                if n <= 0:
                    return -1
                done += n
    return 0
