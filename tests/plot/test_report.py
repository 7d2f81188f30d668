"""Corrected image and residual, figures, VTK / CSV exports (issue 4)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import scipy.ndimage as ndi

import chunkdic
from chunkdic.cli import report_commands as _cli_report
from chunkdic.errors import InputError
from chunkdic.synth import synthetic
from chunkdic.export.corrected_image import open_corrected, write_corrected
from chunkdic.export.meshfiles import VTK_HEX_ORDER, hexahedra
from chunkdic.plot.report import plot_epszz_maps, plot_uz_maps, report

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
T = (1.3, -0.7, 0.4)


def _run(argv) -> int:
    parser = argparse.ArgumentParser(prog="chunkdic")
    _cli_report.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.fixture(scope="module")
def translation(tmp_path_factory):
    """An exact translation pair (analytic texture, no interpolation) and its result."""
    d = tmp_path_factory.mktemp("translation")
    pair = synthetic.synthesize(d, (48, 48, 48), field=synthetic.Translation(T), seed=3, dtype="float32")
    res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=12, output=d / "result.zarr")
    assert res.converged
    return pair, res, d


def test_corrected_image_matches_reference(translation, tmp_path):
    pair, res, _ = translation
    out = write_corrected(res, tmp_path / "corrected.zarr")
    assert out["gap"] < 0.01 and out["excluded"] == 0
    # same sums as the engine; its final gap is measured before its last increment (3.4e-4
    # voxel here, below the tolerance), which lowers the gap of the returned field by 0.16 %
    assert out["gap"] == pytest.approx(res.final_gap, rel=3e-3)
    corrected, residual, meta = open_corrected(tmp_path / "corrected.zarr")
    roi = tuple(slice(a, b) for a, b in res.info["roi"])
    whole = chunkdic.open_scan(pair["reference"]).level(0).compute()  # 48³ test volume
    f = whole[roi]
    # the engine compares the low-passed scans: the whole reference filtered at once (scipy,
    # mirror faces) must equal what the block tasks saw
    sigma = res.info["settings"]["smoothing"]
    assert sigma > 0 and meta["smoothing"] == sigma
    f_seen = ndi.gaussian_filter(whole.astype(np.float64), sigma, mode="mirror", truncate=4.0)[roi]
    c = corrected[...]
    assert c.shape == f.shape and np.isfinite(c).all()
    rng = float(f.max() - f.min())
    assert np.sqrt(np.mean((c - f_seen) ** 2)) / rng < 0.01
    assert np.allclose(residual[...], f_seen - c, atol=1e-5)
    # the uncorrected deformed image is far from the reference
    g = chunkdic.open_scan(pair["deformed"]).level(0)[roi].compute()
    assert np.sqrt(np.mean((g - f) ** 2)) / rng > 5 * out["gap"]
    assert meta["complete"] is True and meta["level"] == 0


def test_corrected_refuses_existing_output_and_missing_scans(translation, tmp_path):
    _, res, _ = translation
    (tmp_path / "c.zarr").mkdir()
    with pytest.raises(InputError):
        write_corrected(res, tmp_path / "c.zarr")
    mem = chunkdic.Result(res.displacement, res.node_coords, res.history,
                          {**res.info, "inputs": {"reference": "<in-memory ndarray>", "deformed": "<in-memory ndarray>"}})
    with pytest.raises(InputError, match="not on disk"):
        write_corrected(mem, tmp_path / "d.zarr")


def _assert_png_not_blank(path):
    import matplotlib.image as mpimg

    data = open(path, "rb").read()
    assert data[:8] == PNG_MAGIC, path
    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
    assert img[..., :3].std() > 0.05, path  # a figure, not an empty canvas


def test_report_figures(translation, tmp_path):
    _, res, d = translation
    assert _run(["report", str(d / "result.zarr"), "-o", str(tmp_path / "fig")]) == 0
    names = ["cut_x", "cut_y", "cut_z", "residual", "uz_map", "uy_map", "ux_map", "epszz_map", "epszz_profile",
             "gap", "uncertainty_map"]
    for name in names:
        _assert_png_not_blank(tmp_path / "fig" / f"{name}.png")
    # several results: one panel each
    plot_uz_maps([res, res], tmp_path / "uz2.png")
    plot_epszz_maps([res, res, res, res], tmp_path / "eps4.png")
    _assert_png_not_blank(tmp_path / "uz2.png")
    _assert_png_not_blank(tmp_path / "eps4.png")


def test_report_without_scans_skips_cuts(translation, tmp_path):
    _, res, _ = translation
    mem = chunkdic.Result(res.displacement, res.node_coords, res.history,
                          {**res.info, "inputs": {"reference": "<in-memory ndarray>"}})
    msgs = []
    paths = report(mem, tmp_path / "fig", progress=msgs.append)
    assert set(paths) == {"uz_map", "uy_map", "ux_map", "epszz_map", "epszz_profile", "epszz_profile_csv", "gap",
                          "uncertainty_map"}
    assert any("skipped" in m for m in msgs)


def test_vtk_and_csv_export(translation, tmp_path):
    import meshio

    _, res, d = translation
    vtu, csv_path = tmp_path / "mesh.vtu", tmp_path / "nodes.csv"
    assert _run(["export", str(d / "result.zarr"), "--vtk", str(vtu), "--csv", str(csv_path)]) == 0
    m = meshio.read(vtu)
    nodes = res.displacement.shape[1:]
    assert len(m.points) == np.prod(nodes)
    assert len(m.cells_dict["hexahedron"]) == np.prod([n - 1 for n in nodes])
    # point 0 is node (0, 0, 0); VTK vectors are (x, y, z)
    assert np.allclose(m.points[0], res.node_coords[::-1, 0, 0, 0])
    assert np.allclose(m.point_data["displacement"][7], res.displacement[::-1].reshape(3, -1)[:, 7])
    assert m.point_data["displacement"][0] == pytest.approx(T[::-1], abs=0.02)
    assert m.cell_data["strain"][0].shape == (len(m.cells_dict["hexahedron"]), 9)
    # the per-node uncertainty travels with the field (VTK (x, y, z) order; CSV z, y, x)
    assert np.allclose(m.point_data["uncertainty"][7], res.uncertainty[::-1].reshape(3, -1)[:, 7])
    assert np.array_equal(m.point_data["flags"], res.flags.ravel())
    table = np.loadtxt(csv_path, delimiter=",", skiprows=1)  # one header line (metadata: NODES.csv.json)
    assert table.shape == (np.prod(nodes), 13)
    assert np.allclose(table[:, 6:9], res.displacement.reshape(3, -1).T, atol=1e-6)
    assert np.allclose(table[:, 9:12], res.uncertainty.reshape(3, -1).T, rtol=1e-6)
    assert np.array_equal(table[:, 12], res.flags.ravel())
    with pytest.raises(InputError):
        _run(["export", str(d / "result.zarr"), "--vtk", str(vtu)])  # exists, no --overwrite


def test_hexahedra_are_positively_oriented():
    cells = hexahedra((2, 2, 2))
    assert cells.tolist() == [[0, 1, 3, 2, 4, 5, 7, 6]]
    pts = np.array([(dx, dy, dz) for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)], float)  # VTK (x, y, z)
    p = pts[cells[0]]
    # VTK_HEXAHEDRON: the bottom face 0-1-2-3 turns counter-clockwise seen from the top face
    normal = np.cross(p[1] - p[0], p[3] - p[0])
    assert normal @ (p[4] - p[0]) > 0
    assert len(VTK_HEX_ORDER) == 8


def test_strain_command(translation, capsys):
    _, _, d = translation
    assert _run(["strain", str(d / "result.zarr")]) == 0
    out = capsys.readouterr().out
    assert "tr(eps)" in out and "principal" in out and "(1 - 2 ell / L)" in out


# --------------------------------------------------------------------------- tools of the ecosystem (issue 13, item 3)


def test_result_opens_in_xarray_with_named_dimensions(translation):
    xr = pytest.importorskip("xarray")
    _, res, d = translation
    ds = xr.open_zarr(d / "result.zarr", consolidated=False)
    u = ds["displacement"]
    assert u.dims == ("component", "z", "y", "x")
    assert np.array_equal(u.values, res.displacement)  # the stored field, bit for bit
    assert u.attrs["units"] == "voxel"
    assert ds["strain"].dims == ("component_i", "component_j", "ez", "ey", "ex")
    assert np.array_equal(ds["flags"].values, res.flags)
    # node positions as coordinates: node k at ROI start + k ell - 0.5 (DESIGN.md)
    (z0, _), (y0, _), (x0, _) = res.info["roi"]
    ell = res.info["element_size"]
    assert np.array_equal(ds["z"].values, z0 + ell * np.arange(ds.sizes["z"]) - 0.5)
    assert np.array_equal(ds["x"].values, x0 + ell * np.arange(ds.sizes["x"]) - 0.5)
    assert np.array_equal(ds["ey"].values, y0 + ell * np.arange(ds.sizes["ey"]) + ell / 2 - 0.5)
    for name, var in ds.variables.items():
        assert "units" in var.attrs, name
    hist = xr.open_zarr(d / "result.zarr", group="history", consolidated=False)
    assert np.array_equal(hist["gap"].values, res.history["gap"]) and hist["gap"].dims == ("step",)
    # the in-memory twin
    mem = res.to_xarray()
    assert np.array_equal(mem["displacement"].sel(component="x").values, res.displacement[2])
    assert mem.attrs["element_size"] == ell and mem.attrs["status"] == "converged"
    assert "z_physical" not in mem.coords  # no voxel size on this pair
    assert np.array_equal(mem["history_gap"].values, res.history["gap"])


def test_to_xarray_physical_coordinates_and_missing_xarray(translation, monkeypatch):
    pytest.importorskip("xarray")
    _, res, _ = translation
    at_level1 = chunkdic.Result(res.displacement, res.node_coords, res.history,
                                {**res.info, "voxel_size": [2.0, 3.0, 4.0], "unit": "micrometer", "scale": 2})
    ds = at_level1.to_xarray()
    # level-1 node at coordinate c sits at level-0 coordinate 2 c + 0.5 (voxel centres, DESIGN.md)
    assert np.allclose(ds["y_physical"].values, (2 * ds["y"].values + 0.5) * 3.0)
    assert ds["y_physical"].attrs["units"] == "micrometer"
    import builtins

    real_import = builtins.__import__

    def no_xarray(name, *args, **kwargs):
        if name == "xarray":
            raise ImportError("no module named xarray")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_xarray)
    with pytest.raises(ImportError, match="pip install xarray"):
        res.to_xarray()


def test_vtu_field_data_and_csv_for_pandas(translation, tmp_path):
    import json

    import meshio

    from chunkdic.export.meshfiles import CSV_COLUMNS, read_vtk_metadata

    pd = pytest.importorskip("pandas")
    _, res, d = translation
    vtu, csv_path = tmp_path / "mesh.vtu", tmp_path / "nodes.csv"
    assert _run(["export", str(d / "result.zarr"), "--vtk", str(vtu), "--csv", str(csv_path)]) == 0
    fd = meshio.read(vtu).field_data
    assert fd["element_size"].tolist() == [12.0] and fd["level"].tolist() == [0]
    assert fd["final_gap"][0] == pytest.approx(res.final_gap, rel=1e-12)
    meta = read_vtk_metadata(vtu)
    assert meta["status"] == "converged" and meta["converged"] == 1
    assert meta["coordinates"] == "voxel, level 0" and meta["chunkdic_version"] == chunkdic.__version__
    assert "voxel_size" not in meta and "unit" not in meta  # this pair has none
    # a plain pandas.read_csv: one header line, the result's values
    table = pd.read_csv(csv_path)
    assert tuple(table.columns) == CSV_COLUMNS
    assert np.allclose(table[["Uz", "Uy", "Ux"]].to_numpy().T, res.displacement.reshape(3, -1), atol=5e-8)
    assert np.allclose(table[["z", "y", "x"]].to_numpy().T, res.node_coords.reshape(3, -1))
    assert table["iz"].max() == res.displacement.shape[1] - 1
    side = json.loads((tmp_path / "nodes.csv.json").read_text())
    assert side["kind"] == "csv-meta" and side["table"] == "nodes.csv" and side["element_size"] == 12
    assert side["columns"]["Ux"] == "voxel, level 0" and side["columns"]["flags"] == "1"
    assert side["status"] == "converged" and side["final_gap"] == pytest.approx(res.final_gap)
    # both files are chunkdic's: --overwrite replaces them, a user's CSV is refused
    assert _run(["export", str(d / "result.zarr"), "--csv", str(csv_path), "--overwrite"]) == 0
    user = tmp_path / "mine.csv"
    user.write_text("a,b\n1,2\n")
    with pytest.raises(InputError, match="did not write"):
        _run(["export", str(d / "result.zarr"), "--csv", str(user), "--overwrite"])
    assert user.read_text() == "a,b\n1,2\n" and not (tmp_path / "mine.csv.json").exists()


def test_vtu_field_data_with_a_voxel_size(translation, tmp_path):
    from chunkdic.export.meshfiles import read_vtk_metadata, write_vtk

    _, res, _ = translation
    phys = chunkdic.Result(res.displacement, res.node_coords, res.history,
                           {**res.info, "voxel_size": [2.0, 3.0, 4.0], "unit": "micrometer"})
    write_vtk(phys, tmp_path / "m.vtu", units="physical")
    meta = read_vtk_metadata(tmp_path / "m.vtu")
    assert meta["voxel_size"] == (4.0, 3.0, 2.0)  # VTK order (x, y, z)
    assert meta["unit"] == "micrometer" and meta["coordinates"] == "micrometer"


# --------------------------------------------------------------------------- figures a researcher can use (issue 13, item 6)

A_ZZ = -0.01  # the affine pair's axial strain


@pytest.fixture(scope="module")
def affine(tmp_path_factory):
    """An affine pair (1 % axial compression, shear, lateral stretch; exact deformed image)."""
    d = tmp_path_factory.mktemp("affine")
    field = synthetic.Affine(matrix=((A_ZZ, 0.0, 0.004), (0.0, 0.003, 0.0), (0.0, 0.0, 0.0)),
                             center=(24.0, 24.0, 24.0), translation=(0.3, -0.2, 0.1))
    pair = synthetic.synthesize(d, (48, 48, 48), field=field, seed=5, dtype="float32")
    res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=12, output=d / "result.zarr")
    assert res.converged
    return pair, res, d


def _profile_rows(path):
    import csv

    from chunkdic.plot.profile import PROFILE_COLUMNS

    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert rows and tuple(rows[0]) == PROFILE_COLUMNS
    return rows


def _in_memory(res):
    """The result with its scans 'not on disk': the report skips the cuts (fast)."""
    return chunkdic.Result(res.displacement, res.node_coords, res.history,
                           {**res.info, "inputs": {"reference": "<in-memory ndarray>"}}, strain=res.strain)


def test_epszz_profile_csv_against_strains_and_truth(affine, translation, tmp_path):
    _, res, d = affine
    _, res_t, d_t = translation
    out = tmp_path / "fig"
    assert _run(["report", str(d / "result.zarr"), str(d_t / "result.zarr"), "-o", str(out),
                 "--format", "svg", "--cuts-from", str(d / "result.zarr"), "--strain", "small"]) == 0
    rows = _profile_rows(out / "epszz_profile.csv")
    for r, truth in ((res, A_ZZ), (res_t, 0.0)):
        mine = [row for row in rows if row["result"] == r.path]
        # independent: the stored element strains, averaged per element layer
        eps = np.asarray(r.strain)[0, 0]
        expect = eps.mean(axis=(1, 2))
        assert [int(row["layer"]) for row in mine] == list(range(eps.shape[0]))
        assert np.allclose([float(row["eps_zz"]) for row in mine], expect, rtol=0, atol=1e-14)
        assert all(int(row["elements"]) == eps.shape[1] * eps.shape[2] for row in mine)
        # element-layer centres: z0 + (k + 1/2) ell - 1/2 (level voxels)
        z0, ell = r.info["roi"][0][0], r.info["element_size"]
        assert np.allclose([float(row["z"]) for row in mine], z0 + ell * (np.arange(eps.shape[0]) + 0.5) - 0.5)
        # the synthetic truth found from the scans' attributes: the imposed dUz/dZ, exactly
        true = np.array([float(row["eps_zz_true"]) for row in mine])
        assert np.allclose(true, truth, atol=1e-12)
        # and the measurement within a bound of it (measured: 6e-6 on the affine pair)
        assert np.abs(expect - truth).max() < 1e-4, expect
    # every figure in SVG, the cuts from the affine result
    for name in ("gap", "uz_map", "uy_map", "ux_map", "epszz_map", "epszz_profile", "cut_x", "residual"):
        head = (out / f"{name}.svg").read_bytes()[:400]
        assert head.startswith(b"<?xml") and b"<svg" in head, name
    assert not list(out.glob("*.png"))
    assert "ℓ = 12" in (out / "cut_z.svg").read_text()
    # both results named (same stem "result": told apart by their folders) in every legend and title
    names = [f"{p.name}/result" for p in (d, d_t)]
    for fig in ("gap", "epszz_profile", "uz_map", "epszz_map", "uncertainty_map"):
        text = (out / f"{fig}.svg").read_text()
        assert all(n in text for n in names), (fig, names)
    for fig in ("cut_x", "cut_y", "cut_z", "residual"):
        assert names[0] in (out / f"{fig}.svg").read_text() and names[1] not in (out / f"{fig}.svg").read_text()
    # the default measure, Green-Lagrange: E_zz = dUz/dZ + |dU/dZ|^2 / 2 per element, and its truth
    out2 = tmp_path / "fig-gl"
    assert _run(["report", str(d / "result.zarr"), "-o", str(out2), "--format", "svg"]) == 0
    mine = _profile_rows(out2 / "epszz_profile.csv")
    H = res.displacement  # the element strains of the stored field, Green-Lagrange
    from chunkdic.results.strain import element_strain

    E = element_strain(H, res.info["element_size"], "green-lagrange")[0, 0]
    assert np.allclose([float(row["eps_zz"]) for row in mine], E.mean(axis=(1, 2)), rtol=0, atol=1e-14)
    assert np.allclose([float(row["eps_zz_true"]) for row in mine], A_ZZ + A_ZZ**2 / 2, atol=1e-12)
    assert "E_zz" in (out2 / "epszz_profile.svg").read_text()


def test_true_layer_strain_of_a_band_against_quadrature(affine):
    """The profile's truth on a band (Uz depends on z only) equals the integral of the
    analytic strain profile over each element layer, at level 0 and at level 1."""
    from scipy.integrate import quad

    from chunkdic.plot.profile import true_layer_strain

    _, res, _ = affine
    band = synthetic.Band(center_z=22.0, width=10.0, strain=-0.05, lateral=0.3, center_y=20.0, center_x=25.0)
    e, h = band.width / 8, band.width / 2

    def p(s):  # dUz/dZ = strain * p(s), written out (fields.Band docstring)
        return band.strain * 0.5 * (np.tanh((s + h) / e) - np.tanh((s - h) / e))

    for scale in (1, 2):
        r = chunkdic.Result(res.displacement, res.node_coords, res.history, {**res.info, "scale": scale})
        t = true_layer_strain(r, band)
        z0, ell = r.info["roi"][0][0], r.info["element_size"]
        for k in range(t.shape[0]):
            a, b = (scale * (z0 - 0.5 + np.array([k, k + 1]) * ell) + (scale - 1) / 2) - band.center_z
            expect = quad(p, a, b, epsabs=1e-13)[0] / (b - a)
            assert np.allclose(t[k], expect, atol=1e-10), (scale, k)


def test_gap_figure_labels_levels_and_plain_percent(translation):
    from chunkdic.plot.report import gap_figure

    _, res, _ = translation
    fig = gap_figure([res])
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    levels = list(dict.fromkeys(np.asarray(res.history["level"]).tolist()))
    expect = [f"result: level {s} (ℓ = 12)" for s in levels]
    if (np.asarray(res.history["iteration"]) < 0).any():
        expect.insert(1, "rigid translation steps")
    assert labels == expect
    # one curve per level: its points are that level's Gauss-Newton iterations
    lines = {ln.get_label(): ln for ln in ax.get_lines()}
    lev, it = np.asarray(res.history["level"]), np.asarray(res.history["iteration"])
    for s in levels:
        ys = lines[f"result: level {s} (ℓ = 12)"].get_ydata()
        assert np.allclose(ys, 100 * np.asarray(res.history["gap"])[(lev == s) & (it >= 0)])
    fmt = ax.yaxis.get_major_formatter()
    assert fmt(0.5, 0) == "0.5 %" and fmt(20.0, 0) == "20 %"
    assert ax.get_yscale() == "log"


def test_report_format_and_dpi(translation, tmp_path):
    import struct

    _, res, _ = translation
    mem = _in_memory(res)
    widths = {}
    for dpi in (50, 100):
        paths = report(mem, tmp_path / f"d{dpi}", dpi=dpi)
        data = open(paths["gap"], "rb").read(24)
        assert data[:8] == PNG_MAGIC
        widths[dpi] = struct.unpack(">II", data[16:24])  # IHDR width, height
    gap_w = 7.5  # inches (gap_figure)
    assert widths[50][0] == round(gap_w * 50) and widths[100][0] == round(gap_w * 100)
    assert abs(widths[100][1] - 2 * widths[50][1]) <= 1
    paths = report(mem, tmp_path / "pdf", fmt="pdf")
    for name, path in paths.items():
        if name != "epszz_profile_csv":
            assert path.endswith(".pdf") and open(path, "rb").read(5) == b"%PDF-", name
    with pytest.raises(InputError, match="format"):
        report(mem, tmp_path / "bad", fmt="jpg")
    assert not (tmp_path / "bad").exists()


def test_cuts_from_must_be_one_of_the_results(translation, affine, tmp_path, capsys):
    from chunkdic.cli.app import main

    _, _, d = translation
    _, _, d_a = affine
    out = tmp_path / "fig"
    assert main(["report", str(d / "result.zarr"), "-o", str(out), "--cuts-from", str(d_a / "result.zarr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--cuts-from" in err[0] and "not one of the results given" in err[0]
    assert str(d_a / "result.zarr") in err[0] and "Traceback" not in err[0]
    assert not out.exists()


def test_maps_share_extent_colour_bar_and_centre(translation, tmp_path):
    """Results of different ROIs: every panel on the same extent, one colour bar, limits
    symmetric about 0; with a voxel size the axes are in the scan's unit."""
    import matplotlib.figure

    from chunkdic.plot import maps

    _, res, _ = translation
    small = chunkdic.Result(res.displacement[:, :3, :3, :3], res.node_coords[:, :3, :3, :3], res.history,
                            {**res.info, "roi": [[a, a + 24] for a, _ in res.info["roi"]]})
    figs = []
    real_save = maps.save
    maps.save = lambda fig, path, dpi=None: figs.append(fig) or real_save(fig, path, dpi)
    try:
        maps.plot_u_maps([res, small], tmp_path / "uy.png", "y")
    finally:
        maps.save = real_save
    fig = figs[0]
    assert isinstance(fig, matplotlib.figure.Figure)
    panels = [ax for ax in fig.axes if ax.get_images()]
    assert len(panels) == 2 and len(fig.axes) == 3  # two panels, one colour bar
    assert panels[0].get_xlim() == panels[1].get_xlim() and panels[0].get_ylim() == panels[1].get_ylim()
    lo, hi = panels[0].get_images()[0].get_clim()
    assert lo == -hi and hi == pytest.approx(np.abs(res.displacement[1]).max(), rel=0.05)
    assert panels[0].get_images()[0].get_cmap().name == "RdBu_r"
    # physical unit: level-0 voxel c at c * voxel size; Uy in the unit
    phys = chunkdic.Result(res.displacement, res.node_coords, res.history,
                           {**res.info, "voxel_size": [2.0, 3.0, 4.0], "unit": "micrometer"})
    figs.clear()
    maps.save = lambda fig, path, dpi=None: figs.append(fig) or real_save(fig, path, dpi)
    try:
        maps.plot_u_maps(phys, tmp_path / "uyp.png", "y")
    finally:
        maps.save = real_save
    ax = [a for a in figs[0].axes if a.get_images()][0]
    (y0, y1), (z0, z1) = res.info["roi"][1], res.info["roi"][0]
    assert ax.get_images()[0].get_extent() == pytest.approx([3.0 * (y0 - 0.5), 3.0 * (y1 - 0.5),
                                                             2.0 * (z0 - 0.5), 2.0 * (z1 - 0.5)])
    assert ax.get_xlabel() == "y (µm)" and ax.get_images()[0].get_clim()[1] == pytest.approx(3.0 * hi)


