"""M kept in the output for a resumed run (chunkdic.passes.stored_matrix; issue 21, item 5):
read back only complete and for the same key, never after a kill while it was written."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from chunkdic.method.operator import Assembled
from chunkdic.passes.stored_matrix import StoredMatrix, cells_bytes, field_hash, stored_bytes


@pytest.fixture
def output(tmp_path):
    path = tmp_path / "out.zarr"
    zarr.open_group(str(path), mode="w", zarr_format=3).attrs["chunkdic"] = {"kind": "result", "complete": False}
    return path


def _m(nodes=(5, 4, 6), active=True):
    rng = np.random.default_rng(5)
    return Assembled(rng.normal(size=nodes + (14, 3, 3)).astype(np.float32), rng.normal(size=(3, 7)),
                     rng.random(tuple(n - 1 for n in nodes)) > 0.3 if active else None, -3.5, 812.25)


def _key(nodes=(5, 4, 6), u=None):
    u = np.zeros((3,) + nodes) if u is None else u
    return {"level": 0, "nodes": list(nodes), "blocks": 2, "f_grid": [0.0, 1.0, "float32"], "field": field_hash(u)}


@pytest.mark.parametrize("active", [True, False])
def test_m_reads_back_as_written_for_its_key_only(output, active):
    m, kept = _m(active=active), StoredMatrix(output)
    assert kept.load(_key()) is None and kept.level() is None
    kept.save(_key(), m)
    got = kept.load(_key())
    np.testing.assert_array_equal(got.stencil, m.stencil)
    np.testing.assert_array_equal(got.lags, m.lags)
    if active:
        np.testing.assert_array_equal(got.active, m.active)
    else:
        assert got.active is None
    assert (got.fmin, got.fmax, kept.level()) == (-3.5, 812.25, 0)
    moved = np.zeros((3, 5, 4, 6))
    moved[0, 1, 1, 1] = 1e-9  # M built at another field
    assert kept.load(_key(u=moved)) is None
    assert kept.load({**_key(), "blocks": 4}) is None
    # other attributes of the output are kept (the checkpoint's pointer, ...)
    assert zarr.open_group(str(output), mode="r").attrs["chunkdic"]["kind"] == "result"


def test_a_kill_while_m_is_written_leaves_nothing_to_read(output):
    """The record goes first and comes last: arrays written without it are never read."""
    kept = StoredMatrix(output)
    kept.save(_key(), _m())
    real = StoredMatrix._set_record

    class Killed(Exception):
        pass

    def dies_before_the_record(self, root, record):
        if record is not None:
            raise Killed
        real(self, root, record)

    StoredMatrix._set_record = dies_before_the_record
    try:
        with pytest.raises(Killed):
            kept.save(_key(), _m(nodes=(5, 4, 6)))
    finally:
        StoredMatrix._set_record = real
    assert kept.load(_key()) is None


def test_dropped_m_is_gone(output):
    kept = StoredMatrix(output)
    kept.save(_key(), _m())
    kept.drop()
    assert kept.load(_key()) is None
    assert not [p for p in output.rglob("*") if "matrix" in p.name]


def test_brightness_cells_read_back_with_m(output):
    # the cells' Schur complement (kernels.m.cell_couplings) is part of the step's matrix: a
    # resumed run reads it with the stencil, and an M kept without it is not read for cells
    m, kept = _m(), StoredMatrix(output)
    m.cells = np.random.default_rng(2).normal(size=(2, 2, 3, 3, 3, 3, 3, 4)).astype(np.float32)
    kept.save(_key(), m)
    np.testing.assert_array_equal(kept.load(_key()).cells, m.cells)
    kept.save(_key(), _m())
    assert kept.load(_key()).cells is None
    assert not [p for p in output.rglob("*") if p.name == "matrix_cells"]


def test_size_per_node():
    # 14 blocks of 3 x 3 float32 per node; the 128³ nodes of a 2048³ level-0 run at ell = 16
    assert stored_bytes((128, 128, 128)) == 128**3 * 14 * 9 * 4 == 1_056_964_608
    # with cells of 2³ elements: (2 + 1)³ nodes x 3 x 4 float32 per cell, 64³ cells
    assert cells_bytes((127, 127, 127), 2) == 64**3 * 27 * 48 == 339_738_624
    assert stored_bytes((128, 128, 128), 2) == 1_056_964_608 + 339_738_624
    assert cells_bytes((127, 127, 127), 1) == 0
