"""Settings: validation, TOML round trip, errors naming the key; atomic storage helpers."""

from __future__ import annotations

import os
import tomllib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mpcmobo.experiment.settings import (
    Settings,
    SettingsError,
    load_settings,
    settings_to_toml,
    validate_settings,
)
from mpcmobo.experiment.storage import (
    atomic_write_bytes,
    read_json,
    read_pickle,
    write_json,
    write_pickle,
)


def test_defaults_are_the_paper_study():
    s = Settings()
    assert s.system.name == "cstr"
    assert s.episodes == 600
    assert s.start_mode == "cycle"
    assert s.learners == ["mpc-rl", "bo", "mobo"]
    assert s.seeds == [0]
    assert s.evaluation.n_starts == 10 and s.evaluation.eval_every == 10
    assert s.workers == 2 and s.backend == "process"


def test_resolved_fills_system_defaults_and_round_trips(tmp_path):
    r = load_settings(None, learners=["mpc-rl"]).resolved()
    assert r.mpc.horizon == 10 and r.mpc.gamma == 0.99 and r.steps == 60
    assert r.exploration.std is not None and len(r.exploration.std) == 2
    assert r.evaluation.steps == 60
    text = settings_to_toml(r)
    p = tmp_path / "config.toml"
    p.write_text(text)
    again = load_settings(p)
    assert again == r
    assert tomllib.loads(text)["system"]["name"] == "cstr"


def test_overrides_merge_into_file(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('episodes = 7\n[mpc]\nhorizon = 5\ntol = 1e-6\n[system]\nname = "lq"\n')
    s = load_settings(p, mpc__horizon=4, seeds=[1, 2], episodes=None)
    assert s.episodes == 7 and s.mpc.horizon == 4 and s.mpc.tol == 1e-6 and s.seeds == [1, 2]
    assert s.system.name == "lq"


@pytest.mark.parametrize(
    "data, key, allowed",
    [
        ({"mpc": {"horizn": 3}}, "mpc.horizn", "horizon"),
        ({"bogus": 1}, "bogus", "episodes"),
        ({"start_mode": "zigzag"}, "start_mode", "'random' or 'cycle'"),
        ({"system": {"name": "nope"}}, "system.name", "cstr"),
        ({"learners": ["sgd"]}, "learners", "mpc-rl"),
        ({"episodes": 0}, "episodes", "greater than or equal to 1"),
        ({"mpc": {"gamma": 1.5}}, "mpc.gamma", "less than or equal to 1"),
        ({"critic": {"method": "td"}}, "critic.method", "'lstd' or 'paper'"),
        ({"exploration": {"std": [1.0]}}, "exploration.std", "2 inputs"),
        ({"backend": "dask"}, "backend", "'process' or 'ray'"),
        ({"seeds": [1, 1]}, "seeds", "only once"),
        ({"workers": True}, "workers", "integer"),
    ],
)
def test_invalid_values_name_the_key(data, key, allowed):
    with pytest.raises(SettingsError) as exc:
        validate_settings(data)
    msg = str(exc.value)
    assert key in msg and allowed in msg, msg


def test_bad_files(tmp_path):
    with pytest.raises(SettingsError, match="not found"):
        load_settings(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("episodes = = 3\n")
    with pytest.raises(SettingsError, match="not valid TOML"):
        load_settings(bad)


# ---------------------------------------------------------------------- property tests
KEYS = [
    "system",
    "mpc",
    "exploration",
    "episodes",
    "steps",
    "start_mode",
    "critic",
    "beta",
    "learners",
    "learner_options",
    "evaluation",
    "seeds",
    "workers",
    "backend",
    "name",
    "horizon",
    "gamma",
    "std",
    "decay",
    "n_starts",
    "learn_model",
    "weight_log_range",
    "method",
    "eval_every",
    "records",
    "junk",
]
scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.sampled_from(["cstr", "lq", "mpc-rl", "bo", "random", "cycle", "lstd", "ray", "k0"]),
)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4),
        st.dictionaries(st.sampled_from(KEYS), inner, max_size=4),
    ),
    max_leaves=12,
)
toml_like = st.dictionaries(st.sampled_from(KEYS), values, max_size=6)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(toml_like)
def test_malformed_settings_only_raise_settings_error(data):
    try:
        s = validate_settings(data)
    except SettingsError as err:
        assert str(err)
        return
    # whatever validates can be resolved and written as TOML and read back identically
    r = s.resolved()
    assert validate_settings(tomllib.loads(settings_to_toml(r))) == r


@settings(max_examples=50, deadline=None)
@given(st.binary(max_size=60))
def test_garbage_files_only_raise_settings_error(tmp_path_factory, blob):
    p = tmp_path_factory.mktemp("g") / "c.toml"
    p.write_bytes(blob)
    try:
        load_settings(p)
    except SettingsError:
        pass


# ---------------------------------------------------------------------- storage
def test_atomic_writes(tmp_path):
    obj = {"a": np.arange(3), "b": float("nan"), "c": [np.float64(1.5), np.int64(2)]}
    write_json(tmp_path / "x.json", obj)
    assert read_json(tmp_path / "x.json") == {"a": [0, 1, 2], "b": None, "c": [1.5, 2]}
    write_pickle(tmp_path / "p.pkl", {"z": np.ones(2)})
    assert np.array_equal(read_pickle(tmp_path / "p.pkl")["z"], np.ones(2))
    # a failing write leaves the old file and no temporary files behind
    target = tmp_path / "keep.bin"
    atomic_write_bytes(target, b"old")

    with pytest.raises(TypeError):
        atomic_write_bytes(target, object())  # type: ignore[arg-type]
    assert target.read_bytes() == b"old"
    assert sorted(os.listdir(tmp_path)) == ["keep.bin", "p.pkl", "x.json"]


def test_atomic_writes_follow_the_umask_without_changing_it(tmp_path):
    """Files get the mode of any new file (0o666 less the umask), not mkstemp's 0o600, and
    neither importing nor writing changes the process umask."""
    old = os.umask(0o027)
    try:
        atomic_write_bytes(tmp_path / "a.bin", b"x")
        assert os.stat(tmp_path / "a.bin").st_mode & 0o777 == 0o640
        assert os.umask(0o027) == 0o027  # still the one set above
    finally:
        os.umask(old)