def test_labels_name_every_curve_and_twelve_curves_differ(translation, affine, tmp_path):
    """Issue 23 item 3: --label / labels= in every legend and panel title; 12 curves, 12 (colour, style) pairs."""
    from chunkdic.plot.figures import with_labels
    from chunkdic.plot.report import gap_figure

    a, b = _in_memory(translation[1]), _in_memory(affine[1])
    out = tmp_path / "fig"
    assert _run(["report", str(translation[2] / "result.zarr"), str(affine[2] / "result.zarr"), "-o", str(out),
                 "--format", "svg", "--label", "tension A", "--label", "shear B"]) == 0
    for fig in ("gap", "epszz_profile", "uz_map", "epszz_map", "uncertainty_map"):
        text = (out / f"{fig}.svg").read_text()
        assert "tension A" in text and "shear B" in text, fig
    assert "tension A" in (out / "cut_z.svg").read_text()
    # the labels read back from the matplotlib objects, and one label per result or nothing written
    ax = gap_figure(with_labels([a, b], ["tension A", "shear B"])).axes[0]
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any(t.startswith("tension A: level") for t in texts) and any(t.startswith("shear B: level") for t in texts)
    with pytest.raises(InputError, match="1 label"):
        report([a, b], tmp_path / "bad", labels=["only one"])
    assert not (tmp_path / "bad").exists()
    # 12 curves: 12 distinct (colour, line style) pairs
    one = chunkdic.Result(a.displacement, a.node_coords,
                          {k: np.asarray(v)[np.asarray(a.history["level"]) == 0] for k, v in a.history.items()},
                          a.info)
    many = with_labels([one] * 12, [f"r{i}" for i in range(12)])
    lines = [ln for ln in gap_figure(many).axes[0].get_lines() if ": level" in ln.get_label()]
    assert len(lines) == 12
    from matplotlib.colors import to_hex

    assert len({(to_hex(ln.get_color()), ln.get_linestyle()) for ln in lines}) == 12


