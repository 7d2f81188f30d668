"""Arrays parked on the scratch disk read back as they were written."""

from __future__ import annotations

import numpy as np

from chunkdic.method.protocol import stack_rows
from chunkdic.passes.parked import Parked


def test_an_array_and_a_list_of_rows_read_back_exactly_and_the_file_goes_with_the_object(tmp_path):
    rng = np.random.default_rng(3)
    a = rng.normal(size=(3, 5, 6, 7))
    parked = Parked(a, tmp_path)
    np.testing.assert_array_equal(np.asarray(parked), a)
    np.testing.assert_array_equal(parked[1, 2], a[1, 2])
    assert parked.shape == a.shape and parked.dtype == a.dtype and len(parked) == 3
    # rows as element_fields gives them: the pass's own arrays and broadcast constants
    rows = [a[0, 0], np.broadcast_to(np.float64(-2.5), (6, 7)), a[2, 4], np.broadcast_to(np.nan, (6, 7))]
    stacked = stack_rows(rows)
    assert stacked.shape == (4, 6, 7) and stacked[1].min() == stacked[1].max() == -2.5
    np.testing.assert_array_equal(stacked[0], a[0, 0])
    np.testing.assert_array_equal(np.asarray(Parked(rows, tmp_path)), stacked)
    assert stack_rows(a) is a
    path = parked.path
    assert path.exists()
    del parked
    assert not path.exists()
