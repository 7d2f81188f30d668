"""Issue 10: the default engine on CT-like specimens, against known fields and al-dvc.

The pairs are the standard cases of :func:`chunkdic.synth.synthetic.standard_case` (grains and
concrete specimens imaged by simulated CT: partial-volume edges, filtered back-projection,
reconstruction noise 0.02 of the phase contrast, uint16), written and correlated once per
session (``tests/ctcases.py``). Every figure is :func:`chunkdic.score_displacement`: nodes
at least ``ell`` from the faces, σ pooled over the three components, RMS vector error.

Sizes: the shifts at 80³ (at 64³ only 8 nodes are ``>= 16`` voxels from the faces), the
band and its grey-level changes at 96³ (at 80³ the band spans too few scored nodes: RMS
0.0505 at ℓ = 12 against 0.040 at 96³).

al-dvc 1.2.1 (``al-dvc run --winsize 2ℓ --step ℓ``, its defaults; validation/scripts/bench_vs_aldvc.py,
measured by the lead on the same specimens at 100³, same scoring) gives the bounds of issue 10.
Each test's comment holds the figure measured here (default settings unless stated).
"""

from __future__ import annotations

import numpy as np
import pytest
from textures import smooth_noise

from chunkdic.cli.app import main

# end-to-end runs (whole commands, clusters, kills): `pytest -m 'not slow'` leaves them out
pytestmark = pytest.mark.slow

SHIFT_SIZE = 80
BAND_SIZE = 96

# al-dvc at 100³, ℓ = 16 / 12 / 8: σ on the independent-noise shift, σ on the Fourier shift
# (grains only), RMS on the band (lateral factor 0.05)
ALDVC_SHIFT = {"grains": {16: 0.0011, 12: 0.0025, 8: 0.0053}, "concrete": {16: 0.0019, 12: 0.0030, 8: 0.0067}}
ALDVC_FOURIER = {"grains": {16: 0.0008, 12: 0.0016, 8: 0.0037}}
ALDVC_BAND = {"grains": {12: 0.069, 8: 0.060}, "concrete": {12: 0.070, 8: 0.060}}


@pytest.mark.parametrize("ell", [16, 12, 8])
def test_fourier_shift_converges_at_or_below_aldvc(ct_cases, ell):
    """Paper section 4.2: the reference Fourier-shifted by (0.5, 0.5, 0.5) voxel (shared noise).

    Measured (80³): σ 0.00003 / 0.00004 / 0.00006, |bias| < 0.0001 (the automatic
    regularisation length is long, 32ℓ, for a uniform field); al-dvc 0.0008 / 0.0016 / 0.0037.
    """
    res, score = ct_cases.run("grains", "fourier-shift", SHIFT_SIZE, ell)
    assert res.info["status"] == "converged" and res.converged
    assert score.n_failed == 0 and score.n_points >= 27
    assert score.sigma <= ALDVC_FOURIER["grains"][ell]
    assert np.abs(score.bias).max() < 0.001


@pytest.mark.parametrize("specimen", ["grains", "concrete"])
@pytest.mark.parametrize("ell", [16, 12, 8])
def test_independent_noise_shift_converges_at_or_below_aldvc(ct_cases, specimen, ell):
    """The same translation rendered from the geometry: each scan has its own CT noise.

    Measured (80³) σ: grains 0.0007 / 0.0008 / 0.0021, concrete 0.0015 / 0.0018 / 0.0020
    (ℓ = 16 / 12 / 8; max |bias| 0.0022); al-dvc grains 0.0011 / 0.0025 / 0.0053, concrete
    0.0019 / 0.0030 / 0.0067. Lead at 100³: grains 0.0004 / 0.0006 / 0.0021, concrete
    0.0008 / 0.0010 / 0.0012.
    """
    res, score = ct_cases.run(specimen, "shift", SHIFT_SIZE, ell)
    assert res.info["status"] == "converged" and res.converged
    assert score.n_failed == 0
    assert score.sigma <= ALDVC_SHIFT[specimen][ell]
    assert np.abs(score.bias).max() < 0.005


@pytest.mark.parametrize("ell, bound", [(12, 0.05), (8, 0.048)])
def test_band_converges_with_small_error(ct_cases, ell, bound):
    """Compression band: -8 % peak, 6 voxels wide, lateral factor 0.05, at mid-height.

    Measured (96³) RMS: 0.0401 (ℓ = 12, automatic ℓ_reg 17 voxels), 0.0436 (ℓ = 8, ℓ_reg 16);
    al-dvc 0.069 / 0.060. Issue 10 asks ≤ 0.05 at ℓ = 12 (met) and ≤ 0.035 at ℓ = 8: not met,
    see :func:`test_band_meets_the_issue_target_at_ell_8`; the bound here is the measured
    value plus 10 %. The C8 basis alone (the L2 projection of this field on the ℓ = 8 mesh)
    leaves 0.026 at the nodes (lead's measurement).
    """
    res, score = ct_cases.run("grains", "band", BAND_SIZE, ell)
    assert res.info["status"] == "converged" and res.converged
    assert score.n_failed == 0
    assert score.rms <= bound
    assert score.rms <= ALDVC_BAND["grains"][ell]


