# ruff: noqa: B008 - typer declares options as argument defaults
"""The command line: ``mpcmobo run``, ``plot``, ``evaluate``, ``systems``.

``mpcmobo run`` with no arguments runs the paper's CSTR study on the default settings into a new
directory ``runs/<timestamp>``. Seeds can be given as ``--seeds 0 --seeds 1``, ``--seeds 0 1 2``
or ``--seeds 0,1,2``. Invalid settings exit with code 2 and a message naming the key.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from mpcmobo.experiment.rundir import RunDirectory, StudyError
from mpcmobo.experiment.settings import Settings, SettingsError, load_settings
from mpcmobo.learners.registry import LEARNER_SPECS

app = typer.Typer(
    name="mpcmobo",
    help="Tune an MPC from closed-loop data: MPC-RL (CDPG), BO and MPC-RL-MOBO.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console()
err_console = Console(stderr=True)


def _fail(message: str, code: int) -> None:
    err_console.print(f"[bold red]Error:[/] {escape(message)}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def _parse_seeds(values: list[str] | None, extra: list[str]) -> list[int] | None:
    if not values and not extra:
        return None
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


def _learners(option: str | None) -> list[str] | None:
    if option is None:
        return None
    if option == "all":
        return list(LEARNER_SPECS)
    return [p for p in option.replace(",", " ").split() if p]


def _fmt(x: float | None, digits: int = 5) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.{digits}g}"


def _progress() -> Progress:
    """Progress bars, one line per job (fed by :class:`_Bars`)."""
    return Progress(
        TextColumn("{task.description:<14}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("f1 {task.fields[f1]:>10}"),
        TextColumn("best J_eval {task.fields[best]:>10}"),
        TimeElapsedColumn(),
        console=console,
        transient=False,
    )


class _Bars:
    """Rich progress bars, one per (learner, seed) job, fed by the study's progress events."""

    def __init__(self, progress: Progress) -> None:
        self.progress = progress
        self.tasks: dict[tuple[str, int], int] = {}
        self.ref_task: int | None = None

    def __call__(self, event: dict) -> None:
        kind = event.get("kind")
        if kind == "start":
            for n, s in event["jobs"]:
                self.tasks[(n, s)] = self.progress.add_task(
                    f"{n} s{s}", total=event["episodes"], f1="-", best="-"
                )
        elif kind == "reference":
            if event["status"] == "running":
                self.ref_task = self.progress.add_task("J*, J(theta0)", total=1, f1="", best="")
            elif self.ref_task is not None:
                self.progress.update(self.ref_task, completed=1, best=f"J*={_fmt(event['J_star'])}")
        elif kind == "episode":
            task = self.tasks.get((event["learner"], event["seed"]))
            if task is not None:
                self.progress.update(
                    task,
                    completed=event["episode"],
                    f1=_fmt(event["f1"]),
                    best=_fmt(event["best_J_eval"]),
                )


