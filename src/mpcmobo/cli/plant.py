# ruff: noqa: B008 - typer declares options as argument defaults
"""The command line of a real plant: ``mpcmobo ask``, ``tell``, ``status``, ``export``.

``ask DIR`` starts a tuner in DIR the first time (from ``--config`` / ``--system``), prints the
next trial as JSON and writes its controller next to it (``DIR/trials/<id>/``); ``tell DIR
TRIAL FILE`` takes the logged episode (CSV or Parquet, the system's state and input names as
columns); ``status DIR`` shows what is deployed, the trials and what to do (``--json``: as
data); ``retract DIR TRIAL`` takes a told trial back; ``export DIR`` writes the tuned MPC as a
CasADi function or as C code. A bad trial or log exits with code 2 and a message; nothing
recorded is changed; an interrupted ``tell`` (exit code 130) leaves its trial pending.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import typer
from rich.markup import escape
from rich.table import Table

from mpcmobo import cli
from mpcmobo.cli.progress import Waiting, WorkProgress, fmt
from mpcmobo.experiment import storage
from mpcmobo.experiment.interrupts import Interrupted
from mpcmobo.experiment.plantlog import TunerError
from mpcmobo.experiment.rundir import OlderRunError, RunDirectory, RunDirError, StudyError
from mpcmobo.experiment.settings import SettingsError
from mpcmobo.experiment.tunerfiles import LOCK_FILE, TunerFiles, held_elsewhere
from mpcmobo.experiment.tunerstatus import saved_status

__all__ = ["ask", "export", "retract", "serve", "status", "tell"]

app: typer.Typer = cli.app


def _errors(fn: Any) -> Any:
    """Run ``fn`` with the tuner's, the settings' and the directory's errors as exit code 2, a
    run's files that cannot be read as exit code 1; an error raised while a Ctrl-C unwound ``fn`` is the Ctrl-C
    (:func:`_during_interrupt`)."""
    try:
        return fn()
    except (TunerError, SettingsError, OlderRunError, RunDirError) as err:
        cli._fail(str(err), 2)
    except StudyError as err:
        cli._fail(str(err), 1)
    except Exception as err:
        if _during_interrupt(err):
            raise KeyboardInterrupt from err
        raise


def _during_interrupt(err: BaseException) -> bool:
    """Whether ``err`` was raised while a ``KeyboardInterrupt`` was being handled: a library's
    clean-up that failed on the way out (BoTorch restoring a GP's state after a fit that Ctrl-C
    stopped raises a ``RuntimeError``), so the interrupt is in its context chain."""
    seen: BaseException | None = err
    while seen is not None:
        if isinstance(seen, KeyboardInterrupt):
            return True
        seen = seen.__context__
    return False


def _tuner(directory: Path, changes: dict[str, Any], **create: Any) -> Any:
    """The tuner of ``directory``: loaded (``changes``: a larger budget of ``episodes``,
    another ``exploration_budget``), or made there from ``create`` and them the first time
    (None: the default)."""
    from mpcmobo.experiment.tuner import Tuner

    run_dir = RunDirectory(directory)
    if run_dir.holds_run():
        given = [f"--{k}" for k, v in create.items() if v is not None]
        if given and run_dir.is_tuner():
            raise TunerError(
                f"{directory} holds a tuner already; {', '.join(given)} "
                f"{'applies' if len(given) == 1 else 'apply'} only when one is made "
                "(--episodes extends its budget, --exploration-budget changes that one)"
            )
        return Tuner.load(directory, **changes)  # a study: refused, named as one
    made = {k: v for k, v in create.items() if v is not None}
    if "system" not in made and "config" not in made:
        raise TunerError(
            f"{directory} holds no tuner yet: make one with --system NAME (e.g. --system "
            "path/to/file.py:make_system; mpcmobo systems lists the names) or --config FILE "
            "(a settings file with a [system] table)"
        )
    if changes["episodes"] is not None:
        made["episodes"] = changes["episodes"]
    if changes["exploration_budget"] is not None:
        made["exploration"] = {"budget": changes["exploration_budget"]}
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
    exploration_budget: float | None = typer.Option(
        None,
        "--exploration-budget",
        help="what a candidate may cost beyond the deployed controller ([exploration] budget, "
        "0.5: 1.5x; inf: any); on a tuner, from the next trial on",
    ),
) -> None:
    """Print the next trial as JSON and write it, with its controller, to DIR/trials/ID/
    (a trial that ``tell`` prepared is printed as it was written, without loading the tuner)."""
    create = {"system": system, "learner": learner, "seed": seed, "config": config}
    changes = {"episodes": episodes, "exploration_budget": exploration_budget}
    given = any(v is not None for v in (*changes.values(), *create.values()))
    prepared = None if given else _prepared_trial(directory)
    if prepared is not None:
        cli.console.print_json(json.dumps(prepared))
        return
    if not any(v is not None for v in create.values()):
        served, data = _served(directory, "ask", **changes)
        if served:
            cli.console.print_json(json.dumps(data))
            return

    def go() -> dict:
        return _write_trial(directory, _tuner(directory, changes, **create))

    data = _errors(go)
    cli.console.print_json(json.dumps(data))


def _write_trial(directory: Path, tuner: Any) -> dict:
    """The tuner's next trial (the pending one), written with its controller to
    ``DIR/trials/<id>/`` (each file whole: written aside, then renamed); its JSON."""
    from mpcmobo.mpc.export import export_casadi

    trial = tuner.ask()
    where = directory / "trials" / str(trial.id)
    where.mkdir(parents=True, exist_ok=True)
    data = trial.to_json()
    part = where / f"controller.casadi.{os.getpid()}.part"  # then renamed: a plant program
    # loading the controller, or another command writing it, never meets half a file
    try:
        export_casadi(trial.mpc, trial.theta, part)
        os.replace(part, where / "controller.casadi")
    finally:
        part.unlink(missing_ok=True)
    storage.atomic_write_text(where / "trial.json", json.dumps(data, indent=1) + "\n")
    return dict(data)


def _prepared_trial(directory: Path) -> dict | None:
    """The pending trial as ``DIR/trials/<id>/trial.json`` holds it, where the tuner's
    ``status.json`` is current and names it pending, no other process changes the tuner (a
    tell of that trial under way), its controller was written and its system's file is not
    newer than its reference (None: the tuner must be loaded to ask, which waits for the
    other process)."""
    if held_elsewhere(directory / LOCK_FILE):  # first: a tell that ends now is read whole
        return None
    st = saved_status(directory)
    if st is None or st["pending"] is None or st.get("learning") is not None:
        return None
    if RunDirectory(directory).system_file_changed():  # loading the tuner checks the system
        return None
    where = directory / "trials" / str(st["pending"])
    if not (where / "controller.casadi").is_file():
        return None
    try:
        data = json.loads((where / "trial.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("id") == st["pending"] else None


@app.command()
def tell(
    directory: Path = typer.Argument(..., help="the tuner's directory"),
    trial: int = typer.Argument(..., help="the trial's id"),
    log: Path | None = typer.Argument(
        None, help="the episode: a CSV or Parquet file (with --force: the quarantined one)"
    ),
    force: bool = typer.Option(
        False, "--force", help="accept a log the checks would quarantine (or the quarantined)"
    ),
) -> None:
    """Take a trial's logged episode: a row per step, the state and input names as columns.
    The learner's long work (the twin's tuning) shows as a progress line. Then the next trial
    is prepared, so that ``ask`` prints it at once."""
    from mpcmobo.experiment.plantlog import log_columns, read_log_file

    def header() -> None:  # the file first, before the tuner and its learner are loaded
        if log is None:
            if not force:
                raise TunerError("give the log file (or --force to accept the quarantined log)")
            return
        _check_columns(directory, log_columns(log))

    _errors(header)
    if _told_by_the_process(directory, trial, log, force):
        return
    df = None if log is None else _errors(lambda: read_log_file(log))

    def go() -> Any:
        from mpcmobo.experiment.tuner import Tuner

        tuner = Tuner.load(directory)
        with WorkProgress(cli.err_console) as progress:
            return tuner, tuner.tell(trial, df, force=force, progress=progress)

    try:
        tuner, row = _errors(go)
    except KeyboardInterrupt:
        _interrupted(
            f"trial {trial} is still pending (nothing of this tell is recorded); "
            f"tell it again: mpcmobo tell {directory} {trial} LOG"
        )
    rows = tuner.job.rows
    before = rows[-2].incumbent if len(rows) > 1 else tuner.job.run.learner.theta0
    moved = not np.array_equal(rows[-1].incumbent, before)
    changed = " (the deployed theta changed)" if moved else ""
    told = tuner.files.told(row.episode) or {}
    forced = _forced(sorted({p["check"] for p in told.get("problems", [])}))
    cli.console.print(
        f"trial {row.episode} told{forced}: plant cost {fmt(row.plant_cost)} (f1 "
        f"{fmt(row.f1)}), {tuner.episodes} of "
        f"{tuner.settings.episodes} trials{changed}",
        highlight=False,
    )
    if not tuner.job.done:
        _prepare_next(directory, tuner, row.episode)


def _forced(checks: list[str]) -> str:
    """What a tell's line says of the checks its log was accepted despite (``--force``)."""
    return f" (accepted with --force despite: {', '.join(checks)})" if checks else ""