def test_band_meets_the_issue_target_at_ell_8(ct_cases):
    """Issue 10's 0.035 at ℓ = 8 (C8 projection floor 0.026): 0.0436 with the plain curvature
    penalty (ℓ_reg 16); met since the robust reweighting frees the band's curvature terms
    (docs/engine.md, "Robust reweighting"; this test was a strict xfail until then)."""
    _, score = ct_cases.run("grains", "band", BAND_SIZE, 8)
    assert score.rms <= 0.035


@pytest.mark.parametrize("grey, gain, drift", [("grey-up", 1.1, 0.03), ("grey-down", 0.9, -0.03)])
def test_grey_level_change_leaves_the_field_unchanged(ct_cases, grey, gain, drift):
    """The deformed scan brighter/darker, offset ±5 %, drift ±3 % along z; same seed (same noise).

    Measured (96³, ℓ = 12): field difference 0.00011 (up) / 0.00014 (down) voxel RMS; the
    brightness found: gain 0.90952 / 1.11163 (truth 1/1.1, 1/0.9), z drift -9.32 / 11.47
    grey levels per voxel (truth -9.41 / 11.50). Before the noise correlation factor was
    made offset-invariant the automatic ℓ_reg changed from 17 to 24 voxels with the grey
    change and the field by 0.023 voxel RMS.
    """
    ref, _ = ct_cases.run("grains", "band", BAND_SIZE, 12)
    res, _ = ct_cases.run("grains", "band+" + grey, BAND_SIZE, 12)
    assert res.info["status"] == "converged"
    diff = res.displacement - ref.displacement
    assert np.sqrt((diff**2).sum(axis=0).mean()) <= 0.005
    # f ≈ gain · g + offset + drift · z: g = G v + ... in phase units, both scans mapping
    # [-0.5, 1.5] to the uint16 range (32767.5 grey levels per unit), drift over nz - 1 slices
    brightness = res.info["grey_level"]
    assert brightness["model"] == "drift"
    assert brightness["gain"] == pytest.approx(1 / gain, rel=2e-3)
    assert brightness["drift"][0] == pytest.approx(-drift / gain * 32767.5 / (BAND_SIZE - 1), rel=0.02)


def test_the_papers_plain_settings_are_still_reachable(ct_cases):
    """No low-pass, no brightness model, no regularisation: the paper's C8-DIC.

    Measured (80³, Fourier shift, ℓ = 12): converged, σ 0.0107 (issue 10 reported 0.0101
    on a real texture at ℓ = 12 with these settings), against 0.00004 with the defaults.
    """
    res, score = ct_cases.run("grains", "fourier-shift", SHIFT_SIZE, 12, smoothing=0, grey="none",
                              regularization="none")
    assert res.info["status"] == "converged"
    assert res.info["settings"]["smoothing"] == 0 and res.info["grey_level"]["model"] == "none"
    assert res.info["regularization"] == {"kind": "none", "length": None, "automatic": True,
                                          "nominal_l10": pytest.approx(2.767 * 12, rel=1e-3),  # C8 alone
                                          "reweights": 0, "freed_terms": 0}
    assert 0.005 < score.sigma < 0.015
    _, default = ct_cases.run("grains", "fourier-shift", SHIFT_SIZE, 12)
    assert default.sigma < score.sigma / 10


def test_stagnating_gap_is_reported_stalled_with_exit_1(tmp_path, capsys):
    """Unrelated scans: nothing to find; the gap stops improving and so do the increments.

    Without regularisation (and without brightness model) the gap reaches its lowest value
    (0.1652, measured) and then grows for 4 passes (to 0.1712) while the increments stay
    large: ``stalled``, exit 1, the best field kept. (With the default Tikhonov term the
    same pair ends ``max-iterations``: the gap keeps creeping down by 1e-5 to 1e-3 of itself
    per pass while the increments stay at 0.2-0.6 voxel, which the stopping rule counts as
    improvement; never ``converged`` either way.)
    """
    import chunkdic
    from chunkdic.method.stopping import STALL_PATIENCE

    f = smooth_noise((48, 48, 48), sigma=1.2, seed=1).astype(np.float32)
    g = smooth_noise((48, 48, 48), sigma=1.2, seed=2).astype(np.float32)
    np.save(tmp_path / "f.npy", f)
    np.save(tmp_path / "g.npy", g)
    out = tmp_path / "r.zarr"
    code = main(["correlate", str(tmp_path / "f.npy"), str(tmp_path / "g.npy"), "-o", str(out),
                 "--element-size", "8", "--grey-level", "none", "--regularization", "none"])
    assert code == 1
    assert "stalled: neither the gap nor the increments improved" in capsys.readouterr().err
    res = chunkdic.open_result(out)
    assert res.info["status"] == "stalled" and not res.converged
    h = res.history
    passes = (h["level"] == 0) & (h["iteration"] >= 0)  # Gauss-Newton passes (not the rigid step)
    gaps, deltas = h["gap"][passes], h["max_delta"][passes]
    best = int(np.argmin(gaps))
    assert res.final_gap == gaps[best]  # the best field is returned
    assert len(gaps) - 1 - best >= STALL_PATIENCE  # no better gap since
    assert np.nanmin(deltas[best:]) > 0.1  # increments far from any tolerance