def _rotated(theta_deg: float = 10.0):
    """A result whose field is a rigid rotation by ``theta`` about the x axis (in the z-y plane)."""
    from chunkdic.mesh import Mesh

    mesh = Mesh((4, 4, 4), 8, (4, 4, 4))
    X = mesh.node_coords()
    t = np.radians(theta_deg)
    R = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1.0]])
    c = np.array([20.0, 20.0, 20.0])[:, None, None, None]
    u = np.einsum("ij,j...->i...", R - np.eye(3), X - c)
    hist = {k: np.zeros(1) for k in ("level", "iteration", "gap", "max_delta", "excluded")}
    info = {"element_size": 8, "roi": [[4, 36]] * 3, "level": 0, "scale": 1, "final_gap": 0.01,
            "input_shapes": {"reference": [40, 40, 40]}, "inputs": {"reference": "<in-memory ndarray>"}}
    return chunkdic.Result(u, X, hist, info)


def test_a_rigid_rotation_exports_no_strain_by_default(tmp_path):
    """Issue 23 item 2: VTK cells and the fields image of a 10° rotation: |eps| < 1e-3 by default
    (Green-Lagrange), the small strain's cos(10°) - 1 = -0.0152 with --strain small."""
    import meshio

    from chunkdic.export.meshfiles import read_vtk_metadata, write_vtk
    from chunkdic.export.fields_image import write_fields

    res = _rotated()
    res.save(tmp_path / "rot.zarr")
    assert _run(["export", str(tmp_path / "rot.zarr"), "--vtk", str(tmp_path / "gl.vtu")]) == 0
    cells = meshio.read(tmp_path / "gl.vtu").cell_data
    assert np.abs(cells["strain"][0]).max() < 1e-3 and np.abs(cells["strain"][0]).max() < 1e-12
    assert read_vtk_metadata(tmp_path / "gl.vtu")["strain_measure"] == "green-lagrange"
    write_vtk(res, tmp_path / "small.vtu", strain="small")
    small = meshio.read(tmp_path / "small.vtu").cell_data
    assert np.allclose(small["eps_zz"][0], np.cos(np.radians(10)) - 1, atol=1e-12)
    # the fields image: eps_zz and eps_eq per voxel
    out = write_fields(res, tmp_path / "f.zarr", residual=False)
    import zarr

    vol = zarr.open_array(str(tmp_path / "f.zarr"), path="0")[4:6]
    inside = np.isfinite(vol[0])
    assert inside.sum() == 32**3 and np.abs(vol[:, inside]).max() < 1e-6
    assert out["path"].endswith("f.zarr")
    vol = np.asarray(zarr.open_array(str(write_fields(res, tmp_path / "s.zarr", residual=False, strain="small")["path"]),
                                     path="0")[4])
    assert np.allclose(vol[np.isfinite(vol)], np.cos(np.radians(10)) - 1, atol=1e-6)
    with pytest.raises(InputError, match="strain measure"):
        write_vtk(res, tmp_path / "x.vtu", strain="cauchy")
    assert not (tmp_path / "x.vtu").exists()


