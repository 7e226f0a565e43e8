"""The command line: run, resume, evaluate, systems; invalid settings exit with code 2."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from mpcmobo.cli import app
from mpcmobo.experiment import storage

runner = CliRunner()
SMALL = [
    "--system",
    "lq",
    "--learner",
    "mpc-rl",
    "--episodes",
    "3",
    "--steps",
    "8",
    "--workers",
    "1",
]


def test_systems_is_a_narrow_table_and_one_description_line_per_system(monkeypatch):
    """``mpcmobo systems`` in 80 columns: a table of the built-in systems that fits without
    folding a cell (one line per system), then one line per system with its kind and
    description."""
    from rich.console import Console

    import mpcmobo.cli as cli
    from mpcmobo.systems import get_system

    help_text = " ".join(runner.invoke(app, ["systems", "--help"]).output.split())
    assert (
        "[system] factory" in help_text and '[project.entry-points."mpcmobo.systems"]' in help_text
    )
    monkeypatch.setattr(cli, "console", Console(width=80))
    res = runner.invoke(app, ["systems"])
    assert res.exit_code == 0, res.output
    out = res.output.splitlines()
    header = next(line for line in out if line.startswith("┃"))
    assert header.replace("┃", " ").split() == [
        "name",
        "source",
        "states",
        "inputs",
        "theta",
        "steps",
        "J*",
    ]
    rows = {line.split()[1]: line for line in out if line.startswith("│")}
    # one line per system, no folded cell (a test may have registered a system of its own)
    from mpcmobo.systems.registry import available_systems

    assert {"cstr", "cstr-structural", "lq"} <= set(rows)
    assert len(rows) == len([line for line in out if line.startswith("│")])
    assert set(rows) == set(available_systems())
    assert all(len(line) <= 80 for line in out if line[:1] in "┏┃┡│└")
    cstr = get_system("cstr")
    assert rows["cstr"].replace("│", " ").split() == [
        "cstr",
        "built-in",
        "V,",
        "Ca,",
        "T",
        "qs,",
        "qc",
        str(cstr.search_space.n_theta),
        str(cstr.episode_steps),
        "yes",
    ]
    text = " ".join(res.output.split())
    for name in ("cstr", "cstr-structural", "lq"):
        s = get_system(name)
        assert f"{name} (continuous-time): {' '.join(s.description.split())}" in text
    assert "--system path/to/file.py:make_system" in text


@pytest.mark.parametrize(
    "args, key",
    [
        (["run", "--episodes", "0"], "episodes"),
        (["run", "--system", "nope"], "system.name"),
        (["run", "--learner", "sgd"], "learners"),
        (["run", "--seeds", "0", "x"], "seeds"),
        (["run", "--workers", "0"], "workers"),
    ],
)
def test_invalid_settings_exit_2_naming_the_key(args, key, tmp_path):
    res = runner.invoke(app, [*args, "--out", str(tmp_path / "o")])
    assert res.exit_code == 2, res.output
    assert key in res.output
    assert "Traceback" not in res.output
    assert not (tmp_path / "o" / "config.toml").exists()


def test_invalid_config_file_exit_2(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text('[mpc]\nhorizn = 3\n[exploration]\nstd = "big"\n')
    res = runner.invoke(app, ["run", "--config", str(cfg), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2
    assert "mpc.horizn" in res.output and "horizon" in res.output
    assert "exploration.std" in res.output
    res = runner.invoke(app, ["run", "--config", str(tmp_path / "missing.toml")])
    assert res.exit_code == 2 and "not found" in res.output


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    st.dictionaries(
        st.sampled_from(
            ["episodes", "mpc", "seeds", "learners", "beta", "system", "learner_options", "zz"]
        ),
        st.one_of(
            st.integers(-5, 5),
            st.text(max_size=4),
            st.lists(st.integers(-2, 2), max_size=3),
            st.floats(allow_nan=False, allow_infinity=False),
        ),
        min_size=1,
        max_size=3,
    )
)
def test_malformed_config_files_never_traceback(tmp_path_factory, data):
    import tomli_w

    from mpcmobo.experiment.settings import SettingsError, validate_settings

    try:  # only invalid files: a valid one would start a study
        validate_settings(data)
    except SettingsError:
        pass
    else:
        assume(False)
    d = tmp_path_factory.mktemp("h")
    cfg = d / "c.toml"
    cfg.write_text(tomli_w.dumps(data))

    def no_study(*args, **kwargs):
        raise AssertionError("a study was started from an invalid settings file")

    with pytest.MonkeyPatch.context() as mp:  # the file alone must stop the run
        mp.setattr("mpcmobo.experiment.study.run_study", no_study)
        res = runner.invoke(app, ["run", "--config", str(cfg), "--out", str(d / "o")])
    assert res.exit_code == 2, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit)
    assert "Error:" in res.output
    assert any(key in res.output for key in data), res.output  # the message names a key
    assert not (d / "o" / "config.toml").exists()


def test_run_seeds_forms_resume_and_evaluate(tmp_path):
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", *SMALL, "--seeds", "0", "1", "--out", str(out), "-q"])
    assert res.exit_code == 0, res.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["settings"]["seeds"] == [0, 1]
    assert summary["learners"]["mpc-rl"]["complete"] is True
    out2 = tmp_path / "runs" / "run2"  # --out makes a missing parent, not a longer path
    res = runner.invoke(app, ["run", *SMALL, "--out", str(tmp_path / "a" / "b" / "run"), "-q"])
    assert res.exit_code != 0 and "does not exist" in res.output and not (tmp_path / "a").exists()
    res = runner.invoke(app, ["run", *SMALL, "--seeds", "3,4", "--out", str(out2), "-q"])
    assert res.exit_code == 0, res.output
    assert json.loads((out2 / "summary.json").read_text())["settings"]["seeds"] == [3, 4]
    # resume of a finished run: nothing changes, exit 0; options other than --workers refused
    before = storage.read_episodes(out)
    res = runner.invoke(app, ["run", "--resume", "--out", str(out), "-q"])
    assert res.exit_code == 0, res.output
    assert storage.read_episodes(out).equals(before)
    res = runner.invoke(app, ["run", "--resume", "--out", str(out), "--steps", "9"])
    assert res.exit_code == 2 and "--steps" in res.output
    # --episodes extends the budget of a resumed run, never shortens it
    res = runner.invoke(app, ["run", "--resume", "--out", str(out), "--episodes", "2"])
    assert res.exit_code == 2 and "extended, not shortened" in res.output
    res = runner.invoke(app, ["run", "--resume", "--out", str(out), "--episodes", "4", "-q"])
    assert res.exit_code == 0, res.output
    assert len(storage.read_episodes(out)) == 2 * 4
    assert json.loads((out / "summary.json").read_text())["settings"]["episodes"] == 4
    res = runner.invoke(app, ["run", *SMALL, "--out", str(out)])
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and "holds a run; choose a new --out directory" in said
    assert "--resume --episodes N extends it" in said
    res = runner.invoke(app, ["evaluate", str(out), "--n-starts", "2"])
    assert res.exit_code == 0, res.output
    assert "mpc-rl" in res.output and "J_eval" in res.output


def test_evaluate_reports_the_runs_j_of_theta0_for_a_job_that_deployed_nothing():
    """A job with identification has theta0 with the nominal model parameters in its own MPC:
    the same controller as the study's theta0, whose J the run records; evaluate says the
    same, not another solve of it."""
    from types import SimpleNamespace

    from rich.console import Console

    from mpcmobo.cli import _evaluation_table

    class Evaluator:
        def __init__(self, J, theta0):
            self.J, self.theta0, self.cache = J, theta0, {}

        def J_star(self):
            return 3297.9

        def J_eval(self, theta):
            return self.cache.get(None if theta is None else tuple(theta), self.J)

        def remember(self, theta, value):
            self.cache[tuple(theta)] = value

        def mpc(self, model):
            return SimpleNamespace(theta0=self.theta0)

    theta0 = np.array([1.0, 2.0, 0.5])
    study, own = Evaluator(15410.0, theta0[:2]), Evaluator(15126.0, theta0)
    settings = SimpleNamespace(system=SimpleNamespace(name="cstr"))
    table = _evaluation_table(settings, [("mobo", 0, 8, theta0)], study, {"mobo": own})
    console = Console(record=True, width=200)
    console.print(table)
    text = console.export_text()
    assert "15410" in text.split("\n", 1)[1] and "15126" not in text, text


def test_run_with_progress_bars(tmp_path):
    out = tmp_path / "bars"
    res = runner.invoke(app, ["run", *SMALL, "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "mpc-rl s0" in res.output and "best J_eval" in res.output
    assert "J_final" in res.output
    # a complete run draws figures 1-4, and 5 of the identified model, unless told not to
    names = sorted(p.stem for p in (out / "figures").glob("fig*.png"))
    assert names == [
        "fig1_performance",
        "fig2_advantage_pareto",
        "fig3_states",
        "fig4_inputs",
        "fig5_identified",
    ]
    res = runner.invoke(app, ["run", *SMALL, "--out", str(tmp_path / "np"), "-q", "--no-plot"])
    assert res.exit_code == 0, res.output
    assert not (tmp_path / "np" / "figures").exists()


def test_learner_may_be_repeated_or_a_comma_list():
    """``--learner mobo --learner identify`` runs both (it kept the last one), as does
    ``--learner mobo,identify``; ``all`` is every learner; not given, the settings decide."""
    from mpcmobo.cli import _learners
    from mpcmobo.learners.registry import LEARNER_SPECS

    assert _learners(["mobo", "identify"]) == _learners(["mobo,identify"]) == ["mobo", "identify"]
    assert _learners(["all"]) == list(LEARNER_SPECS)
    assert _learners(None) is None and _learners([]) is None
    for args in (["--learner", "identify", "bo"], ["--learner", "identify", "bo", "--seeds", "0"]):
        res = runner.invoke(app, ["run", *args, "--episodes", "1"])
        text = " ".join(res.output.split())
        assert res.exit_code == 2 and "unexpected argument 'bo': --learner takes one name" in text


def test_the_command_list_gives_each_command_its_summary_as_prose():
    """``mpcmobo --help`` on a wide terminal: each command's row holds the first paragraph of
    its docstring on one line (the source's line breaks are not the reader's), with nothing of
    it lost to markup (``DIR/trials/ID/``)."""
    import inspect

    import typer

    commands = typer.main.get_command(app).commands  # type: ignore[attr-defined]
    wide = runner.invoke(app, ["--help"], env={"COLUMNS": "400", "TERM": "dumb"}).output
    panel = wide[wide.index("Commands") :].splitlines()[1:]
    rows: dict[str, list[str]] = {}
    for line in panel:  # a row begins with its command's name; a folded line continues it
        cells = line.strip("│ ╰─╯").split()
        if cells and cells[0] in commands and line.startswith("│ " + cells[0]):
            rows[cells[0]] = cells[1:]
        elif cells and rows:
            rows[list(rows)[-1]].extend(cells)
    for name, command in commands.items():
        summary = " ".join(inspect.cleandoc(command.help or "").split("\n\n")[0].split())
        assert " ".join(rows[name]) == summary.replace("``", "").replace("`", ""), name


def test_several_names_after_one_learner_flag_are_named_with_the_ones_given(tmp_path):
    """``--learner mobo identify``: the second name is a stray argument; the message shows how
    to give both, with the names the user gave."""
    res = runner.invoke(app, ["run", "--learner", "mobo", "identify", "--out", str(tmp_path / "r")])
    said = " ".join(res.output.split())
    assert res.exit_code == 2, said
    assert "--learner mobo,identify or --learner mobo --learner identify" in said
    assert not (tmp_path / "r").exists()
