"""Fixtures shared by the loss tests."""

import numpy as np
import pytest


@pytest.fixture
def heavy_tailed_pair():
    rng = np.random.default_rng(7)
    # Student-t noise: heavy tails in every subband (kurtosis well above 0)
    pred = rng.standard_t(df=4, size=(2, 3, 64, 48)) * 0.1 + 0.5
    gt = rng.standard_t(df=6, size=(2, 3, 64, 48)) * 0.1 + 0.5
    return pred, gt
