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
from mpcmobo.learners.registry import learner_options


def test_defaults_are_the_paper_study():
    s = Settings()
    assert s.system.name == "cstr"
    assert s.episodes == 600
    assert s.start_mode == "cycle"
    assert s.learners == ["mpc-rl", "bo", "mobo", "identify"]
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
    # every option of the study's learners, with its default (what config.toml holds)
    assert r.learner_options == {"mpc-rl": learner_options("mpc-rl")}
    assert tomllib.loads(text)["learner_options"]["mpc-rl"]["optimizer"]["lr"] == 0.03


def test_resolved_learner_options_keep_the_given_ones_and_fill_the_rest():
    """Given options stay, shorthands are written out in full (``deploy = "incumbent"``,
    ``trust_region = true``), the rest take their defaults; a table for a learner that the
    study does not run is kept too."""
    s = load_settings(
        None,
        learners=["mpc-rl", "mobo"],
        learner_options={
            "mobo": {"n_init": 3, "search": {"num_restarts": 2, "raw_samples": 32, "maxiter": 20}},
            "mpc-rl": {"optimizer": "gd", "deploy": "iterate"},
            "bo": {"deploy": "incumbent", "trust_region": True},
        },
    )
    opts = s.resolved().learner_options
    assert list(opts) == ["mpc-rl", "mobo", "bo"]
    assert opts["mpc-rl"] == {
        "optimizer": {"rule": "gd", "lr": 0.003},
        "deploy": {"rule": "iterate"},
    }
    mobo = learner_options("mobo")
    assert opts["mobo"]["search"] == dict(
        mobo["search"], num_restarts=2, raw_samples=32, maxiter=20
    )
    assert opts["mobo"]["n_init"] == 3 and opts["mobo"]["deploy"] == mobo["deploy"]
    assert {k: v for k, v in opts["mobo"].items() if k not in ("n_init", "search")} == {
        k: v for k, v in mobo.items() if k not in ("n_init", "search")
    }
    bo = learner_options("bo")
    assert opts["bo"] == dict(bo, deploy={"rule": "incumbent"})
    assert opts["bo"]["trust_region"] == bo["trust_region"]  # ``true``: the default table
    # the resolved options are valid settings, and resolving them again changes nothing
    assert s.resolved().resolved().learner_options == opts


def test_overrides_merge_into_file(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('episodes = 7\n[mpc]\nhorizon = 5\ntol = 1e-6\n[system]\nname = "lq"\n')
    s = load_settings(p, mpc__horizon=4, seeds=[1, 2], episodes=None)
    assert s.episodes == 7 and s.mpc.horizon == 4 and s.mpc.tol == 1e-6 and s.seeds == [1, 2]
    assert s.system.name == "lq"


def test_a_wrong_value_in_the_file_is_refused_where_an_override_sets_it_too(tmp_path):
    """The command line setting a key does not hide that the file's value is wrong."""
    p = tmp_path / "c.toml"
    p.write_text('episodes = "ten"\n[mpc]\nhorizon = 0\n[system]\nname = "lq"\n')
    with pytest.raises(SettingsError, match=r"(?s)in the file .*\n  episodes: .*'ten'"):
        load_settings(p, episodes=2, mpc__horizon=4)
    with pytest.raises(SettingsError, match=r"mpc\.horizon: .*greater than or equal to 1"):
        load_settings(p, episodes=2, mpc__horizon=4)
    p.write_text('episodes = 7\n[mpc]\nhorizon = 5\n[system]\nname = "lq"\n')
    assert load_settings(p, episodes=2, mpc__horizon=4).episodes == 2


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
        ({"mpc": {"barrier_steps": 3}}, "mpc.barrier_steps", "newton_steps"),
        ({"learner_options": {"sgd": {}}}, "learner_options.sgd", "an unknown learner"),
        ({"learner_options": {"bo": 3}}, "learner_options.bo", "valid dictionary"),
        ({"learner_options": 0}, "learner_options", "valid dictionary"),
        (
            {"learner_options": {"bo": {"deploy": {"confidence": 1.5}}}},
            "learner_options.bo.deploy.confidence:",
            "(got 1.5)",
        ),
        ({"learner_options": {"mpc-rl": {"lr": 0.1}}}, "learner_options.mpc-rl.lr:", "unknown"),
        (
            {"learner_options": {"mobo": {"search": {"num_restarts": 0}}}},
            "learner_options.mobo.search.num_restarts:",
            "greater than or equal to 1",
        ),
        (
            {"learner_options": {"hybrid": {"deploy": "verified"}}},
            "learner_options.hybrid.deploy:",
            "'evidence', 'incumbent'",
        ),
        (
            {"learner_options": {"mpc-rl": {"deploy": {"runs": 8, "max_runs": 6}}}},
            "learner_options.mpc-rl.deploy:",
            "max_runs (6) must be at least runs (8)",
        ),
        ({"system": {"learn_model": ["k0", "k0"]}}, "system.learn_model:", "only once"),
        ({"system": {"identify": ["k0", "k0"]}}, "system.identify:", "only once"),
        ({"beta": -1.0}, "beta:", "greater than 0"),
    ],
)
def test_invalid_values_name_the_key(data, key, allowed):
    with pytest.raises(SettingsError) as exc:
        validate_settings(data)
    msg = str(exc.value)
    assert key in msg and allowed in msg, msg