def _told_by_the_process(directory: Path, trial: int, log: Path | None, force: bool) -> bool:
    """The tell sent to the tuner's process where one serves ``directory`` (False: none
    does); it answers once the log is checked and goes on learning."""
    where = None if log is None else str(log.resolve())
    served, answer = _served(directory, "tell", trial=trial, log=where, force=force)
    if served:
        last = trial + 1 >= answer["budget"]
        then = (
            f"that was the last trial of the budget: mpcmobo status {directory} shows the "
            "result once it has learned"
            if last
            else f"and prepares the next trial: mpcmobo ask {directory} prints it"
        )
        cli.console.print(
            f"trial {trial} told{_forced(answer.get('despite') or [])}: plant cost {fmt(answer['plant_cost'])}, {trial + 1} of "
            f"{answer['budget']} trials; the tuner's process learns from it{';' if last else ''} "
            f"{then}",
            highlight=False,
        )
    return bool(served)


def _prepare_next(directory: Path, tuner: Any, told: int) -> None:
    """After trial ``told``: the next trial written for ``ask`` (Ctrl-C there loses nothing
    and says so)."""
    try:
        nxt = _errors(lambda: _write_trial(directory, tuner))
    except KeyboardInterrupt:
        _interrupted(
            f"while preparing the next trial: trial {told} is told and recorded; "
            f"mpcmobo ask {directory} prepares the next one"
        )
    cli.console.print(f"trial {nxt['id']} is ready: mpcmobo ask {directory}", highlight=False)


