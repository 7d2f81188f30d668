"""Shared test fixtures."""

from __future__ import annotations

import numpy as np
import pytest
from textures import smooth_noise


@pytest.fixture(scope="session")
def noise64():
    return smooth_noise((64, 64, 64), sigma=1.2, seed=3).astype(np.float32)


@pytest.fixture(scope="session")
def ct_cases(tmp_path_factory):
    """CT-like pairs and their correlations, each made once per session (``tests/ctcases.py``)."""
    from ctcases import CTCases

    return CTCases(tmp_path_factory.mktemp("ct"))
