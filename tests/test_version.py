"""``mpcmobo.__version__`` and ``mpcmobo --version`` come from the installed package metadata,
and this release is 1.1.0."""

from __future__ import annotations

import tomllib
from importlib.metadata import version
from pathlib import Path

from typer.testing import CliRunner

import mpcmobo
from mpcmobo.cli import app

PYPROJECT = Path(__file__).parents[1] / "pyproject.toml"


def test_version_is_the_package_metadata():
    assert mpcmobo.__version__ == version("mpcmobo")


def test_the_release_is_1_1_0():
    """The source declares 1.1.0, and the installed metadata (what ``--version`` reads) is
    that of this source: a stale install would report another version."""
    assert tomllib.loads(PYPROJECT.read_text())["project"]["version"] == "1.1.0"
    assert mpcmobo.__version__ == "1.1.0"


def test_cli_version_flag_prints_it_and_exits_0():
    result = CliRunner().invoke(app, ["--version"])
    assert result.exit_code == 0, result.output
    assert result.output.strip() == "mpcmobo 1.1.0"
    assert result.output.strip() == f"mpcmobo {version('mpcmobo')}"
    # the flag does not get in the way of the commands
    assert CliRunner().invoke(app, ["systems"]).exit_code == 0


def test_python_m_mpcmobo_is_the_command_line():
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-m", "mpcmobo", "--version"], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "mpcmobo 1.1.0"
