# ruff: noqa: B008 - typer declares options as argument defaults
"""The command line of a real plant: ``mpcmobo ask``, ``tell``, ``status``, ``export``.

``ask DIR`` starts a tuner in DIR the first time (from ``--config`` / ``--system``), prints the
next trial as JSON and writes its controller next to it (``DIR/trials/<id>/``); ``tell DIR
TRIAL FILE`` takes the logged episode (CSV or Parquet, the system's state and input names as
columns); ``status DIR`` shows what is deployed; ``export DIR`` writes the tuned MPC as a CasADi
function or as C code. A bad trial or log exits with code 2 and a message; nothing recorded is
changed.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import typer
from rich.table import Table

from mpcmobo import cli
from mpcmobo.cli.progress import fmt
from mpcmobo.experiment import storage
from mpcmobo.experiment.rundir import OlderRunError, RunDirectory, StudyError
from mpcmobo.experiment.settings import SettingsError

__all__ = ["ask", "export", "status", "tell"]

app: typer.Typer = cli.app


def _errors(fn: Any) -> Any:
    """Run ``fn`` with the tuner's and the settings' errors as exit code 2, a run's files that
    cannot be read as exit code 1."""
    from mpcmobo.experiment.tuner import TunerError

    try:
        return fn()
    except (TunerError, SettingsError, OlderRunError) as err:
        cli._fail(str(err), 2)
    except StudyError as err:
        cli._fail(str(err), 1)


def _tuner(directory: Path, episodes: int | None, **create: Any) -> Any:
    """The tuner of ``directory``: loaded (``episodes``: a larger budget), or made there from
    ``create`` the first time (None: the default)."""
    from mpcmobo.experiment.tuner import Tuner, TunerError

    if RunDirectory(directory).holds_run():
        given = [f"--{k}" for k, v in create.items() if v is not None]
        if given:
            raise TunerError(
                f"{directory} holds a tuner already; {', '.join(given)} apply only when one "
                "is made (--episodes extends its budget)"
            )
        return Tuner.load(directory, episodes=episodes)
    made = {k: v for k, v in create.items() if v is not None}
    if episodes is not None:
        made["episodes"] = episodes
    return Tuner(out=directory, **made)


@app.command()
def ask(
    directory: Path = typer.Argument(..., help="the tuner's directory (made the first time)"),
    config: Path | None = typer.Option(None, "--config", "-c", help="settings file (TOML)"),
    system: str | None = typer.Option(None, "--system", help="system: a name or a factory"),
    learner: str | None = typer.Option(None, "--learner", "-l", help="the learner (mobo)"),
    seed: int | None = typer.Option(None, "--seed", help="the tuner's seed (0)"),
    episodes: int | None = typer.Option(
        None, "--episodes", "-n", help="the budget of trials; on a tuner, a larger one"
    ),
) -> None:
    """Print the next trial as JSON and write it, with its controller, to DIR/trials/<id>/."""
    from mpcmobo.mpc.export import export_casadi

    create = {"system": system, "learner": learner, "seed": seed, "config": config}

    def go() -> dict:
        tuner = _tuner(directory, episodes, **create)
        trial = tuner.ask()
        where = directory / "trials" / str(trial.id)
        where.mkdir(parents=True, exist_ok=True)
        data = trial.to_json()
        (where / "trial.json").write_text(json.dumps(data, indent=1) + "\n")
        export_casadi(trial.mpc, trial.theta, where / "controller.casadi")
        return data

    data = _errors(go)
    cli.console.print_json(json.dumps(data))


@app.command()
def tell(
    directory: Path = typer.Argument(..., help="the tuner's directory"),
    trial: int = typer.Argument(..., help="the trial's id"),
    log: Path = typer.Argument(..., help="the episode: a CSV or Parquet file"),
) -> None:
    """Take a trial's logged episode: a row per step, the state and input names as columns."""
    import pandas as pd

    from mpcmobo.experiment.tuner import Tuner, TunerError

    def go() -> Any:
        tuner = Tuner.load(directory)
        if not log.exists():
            raise TunerError(f"the log {log} does not exist")
        try:
            df = pd.read_parquet(log) if log.suffix == ".parquet" else pd.read_csv(log)
        except Exception as err:  # noqa: BLE001 - any unreadable file is reported the same way
            raise TunerError(f"the log {log} cannot be read: {type(err).__name__}: {err}") from None
        row = tuner.tell(trial, df)
        return tuner, row

    tuner, row = _errors(go)
    rows = tuner.job.rows
    before = rows[-2].incumbent if len(rows) > 1 else tuner.job.run.learner.theta0
    moved = not np.array_equal(rows[-1].incumbent, before)
    changed = " (the deployed theta changed)" if moved else ""
    cli.console.print(
        f"trial {row.episode} told: f1 {fmt(row.f1)}, {tuner.episodes} of "
        f"{tuner.settings.episodes} trials{changed}",
        highlight=False,
    )


