"""The napari view (issue 23, item 5): chunkdic's npe2 reader and ``chunkdic view``.

A 40³ float32 foam pair with a voxel size of 6.5 µm and a 3-level pyramid, an affine
field, correlated at ℓ = 8 (ROI 4:36, 5³ nodes): once plain (with an ``export --fields``
image beside it), once with a specimen mask; and a 3-scan loading series of the same foam.
The reader is found through the manifest by npe2's own machinery, headless (no viewer, no
Qt), and every layer it returns is built by napari's layer classes.
"""

from __future__ import annotations

import dataclasses
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

import chunkdic
from chunkdic.cli.app import main
from chunkdic.results.result import FLAG_MASKED, FLAG_NO_DATA, FLAG_WEAK
from chunkdic.synth import synthetic
from chunkdic.viewer.layers import layers_of, result_layers
from chunkdic.viewer.mesh_layers import Frame, stride, weak_layer
from chunkdic.viewer.reader import napari_get_reader
from chunkdic.export.voxel_values import CHANNELS
from chunkdic.export.fields_reader import open_levels
from chunkdic.export.fields_image import write_fields

N, ELL, VOXEL = 40, 8, 6.5
C = (N - 1) / 2
MANIFEST = Path(chunkdic.__file__).parent / "viewer" / "napari.yaml"
OPTIONS = dict(element_size=ELL, regularization="none")


def field(k: int):
    e = -0.01 * k
    return synthetic.Affine(matrix=((e, 0, 0), (0, -0.3 * e, 0), (0, 0, -0.3 * e)), center=(C, C, C),
                            translation=(0.4 * k, -0.25 * k, 0.15 * k))


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    d = tmp_path_factory.mktemp("napari")
    scans = []
    for k in range(3):
        lazy = synthetic.as_dask((N,) * 3, chunks=N, field=None if k == 0 else field(k), seed=5,
                                 which="reference" if k == 0 else "deformed", dtype="float32")
        scans.append(chunkdic.write_scan(d / f"scan{k}.zarr", lazy, voxel_size=VOXEL, unit="um", levels=2).path)
    res = chunkdic.correlate(scans[0], scans[1], output=d / "r.zarr", **OPTIONS)
    write_fields(res, d / "r-fields.zarr")
    mask = np.zeros((N,) * 3, np.uint8)
    mask[:, 2:38, 2:38] = 1
    mask[:, 2:10, 2:10] = 0  # a corner of air: the element (0, 0) column is left out
    np.save(d / "mask.npy", mask)
    masked = chunkdic.correlate(scans[0], scans[1], output=d / "masked.zarr", mask=d / "mask.npy", **OPTIONS)
    series = chunkdic.series(scans, d / "series.zarr", mode="incremental", **OPTIONS)
    return {"dir": d, "scans": scans, "res": res, "masked": masked, "mask": mask, "series": series}


def by_name(layers):
    return {kw["name"]: (data, kw, kind) for data, kw, kind in layers}


def test_result_layers_names_shapes_and_physical_frame(made):
    d, res = made["dir"], made["res"]
    layers = layers_of(d / "r.zarr")
    assert [(kw["name"], kind) for _, kw, kind in layers] == [
        ("reference", "image"), ("|U|", "image"), ("eps_zz", "image"), ("eps_eq", "image"),
        ("residual", "image"), ("displacement", "vectors")]
    named = by_name(layers)
    data, kw, _ = named["reference"]
    assert kw["multiscale"] and [a.shape for a in data] == [(40,) * 3, (20,) * 3, (10,) * 3]
    assert kw["scale"] == [VOXEL] * 3 and kw["translate"] == [0.0] * 3 and kw["units"] == ("micrometer",) * 3
    level0 = np.asarray(data[0])
    assert np.allclose(np.asarray(data[1])[3, 4, 5], level0[6:8, 8:10, 10:12].mean(), rtol=1e-6)  # a mean level
    lo, hi = kw["contrast_limits"]
    assert level0.min() <= lo < hi <= level0.max()

    # the fields image found beside the result: its channels on the scan's frame
    levels, _ = open_levels(d / "r-fields.zarr")
    for name in ("|U|", "eps_zz", "eps_eq", "residual"):
        data, kw, _ = named[name]
        assert [a.shape for a in data] == [a.shape[1:] for a in levels] and kw["scale"] == [VOXEL] * 3
        assert np.array_equal(np.asarray(data[0]), levels[0][CHANNELS.index(name)], equal_nan=True)
        assert kw["visible"] == (name == "|U|") and kw["contrast_limits"][0] < kw["contrast_limits"][1]

    # every node (5³ <= 4000), at its level-0 position, the result's displacement, |U| in µm
    data, kw, _ = named["displacement"]
    X = res.node_coords.reshape(3, -1).T
    u = res.displacement.reshape(3, -1).T
    assert data.shape == (125, 2, 3) and kw["scale"] == [VOXEL] * 3
    assert np.allclose(data[:, 0], X, atol=1e-5) and np.allclose(data[:, 1], u, atol=1e-6)
    assert X[0].tolist() == [3.5, 3.5, 3.5]  # node o - 0.5 of the ROI 4:36
    assert np.allclose(kw["features"]["|U|"], VOXEL * np.linalg.norm(u, axis=1), rtol=1e-5)
    longest = kw["length"] * np.linalg.norm(u * VOXEL, axis=1).max()
    assert longest == pytest.approx(0.8 * ELL * VOXEL)  # the longest arrow: 0.8 of the node spacing


