"""``texture_scale`` of the CT specimens: every size scaled, fractions kept, the texture's
correlation length in proportion (docs/synthetic.md, "Texture scale").

Truths: a Boolean model scaled by ``s`` is the same model with every length times ``s`` (radii,
lattice, hence the autocorrelation); its volume fraction does not depend on ``s``.
"""

from __future__ import annotations

import numpy as np
import pytest

import chunkdic
from chunkdic.errors import InputError
from chunkdic.synth import microstructure as M
from chunkdic.synth import synthetic as S


@pytest.mark.parametrize("scale", [2.0, 3.5])
def test_radii_scale_and_fractions_stay(scale):
    """Drawn radii: the same truncated lognormal law times ``scale`` (median, bounds); the
    intensity of the centres falls as ``scale³`` so that the union's fraction stays 0.6."""
    base = M.spheres(M.GrainsParams(seed=5), "grains", (0, 0, 0), (300, 300, 300))
    big = M.spheres(M.GrainsParams(seed=5, texture_scale=scale), "grains", (0, 0, 0),
                    (300 * scale, 300 * scale, 300 * scale))
    assert np.median(big["radius"]) == pytest.approx(scale * np.median(base["radius"]), rel=0.05)
    assert big["radius"].min() >= 3.0 * scale and big["radius"].max() <= 10.0 * scale
    assert big["intensity"] == pytest.approx(base["intensity"] / scale**3, rel=1e-9)
    concrete = M.ConcreteParams(seed=5, texture_scale=scale)
    assert concrete.aggregates.median == 6.0 * scale and concrete.pores.r_max == 5.0 * scale
    assert concrete.aggregates.fraction == 0.4


def test_autocorrelation_length_grows_in_proportion():
    """Noise-free grains phantoms at scales 1 and 2 (72³ and 144³ windows, the same number of
    grains): the report's autocorrelation length doubles within 15 % on every axis."""
    small = M.render_phantom(M.GrainsParams(seed=2), (72, 72, 72))
    large = M.render_phantom(M.GrainsParams(seed=2, texture_scale=2.0), (144, 144, 144))
    a = chunkdic.texture(small, [], noise=1e-3, edge=72).acl
    b = chunkdic.texture(large, [], noise=1e-3, edge=144).acl
    assert 4.5 < min(a) and max(a) < 7.0  # ~6 voxels at the default scale
    for x, y in zip(a, b):
        assert y / x == pytest.approx(2.0, rel=0.15)


def test_texture_scale_out_of_range_is_refused_and_recorded_when_given(tmp_path, capsys):
    from chunkdic.cli.app import main

    with pytest.raises(InputError, match="texture_scale must lie in"):
        M.GrainsParams(texture_scale=0.1)
    out = tmp_path / "c"
    assert main(["synth", str(out), "--shape", "24", "--specimen", "concrete", "--field", "none",
                 "--texture-scale", "2"]) == 0
    assert S.load_specimen(out).texture_scale == 2.0
    foam = tmp_path / "foam"
    assert main(["synth", str(foam), "--shape", "16", "--texture-scale", "2"]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith("chunkdic: error: --texture-scale only apply")
    assert not foam.exists()
