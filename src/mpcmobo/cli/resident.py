"""A tuner held in memory by a process of its own: ``mpcmobo serve DIR``.

Without it every ``ask``, ``tell`` and ``retract`` starts an interpreter, imports PyTorch and
loads the tuner (seconds), and a ``tell`` waits for the learner (a GP fit, the next proposal:
seconds to a minute). ``mpcmobo serve DIR`` loads the tuner once and keeps it; while it runs,
those commands send their request to it over a local socket and it answers from memory:

- ``tell`` is answered once the log is checked and kept (:meth:`Tuner.accept`); the process
  then learns from it and prepares the next trial (:meth:`Tuner.learn`, ``ask``) in the
  background, and ``status`` says so meanwhile;
- ``ask`` is answered with the prepared trial, after the learning it waits for (its progress
  shown);
- ``retract`` waits for the learning, then retracts.

A crash of the process loses nothing: an accepted log is on disk (``accepted/``), and the next
load learns from it. The process reloads the tuner when its files changed under it (the Python
``Tuner`` used on the same directory). ``DIR/resident.json`` names its socket and process; the
key that authenticates a command (``DIR/resident.key``, readable by the owner only) is made
anew at each start. Only the user who can read DIR can talk to it.
"""

from __future__ import annotations

import json
import os
import secrets
import tempfile
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing import AuthenticationError
from multiprocessing.connection import Client, Connection, Listener
from pathlib import Path
from typing import Any

from mpcmobo.experiment.interrupts import process_alive

__all__ = ["ADDRESS_FILE", "KEY_FILE", "Resident", "ResidentError", "learns", "request", "serving"]

ADDRESS_FILE = "resident.json"
KEY_FILE = "resident.key"
# a Unix socket's path is limited to about 107 bytes; a longer one goes to the temporary dir
MAX_SOCKET_PATH = 100
# how often a command waiting for the learner hears what it does
PROGRESS_EVERY_S = 0.5