def test_without_fields_the_mesh_images_and_a_bounded_vector_count(made):
    d = made["dir"]
    layers = layers_of(d / "masked.zarr", max_vectors=8)
    named = by_name(layers)
    assert list(named) == ["reference", "|U| (nodes)", "eps_zz (elements)", "mask", "displacement"]
    data, kw, kind = named["mask"]
    assert kind == "labels" and kw["scale"] == [VOXEL] * 3 and np.array_equal(np.asarray(data), made["mask"])
    data, kw, _ = named["eps_zz (elements)"]
    masked = made["masked"]
    expected = masked.element_strain()[0, 0].copy()
    expected[masked.active == 0] = np.nan
    assert data.shape == (4, 4, 4) and np.allclose(data, expected, equal_nan=True) and np.isnan(data[:, 0, 0]).all()
    assert kw["scale"] == [ELL * VOXEL] * 3 and kw["translate"] == [7.5 * VOXEL] * 3  # element centres
    data, kw, _ = named["|U| (nodes)"]
    assert data.shape == (5, 5, 5) and kw["translate"] == [3.5 * VOXEL] * 3
    data, kw, _ = named["displacement"]
    assert stride((5, 5, 5), 8) == 3 and kw["metadata"]["stride"] == 3
    u = masked.displacement[:, ::3, ::3, ::3].reshape(3, -1).T
    assert len(data) == np.isfinite(u).all(axis=1).sum() <= 8


def test_series_has_a_time_axis(made):
    d, s = made["dir"], made["series"]
    named = by_name(layers_of(d / "series.zarr"))
    assert list(named) == ["scans", "|U| (nodes)", "eps_zz (elements)", "displacement"]
    data, kw, _ = named["scans"]
    assert [a.shape for a in data] == [(3, 40, 40, 40), (3, 20, 20, 20), (3, 10, 10, 10)]
    assert kw["scale"] == [1.0] + [VOXEL] * 3 and kw["axis_labels"] == ("t", "z", "y", "x")
    assert np.array_equal(np.asarray(data[0][2]), np.asarray(chunkdic.open_scan(made["scans"][2]).level(0)))
    data, kw, _ = named["eps_zz (elements)"]
    assert data.shape == (3, 4, 4, 4) and not data[0].any()
    assert np.allclose(data[2], s.cumulative[2].element_strain()[0, 0])
    data, kw, _ = named["displacement"]
    assert data.shape == (250, 2, 4) and sorted(set(data[:, 0, 0])) == [1.0, 2.0] and not data[:, 1, 0].any()
    at2 = data[data[:, 0, 0] == 2]
    assert np.allclose(at2[:, 1, 1:], s.cumulative[2].displacement.reshape(3, -1).T, atol=1e-5)


