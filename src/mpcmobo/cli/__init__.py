"""The command line: ``mpcmobo run``, ``plot``, ``evaluate``, ``systems``.

``mpcmobo run`` with no arguments runs the paper's CSTR study on the default settings into a new
directory ``runs/<timestamp>``. Seeds can be given as ``--seeds 0 --seeds 1``, ``--seeds 0 1 2``
or ``--seeds 0,1,2``. Invalid settings exit with code 2 and a message naming the key.
"""

# ruff: noqa: B008 - typer declares options as argument defaults

from __future__ import annotations

import os
import sys
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, NoReturn

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from mpcmobo import __version__
from mpcmobo.cli.progress import Bars, Lines, fmt, progress_bars
from mpcmobo.experiment.interrupts import Interrupted
from mpcmobo.experiment.price import UNPRICED
from mpcmobo.experiment.rundir import (
    OlderRunError,
    RunDirectory,
    RunDirError,
    StudyError,
    read_run_file,
)
from mpcmobo.experiment.settings import DEFAULT_LEARNERS, Settings, SettingsError, load_settings
from mpcmobo.learners.registry import LEARNER_SPECS

if TYPE_CHECKING:
    from mpcmobo.experiment.evaluation import Evaluator

app: typer.Typer = typer.Typer(
    name="mpcmobo",
    help="Tune an MPC from closed-loop data: MPC-RL (CDPG), BO and MPC-RL-MOBO.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="markdown",
)
console = Console()
err_console = Console(stderr=True)


def _print_version(value: bool) -> None:
    if value:
        console.print(f"mpcmobo {__version__}", highlight=False)
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(
        False,
        "--version",
        callback=_print_version,
        is_eager=True,
        help="print the installed version (package metadata) and exit",
    ),
) -> None:
    """Tune an MPC from closed-loop data: MPC-RL (CDPG), BO and MPC-RL-MOBO."""


def _fail(message: str, code: int) -> NoReturn:
    err_console.print(f"[bold red]Error:[/] {escape(message)}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def _parse_seeds(
    values: list[str] | None, extra: list[str], learners: list[str] | None = None
) -> list[int] | None:
    """The seeds of ``--seeds`` (and stray arguments after it); a learner's name among the
    stray ones is a ``--learner`` given several names, named so (``learners``: the names
    ``--learner`` took)."""
    if not values and not extra:
        return None
    stray = [a for a in extra if a in LEARNER_SPECS]
    if stray:  # --learner mobo identify: the second name is an argument of its own
        first = (learners or ["identify"])[-1]
        _fail(
            f"unexpected argument {stray[0]!r}: --learner takes one name per flag or a comma "
            f"list (--learner {first},{stray[0]} or --learner {first} --learner {stray[0]})",
            2,
        )
    if extra and not values:
        _fail(f"unexpected arguments: {' '.join(extra)}", 2)
    seeds: list[int] = []
    for v in [*(values or []), *extra]:
        for part in v.replace(",", " ").split():
            try:
                seeds.append(int(part))
            except ValueError:
                _fail(f"seeds: '{part}' is not an integer (use --seeds 0 1 2 or --seeds 0,1,2)", 2)
    return seeds


def _learners(option: list[str] | None) -> list[str] | None:
    """The learners of ``--learner`` (given once or more, each a name or a comma list)."""
    if not option:
        return None
    names = [p for o in option for p in o.replace(",", " ").split() if p]
    return list(LEARNER_SPECS) if names == ["all"] else names


def _default(key: str) -> Any:
    return Settings.model_fields[key].get_default(call_default_factory=True)


def _options_epilog() -> str:
    from mpcmobo.experiment.options_doc import learner_option_lines

    lines = [
        "Learner options, a table \\[learner_options.NAME] in the --config file (every option "
        "and its meaning: docs/configuration.md). The defaults in force:"
    ]
    lines += [f"{name}: {'; '.join(learner_option_lines(name))}" for name in LEARNER_SPECS]
    return "\n\n".join(lines)


