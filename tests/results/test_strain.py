"""Element strains, mean strain with/without the outer layer, principal values (issue 4)."""

from __future__ import annotations

import numpy as np
import pytest

from chunkdic.mesh import Mesh
from chunkdic.results.result import Result, open_result
from chunkdic.results.strain import (
    displacement_gradient,
    element_strain,
    mean_strain,
    principal_strains,
)


def _affine_nodes(mesh: Mesh, A: np.ndarray, t) -> np.ndarray:
    X = mesh.node_coords()
    return np.einsum("ij,j...->i...", A, X) + np.asarray(t)[:, None, None, None]


def test_affine_field_strain_is_its_symmetric_gradient():
    rng = np.random.default_rng(0)
    A = rng.normal(scale=0.03, size=(3, 3))
    mesh = Mesh((5, 3, 7), 6, (4, 3, 5))
    u = _affine_nodes(mesh, A, (1.2, -0.4, 3.0))
    H = displacement_gradient(u, 6)
    assert H.shape == (3, 3, 4, 3, 5)
    assert np.abs(H - A[:, :, None, None, None]).max() < 1e-9
    eps = element_strain(u, 6)
    assert np.abs(eps - 0.5 * (A + A.T)[:, :, None, None, None]).max() < 1e-9
    s = mean_strain(u, 6)
    assert np.abs(s.mean - 0.5 * (A + A.T)).max() < 1e-9
    assert np.abs(s.mean_all - s.mean).max() < 1e-9


def test_trilinear_centre_gradient_is_the_edge_average():
    # u_z = z*y (bilinear): at an element centre dUz/dz = y_centre, dUz/dy = z_centre
    mesh = Mesh((0, 0, 0), 4, (2, 2, 2))
    z, y, x = mesh.node_coords()
    u = np.stack([z * y, 0 * z, 0 * z])
    H = displacement_gradient(u, 4)
    cz = (np.arange(2) * 4 + 1.5)  # element centres (nodes at k*4 - 0.5)
    assert np.allclose(H[0, 0], cz[None, :, None] * np.ones((2, 2, 2)))
    assert np.allclose(H[0, 1], cz[:, None, None] * np.ones((2, 2, 2)))


def test_mean_strain_with_and_without_outer_layer_hand_values():
    # 5 elements along z of edge 10; eps_zz = -0.05 in the first (outer) layer only:
    # all elements: -0.05 / 5 = -0.01; without the outer layer: 0 (and corrected 0)
    ell, n = 10, 5
    kz = np.arange(n + 1, dtype=float)
    uz_profile = np.where(kz >= 1, -0.05 * ell, -0.05 * ell * kz)
    u = np.zeros((3, n + 1, n + 1, n + 1))
    u[0] = uz_profile[:, None, None]
    s = mean_strain(u, ell)
    assert s.mean_all[0, 0] == pytest.approx(-0.01, abs=1e-12)
    assert s.mean[0, 0] == pytest.approx(0.0, abs=1e-12)
    assert s.elements == (3, 3, 3) and s.excluded == (True, True, True)
    # strain only inside: 4 % in the middle layer, inner mean 4/3 %, corrected (1 - 2/5) of it
    uz_profile = np.where(kz >= 3, -0.04 * ell, 0.0)
    u[0] = uz_profile[:, None, None]
    s = mean_strain(u, ell)
    assert s.mean_all[0, 0] == pytest.approx(-0.04 / 5, abs=1e-12)
    assert s.eps_zz == pytest.approx(-0.04 / 3, abs=1e-12)
    assert s.eps_zz_corrected == pytest.approx(-0.04 / 3 * (1 - 2 * ell / (n * ell)), abs=1e-12)
    # ... which is the mean over the whole ROI when the removed elements carry no strain
    assert s.eps_zz_corrected == pytest.approx(s.mean_all[0, 0], abs=1e-12)
    assert s.volume_change == pytest.approx(s.eps_zz)
    assert s.delta_eps == pytest.approx(0.04 / 3)
    assert not np.any(np.isnan(s.principal))
    off = mean_strain(u, ell, exclude_outer=False)
    assert off.eps_zz == pytest.approx(s.mean_all[0, 0]) and off.excluded == (False,) * 3


def test_principal_strains_sorted_and_invariant():
    rng = np.random.default_rng(1)
    R, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    eps = R @ np.diag([0.01, -0.03, 0.002]) @ R.T
    p = principal_strains(eps)
    assert np.allclose(p, [0.01, 0.002, -0.03])
    field = np.broadcast_to(eps[:, :, None, None], (3, 3, 2, 2)).copy()
    assert np.allclose(principal_strains(field)[:, 1, 1], [0.01, 0.002, -0.03])


