"""What the dashboard tests share: a small finished run, a server on a free port, Chromium."""

from __future__ import annotations

import os
import shutil
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from typer.testing import CliRunner

from mpcmobo.cli import app

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
# the README's test command installs Chromium: in CI (CI=true) a missing one fails the tests
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None and not os.environ.get("CI"),
    reason="no chromium on PATH (the README's test command installs it)",
)
SMALL_RUN = "--system lq --learner identify,mobo --episodes 3 --steps 8 --seeds 0 1 -q --no-plot"


def make_small_run(out: Path) -> Path:
    """A finished run of identify and mobo on lq, 2 seeds x 3 episodes (about 15 s)."""
    res = CliRunner().invoke(app, ["run", *SMALL_RUN.split(), "--workers", "1", "--out", str(out)])
    assert res.exit_code == 0, res.output
    return out


@contextmanager
def serving(*directories: Path) -> Iterator[str]:
    """The dashboard of ``directories`` on a free port of 127.0.0.1; yields its address."""
    from mpcmobo.dashboard import make_server

    server = make_server(list(directories), port=0)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_port}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5)


@contextmanager
def chromium() -> Iterator[object]:
    """Headless Chromium of the OS, driven by Playwright (which downloads no browser)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()
