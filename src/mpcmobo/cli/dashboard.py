# ruff: noqa: B008 - typer declares options as argument defaults
"""``mpcmobo dashboard DIR [DIR ...]``: a live, read-only page of run and tuner directories."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from mpcmobo import cli

__all__ = ["dashboard"]

app: typer.Typer = cli.app


@app.command(
    help="Serve a live page of one or several run or tuner directories: cost on the plant and "
    "J_eval of the deployed theta, the changes of the deployed theta and their evidence, one "
    "episode's states and inputs against their limits, the identified model, f1..f4 and their "
    "Pareto front, a tuner's pending trial and trials. The page reads the records as they "
    "grow (every 2 s) and writes nothing; it binds to 127.0.0.1 unless --host says otherwise."
)
def dashboard(
    directories: Annotated[list[Path], typer.Argument(help="Run or tuner directories.")],
    port: Annotated[
        int, typer.Option(min=0, max=65535, help="The port to serve on (0: any free one).")
    ] = 8050,
    host: Annotated[
        str, typer.Option(help="The address to bind (0.0.0.0: every interface).")
    ] = "127.0.0.1",
) -> None:
    """Serve the dashboard until Ctrl-C."""
    for d in directories:
        if d.exists() and not d.is_dir():
            cli._fail(f"{d} is a file, not a run directory", 2)
        if not d.exists():
            cli._fail(
                f"{d} does not exist: to watch a run from its start, create it first (mkdir "
                f"{d}; mpcmobo run --out {d} writes into an empty directory)",
                2,
            )
    from mpcmobo.cli.resident import serving
    from mpcmobo.dashboard import make_server

    try:
        server = make_server(directories, host=host, port=port, serving=serving)
    except OSError as err:
        cli._fail(f"cannot serve on {host}:{port} ({err.strerror or err})", 2)
    typer.echo(f"reading {len(directories)} run(s) ...")
    server.warm()
    typer.echo(f"mpcmobo dashboard on http://{host}:{server.server_port}/  (Ctrl-C stops it)")
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
