"""The 2-D check shares the 3-D engine's stopping rule without loading the 3-D engine."""

from __future__ import annotations

import json
import subprocess
import sys


def test_q4_loads_neither_the_block_kernels_nor_the_multigrid():
    code = ("import json, sys, chunkdic.analysis.q4; "
            "print(json.dumps(sorted(m for m in sys.modules if m.startswith('chunkdic'))))")
    loaded = set(json.loads(subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                                           text=True).stdout))
    assert "chunkdic.method.stopping" in loaded  # the shared rule is there...
    heavy = {m for m in loaded if m.startswith(("chunkdic.kernels.", "chunkdic.solve."))}
    heavy |= loaded & {"chunkdic.passes.level", "chunkdic.method.gauss_newton", "chunkdic.engine.driver"}
    assert not heavy, sorted(heavy)  # ...and none of the 3-D block engine or its solvers
