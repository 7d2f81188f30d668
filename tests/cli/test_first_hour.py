"""First hour (issue 23, item 8): the README's demo runs on the core dependencies alone.

``pip install -e .`` installs ``[project] dependencies`` only; the test extra (pytest,
xarray, pandas, ome-zarr, napari, ...) is for the tests. The demo runs here in a process
where every test-only package fails to import.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[2]
#: import names of the test extra's packages (and napari's reader stack), blocked in the demo's process
TEST_ONLY = ("pytest", "xarray", "pandas", "ome_zarr", "napari", "napari_ome_zarr", "npe2", "dask_jobqueue",
             "importlinter")
BLOCKER = f"""
import sys
class _TestOnly:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {TEST_ONLY!r}:
            raise ImportError("test-only package " + name + " imported by the demo")
sys.meta_path.insert(0, _TestOnly())
"""


def test_the_readme_starts_with_the_demo_on_core_dependencies_then_the_tests():
    readme = (ROOT / "README.md").read_text().splitlines()
    assert readme[3] == "python3 -m venv .venv && .venv/bin/pip install -e . && .venv/bin/chunkdic demo"
    assert readme[4] == "python3 -m venv .venv && .venv/bin/pip install -e '.[test]' && .venv/bin/python -m pytest -q"
    core = " ".join(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]).lower()
    assert not [name for name in ("pytest", "xarray", "pandas", "ome-zarr", "napari", "jobqueue", "import-linter")
                if name in core]


@pytest.mark.slow
def test_demo_runs_without_the_test_extra(tmp_path):
    (tmp_path / "site").mkdir()
    (tmp_path / "site" / "sitecustomize.py").write_text(BLOCKER)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), str(ROOT)])}
    proc = subprocess.run([sys.executable, "-m", "chunkdic", "demo", str(tmp_path / "demo"), "--size", "32",
                           "--element-size", "8"], capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    assert "RMS nodal error vs the known field" in proc.stderr and "test-only" not in proc.stderr
    # the blocker works: the same process refuses a test-only import
    check = subprocess.run([sys.executable, "-c", "import xarray"], capture_output=True, text=True, env=env)
    assert check.returncode == 1 and "test-only package xarray" in check.stderr