RUN_HELP = (
    "Run a study (learners x seeds): records, summary and, once complete, the figures.\n\n"
    "Ctrl-C (SIGINT) or SIGTERM stops the run at the end of the current MPC step (exit code "
    "130 or 143) with every finished episode recorded; --resume continues it. Library "
    "warnings go to DIR/run.log (written at the first one); with its output redirected, the "
    "run prints a progress line per job every few episodes."
)


# the options of `mpcmobo run`
_Config = Annotated[
    Path | None,
    typer.Option(
        "--config", "-c", help="settings file (TOML)", show_default="none, the defaults below"
    ),
]
_System = Annotated[
    str | None,
    typer.Option(
        "--system",
        help=(
            "system: a name (`mpcmobo systems`), 'module:function' or 'file.py:function'; "
            "in place of the --config file's system, whose other [system] keys still apply"
        ),
        show_default=_default("system").name,
    ),
]
_Learner = Annotated[
    list[str] | None,
    typer.Option(
        "--learner",
        "-l",
        help=f"{' | '.join([*LEARNER_SPECS, 'all'])} (or a comma list; may repeat)",
        show_default=",".join(DEFAULT_LEARNERS),
    ),
]
_Episodes = Annotated[
    int | None,
    typer.Option(
        "--episodes", "-n", help="episodes per job", show_default=str(_default("episodes"))
    ),
]
_Steps = Annotated[
    int | None,
    typer.Option(
        "--steps", help="time steps per episode", show_default="the system's episode length"
    ),
]
_Seeds = Annotated[
    list[str] | None,
    typer.Option(
        "--seeds",
        "-s",
        help="seeds: --seeds 0 1 2, --seeds 0,1,2 or repeated --seeds",
        show_default=" ".join(map(str, _default("seeds"))),
    ),
]
_Out = Annotated[
    Path | None,
    typer.Option(
        "--out",
        "-o",
        help="output directory, new or empty (a missing parent is made, not a longer path)",
        show_default="runs/<timestamp>",
    ),
]
_Resume = Annotated[
    bool,
    typer.Option(
        "--resume",
        help="continue the run recorded in --out (with --episodes N: extend its budget to N)",
    ),
]
_Workers = Annotated[
    int | None,
    typer.Option(
        "--workers", "-w", help="parallel processes", show_default=str(_default("workers"))
    ),
]
_Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="no progress output")]
_NoPlot = Annotated[bool, typer.Option("--no-plot", help="do not draw the figures at the end")]


@app.command(context_settings={"allow_extra_args": True}, help=RUN_HELP, epilog=_options_epilog())
def run(
    ctx: typer.Context,
    config: _Config = None,
    system: _System = None,
    learner: _Learner = None,
    episodes: _Episodes = None,
    steps: _Steps = None,
    seeds: _Seeds = None,
    out: _Out = None,
    resume: _Resume = False,
    workers: _Workers = None,
    quiet: _Quiet = False,
    no_plot: _NoPlot = False,
) -> None:
    """Run a study (learners x seeds): records, summary and, once complete, the figures."""
    from mpcmobo.experiment.study import run_study

    seed_list = _parse_seeds(seeds, list(ctx.args), learner)
    try:
        if resume:
            fixed = {
                "--config": config,
                "--system": system,
                "--learner": learner or None,
                "--steps": steps,
                "--seeds": seed_list,
            }
            settings = _resumed_settings(out, fixed, workers=workers, episodes=episodes)
        else:
            settings = load_settings(
                config,
                system=_system_override(system),
                learners=_learners(learner),
                episodes=episodes,
                steps=steps,
                seeds=seed_list,
                workers=workers,
            )
            given = out is not None
            out = out or Path("runs") / time.strftime("%Y%m%d-%H%M%S")
            # a given --out may create its parent (runs/ of --out runs/mobo), not a longer
            # missing path (a typo in it); the default creates runs/
            RunDirectory(out).check_new(parents=not given or out.parent.parent.exists())
        t0 = time.perf_counter()
        if quiet:
            summary = run_study(settings, out, resume=resume)  # type: ignore[arg-type]  # --resume checked --out
        elif not console.is_terminal:
            summary = run_study(settings, out, resume=resume, progress=Lines(console))  # type: ignore[arg-type]  # --resume checked --out
        else:
            with progress_bars(console) as progress:
                summary = run_study(settings, out, resume=resume, progress=Bars(progress))  # type: ignore[arg-type]  # --resume checked --out
    except (SettingsError, OlderRunError, RunDirError) as err:
        _fail(str(err), 2)
    except StudyError as err:
        _fail(str(err), 1)
    except Interrupted as err:
        _interrupted(out, err.signal_name, err.exit_code)
    except KeyboardInterrupt:
        _interrupted(out, "SIGINT", 130)
    _report(summary, out, time.perf_counter() - t0, no_plot)  # type: ignore[arg-type]  # --resume checked --out


