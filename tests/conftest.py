import numpy as np
import pytest

from mpcmobo.mpc import ParametricMPC
from mpcmobo.systems import get_system


@pytest.fixture(scope="session")
def cstr():
    return get_system("cstr")


@pytest.fixture(scope="session")
def cstr_mpc(cstr):
    return ParametricMPC(cstr, model="imperfect")


@pytest.fixture(scope="session")
def cstr_perfect_mpc(cstr):
    return ParametricMPC(cstr, model="perfect")


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
