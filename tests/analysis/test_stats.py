"""Region statistics, the solve's covariance, rigid motion, gauges: against known answers."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest

import chunkdic
from chunkdic.analysis.covariance import NodalCovariance, gradient_adjoint, mass_stencil, point_stencil, point_weights
from chunkdic.analysis.gauge import gauge
from chunkdic.analysis.regions import box_region, line_region, mask_region, slab_region
from chunkdic.analysis.rigid import _XYZ, fit_rigid, remove_rigid, rotation_matrix
from chunkdic.analysis.stats import profile, region_stats
from chunkdic.cli.app import main
from chunkdic.method.noise import nodal_uncertainty
from chunkdic.errors import InputError
from chunkdic.mesh import LOCAL_NODES, Mesh, shape_table
from chunkdic.results.result import Result
from chunkdic.results.strain import displacement_gradient, strain_summary
from chunkdic.solve.cg import StencilSolver
from chunkdic.solve.regularizer import Regularizer, plane_wave_weight
from chunkdic.solve.stencil import stencil_matvec
from chunkdic.synth.fields import Affine
from chunkdic.synth.foam import render


def _result(mesh: Mesh, u, *, sigma=None, regularization=None, path=None) -> Result:
    info = {"element_size": mesh.element_size, "roi": [[o, o + n * mesh.element_size]
                                                       for o, n in zip(mesh.origin, mesh.shape)],
            "final_gap": 0.0, "level": 0, "scale": 1, "status": "converged",
            "regularization": regularization or {"kind": "none", "length": None}}
    info["roi_level0"] = info["roi"]
    hist = {k: np.zeros(0) for k in ("level", "iteration", "gap", "max_delta", "excluded")}
    return Result(np.asarray(u, float), mesh.node_coords(), hist, info, path, uncertainty=sigma)


# --------------------------------------------------------------------------- building blocks


def test_gradient_adjoint_is_the_transpose_of_the_c8_gradient():
    """``Σ G:H(u) = Σ w·u`` for random ``u`` and ``G``: the weights of any strain functional."""
    rng = np.random.default_rng(1)
    u = rng.standard_normal((3, 4, 5, 3))
    G = rng.standard_normal((3, 3, 3, 4, 2))
    w = gradient_adjoint(G, 6.0)
    assert abs(float(np.sum(G * displacement_gradient(u, 6.0))) - float(np.sum(w * u))) < 1e-12


def test_mass_stencil_is_the_voxel_sum_of_shape_function_products():
    """Hand assembly from the shape table (``Σ_voxels N_a N_b`` per element) against the stencil."""
    ell, nodes = 4, (3, 3, 4)
    N = shape_table(ell).reshape(-1, 8)
    m = N.T @ N / ell**3
    dense = np.zeros((np.prod(nodes),) * 2)
    index = np.arange(np.prod(nodes)).reshape(nodes)
    for e in np.ndindex(*(n - 1 for n in nodes)):
        ids = [index[tuple(np.add(e, d))] for d in LOCAL_NODES]
        dense[np.ix_(ids, ids)] += m
    x = np.random.default_rng(2).standard_normal(nodes + (3,))
    Mx = stencil_matvec(mass_stencil(nodes, ell), x)
    assert np.allclose(Mx, np.einsum("ij,jc->ic", dense, x.reshape(-1, 3)).reshape(x.shape), atol=1e-6)


def test_point_weights_reproduce_the_c8_field():
    mesh = Mesh((2, 3, 4), 5, (3, 2, 4))
    u = np.random.default_rng(3).standard_normal((3,) + mesh.nodes_shape)
    p = np.array([9.3, 7.1, 15.8])
    w = point_weights(mesh, p)
    assert abs(w.sum() - 1) < 1e-12
    assert np.allclose(np.einsum("czyx,zyx->c", u, w), mesh.evaluate(u, p.reshape(3, 1))[:, 0], atol=1e-12)


def _dense_solve_covariance(mesh, M_half, length):
    """``A⁻¹ M A⁻¹`` (dense) of a stencil ``M`` with Tikhonov weighted as the engine weighs it."""
    size = 3 * int(np.prod(mesh.nodes_shape))
    eye = np.eye(size).reshape((size,) + mesh.nodes_shape + (3,))
    M = np.stack([stencil_matvec(M_half, e).ravel() for e in eye], axis=1)
    reg = Regularizer("tikhonov", mesh.nodes_shape, float(mesh.element_size))
    lam = plane_wave_weight(reg, lambda v: stencil_matvec(M_half, v), length)
    R = np.stack([reg.apply(e).ravel() for e in eye], axis=1)
    Ainv = np.linalg.inv(M + lam * 0.5 * (R + R.T))
    return Ainv @ M @ Ainv


@pytest.mark.parametrize("texture", ["uniform", "random"])
def test_homogenised_covariance_against_the_dense_solve(texture):
    """Region means from :class:`NodalCovariance` against ``wᵀ A⁻¹MA⁻¹ w`` computed densely.

    The result holds what the engine stores (its per-node σ of that ``M``). ``uniform``: ``M`` is
    7 times the mass matrix, which the model assumes up to scale: within 3 % (measured 1e-10).
    ``random``: each element's texture tensor ``g_e (I + 0.1 (S + Sᵀ))``, ``g_e = e^(0.5 N(0, 1))``,
    which the homogenised model does not know: within 25 %. A point value near the centre from the
    central node's correlations alone (no solve; a profile's band) likewise.
    """
    mesh = Mesh((0, 0, 0), 4, (5, 5, 5))
    nodes = mesh.nodes_shape
    if texture == "uniform":
        M_half = mass_stencil(nodes, 4).astype(np.float64) * 7.0
    else:
        rng = np.random.default_rng(5)  # contrast varying e^±0.5 between elements, mildly anisotropic
        S = rng.standard_normal((5, 5, 5, 3, 3))
        T = np.exp(0.5 * rng.standard_normal((5, 5, 5, 1, 1))) * (np.eye(3) + 0.1 * (S + np.swapaxes(S, -1, -2)))
        m1 = (lambda h: h @ h.T / 4)(np.stack([1 - (np.arange(4) + 0.5) / 4, (np.arange(4) + 0.5) / 4]))
        M_half = np.zeros(nodes + (14, 3, 3))
        from chunkdic.mesh import STENCIL_OFFSETS

        for da in LOCAL_NODES:
            for db in LOCAL_NODES:
                k = int(np.flatnonzero((STENCIL_OFFSETS == db - da).all(axis=1))[0])
                if k >= 13:
                    at = tuple(slice(int(d), int(d) + 5) for d in da)
                    M_half[at + (k - 13,)] += m1[da[0], db[0]] * m1[da[1], db[1]] * m1[da[2], db[2]] * T
    C = _dense_solve_covariance(mesh, M_half, 12.0)
    # what the engine stores: its per-node σ of this M (chunkdic.method.noise.nodal_uncertainty)
    solver = StencilSolver(M_half.astype(np.float32), multigrid=False)
    reg = Regularizer("tikhonov", nodes, 4.0)
    solver.regularize(reg, plane_wave_weight(reg, lambda v: stencil_matvec(solver.matrix, v), 12.0))
    res = _result(mesh, np.zeros((3,) + nodes), sigma=nodal_uncertainty(solver, 1.0, 1.0),
                  regularization={"kind": "tikhonov", "length": 12.0})
    cov = NodalCovariance.of_result(res)
    tol = 0.03 if texture == "uniform" else 0.25
    for region in (np.s_[:, :, :], np.s_[1:4, 1:4, 1:4], np.s_[0:2, :, 2:6]):
        for c in range(3):
            w = np.zeros((3,) + nodes)
            sel = np.zeros(nodes, bool)
            sel[region] = True
            w[c][sel] = 1.0 / sel.sum()
            exact = float(np.moveaxis(w, 0, -1).ravel() @ C @ np.moveaxis(w, 0, -1).ravel())
            assert abs(cov.variance(w) / exact - 1) < tol, (region, c, cov.variance(w), exact)
    # a point value (a profile's) from the central node's correlations, no solve: the same, near the centre
    nodes_p, pw = point_stencil(mesh, np.array([9.1, 10.7, 11.4]))
    for c in range(3):
        w = np.zeros((3,) + nodes)
        np.add.at(w[c], tuple(nodes_p.T), pw)
        exact = float(np.moveaxis(w, 0, -1).ravel() @ C @ np.moveaxis(w, 0, -1).ravel())
        wl = np.zeros((8, 3))
        wl[:, c] = pw
        assert abs(cov.local_variance_at(nodes_p, wl) / exact - 1) < tol  # measured 1.004; 0.92-1.01


# --------------------------------------------------------------------------- regions


def test_box_slab_and_line_select_what_they_say():
    mesh = Mesh((4, 4, 4), 8, (5, 5, 5))  # nodes at 3.5, 11.5, ..., 43.5
    res = _result(mesh, np.zeros((3,) + mesh.nodes_shape))
    box = box_region(res, "12:28,4:44,16:28")  # extent [11.5, 27.5] x [3.5, 43.5] x [15.5, 27.5]
    assert box.nodes.sum() == 3 * 6 * 2 and box.nodes[1:4, :, 2:4].all()  # nodes z, x at 11.5 … 27.5
    assert box.elements.sum() == 2 * 5 * 2 and box.elements[1:3, :, 1:3].all()  # centres 15.5, 23.5
    with pytest.raises(InputError, match="holds no element centre"):
        box_region(res, "12:28,4:44,20:21")  # one node plane, no element centre
    slab = slab_region(res, "z=12:28")
    assert slab.nodes.sum() == 3 * 36 and slab.elements.sum() == 2 * 25  # centres 15.5, 23.5
    with pytest.raises(InputError, match="holds no node"):
        box_region(res, "100:120,0:10,0:10")
    line = line_region(res, (4, 20, 20), (40, 20, 20), step=4)
    assert line.points.shape == (10, 3) and np.allclose(line.distance, np.arange(10) * 4.0)
    with pytest.raises(InputError, match="outside the mesh"):
        line_region(res, (0, 20, 20), (40, 20, 20))


def test_mask_region_read_by_tasks_counts_each_elements_voxels(tmp_path):
    """A label image as a .npy: element selected when half its voxels carry the label, by hand."""
    mesh = Mesh((4, 4, 4), 8, (3, 3, 3))
    res = _result(mesh, np.zeros((3,) + mesh.nodes_shape))
    res.info["input_shapes"] = {"reference": [32, 32, 32]}
    labels = np.zeros((32, 32, 32), np.uint16)
    labels[4:12, 4:12, 4:12] = 3          # element (0, 0, 0) whole
    labels[12:16, 12:20, 12:20] = 3       # half of element (1, 1, 1): selected (>= 0.5)
    labels[20:23, 20:28, 20:28] = 3       # 3/8 of element (2, 2, 2): not selected
    labels[4:12, 20:28, 4:12] = 7         # another label
    np.save(tmp_path / "labels.npy", labels)
    r = mask_region(res, tmp_path / "labels.npy", label=3)
    expected = np.zeros((3, 3, 3), bool)
    expected[0, 0, 0] = expected[1, 1, 1] = True
    assert np.array_equal(r.elements, expected)
    assert r.nodes.sum() == 15  # the 8 nodes of each of two elements, which share node (1, 1, 1)
    assert mask_region(res, tmp_path / "labels.npy").elements.sum() == 3  # non-zero: the label-7 element too
    with pytest.raises(InputError, match="no element"):
        mask_region(res, tmp_path / "labels.npy", label=9)


# --------------------------------------------------------------------------- exact fields


def test_profile_of_an_affine_field_is_the_field():
    mesh = Mesh((4, 4, 4), 8, (4, 4, 4))
    A = np.array([[-0.01, 0.002, 0.0], [0.0, 0.004, 0.0], [0.003, 0.0, 0.001]])
    u = np.einsum("ij,j...->i...", A, mesh.node_coords()) + np.array([0.5, -0.2, 0.1])[:, None, None, None]
    res = _result(mesh, u)
    line = line_region(res, (6, 10, 30), (30, 20, 8), step=3)
    prof = profile(res, line, measure="small")
    pts = line.points.T
    assert np.allclose(prof.values[:3], A @ pts + np.array([0.5, -0.2, 0.1])[:, None], atol=1e-12)
    assert np.allclose(prof.values[3], -0.01) and np.allclose(prof.values[8], 0.5 * (0.002 + 0.0))
    assert np.isnan(prof.sigma).all()  # no per-node uncertainty: no band, said as NaN
    s = region_stats(res, slab_region(res, "z=10:30"), measure="small")
    assert abs(s.row("eps_zz").mean + 0.01) < 1e-12 and math.isnan(s.row("eps_zz").sigma_mean)


# --------------------------------------------------------------------------- correlations with known fields


def _rotation_case(n=48):
    axis_xyz = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)
    R = _XYZ @ rotation_matrix(axis_xyz, 10.0) @ _XYZ  # acting on (z, y, x)
    F = R @ np.diag([0.99, 1.0, 1.0])  # 1 % compression along the specimen's z, then the turn
    field = Affine(matrix=tuple(map(tuple, F - np.eye(3))), center=((n - 1) / 2,) * 3, translation=(0.4, -0.3, 0.2))
    f = render((n,) * 3, seed=2)
    g = render((n,) * 3, seed=2, field=field, which="deformed")
    return f, g, axis_xyz


def test_remove_rigid_finds_a_10_degree_turn_about_a_tilted_axis(tmp_path):
    """10° about (1, 2, 3) plus −1 % along the specimen's z: angle within 0.05°, axis within 0.5°,
    mean strain of the field without the turn within 2e-4 (small strain and Green–Lagrange)."""
    f, g, axis = _rotation_case()
    res = chunkdic.correlate(f, g, element_size=8, output=tmp_path / "r.zarr")
    motion = fit_rigid(res)
    assert abs(motion.angle - 10.0) < 0.05
    assert math.degrees(math.acos(min(abs(float(motion.axis_xyz @ axis)), 1.0))) < 0.5
    assert motion.angle_sigma < 0.05 and np.all(motion.translation_sigma < 0.01)
    truth = np.diag([-0.01, 0.0, 0.0])
    for measure, expected in (("small", truth), ("green-lagrange", np.diag([(0.99**2 - 1) / 2, 0, 0]))):
        s = strain_summary(remove_rigid(res, motion), measure=measure)
        assert np.abs(s.mean - expected).max() < 2e-4, (measure, s.mean)
    raw = strain_summary(res, measure="small")
    assert np.abs(raw.mean - truth).max() > 5e-3  # the turn shows as strain until removed
    # the command line says the same
    assert main(["strain", str(tmp_path / "r.zarr"), "--remove-rigid", "--strain", "small", "--json", "-q"]) == 0


def test_gauge_across_a_homogeneous_compression_reads_it(tmp_path, capsys):
    """−1 % along z: a point gauge and a plane gauge read −1 % within their 95 % intervals;
    refusals for points outside the ROI and planes on two axes."""
    n = 48
    field = Affine(matrix=((-0.01, 0, 0), (0, 0, 0), (0, 0, 0)), center=(n / 2,) * 3, translation=(0.3, 0.1, -0.2))
    rng = np.random.default_rng(4)
    f0 = render((n,) * 3, seed=5)
    f = (f0 + 0.03 * rng.standard_normal(f0.shape)).astype(np.float32)
    g = (render((n,) * 3, seed=5, field=field, which="deformed") + 0.03 * rng.standard_normal(f0.shape)).astype(
        np.float32)
    out = tmp_path / "r.zarr"
    chunkdic.correlate(f, g, element_size=8, output=out)
    for kind in ({"points": ["8,24,24", "40,24,24"]}, {"planes": ["z=8", "z=40"]}):
        reading = gauge(out, **kind).readings[0]
        assert reading.low <= -0.01 <= reading.high, (kind, reading)
        assert reading.high - reading.low < 2e-3
    assert main(["gauge", str(out), "--points", "8,24,24", "40,24,24", "-o", str(tmp_path / "g"), "-q"]) == 0
    assert (tmp_path / "g" / "gauge.png").exists()
    assert json.loads((tmp_path / "g" / "gauge.json").read_text())["readings"][0]["strain"] == pytest.approx(
        -0.01, abs=1e-3)
    capsys.readouterr()
    assert main(["gauge", str(out), "--points", "0,24,24", "40,24,24"]) == 2
    assert "lies outside the ROI" in capsys.readouterr().err
    assert main(["gauge", str(out), "--planes", "z=8", "y=40"]) == 2


def test_gauge_refuses_a_series_without_steps(tmp_path, capsys):
    import zarr

    g = zarr.open_group(str(tmp_path / "s.zarr"), mode="w", zarr_format=3)
    g.attrs["chunkdic"] = {"kind": "series", "complete": True, "summary": []}
    assert main(["gauge", str(tmp_path / "s.zarr"), "--points", "8,24,24", "40,24,24"]) == 2
    assert "has no step" in capsys.readouterr().err


@pytest.mark.slow
def test_interval_of_a_region_mean_covers_the_truth_19_of_20(capsys):
    """20 independent noise draws of one pair (48³ foam, −1 % along z and a translation, noise 5 % of
    the texture's range in each scan, ℓ = 8, default regularisation): the 95 % interval of each
    region mean (ROI and a corner box; Uz, Uy, Ux, ε_zz) covers the true mean in 19 ± 3 of 20
    draws; the naive std/√n interval covers far fewer where the field is uniform (Uy, Ux, ε_zz;
    printed). 65 s on 2 shared cores."""
    n = 48
    field = Affine(matrix=((-0.01, 0, 0), (0, 0, 0), (0, 0, 0)), center=(n / 2,) * 3, translation=(0.3, -0.2, 0.45))
    f0 = render((n,) * 3, seed=1)
    g0 = render((n,) * 3, seed=1, field=field, which="deformed")
    covered, naive = {}, {}
    t0 = time.perf_counter()
    for draw in range(20):
        rng = np.random.default_rng(100 + draw)
        f = (f0 + 0.05 * rng.standard_normal(f0.shape)).astype(np.float32)
        g = (g0 + 0.05 * rng.standard_normal(f0.shape)).astype(np.float32)
        res = chunkdic.correlate(f, g, element_size=8)
        cov = NodalCovariance.of_result(res)
        for region in (None, box_region(res, "4:28,4:28,4:28")):
            s = region_stats(res, region, truth=field, measure="small", covariance=cov)
            for q in ("Uz", "Uy", "Ux", "eps_zz"):
                r = s.row(q)
                true_mean = r.mean - r.bias
                key = (s.region, q)
                covered[key] = covered.get(key, 0) + int(r.low <= true_mean <= r.high)
                naive[key] = naive.get(key, 0) + int(abs(r.bias) <= 1.959964 * r.naive_sigma_mean)
    with capsys.disabled():
        print(f"\n20 draws in {time.perf_counter() - t0:.0f} s; covered of 20 (solve's covariance / naive std/√n):")
        for key in covered:
            print(f"  {key[0]:<28} {key[1]:<7} {covered[key]:>2} / {naive[key]:>2}")
    assert all(16 <= c <= 20 for c in covered.values()), covered
    assert all(naive[k] <= 10 for k in naive if k[1] != "Uz")  # Uz varies over the region: its std is the signal