@app.command()
def status(directory: Path = typer.Argument(..., help="the tuner's directory")) -> None:
    """Show the deployed theta, its evidence and the trials so far."""
    from mpcmobo.experiment.tuner import Tuner

    st = _errors(lambda: Tuner.load(directory).status())
    cli.console.print(
        f"{st['learner']}: {st['trials']} of {st['budget']} trials told"
        + (f", trial {st['pending']} pending" if st["pending"] is not None else "")
        + f"; the deployed theta ran {st['deployed_episodes']} of them and changed "
        f"{st['changes_of_deployed']} times",
        highlight=False,
    )
    if st["J_initial"] is not None:  # a simulated plant
        J = "not evaluated yet" if st["J_eval"] is None else fmt(st["J_eval"])
        cli.console.print(
            f"J_eval of the deployed theta {J}, J(theta0) {fmt(st['J_initial'])}, "
            f"J* {fmt(st['J_star'])}",
            highlight=False,
        )
    table = Table(title="deployed theta")
    table.add_column("parameter")
    table.add_column("value", justify="right")
    for name, value in st["deployed"].items():
        table.add_row(name, fmt(value, 6))
    cli.console.print(table)
    if st["identification"] is not None:
        _print_identification(st["identification"])
    summary = directory / "summary.json"
    if summary.exists():  # an identified parameter held by its bounds
        cli.warn_bounds(storage.read_json(summary))


def _print_identification(ident: dict[str, Any]) -> None:
    """The last fit of the model (``Tuner.status``'s ``identification``) as a table and a line
    on how it predicts the held-out transitions."""
    table = Table(title="identified model (the last fit)")
    for col in ("parameter", "nominal", "estimate", "std"):
        table.add_column(col, justify="left" if col == "parameter" else "right")
    for name, p in ident["parameters"].items():
        table.add_row(name, fmt(p["nominal"], 6), fmt(p["estimate"], 6), fmt(p["std"], 2))
    cli.console.print(table)
    cli.console.print(
        f"fitted on {ident['transitions']} transitions; one-step error on held-out ones (RMS, "
        f"scaled by x_scale) {fmt(ident['holdout_error'], 3)}, the nominal model's "
        f"{fmt(ident['nominal_error'], 3)}",
        highlight=False,
    )