def _served(directory: Path, op: str, **kwargs: Any) -> tuple[bool, Any]:
    """``op`` answered by the tuner's process where one serves ``directory`` (``mpcmobo
    serve``): ``(True, answer)``; ``(False, None)`` where none does."""
    from mpcmobo.cli.resident import ResidentError, request

    with Waiting(cli.err_console) as show:
        try:
            return request(directory, op, progress=show, **kwargs)
        except ResidentError as err:
            cli._fail(str(err), err.code)
        except KeyboardInterrupt:
            _interrupted(
                f"the tuner's process goes on with the {op}; mpcmobo status {directory} "
                "shows where it is"
            )


@app.command()
def serve(directory: Path = typer.Argument(..., help="the tuner's directory")) -> None:
    """Keep the tuner in memory and answer ask, tell and retract from it until Ctrl-C or SIGTERM
    (exit code 130 or 143): a tell returns once its log is checked, the learning and the next
    trial's proposal go on here."""
    from mpcmobo.cli.resident import Resident, ResidentError

    if not RunDirectory(directory).holds_run():
        cli._fail(f"{directory} holds no tuner: make one with mpcmobo ask {directory} --system", 2)

    def log(text: str) -> None:
        cli.console.print(f"{time.strftime('%H:%M:%S')} {text}", highlight=False, markup=False)

    resident = Resident(directory, log)
    try:
        _errors(resident.open)
    except ResidentError as err:
        cli._fail(str(err), err.code)
    log(
        f"serving the tuner in {directory} (pid {os.getpid()}): mpcmobo ask, tell and retract "
        "answer from memory; Ctrl-C stops"
    )

    def stop(signum: int, frame: Any) -> None:
        raise Interrupted(signum)

    signal.signal(signal.SIGTERM, stop)  # a service manager stops it so
    try:
        resident.serve()
    except KeyboardInterrupt as err:
        code = getattr(err, "exit_code", 130)
        waiting = bool(TunerFiles(directory).accepted_logs())
        log(
            "stopped; the accepted log not learned from yet is learned at the next load"
            if waiting
            else "stopped"
        )
        if resident.work.what:  # a learning in a thread, in C++ code: no interpreter shutdown
            sys.stdout.flush()  # under it (that aborts); what it learns is on disk already
            sys.stderr.flush()
            os._exit(code)
        raise typer.Exit(code) from None