def test_strain_stored_with_result(tmp_path):
    mesh = Mesh((2, 2, 2), 8, (3, 3, 3))
    A = np.diag([-0.02, 0.01, 0.0])
    u = _affine_nodes(mesh, A, (0, 0, 0))
    hist = {k: np.zeros(1) for k in ("level", "iteration", "gap", "max_delta", "excluded")}
    info = {"element_size": 8, "roi": [[2, 26]] * 3, "level": 0, "final_gap": 0.01}
    Result(u, mesh.node_coords(), hist, info).save(tmp_path / "r.zarr")
    r = open_result(tmp_path / "r.zarr")
    assert r.strain.shape == (3, 3, 3, 3, 3)
    assert np.allclose(r.strain[0, 0], -0.02) and np.allclose(r.strain[1, 1], 0.01)


def test_mean_strain_of_a_masked_result_counts_its_active_elements_only(tmp_path, capsys):
    """A mask's inactive elements never count: ``strain`` (CLI), the series table's
    ``eps_zz`` and ``table`` give the prescribed strain of the active elements, which the
    inactive ones (their nodes measured, at the mask's rim) would change."""
    import json

    from chunkdic.analysis.loadseries import _row
    from chunkdic.analysis.zoisweep import zoi_table
    from chunkdic.cli.app import main
    from chunkdic.results.strain import strain_summary

    mesh = Mesh((0, 0, 0), 8, (6, 6, 6))
    z = mesh.node_coords()[0]
    # eps_zz = -0.01 in element layers 0..3 (the material), +0.05 in layers 4..5 (outside it)
    knee = mesh.node_axes()[0][4]
    uz = np.where(z <= knee, -0.01 * z, -0.01 * knee + 0.05 * (z - knee))
    u = np.stack([uz, np.zeros_like(z), np.zeros_like(z)])
    active = np.zeros((6, 6, 6), np.uint8)
    active[:4] = 1
    hist = {k: np.zeros(1) for k in ("level", "iteration", "gap", "max_delta", "excluded")}
    info = {"element_size": 8, "roi": [[0, 48]] * 3, "level": 0, "final_gap": 0.01, "status": "converged"}
    res = Result(u, mesh.node_coords(), hist, info, active=active)
    # the inner layers 1..4: without the mask (3 * -0.01 + 0.05) / 4 = +0.005
    assert mean_strain(u, 8).eps_zz == pytest.approx(0.005, abs=1e-12)
    assert strain_summary(res, measure="small").eps_zz == pytest.approx(-0.01, abs=1e-12)
    # the default measure (Green-Lagrange, issue 23): E_zz = a + a^2 / 2 of the same elements
    assert strain_summary(res).eps_zz == pytest.approx(-0.01 + 0.5e-4, abs=1e-12)
    assert _row(res, 1, "0→1", "incremental", "steps/001-incremental", "computed", 0.0)["eps_zz"] == \
        pytest.approx(-0.01 + 0.5e-4, abs=1e-12)
    res.save(tmp_path / "r.zarr")
    assert main(["strain", str(tmp_path / "r.zarr"), "--json", "--strain", "small"]) == 0
    assert json.loads(capsys.readouterr().out)["eps_zz"] == pytest.approx(-0.01, abs=1e-12)
    assert zoi_table([tmp_path / "r.zarr"])[0]["eps_zz"] == pytest.approx(-0.01, abs=1e-12)
    # no active element left: one line, no traceback; the series row says NaN
    res.active = np.zeros_like(active)
    assert np.isnan(_row(res, 1, "0→1", "incremental", "x", "computed", 0.0)["eps_zz"])
    res.save(tmp_path / "none.zarr")
    assert main(["strain", str(tmp_path / "none.zarr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no element to average" in err[0]


# ------------------------------------------------------------------ finite strain (issue 23)


def _rotation(deg: float, axis: int = 0) -> np.ndarray:
    t = np.radians(deg)
    c, s = np.cos(t), np.sin(t)
    a, b = [i for i in range(3) if i != axis]
    R = np.eye(3)
    R[a, a], R[a, b], R[b, a], R[b, b] = c, -s, s, c
    return R


def test_rigid_rotation_gives_no_strain_with_the_default_measure(capsys):
    """A 10° rigid rotation about z (nodal field u = (R - I)(X - c), exact for C8): the
    default (Green-Lagrange) strain is zero to round-off, the rotation is 10°; the small
    strain shows the known false strain cos 10° - 1 = -0.01519 on the in-plane axes, and
    the command-level warning says so."""
    from chunkdic.cli.report_commands import rotation_warning
    from chunkdic.results.strain import (
        DEFAULT_MEASURE,
        displacement_gradient,
        element_strain,
        rotation_angle,
    )

    mesh = Mesh((0, 0, 0), 8, (4, 4, 4))
    X = mesh.node_coords()
    c = X.mean(axis=(1, 2, 3))[:, None, None, None]
    R = _rotation(10.0, axis=0)
    u = np.einsum("ij,j...->i...", R - np.eye(3), X - c)
    assert DEFAULT_MEASURE == "green-lagrange"
    s = mean_strain(u, 8, measure=DEFAULT_MEASURE)
    assert np.abs(s.mean).max() < 1e-3 and np.abs(s.mean).max() < 1e-12
    assert np.abs(element_strain(u, 8, measure="green-lagrange")).max() < 1e-12
    np.testing.assert_allclose(rotation_angle(displacement_gradient(u, 8)), 10.0, atol=1e-9)
    assert s.max_rotation == pytest.approx(10.0, abs=1e-9)
    small = mean_strain(u, 8, measure="small")
    assert small.mean[1, 1] == pytest.approx(np.cos(np.radians(10)) - 1, abs=1e-12)
    assert rotation_warning(small) is not None and rotation_warning(s) is None
    # stretch: E = a + a^2 / 2 exactly for a uniform gradient a
    a = -0.01
    uz = np.stack([a * (X[0] - c[0]), 0 * X[0], 0 * X[0]])
    assert mean_strain(uz, 8, measure="green-lagrange").eps_zz == pytest.approx(a + a * a / 2, abs=1e-14)


def test_corrected_mean_strain_line_only_when_it_applies(tmp_path, capsys):
    """Uniform -1 % compression: the plain mean is the truth, the (1 - 2 ell/L) line would say
    -0.01 * (1 - 2/6) = -0.00667 and is not printed (its assumption, an unstrained outer layer,
    is stated instead). A band inside unstrained outer layers: the line is printed."""
    import json

    from chunkdic.cli.app import main

    mesh = Mesh((0, 0, 0), 8, (6, 6, 6))
    z = mesh.node_coords()[0]
    hist = {k: np.zeros(1) for k in ("level", "iteration", "gap", "max_delta", "excluded")}
    info = {"element_size": 8, "roi": [[0, 48]] * 3, "level": 0, "final_gap": 0.01, "status": "converged"}
    uniform = np.stack([-0.01 * z, 0 * z, 0 * z])
    Result(uniform, mesh.node_coords(), hist, info).save(tmp_path / "u.zarr")
    assert main(["strain", str(tmp_path / "u.zarr"), "--strain", "small"]) == 0
    out = capsys.readouterr().out
    assert "eps_zz = -0.01000" in out and "corrected by" not in out and "unstrained outer layer" in out
    # a band: strain only in element layers 1..4 (the inner ones), none in the outer layer
    k = mesh.node_axes()[0]
    band = np.stack([-0.01 * np.clip(z - k[1], 0, k[5] - k[1]), 0 * z, 0 * z])
    Result(band, mesh.node_coords(), hist, info).save(tmp_path / "b.zarr")
    assert main(["strain", str(tmp_path / "b.zarr"), "--strain", "small", "--all-elements"]) == 0
    capsys.readouterr()
    assert main(["strain", str(tmp_path / "b.zarr"), "--strain", "small"]) == 0
    out = capsys.readouterr().out
    # the whole-ROI mean is -0.01 * 4/6; the inner mean -0.01; corrected -0.01 * (1 - 2/6)
    assert "corrected by" in out and "eps_zz = -0.00667" in out
    assert main(["strain", str(tmp_path / "b.zarr"), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["measure"] == "green-lagrange" and d["eps_zz"] == pytest.approx(-0.01 + 0.5e-4, abs=1e-12)


def test_band_with_lateral_expansion_is_corrected_along_z_only():
    """A band normal to z (4 % compression in the middle layer, +1 % expansion along y there)
    spans the whole width: its outer layers normal to y are strained as much as the inner
    ones, those normal to z not at all (x carries no strain: nothing to judge). The
    correction holds along z and x, not y, and along z it gives the exact mean over the
    whole ROI (hand values, 5 elements of edge 10)."""
    ell, n = 10, 5
    k = np.arange(n + 1, dtype=float)
    band = (k >= 3)[:, None, None] * np.ones((n + 1, n + 1, n + 1))  # nodes above the middle layer
    inside = np.zeros(n + 1)
    inside[2:4] = 1.0  # element layer 2 (nodes 2 and 3) is the band
    u = np.zeros((3, n + 1, n + 1, n + 1))
    u[0] = -0.04 * ell * band
    lateral = 0.01 * inside[:, None, None]  # nodal dUy/dY on the band's nodes
    u[1] = lateral * (k[None, :, None] * ell - n * ell / 2)
    s = mean_strain(u, ell, measure="small")
    assert s.correction_axes == (True, False, True) and not s.correction_applies
    assert s.eps_zz_corrected == pytest.approx(s.mean_all[0, 0], abs=1e-12)  # -0.04 / 5 exactly
    assert s.mean_all[0, 0] == pytest.approx(-0.04 / 5, abs=1e-12)
