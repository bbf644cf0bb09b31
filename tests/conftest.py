from __future__ import annotations

import numpy as np
import pytest

from twin.model.numeric import build
from twin.model.params import load_params


@pytest.fixture(scope="session")
def params():
    return load_params()


@pytest.fixture(scope="session")
def model(params):
    return build(params)


@pytest.fixture
def rng():
    return np.random.default_rng(20261123)
