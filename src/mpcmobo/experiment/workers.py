"""Where a study's jobs run: here one after the other, in spawned worker processes, or on Ray.

:func:`run_jobs` picks the back-end from the settings (``workers``, ``backend``). Workers report
their progress through their checkpoints, which the study polls (:class:`_Watch`); an interrupt
or a job's error stops every worker at the end of its current MPC step (``DIR/.stop``).
"""

from __future__ import annotations

import importlib.util
import os
import pickle
import signal
import sys
from collections.abc import Callable, Collection
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mpcmobo.experiment import interrupts, storage
from mpcmobo.experiment.job import Progress, explores, progress_event, run_job
from mpcmobo.experiment.rundir import RunDirectory, StudyError
from mpcmobo.experiment.sections import SettingsError
from mpcmobo.experiment.settings import Settings
from mpcmobo.systems.base import System
from mpcmobo.systems.registry import is_registered, system_factory

if TYPE_CHECKING:
    from concurrent.futures import Future, ProcessPoolExecutor


def run_jobs(
    jobs: list[tuple[str, int]],
    args: dict,
    settings: Settings,
    run_dir: RunDirectory,
    emit: Progress,
) -> None:
    """Run the jobs here, one after the other, or in worker processes (``settings.backend``):
    with ``backend = "ray"`` and a cluster named by ``RAY_ADDRESS``, on the cluster whatever
    ``workers`` says (its CPUs decide how many jobs run at once); else with one worker, here."""
    cluster = settings.backend == "ray" and bool(os.environ.get("RAY_ADDRESS"))
    if not cluster and (settings.workers == 1 or len(jobs) <= 1 and settings.backend == "process"):
        for n, s in jobs:
            run_job(learner_name=n, seed=s, on_episode=emit, **args)
        return
    if settings.system.factory is None and is_registered(settings.system.name):
        # registered in this process: the workers get the factory (pickled by reference);
        # factory paths and plug-ins are imported by the workers from the settings
        args = dict(args, system_factory=system_factory(settings.system.name))
    watch = _Watch(run_dir, jobs, settings.episodes, emit)
    if settings.backend == "ray":
        _run_ray(jobs, args, settings.workers, watch)
    else:
        _run_processes(jobs, args, settings.workers, watch)


class _Watch:
    """Reports the progress of jobs in other processes by reading their checkpoints."""

    def __init__(
        self, run_dir: RunDirectory, jobs: list[tuple[str, int]], total: int, emit: Progress
    ) -> None:
        self.run_dir, self.jobs, self.total, self.emit = run_dir, jobs, total, emit
        self.seen: dict[tuple[str, int], int] = {}

    def poll(self) -> None:
        """Report the jobs whose checkpoint changed since the last poll."""
        for n, s in self.jobs:
            try:
                mtime = storage.checkpoint_path(self.run_dir.path, n, s).stat().st_mtime_ns
            except FileNotFoundError:
                continue
            if self.seen.get((n, s)) == mtime:
                continue
            self.seen[(n, s)] = mtime
            try:
                ckpt = self.run_dir.checkpoint(n, s)
            except Exception:  # noqa: BLE001 - being replaced right now; next poll
                continue
            if ckpt is not None:
                self.emit(progress_event(n, s, ckpt.rows, self.total, explores(ckpt.state)))


def _sendable(factory: Callable[..., System]) -> None:
    """A system factory must reach the worker processes by reference (pickle)."""
    try:
        pickle.dumps(factory)
    except (pickle.PicklingError, AttributeError, TypeError) as err:
        raise StudyError(
            f"the system factory {factory!r} cannot be sent to worker processes ({err}); "
            "register a function defined at module level, or run with workers = 1"
        ) from None


def _run_processes(
    jobs: list[tuple[str, int]], args: dict[str, Any], workers: int, watch: _Watch
) -> None:
    """The jobs in a pool of spawned worker processes. Each worker ignores SIGINT and watches
    the study's process (:func:`interrupts.init_worker`); if the study stops (interrupt, or a
    job's error), the file ``DIR/.stop`` tells the busy workers to stop at the end of their current MPC
    step, and those that do not within :data:`STOP_TIMEOUT_S` are terminated."""
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    if args.get("system_factory") is not None:
        _sendable(args["system_factory"])
    ctx = mp.get_context("spawn")  # no CasADi / torch state is inherited through fork
    stop = watch.run_dir.path / STOP_FILE
    stop.unlink(missing_ok=True)  # left by a study that was killed while stopping
    pool = ProcessPoolExecutor(
        max_workers=min(workers, len(jobs)),
        mp_context=ctx,
        initializer=interrupts.init_worker,
        initargs=(os.getpid(), str(stop)),
    )
    remaining = set(_submit(pool, jobs, args))
    try:
        while remaining:
            done, remaining = wait(remaining, timeout=0.5, return_when=FIRST_COMPLETED)
            watch.poll()
            for f in done:
                f.result()  # re-raise a job's error here
    except BaseException:
        with interrupts.deferred():
            try:
                _stop_pool(pool, stop, remaining)
            finally:
                stop.unlink(missing_ok=True)
        raise
    pool.shutdown(wait=True)