def test_weak_nodes_are_points_at_their_nodes(made):
    """k nodes flagged weak: one Points layer (top) of k points at the nodes' level-0 positions
    o + i ℓ - 1/2 = 3.5 + 8 i voxels (ROI 4:36, ℓ = 8), 6.5 µm per voxel through napari's
    scale; the count in its name. A weak node with no data is still weak; no-data and
    masked nodes alone are not; no weak node, no layer."""
    res = made["res"]
    flags = np.zeros(res.displacement.shape[1:], np.uint8)
    weak = [(0, 0, 0), (1, 3, 4), (4, 2, 1)]
    for node in weak:
        flags[node] = FLAG_WEAK
    flags[4, 2, 1] |= FLAG_NO_DATA
    flags[2, 2, 2], flags[3, 3, 3] = FLAG_NO_DATA, FLAG_MASKED
    layers = result_layers(dataclasses.replace(res, flags=flags), scan=False)
    data, kw, kind = layers[-1]
    assert (kw["name"], kind) == ("weak nodes (3)", "points") and kw["metadata"]["count"] == 3
    assert np.array_equal(data, [[3.5, 3.5, 3.5], [11.5, 27.5, 35.5], [35.5, 19.5, 11.5]])
    assert kw["scale"] == [VOXEL] * 3 and kw["translate"] == [0.0] * 3
    assert kw["features"]["flags"].tolist() == [2, 2, 3]
    assert [kw["features"][a].tolist() for a in ("iz", "iy", "ix")] == [list(c) for c in zip(*weak)]
    none = result_layers(dataclasses.replace(res, flags=np.zeros_like(flags)), scan=False)
    assert [kw["name"] for _, kw, _ in none] == [kw["name"] for _, kw, _ in layers[:-1]]
    assert weak_layer([dataclasses.replace(res, flags=None)], Frame((1.0,) * 3, (0.0,) * 3, None)) is None

    # a series: t = step, the count per step in the metadata, the most in the name
    two = dataclasses.replace(res, flags=np.where(flags == FLAG_WEAK, flags, 0).astype(np.uint8))
    data, kw, _ = weak_layer([two, dataclasses.replace(res, flags=np.zeros_like(flags))],
                             Frame((2.0,) * 3, (1.0, 0.0, 0.0), "millimeter"))
    assert kw["name"] == "weak nodes (up to 2 per step)" and kw["metadata"]["count"] == [2, 0]
    assert np.array_equal(data, [[1, 3.5, 3.5, 3.5], [1, 11.5, 27.5, 35.5]])
    assert kw["scale"] == [1.0, 2.0, 2.0, 2.0] and kw["translate"] == [0.0, 1.0, 0.0, 0.0]

    pytest.importorskip("napari")
    from napari.layers import Layer

    data, kw, kind = layers[-1]
    layer = Layer.create(data, kw, kind)
    assert len(layer.data) == 3 and np.allclose(layer.data_to_world(layer.data[1]), VOXEL * np.array([11.5, 27.5, 35.5]))


def test_npe2_finds_the_reader_headless_and_napari_builds_every_layer(made):
    npe2 = pytest.importorskip("npe2")
    d = made["dir"]
    pm = npe2.PluginManager.instance()  # napari's own: the one npe2.read uses
    try:
        pm.get_manifest("chunkdic")  # found through the entry point (chunkdic installed)
    except KeyError:
        pm.register(npe2.PluginManifest.from_file(MANIFEST))  # a source checkout: its manifest
    for path in (d / "r.zarr", d / "series.zarr", d / "r-fields.zarr", d / "series.zarr" / "steps" / "002-incremental"):
        readers = [r for r in pm.iter_compatible_readers([str(path)]) if r.plugin_name == "chunkdic"]
        assert len(readers) == 1
        layers = npe2.read([str(path)], stack=False, plugin_name="chunkdic")
        assert [(kw["name"], kind) for _, kw, kind in layers] == [(kw["name"], kind) for _, kw, kind in layers_of(path)]
    with pytest.raises(ValueError):  # not chunkdic's: its reader declines, npe2 says so
        npe2.read([made["scans"][0]], stack=False, plugin_name="chunkdic")
    assert napari_get_reader(made["scans"][0]) is None and napari_get_reader(str(d / "missing.zarr")) is None

    pytest.importorskip("napari")
    from napari.layers import Layer

    for path in (d / "r.zarr", d / "masked.zarr", d / "series.zarr"):
        for data, kw, kind in layers_of(path):
            layer = Layer.create(data, kw, kind)
            assert layer.name == kw["name"] and list(layer.scale) == kw["scale"]


def test_the_manifest_is_declared_and_shipped():
    pyproject = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    assert pyproject["project"]["entry-points"]["napari.manifest"] == {"chunkdic": "chunkdic.viewer:napari.yaml"}
    assert "napari.yaml" in pyproject["tool"]["setuptools"]["package-data"]["chunkdic.viewer"]
    assert MANIFEST.is_file() and "napari" in pyproject["project"]["optional-dependencies"]


def test_reading_imports_neither_napari_nor_qt(made, tmp_path):
    import subprocess

    code = ("import sys; from chunkdic.viewer.reader import napari_get_reader as g; "
            f"r = g({str(made['dir'] / 'r.zarr')!r}); r({str(made['dir'] / 'r.zarr')!r}); "
            "print(sorted(m for m in ('napari', 'qtpy', 'PyQt5', 'vispy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_view_refuses_in_one_line_without_napari_or_display(made, monkeypatch, capsys):
    path = str(made["dir"] / "r.zarr")
    monkeypatch.setitem(sys.modules, "napari", None)  # import napari -> ImportError
    assert main(["view", path]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "napari is not installed" in err and "chunkdic[napari]" in err
    monkeypatch.delitem(sys.modules, "napari")
    pytest.importorskip("napari")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["view", path]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("chunkdic: error: ") and ("display" in err or "Qt" in err)