@pytest.fixture(scope="module")
def wave32_pair(tmp_path_factory):
    """Grains CT pair, 96³, shear wave ``Ux = 0.5 sin(2π (Z - 47.5) / 32)``, independent 2 % noise."""
    from chunkdic.synth import synthetic

    n = 96
    field = synthetic.Wave(period=32.0, amplitude=0.5, phase=(n - 1) / 2)
    pair = synthetic.synthesize(tmp_path_factory.mktemp("wave32") / "pair", (n,) * 3, field=field,
                                specimen="grains", noise=0.02)
    return pair, field, n


def test_smaller_elements_measure_a_32_voxel_wave_better(wave32_pair):
    """Issue 20's rule: features shorter than 3 × 12 voxels, ℓ = 8 measures them better than ℓ = 12.

    Scored between the nodes (trilinear on the node grid, every voxel ≥ ℓ from the faces).
    Measured with the default (predicted-risk) length: ℓ = 8 RMS 0.0642 (ℓ_reg 8), ℓ = 12
    0.1495 (ℓ_reg 12: three nodes per period cannot follow the wave); with the former
    discrepancy rule 0.0619 (ℓ_reg 11) and 0.1472 (ℓ_reg 17), linearised.
    """
    import chunkdic
    from chunkdic.analysis.scoring import score_between_nodes

    pair, field, n = wave32_pair
    rms = {}
    for ell in (8, 12):
        res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=ell)
        assert res.info["status"] == "converged" and res.converged
        axes = [np.unique(c) for c in res.node_coords]
        rms[ell] = score_between_nodes(axes, res.displacement, field, (n,) * 3, ell).rms
    assert rms[8] < rms[12]
    assert rms[8] <= 0.07


@pytest.fixture(scope="module")
def wave24_pair(tmp_path_factory):
    """Grains CT pair, 64³, shear wave ``Ux = 0.5 sin(2π (Z - 31.5) / 24)``, independent 2 % noise."""
    from chunkdic.synth import synthetic

    n = 64
    field = synthetic.Wave(period=24.0, amplitude=0.5, phase=(n - 1) / 2)
    pair = synthetic.synthesize(tmp_path_factory.mktemp("wave24") / "pair", (n,) * 3, field=field,
                                specimen="grains", noise=0.02, seed=1)
    return pair, field, n


def test_a_24_voxel_wave_at_ell_6_converges_at_the_noise_level(wave24_pair):
    """Issue 20 item 6: ℓ = 6 on a 24-voxel wave stops improving at the noise level while a
    few poorly seen nodes at the specimen's edge run away (1-2.5 voxels per pass, 0.5-5 % of
    the nodes; the median node moves by 0.01 σ_u): ``converged``, those nodes flagged weak,
    not ``stalled`` (before: stalled on all four 64³ pairs, grains / concrete × 2 seeds, with
    fields as good as the converged 80³ ones). Scored between the nodes against the analytic
    wave (RMS 0.354 for a zero field). Measured: RMS 0.0916 (before: 0.1007, stalled);
    with the Tikhonov Hessian (issue 20 item 4) 0.0821, final gap 3.2 % above the level's
    best (the runaway nodes; 1.6 % with the second differences alone);
    docs/engine.md, "Iterations and stopping"."""
    import chunkdic
    from chunkdic.analysis.scoring import score_between_nodes
    from chunkdic.results.result import FLAG_WEAK

    pair, field, n = wave24_pair
    res = chunkdic.correlate(pair["reference"], pair["deformed"], element_size=6)
    assert res.info["status"] == "converged" and res.converged
    h = res.history
    fine = (h["level"] == 0) & (h["iteration"] >= 0)
    # stopped at the noise level, not by the tolerance: the gap near its best (within 5 %; the
    # runaway nodes cost 3.2 %), the increments far above 1e-3 voxel
    assert res.final_gap <= 1.05 * h["gap"][fine].min()
    assert np.nanmin(h["max_delta"][fine]) > 0.01
    axes = [np.unique(c) for c in res.node_coords]
    score = score_between_nodes(axes, res.displacement, field, (n,) * 3, 6)
    assert score.rms < 0.10
    # the nodes left unsettled are flagged, and few (the measured nodes' error stays small)
    weak = (res.flags & FLAG_WEAK) > 0
    assert 0 < weak.mean() < 0.2
