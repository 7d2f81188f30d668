"""Correlating with a known crack surface (``correlate(crack=…)``, docs/cracks.md).

Truths: the analytic crack field of :class:`chunkdic.synth.fields.Crack` on the procedural
foam (noise-free): a ±0.15 voxel jump (opening 0.3) across a plane through the whole volume,
normal to z and oblique; the exact no-crack result when the labels split nothing; the
dense twin against the block passes; the one-line refusals.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import chunkdic
from chunkdic.engine.meshes import plan_meshes
from chunkdic.method.level_solve import run_level
from chunkdic.method.runstate import RunState
from chunkdic.method.settings import Settings
from chunkdic.passes.dense import DensePasses
from chunkdic.passes.prefilter import face_margin
from chunkdic.synth import foam
from chunkdic.synth.fields import Crack

N = 48
ELL = 8


def _pair(normal, n=N):
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    point = (n / 2,) * 3
    field = Crack(normal=tuple(normal), point=point, opening=0.3)
    f = foam.render((n,) * 3, seed=5)
    g = foam.render((n,) * 3, seed=5, field=field, which="deformed")
    X = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"))
    distance = sum((X[i] - point[i]) * normal[i] for i in range(3))
    labels = (np.abs(distance) < np.abs(normal).sum() / 2).astype(np.uint8)  # a 6-separating digital plane
    return f, g, field, labels


@pytest.mark.parametrize("normal", [(1, 0, 0), (1, 0.5, 0)])
def test_a_through_crack_is_measured_within_0_02_voxel_on_both_sides(normal):
    f, g, field, labels = _pair(normal)
    plain = chunkdic.correlate(f, g, element_size=ELL, coarsest=0)
    cracked = chunkdic.correlate(f, g, element_size=ELL, coarsest=0, crack=labels)
    truth = field.displacement(*cracked.node_coords)
    err = np.abs(cracked.displacement - truth).max()
    err_plain = np.abs(plain.displacement - truth).max()
    print(f"normal {normal}: max nodal error {err:.4f} voxel with --crack, {err_plain:.4f} without")
    assert cracked.info["status"] == "converged"
    assert err < 0.02  # every node (a through-crack has no tip), both sides
    assert err_plain > 0.05  # the smeared jump the crack option removes
    assert cracked.info["crack"]["cut_edges"] > 0
    split = np.isfinite(cracked.other_side[0])
    assert split.sum() == cracked.info["crack"]["split_nodes"]
    if split.any():  # the second copies hold the other side's field (extrapolated over a sliver)
        jump = field.jump[:, None]
        other = cracked.other_side[:, split]
        own = truth[:, split]
        assert np.abs(np.abs(other - own) - np.abs(jump)).max() < 0.05


def test_labels_that_split_nothing_give_exactly_the_plain_result():
    f, g, _, _ = _pair((1, 0, 0), n=48)
    blob = np.zeros(f.shape, np.uint8)
    blob[22:24, 22:24, 22:24] = 1  # inside one element, off every mesh edge: no support split
    plain = chunkdic.correlate(f, g, element_size=ELL, coarsest=0)
    cracked = chunkdic.correlate(f, g, element_size=ELL, coarsest=0, crack=blob)
    np.testing.assert_array_equal(cracked.displacement, plain.displacement)
    assert "crack" not in cracked.info and cracked.other_side is None  # the surface meets no mesh edge


def test_the_dense_twin_equals_the_block_passes_with_a_crack():
    f, g, field, labels = _pair((1, 0.5, 0), n=48)
    settings = Settings(element_size=ELL, coarsest=0, block_elements=2)
    meshes = plan_meshes(f.shape, element_size=ELL, level=0, coarsest=0, min_margin=face_margin(settings.smoothing))
    passes = DensePasses(f, g, meshes[0], settings, crack=labels, impl="numba")
    run, outcome = run_level(passes, RunState(), None, meshes=meshes, levels=[0], settings=settings)
    res = chunkdic.correlate(f, g, settings, crack=labels)  # blocks of 2³ elements: cut elements across blocks
    assert len(outcome.split) > 0
    np.testing.assert_allclose(res.displacement, run.gn.u, rtol=0, atol=1e-10)
    # the second copies (slivers of the other side, weakly determined) amplify the float32
    # round-off of M's block sums: 4e-10 measured
    np.testing.assert_allclose(res.other_side[(slice(None), *outcome.split.T)], run.gn.u_other.T, rtol=0, atol=1e-8)


@pytest.mark.parametrize("labels,message", [
    ("wrong.npy", "crack labels have shape"), ("empty.npy", "no non-zero voxel"),
    ("grey.npy", "a label image"), ("missing.npy", "does not exist"),
])
def test_bad_crack_labels_are_refused_in_one_line_before_any_output(tmp_path, labels, message):
    n = 24
    f = foam.render((n,) * 3, seed=5)
    np.save(tmp_path / "f.npy", f)
    np.save(tmp_path / "wrong.npy", np.ones((n - 2, n, n), np.uint8))
    np.save(tmp_path / "empty.npy", np.zeros((n,) * 3, np.uint8))
    np.save(tmp_path / "grey.npy", f)
    out = tmp_path / "r.zarr"
    proc = subprocess.run([sys.executable, "-m", "chunkdic", "correlate", str(tmp_path / "f.npy"),
                           str(tmp_path / "f.npy"), "-o", str(out), "-l", "8", "--coarsest", "0",
                           "--crack", str(tmp_path / labels)], capture_output=True, text=True)
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1 and message in proc.stderr
    assert not out.exists()


def test_the_equilibrium_gap_is_refused_with_a_crack():
    f, g, _, labels = _pair((1, 0, 0), n=24)
    with pytest.raises(chunkdic.InputError, match="equilibrium-gap"):
        chunkdic.correlate(f, g, element_size=ELL, coarsest=0, crack=labels, regularization="equilibrium-gap")
