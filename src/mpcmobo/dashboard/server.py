"""The dashboard's HTTP server: GET only, every asset from the package, on 127.0.0.1 unless
told otherwise.

Routes: ``/`` the page; ``/static/<file>`` its scripts and style sheets; ``/static/uPlot.iife.min.js``
the plotting library (uPlot, stored gzipped in the package); ``/api/state?since=V`` the runs' data
as JSON (``{"version": V}`` alone while no file of the runs changed since version ``V``);
``/api/episode?run=I&learner=L&seed=S&phase=P&episode=E&start=K`` one stored trajectory. Any
other method is refused (405): nothing on the page writes or runs anything.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import threading
from collections.abc import Callable, Sequence
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlparse

from mpcmobo.dashboard.files import FileCache, describe
from mpcmobo.dashboard.jsonable import plain
from mpcmobo.dashboard.payload import run_payload
from mpcmobo.dashboard.runs import RunSource

__all__ = ["Dashboard", "DashboardServer", "make_server"]

JS, CSS = "text/javascript; charset=utf-8", "text/css; charset=utf-8"
STATIC = {
    "index.html": "text/html; charset=utf-8",
    "app.js": JS,
    "plots.js": JS,
    "style.css": CSS,
    "uPlot.iife.min.js": JS,  # uPlot 1.6.32 (MIT, static/vendor/uPlot.LICENSE)
    "uPlot.min.css": CSS,
}
VENDOR = ("uPlot.iife.min.js", "uPlot.min.css")  # stored as static/vendor/<name>.gz


class Dashboard:
    """The runs of the page and their data, rebuilt only when a file of a run changed."""

    def __init__(
        self, directories: Sequence[str | Path], serving: Callable[[Path], bool] | None = None
    ) -> None:
        self.cache = FileCache()
        self.serving = serving  # whether a tuner's process (mpcmobo serve) runs
        self.sources = [RunSource(d, self.cache, serving) for d in directories]
        self._lock = threading.Lock()
        self._state: tuple[str, bytes] | None = None
        self._assets: dict[str, bytes] = {}

    def version(self) -> str:
        """A digest of the stamps of every file of the runs."""
        stamps: list[Any] = [s.stamp() for s in self.sources]
        if self.serving is not None:  # a tuner's process that stops changes the page too
            stamps += [self.serving(s.path) for s in self.sources if s.is_tuner()]
        stamps += [s.study_alive() for s in self.sources]  # and a study's killed process
        return hashlib.sha1(repr(stamps).encode(), usedforsecurity=False).hexdigest()[:16]

    def state(self) -> tuple[str, bytes]:
        """The version and the JSON of every run (built again when the version changed)."""
        with self._lock:
            version = self.version()
            if self._state is None or self._state[0] != version:
                runs = []
                for i, source in enumerate(self.sources):
                    try:
                        runs.append(run_payload(source, i))
                    except Exception as err:  # noqa: BLE001 - shown on the page, not a crash
                        msg = f"{source.path} cannot be shown ({describe(err)})"
                        runs.append(_broken(i, source, msg))
                try:  # the numbers are made JSON-safe as they are read
                    body = json.dumps({"version": version, "runs": runs}, allow_nan=False)
                except (TypeError, ValueError):  # a value of a file that is not
                    body = json.dumps({"version": version, "runs": plain(runs)}, allow_nan=False)
                self._state = (version, body.encode("utf-8"))
            return self._state

    def episode(self, query: dict[str, str]) -> dict[str, Any] | None:
        """One stored trajectory of run ``query["run"]`` (None if not stored)."""
        source = self.sources[int(query["run"])]
        with self._lock:
            source.begin()
            return source.trajectory(query)

    def asset(self, name: str) -> bytes:
        """A file of the page (``static/``; the plotting library from ``static/vendor/``)."""
        if name not in self._assets:
            files = resources.files("mpcmobo.dashboard").joinpath("static")
            if name in VENDOR:
                data = gzip.decompress(files.joinpath("vendor", name + ".gz").read_bytes())
            else:
                data = files.joinpath(name).read_bytes()
            self._assets[name] = data
        return self._assets[name]


def _broken(index: int, source: RunSource, message: str) -> dict[str, Any]:
    """The data of a run that cannot be shown: its message alone."""
    name = source.path.name
    return {"index": index, "path": str(source.path), "name": name, "messages": [message]}


class Handler(BaseHTTPRequestHandler):
    """GET and HEAD of the routes in the module docstring; anything else is a 405."""

    server: DashboardServer
    server_version = "mpcmobo-dashboard"

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base's name
        """Quiet: no line per request."""

    def _send(self, status: int, body: bytes, kind: str, cache: bool = False) -> None:
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "max-age=3600" if cache else "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, obj: Any, status: int = 200) -> None:
        self._send(status, json.dumps(obj, allow_nan=False).encode(), "application/json")

    def do_GET(self) -> None:
        """Serve the page, its assets and its data."""
        url = urlparse(self.path)
        # blank values kept: the reference episodes (theta0's, the perfect model's) have the
        # learner ""
        query = {k: v[-1] for k, v in parse_qs(url.query, keep_blank_values=True).items()}
        try:
            self._route(url.path, query)
        except (KeyError, ValueError, IndexError) as err:
            self._json({"error": f"bad request ({describe(err)})"}, HTTPStatus.BAD_REQUEST)

    do_HEAD = do_GET

    def _route(self, path: str, query: dict[str, str]) -> None:
        d = self.server.dashboard
        if path in ("/", "/index.html"):
            self._send(200, d.asset("index.html"), STATIC["index.html"])
        elif path.startswith("/static/") and path[8:] in STATIC:
            name = path[8:]
            self._send(200, d.asset(name), STATIC[name], cache=name in VENDOR)
        elif path == "/api/state":
            version, body = d.state()
            if query.get("since") == version:
                self._json({"version": version})
            else:
                self._send(200, body, "application/json")
        elif path == "/api/episode":
            got = d.episode(query)
            self._json(got if got is not None else {"error": "not stored"}, 200 if got else 404)
        else:
            self._json({"error": f"no page {path}"}, HTTPStatus.NOT_FOUND)

    def _refuse(self) -> None:
        self._json({"error": "the dashboard is read-only"}, HTTPStatus.METHOD_NOT_ALLOWED)

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _refuse


class DashboardServer(ThreadingHTTPServer):
    """A threading HTTP server holding the :class:`Dashboard` its handlers serve."""

    daemon_threads = True

    def __init__(self, address: tuple[str, int], dashboard: Dashboard) -> None:
        super().__init__(address, Handler)
        self.dashboard = dashboard

    def warm(self) -> None:
        """Read the runs and the page's files once, so that the first page is as fast as the
        next ones."""
        self.dashboard.state()
        for name in STATIC:
            self.dashboard.asset(name)


def make_server(
    directories: Sequence[str | Path],
    host: str = "127.0.0.1",
    port: int = 8050,
    serving: Callable[[Path], bool] | None = None,
) -> DashboardServer:
    """The dashboard's server for ``directories`` (``port`` 0: any free port); call its
    ``serve_forever()``. ``serving(path)``: whether the tuner in ``path`` has its process
    (``mpcmobo serve``) running, what the page says of a told log's learning (None: as
    ``status.json`` says)."""
    return DashboardServer((host, port), Dashboard(directories, serving))