@app.command(context_settings={"allow_extra_args": True})
def run(
    ctx: typer.Context,
    config: Path | None = typer.Option(None, "--config", "-c", help="settings file (TOML)"),
    system: str | None = typer.Option(None, "--system", help="system name (`mpcmobo systems`)"),
    learner: str | None = typer.Option(
        None, "--learner", "-l", help=f"{' | '.join([*LEARNER_SPECS, 'all'])} (or a comma list)"
    ),
    episodes: int | None = typer.Option(None, "--episodes", "-n", help="episodes per job"),
    steps: int | None = typer.Option(None, "--steps", help="time steps per episode"),
    seeds: list[str] | None = typer.Option(
        None, "--seeds", "-s", help="seeds: --seeds 0 1 2, --seeds 0,1,2 or repeated --seeds"
    ),
    out: Path | None = typer.Option(None, "--out", "-o", help="output directory"),
    resume: bool = typer.Option(
        False,
        "--resume",
        help="continue the run recorded in --out (with --episodes N: extend its budget to N)",
    ),
    workers: int | None = typer.Option(None, "--workers", "-w", help="parallel processes"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bars"),
    no_plot: bool = typer.Option(False, "--no-plot", help="do not draw figures 1-4 at the end"),
) -> None:
    """Run a study (learners x seeds): records, summary and, once complete, figures 1-4."""
    from mpcmobo.experiment.study import run_study

    seed_list = _parse_seeds(seeds, list(ctx.args))
    try:
        if resume:
            fixed = {"--config": config, "--system": system, "--learner": learner,
                     "--steps": steps, "--seeds": seed_list}  # fmt: skip
            settings = _resumed_settings(out, fixed, workers=workers, episodes=episodes)
        else:
            settings = load_settings(
                config,
                system__name=system,
                learners=_learners(learner),
                episodes=episodes,
                steps=steps,
                seeds=seed_list,
                workers=workers,
            )
            out = out or Path("runs") / time.strftime("%Y%m%d-%H%M%S")
        t0 = time.perf_counter()
        if quiet:
            summary = run_study(settings, out, resume=resume)
        else:
            with _progress() as progress:
                summary = run_study(settings, out, resume=resume, progress=_Bars(progress))
    except SettingsError as err:
        _fail(str(err), 2)
    except StudyError as err:
        _fail(str(err), 1)
    except KeyboardInterrupt:
        _fail(f"interrupted; continue with: mpcmobo run --resume --out {out}", 130)
    _report(summary, out, time.perf_counter() - t0, no_plot)


def _resumed_settings(
    out: Path | None, fixed: dict[str, object], workers: int | None, episodes: int | None
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
    console.print(f"records in [bold]{out}[/] ({seconds:.1f} s)")
    if not summary["complete"]:
        console.print(f"incomplete; continue with: mpcmobo run --resume --out {out}")
    elif not no_plot:
        from mpcmobo.plots import make_figures

        paths = make_figures(out)
        console.print(f"figures in [bold]{paths[0].parent}[/] (mpcmobo plot {out} redraws them)")


def _summary_table(summary: dict) -> Table:
    table = Table(title=f"{summary['system']}: J* = {_fmt(summary['J_star'])}")
    for col in ("learner", "J_initial", "J_final", "to 2%", "to 5%", "wall time [s]"):
        table.add_column(col, justify="right")
    for name, s in summary["learners"].items():
        table.add_row(
            name,
            _fmt(s["J_initial"]),
            _fmt(s["J_final"]),
            str(s["episodes_to_2pct"]) if s["episodes_to_2pct"] is not None else "-",
            str(s["episodes_to_5pct"]) if s["episodes_to_5pct"] is not None else "-",
            f"{s['wall_time_s']:.1f}",
        )
    return table


def _require_run(directory: Path) -> RunDirectory:
    run_dir = RunDirectory(directory)
    if not run_dir.holds_run():
        _fail(f"{directory} does not hold a run (no config.toml)", 2)
    return run_dir


@app.command()
def plot(
    directory: Path = typer.Argument(..., help="a run directory"),
    learner: str | None = typer.Option(None, help="learner shown in figures 3 and 4"),
) -> None:
    """Draw figures 1-4 (PNG and PDF) into DIR/figures from the records."""
    from mpcmobo.plots import make_figures

    _require_run(directory)
    if not (directory / "episodes.parquet").exists():
        _fail(f"{directory} has no records yet (episodes.parquet)", 2)
    try:
        paths = make_figures(directory, learner=learner)
    except ValueError as err:
        _fail(str(err), 2)
    for p in paths:
        console.print(str(p))


@app.command()
def evaluate(
    directory: Path = typer.Argument(..., help="a run directory"),
    n_starts: int | None = typer.Option(None, help="initial states (default: the run's)"),
    seed: int | None = typer.Option(None, help="seed of the initial states (default: the run's)"),
) -> None:
    """J_eval of the saved incumbents (last episode of every job), as a table."""
    from mpcmobo.experiment.evaluation import make_evaluator
    from mpcmobo.experiment.settings import build_system

    run_dir = _require_run(directory)
    try:
        settings = run_dir.saved_settings(evaluation__n_starts=n_starts, evaluation__seed=seed)
    except SettingsError as err:
        _fail(str(err), 2)
    evaluator = make_evaluator(settings, build_system(settings))
    J_star = evaluator.J_star()
    J0 = evaluator.J_eval(None)
    table = Table(title=f"{settings.system.name}: J* = {_fmt(J_star)}, J(theta0) = {_fmt(J0)}")
    for col in ("learner", "seed", "episodes", "J_eval", "gap to J* [%]"):
        table.add_column(col, justify="right")
    for learner, s, episodes, incumbent in run_dir.incumbents(settings):
        J = evaluator.J_eval(incumbent)
        gap = f"{100 * (J - J_star) / abs(J_star):.2f}"
        table.add_row(learner, str(s), str(episodes), _fmt(J), gap)
    console.print(table)


@app.command()
def systems() -> None:
    """List the systems that can be run."""
    from mpcmobo.systems import available_systems, get_system

    table = Table(title="systems")
    for col in ("name", "states", "inputs", "theta", "steps", "description"):
        table.add_column(col)
    for name in available_systems():
        s = get_system(name)
        table.add_row(
            name,
            ", ".join(s.state_names),
            ", ".join(s.input_names),
            str(s.search_space.n_theta),
            str(s.episode_steps),
            s.description,
        )
    console.print(table)


if __name__ == "__main__":  # pragma: no cover
    app()