def _theta_of(run_dir: RunDirectory, which: str, learner: str | None, seed: int | None) -> Any:
    """The theta ``which`` ("deployed", "final" or a trial's id) of the job of ``run_dir``, and
    the settings."""
    from mpcmobo.experiment.tuner import TunerError

    settings = run_dir.saved_settings()
    jobs = [
        (n, s)
        for n in settings.learners
        for s in settings.seeds
        if (learner is None or n == learner) and (seed is None or s == seed)
    ]
    if len(jobs) != 1:
        listed = ", ".join(f"--learner {n} --seed {s}" for n, s in jobs) or "none"
        raise TunerError(f"choose one job of {run_dir.path}: {listed}")
    ((name, s),) = jobs
    ckpt = run_dir.checkpoint(name, s)
    if ckpt is None or not ckpt.rows:
        raise TunerError(f"the job {name} s{s} has no episode yet: nothing to export")
    if which == "deployed":
        return settings, name, np.asarray(ckpt.rows[-1].incumbent, float)
    if which == "final":
        if not ckpt.done:
            raise TunerError(
                f"the job {name} s{s} has run {len(ckpt.rows)} of {ckpt.episodes} episodes: "
                "it has no final theta yet (--theta deployed exports the one deployed now)"
            )
        return settings, name, np.asarray(ckpt.rows[-1].incumbent, float)
    try:
        k = int(which)
    except ValueError:
        raise TunerError(
            f"--theta must be deployed, final or a trial's id, got {which!r}"
        ) from None
    if not 0 <= k < len(ckpt.rows):
        raise TunerError(f"no trial {k}: the job has trials 0 to {len(ckpt.rows) - 1}")
    return settings, name, np.asarray(ckpt.rows[k].theta, float)


@app.command()
def export(
    directory: Path = typer.Argument(..., help="a tuner's or a study's directory"),
    theta: str = typer.Option("deployed", "--theta", help="deployed | final | a trial's id"),
    fmt_: str = typer.Option("casadi", "--format", help="casadi | c | embedded"),
    out: Path = typer.Option(
        ..., "--out", "-o", help="the file (casadi) or directory (c, embedded)"
    ),
    learner: str | None = typer.Option(None, "--learner", help="the job's learner (a study)"),
    seed: int | None = typer.Option(None, "--seed", help="the job's seed (a study)"),
    compile_c: bool = typer.Option(False, "--compile", help="c, embedded: build the example"),
) -> None:
    """Write the tuned MPC as a CasADi function, as C code calling IPOPT (c) or as C that needs
    only libc and libm (embedded), with a header and a main.c."""
    from mpcmobo.experiment.build import build_system
    from mpcmobo.experiment.tuner import TunerError
    from mpcmobo.mpc import ParametricMPC
    from mpcmobo.mpc.embedded import embedded_compile_command, export_embedded
    from mpcmobo.mpc.export import c_compile_command, export_c, export_casadi

    if fmt_ not in ("casadi", "c", "embedded"):
        cli._fail(f"--format must be casadi, c or embedded, got {fmt_!r}", 2)

    def go() -> str:
        run_dir = cli._require_run(directory)
        if fmt_ != "casadi" and out.exists() and not out.is_dir():
            raise TunerError(f"--out {out} is a file; C code goes into a directory")
        if fmt_ == "casadi" and out.is_dir():
            raise TunerError(f"--out {out} is a directory; the CasADi function is one file")
        settings, name, th = _theta_of(run_dir, theta, learner, seed)
        options = settings.mpc.options()
        if fmt_ == "embedded":  # the MPC's own functions, generated again as plain C
            options["codegen"] = False
        mpc = ParametricMPC(build_system(settings, name), "imperfect", **options)
        if fmt_ == "casadi":
            return f"wrote {export_casadi(mpc, th, out)}"
        if fmt_ == "embedded":
            export_embedded(mpc, th, out)
            cmd = embedded_compile_command(out)
            files = "controller.c, controller.h, mpc_functions.c, mpc_functions.h, main.c"
        else:
            export_c(mpc, th, out)
            cmd = c_compile_command(out)
            files = "controller.c, controller.h, main.c"
        if compile_c:
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0:
                raise TunerError(f"compiling failed: {proc.stderr.strip()[-1500:]}")
        return f"wrote {out}/{files}; build with:\n" + " ".join(cmd)

    cli.console.print(_errors(go), highlight=False, markup=False, soft_wrap=True)
