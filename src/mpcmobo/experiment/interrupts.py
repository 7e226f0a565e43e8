"""Interrupts (SIGINT, SIGTERM) that stop a study cleanly, and workers that never outlive it.

IPOPT runs inside CasADi, which checks Python's signals during a solve: with Python's default
SIGINT handler a Ctrl-C raises inside that check, CasADi swallows the exception and the solve
returns as failed ("NonIpopt_Exception_Thrown"), so that the run goes on with a wrong record.
Here a signal only sets a flag while an MPC solve (or a checkpoint write) runs, and
:class:`Interrupted` is raised when it returns (:func:`deferred`, :func:`guard_solves`): an
interrupt stops a run at the end of the current MPC step and is never a solver failure.
Elsewhere it is raised at once. The episode in progress is discarded (it never reaches a
checkpoint), so the records are a prefix of the uninterrupted run's and ``--resume`` re-runs it.

In a worker process (:func:`init_worker`) SIGINT is ignored (a Ctrl-C reaches the whole process
group; the study's process decides) and a watchdog thread stops the worker when the study's
process creates the stop file or dies (its parent pid changes): a busy worker stops its job at the
end of the current MPC step, an idle one exits at once.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

# exit code of a process stopped by a signal: 128 + signal number (130 SIGINT, 143 SIGTERM)
SIGNALS = (signal.SIGINT, signal.SIGTERM)
WATCH_INTERVAL_S = 0.1  # how often a worker's watchdog looks at its parent and the stop event
ORPHAN_GRACE_S = 3.0  # how long an orphaned busy worker may take to stop its job


class Interrupted(KeyboardInterrupt):
    """The run was interrupted by ``signum`` (SIGINT or SIGTERM); everything checkpointed so far
    is kept, and ``mpcmobo run --resume`` continues it."""

    def __init__(self, signum: int = signal.SIGINT) -> None:
        super().__init__(int(signum))
        self.signum = int(signum)

    @property
    def exit_code(self) -> int:
        """The process exit code of the signal: 128 + its number (130 for SIGINT, 143 for
        SIGTERM)."""
        return 128 + self.signum

    @property
    def signal_name(self) -> str:
        """The signal's name, e.g. ``SIGINT``."""
        try:
            return signal.Signals(self.signum).name
        except ValueError:  # pragma: no cover
            return f"signal {self.signum}"


class _State:
    """This process's interrupt state: the first signal received, how deeply deferred."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.depth = 0  # > 0: inside an MPC solve or a checkpoint write
        self.active = False  # a job or study runs in the main thread: a signal may raise there


_state = _State()


def pending() -> int | None:
    """The signal that asked this process to stop, if any."""
    return _state.signum


def request_stop(signum: int = signal.SIGTERM) -> None:
    """Ask this process to stop (as if ``signum`` had arrived, without raising here)."""
    if _state.signum is None:
        _state.signum = int(signum)


def check() -> None:
    """Raise :class:`Interrupted` if a stop was asked for."""
    if _state.signum is not None:
        raise Interrupted(_state.signum)


def _handler(signum: int, frame: Any) -> None:
    request_stop(signum)
    if _state.active and _state.depth == 0:
        raise Interrupted(_state.signum)  # type: ignore[arg-type]  # set by request_stop
    if _Worker.initialized and not _Worker.busy.is_set():
        os._exit(128 + signum)  # an idle worker told to terminate: nothing to finish


@contextmanager
def deferred() -> Iterator[None]:
    """A signal inside only sets the flag; :class:`Interrupted` is raised on leaving (unless an
    exception is already on its way out)."""
    _state.depth += 1
    try:
        yield
    except BaseException:
        _state.depth -= 1
        raise
    _state.depth -= 1
    if _state.depth == 0 and _state.active:
        check()


def guard_solves(mpc: Any) -> Any:
    """Make every ``mpc.solve`` a deferred region (see the module docstring); returns ``mpc``."""
    if getattr(mpc, "_interrupt_guarded", False):
        return mpc
    solve: Callable[..., Any] = mpc.solve

    def guarded_solve(*args: Any, **kwargs: Any) -> Any:
        with deferred():
            return solve(*args, **kwargs)

    mpc.solve = guarded_solve
    mpc._interrupt_guarded = True
    return mpc


@contextmanager
def active() -> Iterator[None]:
    """A job (or the study) runs in this thread: a signal raises :class:`Interrupted` here."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = _state.active
    _state.active = True
    try:
        check()
        yield
    finally:
        _state.active = before


@contextmanager
def catching() -> Iterator[None]:
    """The study's process: SIGINT and SIGTERM stop the study (:class:`Interrupted`); the
    previous handlers are restored afterwards. Outside the main thread (where Python cannot
    install signal handlers) nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.getsignal(s) for s in SIGNALS}
    _state.signum, _state.depth = None, 0
    for s in SIGNALS:
        signal.signal(s, _handler)
    try:
        with active():
            yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        _state.signum, _state.depth = None, 0


def reclaim() -> None:
    """Install the study's handlers again where a library replaced them (``ray.init`` installs
    its own for SIGTERM, which would kill the study with no word): only while :func:`catching`
    is in force, in the main thread."""
    if _state.active and threading.current_thread() is threading.main_thread():
        for s in SIGNALS:
            signal.signal(s, _handler)


# ---------------------------------------------------------------------- worker processes
class _Worker:
    busy = threading.Event()  # a job runs in this worker
    initialized = False  # this process is a study's worker (init_worker ran)


def init_worker(parent_pid: int, stop: str | None = None) -> None:
    """Initializer of a study's worker process: ignore SIGINT, stop on SIGTERM, and watch the
    parent and the stop file ``stop`` (see the module docstring)."""
    _Worker.initialized = True
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _handler)
    threading.Thread(
        target=_watchdog, args=(parent_pid, stop), name="mpcmobo-watchdog", daemon=True
    ).start()


@contextmanager
def worker_job() -> Iterator[None]:
    """A job runs in this worker (the watchdog then stops it rather than exiting)."""
    _Worker.busy.set()
    try:
        with active():
            yield
    finally:
        _Worker.busy.clear()


def process_alive(pid: int) -> bool:
    """Whether the process ``pid`` runs (one of another user's counts; a zombie, ended and
    not yet reaped by its parent, does not, where ``/proc`` tells)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, but not ours to signal
        return True
    try:
        stat = Path(f"/proc/{pid}/stat").read_text(encoding="ascii", errors="replace")
    except OSError:  # no /proc (not Linux): the signal's answer
        return True
    return stat.rpartition(")")[2].split()[:1] != ["Z"]


def _watchdog(parent_pid: int, stop: str | None) -> None:
    while True:
        orphaned = os.getppid() != parent_pid or not process_alive(parent_pid)
        if orphaned or (stop is not None and os.path.exists(stop)):
            break
        time.sleep(WATCH_INTERVAL_S)
    request_stop(signal.SIGTERM)
    if _Worker.busy.is_set():
        # wake the main thread: it raises at once, or at the end of the current MPC step
        os.kill(os.getpid(), signal.SIGTERM)
    if not orphaned:
        return  # the study's process collects the job's result and shuts the pool down
    deadline = time.monotonic() + ORPHAN_GRACE_S
    while _Worker.busy.is_set() and time.monotonic() < deadline:
        time.sleep(WATCH_INTERVAL_S)
    os._exit(128 + signal.SIGTERM)  # no one is left to talk to; checkpoints are atomic
