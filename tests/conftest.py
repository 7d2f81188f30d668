"""Shared test fixtures."""

from __future__ import annotations

import numpy as np
import pytest

from textures import smooth_noise


@pytest.fixture(scope="session")
def noise64():
    return smooth_noise((64, 64, 64), sigma=1.2, seed=3).astype(np.float32)