def _interrupted(what: str) -> NoReturn:
    """Ctrl-C: say what became of the work (``what``) and exit with 130."""
    cli.err_console.print(f"Interrupted: {what}", highlight=False)
    raise typer.Exit(130) from None


def _check_columns(directory: Path, columns: list[str]) -> None:
    """The log's ``columns`` against the system's state and input names, from the tuner's
    saved reference (no learner loaded); nothing is checked if the directory has none."""
    run_dir = RunDirectory(directory)
    if not run_dir.holds_run():
        raise TunerError(f"{directory} holds no tuner (no config.toml)")
    try:
        info = run_dir.reference()
    except StudyError:
        return  # the tuner's loading reports it
    if info is None:
        return
    names = [*info.system["state_names"], *info.system["input_names"]]
    missing = [n for n in names if n not in columns]
    if missing:
        found = list(columns)
        raise TunerError(
            f"the log has no column {missing[0]!r}; it needs the states "
            f"{list(info.system['state_names'])} and the inputs "
            f"{list(info.system['input_names'])}; its columns are {found}"
        )


@app.command()
def retract(
    directory: Path = typer.Argument(..., help="the tuner's directory"),
    trial: int = typer.Argument(..., help="the told trial to take back"),
    with_later: bool = typer.Option(
        False, "--with-later", help="also the trials told after it (proposed knowing it)"
    ),
) -> None:
    """Take a told trial back: the tuner as before its tell, the trial pending again."""
    from mpcmobo.experiment.tuner import Tuner

    served, ids = _served(directory, "retract", trial=trial, later=with_later)
    if not served:
        ids = _errors(lambda: Tuner.load(directory).retract(trial, later=with_later))
    listed = ", ".join(map(str, ids))
    cli.console.print(
        f"retracted trial{'s' if len(ids) > 1 else ''} {listed} (kept in "
        f"{directory / 'retracted'}); trial {trial} is pending again",
        highlight=False,
    )