def bound_warnings(summary: dict) -> list[str]:
    """One line per identified parameter whose final fit sits on a bound of the
    identification (``identified_at_bound`` of the summary), with the jobs it does so in."""
    jobs: dict[tuple[str, str, float], list[str]] = {}
    for learner, v in summary.get("learners", {}).items():
        for b in v.get("identified_at_bound") or []:
            key = (b["name"], b["bound"], b["value"])
            jobs.setdefault(key, []).extend(f"{learner} seed {s}" for s in b["seeds"])
    return [
        f"the identified '{name}' ends on its {side} bound {value:.4g} in {len(who)} job(s) "
        f"({', '.join(who[:3])}{', ...' if len(who) > 3 else ''}): the plant's value may lie "
        "beyond it; widen [system] model_log_range, or the model's structure may be wrong"
        for (name, side, value), who in jobs.items()
    ]


def unpriced_warnings(summary: dict) -> list[str]:
    """One line for the jobs whose tuning stopped exploring because the model could not price
    a candidate (``stopped_exploring`` of the summary): they kept what they had deployed."""
    jobs = [
        (
            f"{learner} seed {stop['seed']}"
            + ("" if stop.get("episode") is None else f" at episode {stop['episode']}"),
            stop["reason"],
        )
        for learner, stops in (summary.get("stopped_exploring") or {}).items()
        for stop in stops
        if UNPRICED in stop["reason"]
    ]
    if not jobs:
        return []
    who = [name for name, _ in jobs]
    first = jobs[0][1]
    return [
        f"{len(who)} job(s) stopped exploring ({', '.join(who[:3])}"
        f"{', ...' if len(who) > 3 else ''}): {first[first.index(UNPRICED) :]}"
    ]


def _jobs_with(summary: dict, key: str) -> Iterator[tuple[str, str, list[dict]]]:
    """(learner, seed, items) of each job whose per-seed summary lists items under ``key``."""
    for learner, s in summary["learners"].items():
        for seed, per in s.get("per_seed", {}).items():
            items = per.get(key) or []
            if items:
                yield learner, seed, items


def failed_warnings(summary: dict) -> list[str]:
    """One line per job with episodes that failed (``failed_episodes`` of its summary): how
    many, the first with its error, and what it means for the theta that ran it."""
    return [
        f"{learner} seed {seed}: {len(failed)} episode(s) failed (episode "
        f"{failed[0]['episode']}: {failed[0]['error']}); the learner observed no closed loop "
        "there, and a theta with a failed episode is never deployed"
        for learner, seed, failed in _jobs_with(summary, "failed_episodes")
    ]


def unsolved_warnings(summary: dict) -> list[str]:
    """One line per job with recorded episodes in which MPC solves failed
    (``unsolved_episodes`` of its summary): how many, the worst, and what ran the plant."""
    lines = []
    for learner, seed, hit in _jobs_with(summary, "unsolved_episodes"):
        worst = max(hit, key=lambda h: h["failed_solves"])
        lines.append(
            f"{learner} seed {seed}: MPC solves failed in {len(hit)} episode(s) (episode "
            f"{worst['episode']}: {worst['failed_solves']} failed solves), where the "
            "fallback input (the previous plan) drove the plant; check the model with "
            "that episode's theta (a model that is not finite there fails every solve)"
        )
    return lines


def warn_summary(summary: dict, unpriced: bool = True) -> None:
    """Print :func:`bound_warnings`, :func:`failed_warnings`, :func:`unsolved_warnings` and
    (``unpriced``) :func:`unpriced_warnings` of ``summary`` to standard error."""
    lines = bound_warnings(summary) + failed_warnings(summary) + unsolved_warnings(summary)
    lines += unpriced_warnings(summary) if unpriced else []
    for line in lines:
        err_console.print(f"warning: {escape(line)}", highlight=False, soft_wrap=True)


