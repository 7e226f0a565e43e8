"""Generated C code of the MPC (``codegen=True``): same numbers, compiled once, cached on disk."""

import multiprocessing
import os
import shutil
import subprocess

import numpy as np
import pytest
from cstr_reference import fd_sensitivities

from mpcmobo.mpc import ParametricMPC
from mpcmobo.mpc import codegen as cg
from mpcmobo.systems import get_system

needs_cc = pytest.mark.skipif(
    shutil.which(cg.compiler_command()[0]) is None, reason="no C compiler ($CC or cc)"
)


@pytest.fixture(scope="module")
def lq():
    return get_system("lq")


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("codegen-cache")


@pytest.fixture(scope="module")
def lq_pair(lq, cache):
    """The interpreted MPC and the compiled one, both without a warm start."""
    interp = ParametricMPC(lq, warm_start=False, tol=1e-10)
    compiled = ParametricMPC(lq, warm_start=False, tol=1e-10, codegen=True, cache_dir=cache)
    return interp, compiled


def _theta(mpc, rng):
    th = mpc.theta0 * np.exp(rng.normal(0, 0.3, mpc.n_theta))
    b = mpc.param.blocks["G"]
    th[b] = rng.normal(0, 1.0, len(th[b]))
    return th


@needs_cc
def test_compiled_mpc_gives_the_interpreted_numbers(lq, lq_pair):
    interp, compiled = lq_pair
    assert compiled.build_info["codegen"] and compiled.build_info["path"].endswith(".so")
    rng = np.random.default_rng(3)
    for _ in range(3):
        x, th = lq.sample_initial_state(rng), _theta(interp, rng)
        a, b = interp.solve(x, th), compiled.solve(x, th)
        assert a.success and b.success
        np.testing.assert_allclose(b.action, a.action, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(b.value, a.value, rtol=1e-10)
        np.testing.assert_allclose(b.dpi_dtheta, a.dpi_dtheta, rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(b.dV_dtheta, a.dV_dtheta, rtol=1e-8, atol=1e-12)


@needs_cc
def test_compiled_sensitivities_match_central_differences(lq, lq_pair):
    _, mpc = lq_pair
    rng = np.random.default_rng(5)
    x, th = lq.sample_initial_state(rng), _theta(mpc, rng)
    sol = mpc.solve(x, th)
    dpi, dV = fd_sensitivities(mpc, x, th)
    np.testing.assert_allclose(sol.dpi_dtheta, dpi, rtol=1e-4, atol=1e-6 * np.abs(dpi).max())
    np.testing.assert_allclose(sol.dV_dtheta, dV, rtol=1e-4, atol=1e-6 * np.abs(dV).max())


@needs_cc
def test_second_build_loads_the_cached_library(lq, lq_pair, cache, monkeypatch):
    _, first = lq_pair
    path = first.build_info["path"]

    def no_compiler(*args, **kwargs):
        raise AssertionError("compiled again although the library is cached")

    monkeypatch.setattr(subprocess, "run", no_compiler)
    again = ParametricMPC(lq, warm_start=False, tol=1e-10, codegen=True, cache_dir=cache)
    assert again.build_info["cached"] and again.build_info["path"] == path
    # another problem (horizon) is another library
    monkeypatch.undo()
    other = ParametricMPC(lq, horizon=3, codegen=True, cache_dir=cache)
    assert other.build_info["path"] != path and not other.build_info["cached"]
    assert sorted(p.name for p in cache.iterdir()) == sorted(
        os.path.basename(p) for p in (path, other.build_info["path"])
    )  # no temporary files left


def _build(cache_dir):
    mpc = ParametricMPC(get_system("lq"), horizon=2, codegen=True, cache_dir=cache_dir)
    sol = mpc.solve(mpc.system.x_ref + 0.1)
    return mpc.build_info["path"], bool(sol.success), sol.action.tolist()


@needs_cc
def test_concurrent_builds_share_one_library(tmp_path):
    # two processes build the same MPC at the same time: both load a complete library
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        results = pool.map(_build, [tmp_path, tmp_path])
    assert results[0] == results[1] and results[0][1]
    assert [p.name for p in tmp_path.iterdir()] == [os.path.basename(results[0][0])]


def test_codegen_errors(lq, tmp_path, monkeypatch):
    """Without the compiler: the MPC says what to do, and a study with [mpc] codegen = true
    stops before anything is written, naming the setting."""
    from mpcmobo.experiment.settings import SettingsError, load_settings
    from mpcmobo.experiment.study import run_study

    monkeypatch.setenv("CC", "no-such-compiler-xyz")
    with pytest.raises(RuntimeError, match="needs a C compiler, and 'no-such-compiler-xyz'"):
        ParametricMPC(lq, horizon=4, codegen=True, cache_dir=tmp_path)
    settings = load_settings(None, system={"name": "lq"}, mpc={"codegen": True}, episodes=1)
    with pytest.raises(SettingsError, match=r"mpc.codegen: .*\[mpc\] codegen = false"):
        run_study(settings, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_cache_directory_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv("MPCMOBO_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert cg.cache_directory() == tmp_path / "mpcmobo"
    monkeypatch.setenv("MPCMOBO_CACHE_DIR", str(tmp_path / "own"))
    assert cg.cache_directory() == tmp_path / "own"


def test_auto_compiles_where_it_can(lq, tmp_path, monkeypatch):
    """``codegen="auto"`` (the settings' default): compiled with a compiler, CasADi's virtual
    machine without one or where compiling fails (with a warning), the same action either way;
    a value that is neither a bool nor "auto" is refused."""
    from mpcmobo.experiment.settings import load_settings

    assert load_settings(None).mpc.codegen == "auto"
    x = lq.x_ref + 0.1
    monkeypatch.setenv("CC", "no-such-compiler-xyz")
    without = ParametricMPC(lq, horizon=2, codegen="auto", cache_dir=tmp_path)
    assert without.build_info == {"codegen": False} and not list(tmp_path.iterdir())
    monkeypatch.setenv("CC", "false")  # found, but every compile fails
    with pytest.warns(RuntimeWarning, match=r'codegen = "auto"\): compiling the MPC'):
        failed = ParametricMPC(lq, horizon=2, codegen="auto", cache_dir=tmp_path)
    assert failed.build_info["codegen"] is False
    with pytest.raises(ValueError, match="codegen must be true, false or 'auto'"):
        ParametricMPC(lq, horizon=2, codegen="yes", cache_dir=tmp_path)  # type: ignore[arg-type]
    u = without.solve(x).action
    assert np.array_equal(failed.solve(x).action, u)
    if shutil.which("cc"):
        monkeypatch.delenv("CC")
        compiled = ParametricMPC(lq, horizon=2, codegen="auto", cache_dir=tmp_path)
        assert compiled.build_info["codegen"] is True and compiled.build_info["path"]
        np.testing.assert_allclose(compiled.solve(x).action, u, rtol=0, atol=1e-12)