def test_result_methods_and_faces_level_with_the_cli(tmp_path):
    """Issue 23 item 6: Result.strain_summary, chunkdic.write_vtk / write_nodes_csv, chunkdic.report, as the commands."""
    import meshio
    import pandas as pd

    res = _rotated()
    s = res.strain_summary()
    assert s.measure == "green-lagrange" and np.abs(s.mean).max() < 1e-12 and s.max_rotation == pytest.approx(10)
    assert res.strain_summary(measure="small").eps_zz == pytest.approx(np.cos(np.radians(10)) - 1, abs=1e-12)
    info = chunkdic.write_vtk(res, tmp_path / "r.vtu")
    assert info["strain"] == "green-lagrange" and np.abs(meshio.read(tmp_path / "r.vtu").cell_data["strain"][0]).max() < 1e-12
    assert chunkdic.write_nodes_csv(res, tmp_path / "r.csv") == 125
    table = pd.read_csv(tmp_path / "r.csv")
    assert np.allclose(table["Uz"].to_numpy(), res.displacement[0].ravel())
    assert chunkdic.report is report and chunkdic.write_nodes_csv is not None


def test_every_title_that_names_ell_says_the_resolution(translation, tmp_path):
    """Issue 20 item 5: every figure title (and the profile's legend) that names ℓ also says
    the regularisation and the nominal l10 % it implies, read back from the written SVGs
    (matplotlib writes each text as a comment before its glyphs) and checked against the
    result's info; the nominal l10 % of a regularised C8 field lies above the C8 basis' own
    2.767 ℓ (docs/engine.md, "l10 % of the unregularised C8 projection")."""
    import re

    _, res, d = translation
    reg = res.info["regularization"]
    assert reg["kind"] == "tikhonov" and reg["length"] > 0
    out = tmp_path / "fig"
    assert _run(["report", str(d / "result.zarr"), "-o", str(out), "--format", "svg"]) == 0
    said = re.compile(r"ℓ = (\d+) vox, Tikhonov (\d+) vox, l10 % ≥ (\d+) vox")
    seen = {}
    for svg in sorted(out.glob("*.svg")):
        for text in re.findall(r"<!-- (.*?) -->", svg.read_text(), flags=re.S):
            if "ℓ" not in text or "level " in text and "(ℓ = " in text:  # the gap's per-level curves
                continue
            m = said.search(text)
            assert m, (svg.name, text)
            seen.setdefault(svg.stem, []).append(tuple(int(v) for v in m.groups()))
    # the maps (one panel per result), the cuts' title and the profile's legend
    assert {"uz_map", "uy_map", "ux_map", "epszz_map", "uncertainty_map", "cut_z", "cut_x", "epszz_profile"} <= set(seen)
    expect = (12, round(reg["length"]), round(reg["nominal_l10"]))
    assert all(v == [expect] * len(v) for v in seen.values()), seen
    assert reg["nominal_l10"] > 2.767 * 12