def test_an_unknown_learnable_model_parameter_names_its_key():
    with pytest.raises(SettingsError, match=r"system.learn_model: unknown model parameter"):
        load_settings(None, system={"name": "lq", "learn_model": ["mass"]})


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
    "mpc-rl",
    "bo",
    "mobo",
    "hybrid",
    "n_init",
    "deploy",
    "search",
    "trust_region",
    "optimizer",
    "rule",
    "num_restarts",
    "confidence",
    "lr",
]
scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.sampled_from(["cstr", "lq", "mpc-rl", "bo", "random", "cycle", "lstd", "ray", "k0"]),
    st.sampled_from(["incumbent", "evidence", "gd", "adam", "iterate", "verified"]),
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


NO_PARAMETERS = """
import dataclasses
from mpcmobo.systems.lq import make_lq

def make_system():
    return dataclasses.replace(make_lq(), name="lq-known", identifiable=())
"""


def test_the_cycles_own_starts_are_checked_against_the_system_and_the_start_mode():
    """``cycle_starts``: their number is ``n_cycle_starts`` (given both, they must agree);
    each start has the system's states, finite, within its state bounds; under random starts
    they are refused, naming the key."""
    s = load_settings(None, system={"name": "lq"}, cycle_starts=[[1.0, 0.5], [-1.0, 0.0]])
    assert s.n_cycle_starts == 2 and s.resolved().cycle_starts == [[1.0, 0.5], [-1.0, 0.0]]
    assert load_settings(None, cycle_starts=None).cycle_starts is None
    bad = {
        "has 1 value; the system 'lq' has 2 states": [[1.0]],
        r"cycle_starts\[1\]: v = 99.0 is outside the system's state bounds": [[0, 0], [0, 99]],
        "Input should be a finite number": [[0.0, float("nan")]],
        "at least 1 item": [],
    }
    for message, starts in bad.items():
        with pytest.raises(SettingsError, match=message):
            load_settings(None, system={"name": "lq"}, cycle_starts=starts)
    with pytest.raises(SettingsError, match="n_cycle_starts is 3 but cycle_starts holds 2"):
        load_settings(None, system={"name": "lq"}, n_cycle_starts=3, cycle_starts=[[0, 0]] * 2)
    with pytest.raises(SettingsError, match="start_mode = 'cycle' \\(here 'random'"):
        load_settings(None, system={"name": "lq"}, start_mode="random", cycle_starts=[[0, 0]])


def test_numpy_arrays_are_taken_as_the_lists_of_a_settings_file():
    """Settings given in Python (``Tuner(..., **settings)``) may be NumPy arrays and scalars:
    a batch plant's recipes as an array, noise levels, seeds, a count; they are validated and
    stored as the lists and numbers a settings file holds."""
    s = load_settings(
        None,
        system={"name": "cstr", "measurement_noise": np.array([0.1, 0.001, 0.1])},
        cycle_starts=np.array([[100.0, 0.2, 420.0], [95.0, 0.1, 410.0]]),
        exploration={"std": np.array([0.5, 0.5])},
        seeds=np.arange(2),
        episodes=np.int64(7),
    )
    assert s.cycle_starts == [[100.0, 0.2, 420.0], [95.0, 0.1, 410.0]] and s.n_cycle_starts == 2
    assert s.system.measurement_noise == [0.1, 0.001, 0.1] and s.exploration.std == [0.5, 0.5]
    assert s.seeds == [0, 1] and s.episodes == 7
    assert type(s.resolved().cycle_starts[0][0]) is float
    with pytest.raises(SettingsError, match=r"cycle_starts\[0\] has 3 values"):
        load_settings(None, system={"name": "lq"}, cycle_starts=np.zeros((1, 3)))


def test_identify_is_a_default_learner_only_where_there_is_a_model_to_identify(tmp_path):
    """The default study runs the paper's learners and ``identify``; on a system that declares
    no model parameter to identify ``identify`` is left out, and naming it is an error."""
    assert load_settings(None).resolved().learners == ["mpc-rl", "bo", "mobo", "identify"]
    (tmp_path / "noparams.py").write_text(NO_PARAMETERS)
    system = {"factory": f"{tmp_path / 'noparams.py'}:make_system"}
    assert load_settings(None, system=system).resolved().learners == ["mpc-rl", "bo", "mobo"]
    with pytest.raises(SettingsError, match="no model parameter to identify"):
        load_settings(None, system=system, learners=["mobo", "identify"])
