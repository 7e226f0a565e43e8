# ruff: noqa: B008 - typer declares options as argument defaults
"""``mpcmobo connect``: trials of a tuner on a live plant over OPC UA (docs/real-plant.md).

``connect DIR --url opc.tcp://HOST:PORT --nodes nodes.toml --period S [--trials N]
[--dry-run]`` runs N trials of the tuner in DIR (made the first time from ``--config`` /
``--system``, as ``ask`` does, with ``start_mode = "random"`` unless the config sets it): each
is asked, run at the plant's sampling period and told. Exit codes: 0 every trial done, 1 a
trial aborted by a fault of the plant (its log kept, not told; the next ``connect`` runs it
again), 2 bad input or a server that cannot be reached, 130 Ctrl-C (the safe input written).
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import typer

from mpcmobo import cli
from mpcmobo.cli.plant import _errors, _tuner
from mpcmobo.experiment.rundir import RunDirectory

__all__ = ["connect"]

app: typer.Typer = cli.app


def _sets_start_mode(config: Path | None) -> bool:
    """Whether the settings file ``config`` chooses a start mode (unreadable: leave it to the
    settings' own error)."""
    if config is None:
        return False
    try:
        return "start_mode" in tomllib.loads(config.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return True


@app.command()
def connect(
    directory: Path = typer.Argument(..., help="the tuner's directory (made the first time)"),
    url: str = typer.Option(
        ..., "--url", help="the server: opc.tcp://HOST:PORT, with a path if it has one"
    ),
    nodes: Path = typer.Option(..., "--nodes", help="the node map (TOML)"),
    period: float = typer.Option(..., "--period", help="the plant's sampling period (seconds)"),
    trials: int = typer.Option(1, "--trials", "-n", help="trials to run"),
    dry_run: bool = typer.Option(False, "--dry-run", help="read and compute, write nothing"),
    config: Path | None = typer.Option(None, "--config", "-c", help="settings file (TOML)"),
    system: str | None = typer.Option(None, "--system", help="system: a name or a factory"),
    learner: str | None = typer.Option(None, "--learner", "-l", help="the learner (mobo)"),
    seed: int | None = typer.Option(None, "--seed", help="the tuner's seed (0)"),
    episodes: int | None = typer.Option(
        None, "--episodes", help="the budget of trials; on a tuner, a larger one"
    ),
) -> None:
    """Run trials of the tuner in DIR on a live plant over OPC UA: ask, run, tell."""
    from mpcmobo.connect import ConnectError, load_nodes, run_plant
    from mpcmobo.connect.client import public_url

    create: dict[str, Any] = {"system": system, "learner": learner, "seed": seed, "config": config}
    if not RunDirectory(directory).holds_run() and not _sets_start_mode(config):
        create["start_mode"] = "random"  # a plant starts where it is

    def echo(line: str) -> None:
        cli.console.print(line, highlight=False, markup=False)

    def go() -> Any:
        tuner = _tuner(directory, {"episodes": episodes, "exploration_budget": None}, **create)
        node_map = load_nodes(nodes, tuner.system)
        password = node_map.security.password is not None or urlsplit(url).password
        if password and not node_map.security.encrypted:
            echo("warning: no security policy: the password goes to the server unencrypted")
        dry = " (dry run: nothing is written)" if dry_run else ""
        echo(f"connecting to {public_url(url)}{dry}")
        return run_plant(tuner, url, node_map, period, trials, dry_run, echo)

    try:
        outcomes = _errors(lambda: _connect_errors(go, ConnectError))
    except KeyboardInterrupt as err:
        name = getattr(err, "signal_name", "SIGINT")
        cli.err_console.print(f"interrupted ({name}): {err}", highlight=False, soft_wrap=True)
        raise typer.Exit(143 if name == "SIGTERM" else 130) from None
    for outcome in outcomes:
        if outcome.status == "dry-run":
            echo(
                f"trial {outcome.trial} dry run: nothing written, nothing told "
                f"({outcome.log}); {outcome.timing(period)}"
            )
    last = outcomes[-1]
    if last.status == "aborted":
        cli._fail(last.message, 1)


def _connect_errors(go: Any, error: type[Exception]) -> Any:
    """``go()`` with a connection's errors as exit code 2."""
    try:
        return go()
    except error as err:
        cli._fail(str(err), 2)