class ResidentError(Exception):
    """A command the tuner's process refused or failed: ``code`` is the exit code (2: a bad
    trial or log, as without the process; 1: the process failed)."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


# ---------------------------------------------------------------------------- the client
def _address(directory: Path) -> tuple[str, bytes] | None:
    """The socket and key of the process serving ``directory`` (None: none is recorded)."""
    try:
        info = json.loads((directory / ADDRESS_FILE).read_text(encoding="utf-8"))
        key = (directory / KEY_FILE).read_bytes()
    except (OSError, ValueError):
        return None
    socket = info.get("socket") if isinstance(info, dict) else None
    return (socket, key) if isinstance(socket, str) and key else None


def _connect(directory: Path) -> Connection | None:
    """A connection to the process serving ``directory`` (None: none runs)."""
    found = _address(directory)
    if found is None:
        return None
    socket, key = found
    try:
        return Client(socket, family="AF_UNIX", authkey=key)
    except (OSError, EOFError):
        return None  # a process that stopped (its socket gone, or refused)
    except AuthenticationError:
        raise ResidentError(
            f"the tuner's process serving {directory} refused this command's key "
            f"({directory / KEY_FILE}): the files were changed while it ran; stop it and "
            f"start mpcmobo serve {directory} again",
            1,
        ) from None


def request(
    directory: Path, op: str, progress: Callable[[str], None] | None = None, **kwargs: Any
) -> tuple[bool, Any]:
    """Send ``op`` with ``kwargs`` to the process serving ``directory``: ``(False, None)``
    where none runs (the command then loads the tuner itself), else ``(True, answer)``.
    ``progress(text)`` hears what the process does while the command waits. A command it
    refuses or fails raises :class:`ResidentError`."""
    conn = _connect(directory)
    if conn is None:
        return False, None
    with conn:
        try:
            conn.send((op, kwargs))
            while True:
                kind, payload = conn.recv()
                if kind == "progress":
                    if progress is not None:
                        progress(str(payload))
                elif kind == "ok":
                    return True, payload
                else:
                    raise ResidentError(str(payload["message"]), int(payload["code"]))
        except (OSError, EOFError) as err:
            raise ResidentError(
                f"the tuner's process (mpcmobo serve {directory}) stopped while it answered "
                f"({str(err) or type(err).__name__}); nothing it had recorded is lost: "
                f"mpcmobo status {directory} shows whether it kept a told log (the next "
                "command learns from it), else run the command again",
                1,
            ) from None


# how long ``mpcmobo status`` waits for the tuner's process to say whether it learns
PING_TIMEOUT_S = 2.0


def serving(directory: Path) -> bool:
    """Whether the process that serves ``directory`` (``mpcmobo serve``) runs: the one its
    ``resident.json`` names is alive (False: none is named, or it is gone, e.g. killed). A
    check of the process alone, no request: what the dashboard asks at every poll."""
    try:
        info = json.loads((Path(directory) / ADDRESS_FILE).read_text(encoding="utf-8"))
        return process_alive(int(info["pid"]))
    except (OSError, ValueError, KeyError, TypeError):
        return False


def learns(directory: Path) -> bool:
    """Whether a process serving ``directory`` is learning from a told log now: it runs and
    answers that it learns, or is too busy to answer within ``PING_TIMEOUT_S`` (a command it
    serves waits for its learning). What ``mpcmobo status`` says of a log accepted and not
    learned from yet."""
    if not serving(Path(directory)):
        return False
    answers: list[tuple[bool, Any]] = []

    def ping() -> None:
        try:
            answers.append(request(Path(directory), "ping"))
        except ResidentError:
            answers.append((False, None))

    thread = threading.Thread(target=ping, name="mpcmobo-ping", daemon=True)
    thread.start()
    thread.join(PING_TIMEOUT_S)
    if not answers:
        return True
    served, answer = answers[0]
    return bool(served) and str(answer.get("working", "")).startswith("learning")


# ---------------------------------------------------------------------------- the server
@dataclass
class _Work:
    """What the background thread does now (``what``) and the failure of its last work."""

    what: str = ""
    failure: str = ""


class Resident:
    """The process serving the tuner in ``directory`` (module docstring). ``log(text)`` hears
    each request and what the process does."""

    def __init__(self, directory: Path, log: Callable[[str], None]) -> None:
        self.directory = Path(directory).resolve()
        self.log = log
        self.lock = threading.Lock()  # the tuner: one request or background work at a time
        self.work = _Work()
        self.tuner: Any = None
        self.stamp: tuple = ()
        self.listener: Listener | None = None
        self.handed_over = False  # the lock went to the background thread

    # ---------------------------------------------------------------- the tuner
    def _files_stamp(self) -> tuple:
        """What changes when the tuner's files change: status.json and the checkpoints."""
        paths = [self.directory / "status.json", *self.directory.glob("jobs/*/checkpoint*.pkl")]
        return tuple(
            (p.name, p.stat().st_mtime_ns, p.stat().st_size) for p in sorted(paths) if p.exists()
        )

    def _load(self) -> None:
        """The tuner loaded from its files."""
        from mpcmobo.experiment.tuner import Tuner

        self.tuner = Tuner.load(self.directory)
        self.stamp = self._files_stamp()

    def _current(self, episodes: int | None = None, exploration_budget: float | None = None) -> Any:
        """The tuner, reloaded where its files changed since this process wrote them (or with a
        larger budget of ``episodes``, or another ``exploration_budget``)."""
        settings = self.tuner.settings
        larger = episodes is not None and episodes != settings.episodes
        priced = (
            exploration_budget is not None and exploration_budget != settings.exploration.budget
        )
        if larger or priced or self._files_stamp() != self.stamp:
            from mpcmobo.experiment.tuner import Tuner

            self.log("the tuner's files changed: reloading it")
            self.tuner = Tuner.load(
                self.directory, episodes=episodes, exploration_budget=exploration_budget
            )
        return self.tuner

    def _written(self) -> None:
        self.stamp = self._files_stamp()

    # ---------------------------------------------------------------- the requests
    def _ask(self, episodes: int | None = None, exploration_budget: float | None = None) -> dict:
        from mpcmobo.cli.plant import _write_trial

        data = _write_trial(self.directory, self._current(episodes, exploration_budget))
        self._written()
        return data

    def _tell(self, trial: int, log: str | None, force: bool) -> dict:
        tuner = self._current()
        df = None
        if log is not None:
            from mpcmobo.experiment.plantlog import read_log_file

            df = read_log_file(Path(log))
        cost = tuner.accept(trial, df, force=force)
        despite = tuner.accepted_despite  # before the learning takes the accepted log
        self._written()
        self._hand_over(self._learn, f"learning from trial {trial}")
        return {
            "trial": trial,
            "plant_cost": cost,
            "budget": tuner.settings.episodes,
            "despite": despite,
        }

    def _retract(self, trial: int, later: bool) -> list[int]:
        ids: list[int] = self._current().retract(trial, later=later)
        self._written()
        return ids

    def _learn(self) -> None:
        """In the background: the learner learns from the accepted log, then the next trial is
        prepared (unless the budget is spent; a proposal that fails there is only logged: the
        next ``ask`` proposes again and reports it)."""
        tuner = self.tuner
        trial = tuner.learning

        def progress(what: str, done: int, total: int) -> None:
            self.work.what = f"learning from trial {trial}: {what} {done}/{total}"

        try:
            row = tuner.learn(progress=progress)
        except BaseException as err:
            self.work.failure = (
                f"learning from trial {trial} failed ({type(err).__name__}: {err}); nothing of "
                f"it is recorded and trial {trial} is pending again: tell it again"
            )
            raise
        finally:
            self._written()
        self.log(f"trial {row.episode} learned from: f1 {row.f1:.6g}")
        if tuner.job.done:
            return
        self.work.what = f"preparing trial {row.episode + 1}"
        try:
            self._prepare()
        except Exception as err:  # noqa: BLE001 - the next ask proposes again
            self.log(f"preparing the next trial failed: {type(err).__name__}: {err}")
            self._written()  # what the failed proposal wrote is this process's

    def _spent(self, episodes: int | None) -> str | None:
        """The refusal of an ``ask`` while the last trial of the budget (or of the larger one,
        ``episodes``) is learned from; None where a trial can follow it."""
        tuner = self.tuner
        learning = None if tuner is None else tuner.learning
        if learning is None:
            return None
        budget = max(tuner.settings.episodes, episodes or 0)
        if learning + 1 < budget:
            return None
        return (
            f"the tuner's budget of {budget} trials is spent: trial {learning}, the last, is "
            f"told and the tuner's process is learning from it (mpcmobo status "
            f"{self.directory} shows the result once it has); a larger budget goes on: "
            f"mpcmobo ask {self.directory} --episodes N"
        )

    def _hand_over(self, fn: Callable[[], None], what: str) -> None:
        """``fn`` in the background thread. The caller holds the tuner's lock and hands it
        over: the thread releases it when ``fn`` returns."""
        self.work = _Work(what=what)
        self.handed_over = True

        def run() -> None:
            try:
                fn()
            except BaseException:  # noqa: BLE001 - fn says what failed; the log has the rest
                self.log(f"{what} failed:\n{traceback.format_exc()}")
                self._reload_after_failure()
            finally:
                self.work.what = ""
                self.lock.release()

        threading.Thread(target=run, name="mpcmobo-learner", daemon=True).start()

    def _reload_after_failure(self) -> None:
        try:
            self._load()
        except Exception as err:  # noqa: BLE001 - the next request reloads it again
            self.log(f"reloading the tuner failed: {err}")

    def handle(self, conn: Connection, op: str, kwargs: dict[str, Any]) -> None:
        """One request: wait for the tuner (telling the command what the process does), run
        ``op``, send its answer (or its error)."""
        ops: dict[str, Callable[..., Any]] = {
            "ask": self._ask,
            "tell": self._tell,
            "retract": self._retract,
        }
        if op == "ping":  # whether the process answers: the tuner is not needed
            conn.send(("ok", {"pid": os.getpid(), "working": self.work.what}))
            return
        if op not in ops:
            conn.send(("error", {"message": f"unknown request {op!r}", "code": 1}))
            return
        spent = self._spent(kwargs.get("episodes")) if op == "ask" else None
        if spent is not None:  # at once: the learning would end in the same refusal
            conn.send(("error", {"message": spent, "code": 2}))
            return
        while not self.lock.acquire(timeout=PROGRESS_EVERY_S):
            conn.send(("progress", self.work.what or "working"))
        self.handed_over = False
        try:
            failure, self.work.failure = self.work.failure, ""
            if failure:
                raise ResidentError(failure, 1)
            answer = ops[op](**kwargs)
        except ResidentError as err:
            conn.send(("error", {"message": str(err), "code": err.code}))
        except Exception as err:  # noqa: BLE001 - the command reports it
            conn.send(("error", _error_answer(err)))
        else:
            conn.send(("ok", answer))
        finally:
            if not self.handed_over:
                self._written()  # what the request wrote (a quarantine too) is this process's
                self.lock.release()
        self.log(f"{op} {kwargs or ''}".rstrip())

    # ---------------------------------------------------------------- the process
    def _socket_path(self) -> str:
        path = str(self.directory / "resident.sock")
        if len(path.encode()) <= MAX_SOCKET_PATH:
            return path
        return os.path.join(tempfile.mkdtemp(prefix="mpcmobo-"), "resident.sock")

    def open(self) -> None:
        """Load the tuner and listen (:class:`ResidentError` where another process serves the
        directory already)."""
        from mpcmobo.experiment import storage

        conn = _connect(self.directory)
        if conn is not None:
            conn.close()
            raise ResidentError(
                f"a tuner's process serves {self.directory} already "
                f"({self.directory / ADDRESS_FILE})",
                2,
            )
        if (self.directory / "accepted").is_dir() and any((self.directory / "accepted").iterdir()):
            self.log("a told log waits: learning from it before serving (this can take a while)")
        self._load()
        key = secrets.token_bytes(32)
        socket = self._socket_path()
        Path(socket).unlink(missing_ok=True)  # left by a process that was killed
        self.listener = Listener(socket, family="AF_UNIX", authkey=key)
        key_path = self.directory / KEY_FILE
        key_path.unlink(missing_ok=True)
        fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as fh:
            fh.write(key)
        info = {"socket": socket, "pid": os.getpid(), "started_at": time.time()}
        storage.atomic_write_text(self.directory / ADDRESS_FILE, json.dumps(info) + "\n")
        if self.tuner.job.pending is None and not self.tuner.job.done:
            self.lock.acquire()  # handed over to the background thread
            self._hand_over(self._prepare, "preparing the next trial")

    def _prepare(self) -> None:
        """The next trial prepared (in the background: at the start, and after a learning), so
        that the next ``ask`` is quick."""
        from mpcmobo.cli.plant import _write_trial

        data = _write_trial(self.directory, self.tuner)
        self._written()
        self.log(f"trial {data['id']} is ready")

    def serve(self) -> None:
        """Answer requests until interrupted; then the files that name the process go."""
        assert self.listener is not None  # open() first
        try:
            while (listener := self.listener) is not None:  # None: closed (close())
                try:
                    conn = listener.accept()
                except (OSError, EOFError, AuthenticationError):  # a client without the key
                    continue
                with conn:
                    try:
                        op, kwargs = conn.recv()
                        self.handle(conn, op, kwargs)
                    except (OSError, EOFError):
                        continue  # the command went away (Ctrl-C): its work goes on
        finally:
            self.close()

    def close(self) -> None:
        """Stop listening; remove the files that name the process."""
        if self.listener is not None:
            socket = self.listener.address
            self.listener.close()
            self.listener = None
            if isinstance(socket, str):
                Path(socket).unlink(missing_ok=True)
        for name in (ADDRESS_FILE, KEY_FILE):
            (self.directory / name).unlink(missing_ok=True)


def _error_answer(err: Exception) -> dict[str, Any]:
    """A request's exception as the command reports it: the tuner's and settings' errors with
    exit code 2 (as without the process), anything else with 1."""
    from mpcmobo.experiment.plantlog import TunerError
    from mpcmobo.experiment.settings import SettingsError

    if isinstance(err, (TunerError, SettingsError)):
        return {"message": str(err), "code": 2}
    return {"message": f"the tuner's process failed: {type(err).__name__}: {err}", "code": 1}
