"""``mpcmobo.__version__`` and ``mpcmobo --version`` come from the installed package metadata."""

from __future__ import annotations

from importlib.metadata import version

from typer.testing import CliRunner

import mpcmobo
from mpcmobo.cli import app


def test_version_is_the_package_metadata():
    assert mpcmobo.__version__ == version("mpcmobo")


def test_cli_version_flag_prints_it_and_exits_0():
    result = CliRunner().invoke(app, ["--version"])
    assert result.exit_code == 0, result.output
    assert result.output.strip() == f"mpcmobo {version('mpcmobo')}"
    # the flag does not get in the way of the commands
    assert CliRunner().invoke(app, ["systems"]).exit_code == 0
