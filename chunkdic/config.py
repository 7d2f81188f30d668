"""Runtime knobs, kept in ``dask.config`` under the ``chunkdic.`` namespace.

One YAML file (``~/.config/dask/chunkdic.yaml``) or ``DASK_CHUNKDIC__…`` environment
variables configure Dask and chunkdic together, e.g.
``DASK_CHUNKDIC__BLOCK_VOXELS=192`` for larger work units.
"""

from __future__ import annotations

import dask.config

DEFAULTS = {
    "chunkdic": {
        # Target edge of a correlation work unit (voxels); the block holds the largest
        # whole number of elements that fits (at least one).
        "block-voxels": 128,
        # Largest edge (voxels) of a task of the prefilter of g (its halo: 16 voxels per side;
        # None: 160, chunkdic.passes.prefilter.TASK_EDGE).
        "prepare-voxels": None,
        # Peak resident memory per process to plan for ("2GiB"; None: no target): block and
        # prefilter task sizes are chosen to fit it, a run that cannot is refused (docs/engine.md).
        "memory-target": None,
        # Where a level's mesh-sized data (M's stencil, the brightness cells' couplings, the
        # solver's vectors) live: "client" (in the client process), "blocks" (in node blocks on
        # the workers of a cluster, or the stencil and cells in files under the scratch with the
        # embedded scheduler, the vectors in the client) or "auto": in blocks on the levels whose mesh data do not fit the memory
        # target (the plan says which). docs/distributed.md, "Mesh data beyond one process".
        "mesh-data": "auto",
        # Nodes from which a level's mesh data go to blocks: set by the plan under "auto"
        # (None: no level).
        "mesh-blocks-from": None,
        # Where those node blocks go, set by the plan: "workers" (a cluster's) or "disk" (files
        # under the scratch, their products in the client: the embedded scheduler's, and a
        # cluster's whose workers cannot hold their share); None: the scheduler's first choice.
        "mesh-blocks-on": None,
        # Storage in scratch of the low-passed f blocks and the prepared g of a 1- or 2-byte
        # integer scan level: "uint16" (on a 16-bit grid of the dtype's range: half the disk)
        # or "float32" (exact). docs/engine.md, "Scratch disk".
        "scratch-precision": "uint16",
        # Layout of those stores: "fast" (uncompressed), "compact" (a 16x coarser grid,
        # compressed: 0.65 of the bytes, slower passes) or "auto": the plan chooses compact
        # only when the fast layout does not fit the free disk. docs/engine.md, "Scratch disk".
        "scratch-layout": "auto",
        # Bytes of decoded scan chunks each process keeps for the next reads (an LRU shared by
        # its threads; 0: none): a block's low-pass halo crosses 8 chunks of the scan, each
        # shared with the neighbouring blocks (docs/distributed.md, "Reading the scans' chunks").
        "chunk-cache": 100663296,
        # Halo (voxels) around a window prefiltered for cubic B-spline interpolation.
        "bspline-halo": 12,
        # Chunk edge of arrays chunkdic writes (scans, pyramid levels, scratch).
        "chunk-size": 128,
        # Compressor of scans chunkdic writes: "auto" (zstd-1 for 1-byte data, blosc-lz4
        # with bit shuffle for wider types, see docs/scans.md), "zstd", "lz4" or "none".
        "compressor": "auto",
        # Bytes of source read per ingest task (a slab of whole chunks).
        "ingest-slab-bytes": 33554432,
        # Where inputs that are not on disk and missing pyramid levels are spilled.
        "scratch-directory": None,
        # Number of threads of the embedded scheduler (None: all cores).
        "num-threads": None,
        # Seconds to wait for a scheduler at an address to answer (connection + handshake).
        "connect-timeout": 10,
        # Seconds to wait for a first worker when a cluster has none; then refuse.
        "worker-timeout": 60,
        # A correlation whose final pass excludes more than this fraction of the ROI's
        # voxels (X + u(X) outside the deformed scan) is reported "excluded", not converged.
        "max-excluded-fraction": 0.2,
        # ... and "weak-texture" when more than this fraction of its measured nodes see too
        # little texture (their values come from the regularisation, not the images).
        "max-weak-fraction": 0.2,
        # ... and "mismatch" when more than this fraction of its measured nodes leave a
        # residual that is not noise (chunkdic.method.mismatch: the deformed scan does not
        # match the reference there, whatever the field).
        "max-mismatch-fraction": 0.1,
        # A node whose elements hold fewer valid voxels than this fraction of one element
        # has no data: NaN in the result, flagged.
        "min-node-support": 0.1,
    }
}

dask.config.update_defaults(DEFAULTS)


def get(key: str):
    """Return ``dask.config.get("chunkdic." + key)``."""
    return dask.config.get("chunkdic." + key)
