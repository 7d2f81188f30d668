"""Shared cases of the suite: a synthetic pair with a known field, written once per run."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

#: edge of the correlated pair; the issue's "correlate at 96³"
SIZE = 96
#: the element edges the correlation benchmarks are parametrised by
ELLS = (16, 12, 8)


def affine_field(n: int):
    """−1 % along z, 0.5 % shear in (z, x) and a translation, about the volume's centre."""
    from chunkdic.synth import synthetic

    c = (n - 1) / 2.0
    return synthetic.Affine(matrix=((-0.01, 0.0, 0.005), (0.0, 0.0, 0.0), (0.005, 0.0, 0.0)), center=(c, c, c),
                            translation=(1.3, -0.7, 0.4))


def write_pair(root: Path, n: int = SIZE) -> dict:
    """A foam-like pair of edge ``n`` with :func:`affine_field`; the paths of its scans."""
    from chunkdic.synth import synthetic

    synthetic.synthesize(root / "pair", (n, n, n), field=affine_field(n), seed=1)
    return {"ref": str(root / "pair" / "ref.zarr"), "def": str(root / "pair" / "def.zarr"), "n": n}


def workdir(name: str) -> Path:
    """A new temporary directory (``remove`` it in the benchmark's ``teardown``)."""
    root = Path(os.environ.get("CHUNKDIC_ASV_TMP", tempfile.gettempdir()))
    return Path(tempfile.mkdtemp(prefix=f"chunkdic-asv-{name}-", dir=root))


def cache_dir(name: str) -> Path:
    """Where ``setup_cache`` writes: asv runs it in a directory it removes after the benchmarks."""
    path = Path.cwd() / name
    path.mkdir()
    return path


def remove(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


def textured_volume(shape, seed: int = 0) -> np.ndarray:
    """A smooth random texture in 0..255, float32."""
    import scipy.ndimage as ndi

    rng = np.random.default_rng(seed)
    vol = ndi.gaussian_filter(rng.random(shape, dtype=np.float32), 1.2)
    return ((vol - vol.min()) / (vol.max() - vol.min()) * 255).astype(np.float32)