def _system_override(system: str | None) -> dict[str, Any] | None:
    """``--system X``: a name, or a factory path, in place of the settings file's system name
    or factory; the file's other ``[system]`` keys (``identify``, ``learn_model``, ...)
    still apply to it."""
    if system is None:
        return None
    if ":" in system:
        return {"factory": system}
    return {"name": system, "factory": None}


def _interrupted(out: Path | None, name: str, code: int) -> None:
    """An interrupted run: where its records are and how to continue it; exit ``code``."""
    if out is not None and RunDirectory(out).holds_run():
        err_console.print(
            f"interrupted ({name}): every finished episode is recorded in {escape(str(out))}; "
            f"continue with: mpcmobo run --resume --out {escape(str(out))}",
            highlight=False,
            soft_wrap=True,
        )
    else:
        err_console.print(f"interrupted ({name}) before the run started", highlight=False)
    program = Path(sys.argv[0])
    if program.name == "mpcmobo" or program.match("mpcmobo/cli/__main__.py"):
        # the program itself (not the CLI inside a test): everything is on disk and fsync'ed,
        # so skip the interpreter's teardown (torch's alone takes about a second)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    raise typer.Exit(code)


def _resumed_settings(
    out: Path | None, fixed: Mapping[str, object], workers: int | None, episodes: int | None
) -> Settings | None:
    """What ``--resume`` changes in the saved run: None, or its settings with ``--workers`` and
    ``--episodes``; the options in ``fixed`` may not be given."""
    if out is None:
        _fail("--resume needs --out DIR (the run to continue)", 2)
    given = [flag for flag, value in fixed.items() if value is not None]
    if given:
        _fail(
            f"--resume uses the saved DIR/config.toml (only --workers, and --episodes "
            f"to extend the budget, may change); drop {', '.join(given)}",
            2,
        )
    if workers is None and episodes is None:
        return None
    return RunDirectory(out).saved_settings(workers=workers, episodes=episodes)


def _report(summary: dict, out: Path, seconds: float, no_plot: bool) -> None:
    """The summary table, where the records are, and the figures of a complete run."""
    console.print(_summary_table(summary))
    warn_summary(summary)
    console.print(f"records in [bold]{out}[/] ({seconds:.1f} s)")
    if not summary["complete"]:
        console.print(f"incomplete; continue with: mpcmobo run --resume --out {out}")
    elif not no_plot:
        from mpcmobo.plots import make_figures

        paths = make_figures(out)
        console.print(f"figures in [bold]{paths[0].parent}[/] (mpcmobo plot {out} redraws them)")


def _summary_table(summary: dict) -> Table:
    if summary["J_star"] is None:  # no reference model: the results are against theta0
        title = f"{summary['system']}: no J* (no reference model), J(theta0) = "
        title += fmt(summary["J_initial"])
    else:
        title = f"{summary['system']}: J* = {fmt(summary['J_star'])}"
    table = Table(title=title)
    cols = ("learner", "J_initial", "J_final", "worst deployed", "to 2%", "to 5%", "wall time [s]")
    for col in cols:
        table.add_column(col, justify="right")
    for name, s in summary["learners"].items():
        table.add_row(
            name,
            fmt(s["J_initial"]),
            fmt(s["J_final"]),
            fmt(s.get("J_worst")),
            str(s["episodes_to_2pct"]) if s["episodes_to_2pct"] is not None else "-",
            str(s["episodes_to_5pct"]) if s["episodes_to_5pct"] is not None else "-",
            f"{s['wall_time_s']:.1f}",
        )
    return table


def _check_records(directory: Path) -> None:
    """The records that figures are drawn from can be read (else exit 1 naming the file)."""
    import json

    import pandas as pd

    fix = f"rebuild the records from the checkpoints with: mpcmobo run --resume --out {directory}"
    readers = {
        "episodes.parquet": pd.read_parquet,
        "trajectories.parquet": pd.read_parquet,
        "summary.json": lambda p: json.loads(p.read_text(encoding="utf-8")),
    }
    try:
        for name, read in readers.items():
            if (directory / name).exists():
                read_run_file(directory / name, read, fix)
    except StudyError as err:
        _fail(str(err), 1)