def _submit(
    pool: ProcessPoolExecutor, jobs: list[tuple[str, int]], args: dict[str, Any]
) -> dict[Future[Any], tuple[str, int]]:
    """Submit the jobs to the pool, which spawns its workers now. They start with SIGINT
    blocked (a signal mask survives fork and exec), so a Ctrl-C while a worker still imports,
    before init_worker ignores SIGINT, cannot raise inside its start-up; a SIGINT that reaches
    the study meanwhile is delivered to it when the mask is restored."""
    old_mask = (
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        if hasattr(signal, "pthread_sigmask")  # not on Windows
        else None
    )
    try:
        return {
            pool.submit(run_job, learner_name=n, seed=s, parent_pid=os.getpid(), **args): (n, s)
            for n, s in jobs
        }
    finally:
        if old_mask is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)


STOP_TIMEOUT_S = 10.0  # how long stopped workers may take to finish their current MPC step
STOP_FILE = ".stop"  # in the run directory while the study stops its workers


def _stop_pool(pool: ProcessPoolExecutor, stop: Path, remaining: Collection[Future[Any]]) -> None:
    """Stop the workers: cancel what has not started, tell the busy ones to stop (their jobs
    end at the end of the current MPC step, with everything finished checkpointed), wait for
    their jobs to report, then end the worker processes. They are killed rather than waited
    for: a worker's interpreter takes seconds to tear down (torch, CasADi), and all it has to
    keep is already on disk (checkpoints and the log are written whole)."""
    from concurrent.futures import wait

    stop.touch()
    for f in remaining:
        f.cancel()
    processes = list((getattr(pool, "_processes", None) or {}).values())
    wait(remaining, timeout=STOP_TIMEOUT_S)
    for p in processes:
        p.kill()
    for p in processes:
        p.join(timeout=STOP_TIMEOUT_S)
    pool.shutdown(wait=False, cancel_futures=True)


# how long the study waits for a Ray cluster's address to accept a connection
CLUSTER_TIMEOUT_S = 10.0


NO_RAY = (
    "backend: 'ray' needs the optional dependency ray (pip install 'mpcmobo[ray]'); "
    "allowed without it: 'process'"
)


def check_backend(settings: Settings) -> None:
    """Before a new run writes anything: the Ray backend needs ray installed (else a
    :class:`SettingsError`), and a cluster that ``RAY_ADDRESS`` names must answer, unless the
    caller has joined one already (:func:`check_reachable`)."""
    if settings.backend != "ray":
        return
    if importlib.util.find_spec("ray") is None:
        raise SettingsError(NO_RAY)
    address = os.environ.get("RAY_ADDRESS")
    ray = sys.modules.get("ray")
    if address and not (ray is not None and ray.is_initialized()):
        check_reachable(address)


def check_reachable(address: str) -> None:
    """A :class:`StudyError` where ``RAY_ADDRESS`` names a ``host:port`` (or ``ray://host:port``)
    that accepts no connection within ``CLUSTER_TIMEOUT_S``: Ray itself would wait for it for
    minutes, with nothing but its own retries on the terminal. ``auto`` is left to Ray."""
    import socket

    target = address.removeprefix("ray://")
    host, sep, port = target.rpartition(":")
    if not sep or not port.isdigit():
        return
    try:
        socket.create_connection((host or "127.0.0.1", int(port)), CLUSTER_TIMEOUT_S).close()
    except OSError as err:
        raise StudyError(
            f"RAY_ADDRESS={address}: no Ray cluster answers there ({err}); start it (ray start "
            "--head), or unset RAY_ADDRESS to run the jobs on this machine"
        ) from None


def _run_ray(
    jobs: list[tuple[str, int]], args: dict[str, Any], workers: int, watch: _Watch
) -> None:
    try:
        import ray
    except ImportError:
        raise SettingsError(NO_RAY) from None
    started = not ray.is_initialized()  # a cluster of the study's own, shut down after it
    if started:
        address = os.environ.get("RAY_ADDRESS")
        if address:  # an existing cluster: its own CPUs decide how many jobs run at once
            check_reachable(address)
            ray.init(address=address, ignore_reinit_error=True)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, ignore_reinit_error=True)
        interrupts.reclaim()  # Ray's SIGTERM handler would end the study without a word
    remote = ray.remote(num_cpus=1)(run_job)
    refs = [remote.remote(learner_name=n, seed=s, **args) for n, s in jobs]
    try:
        while refs:
            ready, refs = ray.wait(refs, timeout=0.5)
            watch.poll()
            for r in ready:
                ray.get(r)
    except BaseException:
        with interrupts.deferred():
            for r in refs:  # checkpoints are atomic: a killed task loses its episode only
                ray.cancel(r, force=True)
        raise
    finally:
        if started:  # its processes stop now, not after an interrupted CLI has exited
            with interrupts.deferred():
                ray.shutdown()
