import importlib
from pathlib import Path

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


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread():
    """One torch thread, as in a study's worker process: the bo code no longer sets it itself,
    and its small GP matrices run faster on one (tests/test_bo.py: 10 s instead of 16 s)."""
    import torch

    torch.set_num_threads(1)


@pytest.fixture
def benchmark_script(monkeypatch):
    """A script of ``benchmarks/`` as a module, imported as it runs: with ``benchmarks/`` on
    ``sys.path`` (the scripts import each other)."""
    monkeypatch.syspath_prepend(str(Path(__file__).parents[1] / "benchmarks"))
    return importlib.import_module


@pytest.fixture(scope="session")
def dashboard_run(tmp_path_factory):
    """A small finished run for the dashboard's tests (tests/dashboard_helpers.py)."""
    from dashboard_helpers import make_small_run

    return make_small_run(tmp_path_factory.mktemp("dashboard") / "run")
