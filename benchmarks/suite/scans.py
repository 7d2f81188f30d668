"""Ingest of a 128³ uint16 scan and its pyramid; the plan's memory estimate against a run."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from .common import cache_dir, remove, workdir, write_pair

EDGE = 128


class Ingest:
    """``chunkdic.ingest`` of a 128³ uint16 ``.npy`` file, then ``build_pyramid`` to level 3."""

    repeat = (1, 3, 30.0)
    number = 1

    def setup(self):
        self.dir = workdir("ingest")
        rng = np.random.default_rng(0)
        self.src = self.dir / "scan.npy"
        np.save(self.src, rng.integers(0, 65535, (EDGE,) * 3, dtype=np.uint16))
        self.runs = 0

    def teardown(self):
        remove(self.dir)

    def time_ingest(self):
        import chunkdic

        self.runs += 1
        chunkdic.ingest(self.src, self.dir / f"scan{self.runs}.zarr", voxel_size=5.0, unit="um")

    def time_ingest_and_pyramid(self):
        import chunkdic

        self.runs += 1
        out = self.dir / f"scan{self.runs}.zarr"
        chunkdic.ingest(self.src, out, voxel_size=5.0, unit="um")
        chunkdic.build_pyramid(out, 3)


_MEASURE = """
import json, resource, sys
import chunkdic
ref, deformed, out = sys.argv[1:4]
plan = chunkdic.plan(ref, deformed, element_size=8, calibrate=False)
chunkdic.correlate(ref, deformed, element_size=8, output=out)
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps({"planned": plan.process_bytes, "peak": peak}))
"""


class PlanEstimate:
    """The plan's memory per process against the measured peak of the same run (fresh process)."""

    timeout = 600
    repeat = (1, 1, 60.0)

    def setup_cache(self):
        return write_pair(cache_dir("plan"))

    def track_memory_estimate_error(self, pair):
        """(planned − measured) / measured peak resident memory, percent."""
        run = workdir("plan-run")
        try:
            done = subprocess.run([sys.executable, "-c", _MEASURE, pair["ref"], pair["def"], str(run / "result.zarr")],
                                  capture_output=True, text=True, check=True)
        finally:
            remove(run)
        m = json.loads(done.stdout.strip().splitlines()[-1])
        return 100.0 * (m["planned"] - m["peak"]) / m["peak"]

    track_memory_estimate_error.unit = "%"