def _require_run(directory: Path) -> RunDirectory:
    run_dir = RunDirectory(directory)
    if not directory.exists():
        _fail(f"{directory} does not exist", 2)
    if not run_dir.holds_run():
        _fail(f"{directory} does not hold a run (no config.toml)", 2)
    return run_dir


@app.command()
def plot(
    directory: Path = typer.Argument(..., help="a run directory"),
    learner: str | None = typer.Option(None, help="learner shown in figures 3 and 4"),
) -> None:
    """Draw the figures (PNG and PDF) into DIR/figures from the records."""
    from mpcmobo.plots import make_figures

    run_dir = _require_run(directory)
    if not (directory / "episodes.parquet").exists():
        _fail(f"{directory} has no records yet (episodes.parquet)", 2)
    _check_records(directory)
    summary = None
    if not (directory / "summary.json").exists():  # e.g. a run of an older version
        summary = _summary_from_records(run_dir)
    try:
        paths = make_figures(directory, learner=learner, summary=summary)
    except ValueError as err:
        _fail(str(err), 2)
    for p in paths:
        console.print(str(p))


def _summary_from_records(run_dir: RunDirectory) -> dict:
    """The summary of a run without ``summary.json``, from its settings, reference and
    episodes (as the study writes it)."""
    import pandas as pd

    from mpcmobo.experiment.summary import summarize
    from mpcmobo.experiment.training_reference import training_summary

    try:
        settings = run_dir.saved_settings(for_records=True)
        reference = run_dir.reference()
    except (SettingsError, StudyError) as err:
        _fail(str(err), 2)
    if reference is None:
        _fail(f"{run_dir.path} has no reference.pkl: the figures need J*", 2)
    summary = summarize(settings, reference, pd.read_parquet(run_dir.path / "episodes.parquet"), {})
    summary.update(training_summary(reference))
    return summary


@app.command()
def evaluate(
    directory: Path = typer.Argument(..., help="a run directory"),
    n_starts: int | None = typer.Option(None, help="initial states (default: the run's)"),
    seed: int | None = typer.Option(None, help="seed of the initial states (default: the run's)"),
) -> None:
    """J_eval of the saved incumbents (last episode of every job), as a table."""
    from mpcmobo.experiment.build import build_system
    from mpcmobo.experiment.evaluation import make_evaluator

    run_dir = _require_run(directory)
    try:
        settings = run_dir.saved_settings(
            for_records=True, evaluation__n_starts=n_starts, evaluation__seed=seed
        )
        incumbents = run_dir.incumbents(settings)
        _check_evaluated_system(run_dir, settings)
    except SettingsError as err:
        _fail(str(err), 2)
    except StudyError as err:
        _fail(str(err), 1)
    if not incumbents:
        _fail(
            f"no job in {directory} has finished an episode: nothing to evaluate (continue the "
            f"run with: mpcmobo run --resume --out {directory})",
            1,
        )
    try:
        evaluator = make_evaluator(settings, build_system(settings))
        # a job with identification has the identified parameters in theta: its own MPC
        evaluators = {
            n: make_evaluator(settings, build_system(settings, n))
            for n in dict.fromkeys(learner for learner, *_ in incumbents)
        }
    except SettingsError as err:
        _fail(str(err), 2)
    console.print(_evaluation_table(settings, incumbents, evaluator, evaluators))


def _check_evaluated_system(run_dir: RunDirectory, settings: Settings) -> None:
    """Refuse (:class:`StudyError`) to evaluate a run's thetas on a system that is not the one
    its reference was computed with (its file edited since: a cost weight, a bound, the
    equations): the table would measure the run's thetas with another system's J* and cost."""
    from mpcmobo.experiment.build import build_system
    from mpcmobo.experiment.reference import check_same_system, saved_system

    reference = run_dir.reference()
    if reference is None:
        return
    what = f"run in {run_dir.path}"
    if settings.system.factory is not None:
        what += f" (its system from {settings.system.factory})"
    check_same_system(saved_system(reference), build_system(settings), what)