@app.command()
def status(
    directory: Path = typer.Argument(..., help="the tuner's directory"),
    as_json: bool = typer.Option(False, "--json", help="print Tuner.status() as JSON"),
) -> None:
    """Show the deployed theta, its evidence, the trials so far and what to do next."""
    st = _status_of(directory)
    if as_json:
        cli.console.print_json(json.dumps(storage.json_safe(st)))
        return
    cli.console.print(
        f"{st['learner']}: {st['told']} of {st['budget']} trials told"
        + (f", trial {st['pending']} pending" if st["pending"] is not None else "")
        + f"; the deployed theta ran {st['deployed_episodes']} of them and changed "
        + _times(st["changes_of_deployed"]),
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
    _print_trials(st)
    if st["identification"] is not None:
        converged = (st.get("exploration") or {}).get("converged")
        _print_identification(st["identification"], frozen=bool(converged))
    summary = directory / "summary.json"
    if summary.exists():  # an identified parameter held by its bounds (the recommendation
        # below says why tuning stopped exploring)
        cli.warn_summary(storage.read_json(summary), unpriced=False)
    rec = st["recommendation"]
    cli.console.print(f"next: {rec['action']}: {escape(rec['reason'])}", highlight=False)


def _times(n: int) -> str:
    """``n`` as a count of times: never, once, twice, n times."""
    return {0: "never", 1: "once", 2: "twice"}.get(int(n), f"{n} times")


def _status_of(directory: Path) -> dict[str, Any]:
    """``Tuner.status()`` of the tuner in ``directory``: from its ``status.json`` where that is
    up to date (no learner loaded; an accepted log is said to be learned from only where the
    tuner's process answers that it learns), else from the loaded tuner."""
    from mpcmobo.cli.resident import learns

    st = saved_status(directory, learns)
    if st is not None:
        return st
    from mpcmobo.experiment.tuner import Tuner

    loaded: dict[str, Any] = _errors(lambda: Tuner.load(directory).status())
    return loaded


def _print_trials(st: dict[str, Any]) -> None:
    """The trials (``Tuner.status``'s ``trials``) as a table, the cumulative plant cost and
    the quarantined trials."""
    if st["trials"]:
        table = Table(title="trials")
        for col in ("id", "role", "start", "plant cost", "excess", "verdict"):
            table.add_column(col, justify="right" if col in ("id", "plant cost") else "left")
        for t in st["trials"]:
            start = "random" if t["start"] is None else str(t["start"])
            cost = "failed" if t["plant_cost"] is None else fmt(t["plant_cost"])
            excess = "-" if t["excess_cost"] is None else fmt(t["excess_cost"])
            table.add_row(str(t["id"]), t["role"], start, cost, excess, t["verdict"])
        cli.console.print(table)
        total = "n/a" if st["plant_cost"] is None else fmt(st["plant_cost"])
        excess = "not predicted" if st["excess_cost"] is None else fmt(st["excess_cost"])
        cli.console.print(
            f"plant cost of tuning (sum of the trials' mean stage costs) {total}; excess over "
            f"the deployed controller {excess}",
            highlight=False,
        )
    _print_exploration(st["exploration"])
    if st["quarantined"]:
        ids = ", ".join(map(str, st["quarantined"]))
        cli.console.print(
            f"quarantined logs (not learned from): trial {ids}; the reasons in "
            "quarantine/trial-<id>.json",
            highlight=False,
        )


def _print_exploration(ex: dict[str, Any]) -> None:
    """The exploration budget's account (``Tuner.status``'s ``exploration``), one line."""
    if ex["budget"] is None:
        cli.console.print("no exploration budget: every candidate runs", highlight=False)
        return
    refused = ("trials " + ", ".join(map(str, ex["refused"]))) if ex["refused"] else "none"
    simulated = ex.get("simulated") or []  # a status saved before simulated candidates
    learned = (
        f" (learned from in simulation: {', '.join(map(str, simulated))})" if simulated else ""
    )
    err = ex["model_error"]  # the RMS log error of its predictions: a factor exp(err)
    ratio = ex.get("ratio_error")  # a status saved before the ratio error
    error = "not calibrated yet" if err is None else f"within a factor {math.exp(err):.3f}"
    if err is not None and ratio is not None:
        error += f", its ratios of two controllers' costs within {math.exp(ratio):.3f}"
    cli.console.print(
        f"exploration budget {1 + ex['budget']:.2f}x the deployed controller's predicted cost; "
        f"candidates it refused (the deployed controller ran instead): {refused}{learned}; the "
        f"model's prediction error {error}",
        highlight=False,
    )


def _print_identification(ident: dict[str, Any], frozen: bool = False) -> None:
    """The last fit of the model (``Tuner.status``'s ``identification``) as a table and a line
    on how it predicts the held-out transitions; ``frozen``: tuning has converged, and the
    learner fits no later trial."""
    table = Table(title="identified model (the last fit)")
    for col in ("parameter", "nominal", "estimate", "std"):
        table.add_column(col, justify="left" if col == "parameter" else "right")
    for name, p in ident["parameters"].items():
        table.add_row(name, fmt(p["nominal"], 6), fmt(p["estimate"], 6), fmt(p["std"], 2))
    cli.console.print(table)
    cli.console.print(
        f"fitted on {ident['transitions']} transitions; one-step error on held-out ones (RMS, "
        f"scaled by x_scale) {fmt(ident['holdout_error'], 3)}, the nominal model's "
        f"{fmt(ident['nominal_error'], 3)}"
        + ("; tuning has converged: the trials since are not fitted" if frozen else _refits(ident)),
        highlight=False,
    )


def _refits(ident: dict[str, Any]) -> str:
    """When the model is fitted again (a status saved before it said so: nothing)."""
    growth = ident.get("refit_growth")
    if growth is None:
        return ""
    return f" (fitted again once the transitions have grown by {100 * growth:g}%)"


def _job_of(run_dir: RunDirectory, learner: str | None, seed: int | None) -> tuple[str, int]:
    """The one job of ``run_dir`` that ``learner`` and ``seed`` (None: any) name: its learner
    and seed (else a :class:`TunerError` listing the jobs there are)."""
    settings = run_dir.saved_settings()
    jobs = [
        (n, s)
        for n in settings.learners
        for s in settings.seeds
        if (learner is None or n == learner) and (seed is None or s == seed)
    ]
    if not jobs:
        every = ", ".join(
            f"--learner {n} --seed {s}" for n in settings.learners for s in settings.seeds
        )
        asked = " ".join(
            f"--{k} {v}" for k, v in (("learner", learner), ("seed", seed)) if v is not None
        )
        raise TunerError(f"{run_dir.path} holds no job {asked}; its jobs: {every}")
    if len(jobs) != 1:
        listed = ", ".join(f"--learner {n} --seed {s}" for n, s in jobs)
        raise TunerError(f"choose one job of {run_dir.path}: {listed}")
    return jobs[0]


def _nothing_yet(run_dir: RunDirectory, name: str, seed: int) -> str:
    """Why a tuner or a job with no told trial (no episode) has nothing to export."""
    if run_dir.is_tuner():
        return (
            f"no trial of {run_dir.path} is told yet: the deployed controller is still the "
            f"MPC's own (theta0), and nothing is learned to export; tell a trial first "
            f"(mpcmobo ask {run_dir.path})"
        )
    return f"the job {name} s{seed} has no episode yet: nothing to export"


def _theta_of(run_dir: RunDirectory, which: str, learner: str | None, seed: int | None) -> Any:
    """The theta ``which`` ("deployed", "final" or a trial's id) of the job of ``run_dir``, and
    the settings."""
    settings = run_dir.saved_settings()
    name, s = _job_of(run_dir, learner, seed)
    ckpt = run_dir.checkpoint(name, s)
    if ckpt is None or (not ckpt.rows and (ckpt.pending is None or which in ("deployed", "final"))):
        raise TunerError(_nothing_yet(run_dir, name, s))
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
    if ckpt.pending is not None and int(ckpt.pending["episode"]) == k:
        written = run_dir.path / "trials" / str(k) / "controller.casadi"
        where = (
            f"its controller is {written} (written by ask)"
            if written.is_file()
            else f"mpcmobo ask {run_dir.path} writes its controller to {written}"
        )
        raise TunerError(
            f"trial {k} is pending: it has not been told yet, so it has no record; {where}"
        )
    if not 0 <= k < len(ckpt.rows):
        what = "trial" if run_dir.is_tuner() else "episode"
        kept = TunerFiles(run_dir.path).retracted_record(k)
        gone = f" (trial {k} was retracted: its record is kept in {kept})" if kept else ""
        has = f"{what}s 0 to {len(ckpt.rows) - 1}" if ckpt.rows else f"no told {what}"
        raise TunerError(f"no {what} {k}: the job has {has}{gone}")
    return settings, name, np.asarray(ckpt.rows[k].theta, float)


# the files `mpcmobo export` writes per C format (beside them the built example, `controller`)
EXPORT_FILES = {
    "c": ("controller.c", "controller.h", "main.c"),
    "embedded": ("controller.c", "controller.h", "mpc_functions.c", "mpc_functions.h", "main.c"),
}


def _check_export_out(out: Path, fmt_: str) -> None:
    """That ``--out`` can take the export (else a :class:`TunerError`): no file on its path, a
    file for the CasADi function, a directory for C code."""
    blocked = next((p for p in out.parents if p.exists() and not p.is_dir()), None)
    if blocked is not None:
        raise TunerError(f"--out {out}: {blocked} is a file, not a directory")
    if fmt_ != "casadi" and out.exists() and not out.is_dir():
        raise TunerError(f"--out {out} is a file; C code goes into a directory")
    if fmt_ == "casadi" and out.is_dir():
        raise TunerError(f"--out {out} is a directory; the CasADi function is one file")


def _write_controller(mpc: Any, theta: Any, fmt_: str, out: Path, compile_c: bool) -> str:
    """Write the controller of ``mpc`` with ``theta`` in the format ``fmt_`` into ``out``
    (compiled with ``compile_c``); what ``mpcmobo export`` prints."""
    from mpcmobo.mpc.export import ExportError

    try:
        return _exported(mpc, theta, fmt_, out, compile_c)
    except ExportError as err:
        raise TunerError(str(err)) from None


def _exported(mpc: Any, theta: Any, fmt_: str, out: Path, compile_c: bool) -> str:
    """What :func:`_write_controller` does."""
    from mpcmobo.mpc.embedded import embedded_compile_command, export_embedded
    from mpcmobo.mpc.export import c_compile_command, export_c, export_casadi

    if fmt_ == "casadi":
        return f"wrote {export_casadi(mpc, theta, out)}"
    names = EXPORT_FILES[fmt_]
    others = sorted(p.name for p in out.glob("*") if p.name not in (*names, "controller"))
    if others:
        raise TunerError(
            f"--out {out} holds files this export does not write ({', '.join(others[:5])}): "
            "give a new or empty directory, so that no file of another controller stays beside "
            "this one"
        )
    (out / "controller").unlink(missing_ok=True)  # an earlier build: it is built anew
    if fmt_ == "embedded":
        export_embedded(mpc, theta, out)
        cmd = embedded_compile_command(out)
    else:
        export_c(mpc, theta, out)
        cmd = c_compile_command(out)
    files = ", ".join(names)
    if compile_c:
        _compile(cmd, f"wrote {out}/{files}")
    return f"wrote {out}/{files}; build with:\n" + " ".join(cmd)


def _compile(cmd: list[str], written: str) -> None:
    """Run the build ``cmd`` of what ``written`` says was written; a compiler that cannot be
    run or that fails is a :class:`TunerError` (the files stay)."""
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True)
    except OSError as err:
        raise TunerError(
            f"{written}, but the C compiler {cmd[0]!r} cannot be run ({err.strerror}): set $CC "
            "to yours, or build them with:\n" + " ".join(cmd)
        ) from None
    if proc.returncode != 0:
        raise TunerError(f"compiling failed: {proc.stderr.strip()[-1500:]}")


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
    from mpcmobo.experiment.usersystem import restore_system
    from mpcmobo.mpc import ParametricMPC

    if fmt_ not in ("casadi", "c", "embedded"):
        cli._fail(f"--format must be casadi, c or embedded, got {fmt_!r}", 2)

    def go() -> str:
        run_dir = cli._require_run(directory)
        restore_system(directory)  # a tuner's System given as an object
        _check_export_out(out, fmt_)
        settings, name, th = _theta_of(run_dir, theta, learner, seed)
        options = settings.mpc.options()
        if fmt_ == "embedded":  # the MPC's own functions, generated again as plain C
            options["codegen"] = False
        mpc = ParametricMPC(build_system(settings, name), "imperfect", **options)
        return _write_controller(mpc, th, fmt_, out, compile_c)

    cli.console.print(_errors(go), highlight=False, markup=False, soft_wrap=True)
