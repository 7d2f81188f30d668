"""The DVC Challenge 2.0 numbers and the noise floors of repeated scans, against known answers."""

from __future__ import annotations

import json

import numpy as np
import pytest

import chunkdic
from chunkdic.analysis.challenge import challenge_numbers, noise_floors
from chunkdic.cli.app import main
from chunkdic.results.result import open_result
from chunkdic.synth import synthetic
from chunkdic.synth.fields import Affine
from chunkdic.synth.foam import render


def test_noise_floors_of_fields_sharing_the_reference_noise():
    """``u_k = a + b_k`` (``a`` the reference's noise, common; ``b_k`` each repeat's), σ = 0.1 each,
    plus a translation per field: spatial = σ√2, temporal = σ (the common part unseen), within 3 %."""
    rng = np.random.default_rng(0)
    a = 0.1 * rng.standard_normal((3, 40000))
    fields = [a + 0.1 * rng.standard_normal((3, 40000)) + rng.standard_normal((3, 1)) for _ in range(6)]
    d = noise_floors(fields)
    assert d["spatial"] == pytest.approx(0.1 * np.sqrt(2), rel=0.03)
    assert d["temporal"] == pytest.approx(0.1, rel=0.03) and d["temporal_from"] == "fields"
    one = noise_floors(fields[:1])
    assert one["temporal"] == pytest.approx(one["spatial"]) and one["temporal_from"] == "one field"


def test_challenge_numbers_remove_the_translation_only():
    """A rotation left in the error is noise by the definition: σ of ``ω × X`` over a symmetric grid."""
    z, y, x = np.meshgrid(*[np.arange(-5.0, 6.0)] * 3, indexing="ij")
    err = np.stack([0.01 * y + 0.2, -0.01 * z - 0.1, np.zeros_like(x)]).reshape(3, -1)
    d = challenge_numbers(err)
    assert d["bias_z"] == pytest.approx(0.2) and d["bias_y"] == pytest.approx(-0.1)
    assert d["noise_floor_z"] == pytest.approx(0.01 * np.sqrt(10.0))  # std of y over -5..5: √10
    assert d["u_rms"] == pytest.approx(float(np.sqrt(np.mean(err**2))))


def test_uncertainty_repeat_gives_spatial_and_temporal_noise_floors(tmp_path, capsys):
    """Three scans of one foam with independent noise: ``uncertainty --repeat`` correlates the second
    and third against the first; its spatial floor is the std of each stored field about its mean
    (recomputed here from the results), its temporal floor smaller (the first scan's noise is common)."""
    f0 = render((40,) * 3, seed=3)
    paths = []
    for k in range(3):
        rng = np.random.default_rng(10 + k)
        paths.append(str(tmp_path / f"s{k}.npy"))
        np.save(paths[-1], (f0 + 0.03 * rng.standard_normal(f0.shape)).astype(np.float32))
    out = tmp_path / "out"
    assert main(["uncertainty", paths[0], "--repeat", *paths[1:], "-l", "8", "-o", str(out), "-q"]) == 0
    row = next(iter(__import__("csv").DictReader(open(out / "uncertainty.csv"))))
    stds = []
    for k in (1, 2):
        u = open_result(out / f"result-ell8-repeat{k}.zarr").displacement
        inner = u[:, 1:-1, 1:-1, 1:-1].reshape(3, -1)  # the nodes at least ℓ from the faces (ROI 4:36)
        stds.append(inner.std(axis=1))
    assert float(row["spatial"]) == pytest.approx(float(np.sqrt(np.mean(np.square(stds)))), rel=1e-6)
    assert 0 < float(row["temporal"]) < float(row["spatial"])
    assert int(row["fields"]) == 2


def test_stats_truth_gives_the_challenge_numbers_of_the_error(tmp_path, capsys):
    n = 40
    field = Affine(matrix=((-0.01, 0, 0), (0, 0, 0), (0, 0, 0)), center=(n / 2,) * 3, translation=(0.3, 0.2, -0.4))
    pair = synthetic.synthesize(tmp_path / "pair", n, field=field, seed=4, dtype="float32", noise=0.02)
    chunkdic.correlate(pair["reference"], pair["deformed"], element_size=8, output=tmp_path / "r.zarr")
    assert main(["stats", str(tmp_path / "r.zarr"), "--truth", str(tmp_path / "pair"), "--json"]) == 0
    rows = {r["quantity"]: r for r in json.loads(capsys.readouterr().out)["rows"]}
    res = open_result(tmp_path / "r.zarr")
    err = res.displacement - field.displacement(*res.node_coords)
    for c, q in enumerate(("Uz", "Uy", "Ux")):
        assert rows[q]["bias"] == pytest.approx(float(err[c].mean()), abs=1e-12)
        assert rows[q]["noise_floor"] == pytest.approx(float(err[c].std()), abs=1e-12)
        assert rows[q]["u_rms"] == pytest.approx(float(np.sqrt(np.mean(err[c] ** 2))), abs=1e-12)
    assert abs(rows["E_zz"]["mean"] - ((0.99**2 - 1) / 2)) < 5e-4