def _evaluation_table(
    settings: Settings,
    incumbents: list[tuple[str, int, int, Any]],
    evaluator: Evaluator,
    evaluators: dict[str, Evaluator],
) -> Table:
    """J_eval of each job's incumbent (by the evaluator of its learner) and its gap to J* (by
    ``evaluator``, the study's), or without J* its improvement over theta0."""
    J_star = evaluator.J_star()
    J0 = evaluator.J_eval(None)
    for own in evaluators.values():
        # theta0 in a job's own MPC (with the nominal model parameters in theta) is the study's
        # theta0: J(theta0), as the jobs take it, not another solve of the same controller
        # (whose continuations can end at other local minima)
        own.remember(own.mpc("imperfect").theta0, J0)
    table = Table(title=f"{settings.system.name}: J* = {fmt(J_star)}, J(theta0) = {fmt(J0)}")
    # without a reference model (no J*), the gap is the improvement over theta0
    gap_title = "gap to J* [%]" if J_star is not None else "improvement over theta0 [%]"
    for col in ("learner", "seed", "episodes", "J_eval", gap_title):
        table.add_column(col, justify="right")
    for learner, s, episodes, incumbent in incumbents:
        try:
            J = evaluators[learner].J_eval(incumbent)
        except FloatingPointError:  # it runs the plant away from an evaluation start
            table.add_row(learner, str(s), str(episodes), "inf", "the plant ran away")
            continue
        if J_star is not None:
            gap = f"{100 * (J - J_star) / abs(J_star):.2f}"
        else:
            gap = f"{100 * (J0 - J) / abs(J0):.2f}"
        table.add_row(learner, str(s), str(episodes), fmt(J), gap)
    return table


ADD_SYSTEM_HELP = (
    "Add a system: write a function that returns a mpcmobo.systems.System and run it with "
    "--system path/to/file.py:make_system (or my_pkg.my_module:make_system, or "
    '[system] factory = "..." in a --config file); install it as a plug-in with the entry '
    'point group "mpcmobo.systems" in your package\'s pyproject.toml '
    '([project.entry-points."mpcmobo.systems"] my_system = "my_pkg.my_module:make_system"). '
    "See docs/user-systems.md."
)


@app.command(
    help="List the systems that can be run: built-in, registered and plug-ins.\n\n"
    + escape(ADD_SYSTEM_HELP)
)  # the help is Rich markup: keep [..]
def systems() -> None:
    """List the systems that can be run: built-in, registered and plug-ins."""
    from mpcmobo.systems import SystemDefinitionError, SystemSpecError, get_system
    from mpcmobo.systems.registry import describe_systems

    table = Table(title="systems", expand=False)
    for col in ("name", "source", "states", "inputs", "theta", "steps", "J*"):
        table.add_column(col, overflow="fold")
    notes: list[str] = []
    for name, source in describe_systems():
        try:
            s = get_system(name)
        except (SystemSpecError, SystemDefinitionError) as err:
            table.add_row(name, source, "", "", "", "", "")
            notes.append(f"[bold]{escape(name)}[/]: [red]cannot be built: {escape(str(err))}[/]")
            continue
        kind = "discrete-time" if s.discrete_time else "continuous-time"
        if s.nh:
            kind += f", {s.nh} path constraint{'s' if s.nh > 1 else ''}"
        table.add_row(
            name,
            source,
            ", ".join(s.state_names),
            ", ".join(s.input_names),
            str(s.search_space.n_theta),
            str(s.episode_steps),
            "yes" if s.has_reference_model else "no",
        )
        notes.append(f"[bold]{escape(name)}[/] ({kind}): {escape(s.description)}")
    console.print(table)
    for note in notes:
        console.print(note, highlight=False)
    console.print()
    console.print(ADD_SYSTEM_HELP, markup=False, highlight=False)


from mpcmobo.cli import connect as _connect  # noqa: E402, F401 - registers connect
from mpcmobo.cli import dashboard as _dashboard  # noqa: E402, F401 - registers dashboard
from mpcmobo.cli import plant as _plant  # noqa: E402, F401 - registers ask, tell, status, export
