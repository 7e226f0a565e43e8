"""Trials on a live plant over OPC UA, driven by a :class:`~mpcmobo.experiment.tuner.Tuner`.

:func:`run_plant` connects to the server (a :class:`~mpcmobo.connect.nodes.ConnectError` if it
cannot), then per trial: ask, read where the plant is, run the trial
(:func:`~mpcmobo.connect.runner.run_trial`), write its log to ``DIR/trials/<id>/log.csv``
and tell it. A trial starts where the plant is; under ``start_mode = "cycle"`` the plant must
be at the trial's ``x0`` already (else a ``ConnectError`` before anything is written). When a
fault aborts a trial its log so far is kept (``aborted-<n>.csv``, with a JSON note of why), the
trial is not told (the next ``ask`` gives it again) and the run ends after the tool lets go of
the plant: it writes the safe input, after a lost connection once the server answers again
(within ``reconnect_timeout``). It lets go the same way after the last trial and on Ctrl-C,
which then raises ``KeyboardInterrupt``. ``dry_run`` reads and computes, writes nothing and
tells nothing (``dry-run-<n>.csv``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import signal
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mpcmobo.connect.client import PlantClient, PlantFault, Reading, public_url
from mpcmobo.connect.nodes import ConnectError, NodeMap, load_nodes
from mpcmobo.connect.runner import Aborted, TrialLog, run_trial
from mpcmobo.experiment import storage
from mpcmobo.experiment.checks import reading_problem
from mpcmobo.experiment.tuner import START_TOLERANCE, Trial, Tuner, TunerError

__all__ = ["Outcome", "PlantInterrupted", "run_plant"]


class PlantInterrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM (``signal_name``) stopped :func:`run_plant`; the message says whether
    the safe input is written and what became of the trials: the one in progress is aborted
    (its log kept) and not told; between trials, every trial run is told."""

    def __init__(self, message: str, signal_name: str = "SIGINT") -> None:
        super().__init__(message)
        self.signal_name = signal_name


@dataclass(frozen=True)
class Outcome:
    """What became of one trial: ``status`` ``told``, ``aborted`` or ``dry-run``, its log on
    disk, the message (why it was aborted), the told episode's f1 and the read-to-write
    latencies (seconds) of its periods."""

    trial: int
    status: str
    log: Path
    message: str = ""
    f1: float | None = None
    latencies: tuple[float, ...] = ()
    fallbacks: int = 0

    def timing(self, period: float) -> str:
        """The read-to-write times and the fallbacks in a line."""
        if not self.latencies:
            return "no input written"
        p99 = float(np.percentile(self.latencies, 99))
        return (
            f"read to write {np.median(self.latencies) * 1e3:.1f} ms median, {p99 * 1e3:.1f} ms "
            f"p99 ({p99 / period:.0%} of the period), {self.fallbacks} previous-plan inputs"
        )


def run_plant(
    tuner: Tuner,
    url: str,
    nodes: NodeMap | str | Path,
    period: float,
    trials: int = 1,
    dry_run: bool = False,
    echo: Callable[[str], None] | None = None,
) -> list[Outcome]:
    """Run ``trials`` trials of ``tuner`` on the plant at ``url`` (module docstring); the
    outcomes, the last one ``aborted`` if a fault stopped the run."""
    if not period > 0:
        raise ConnectError(f"--period must be positive (seconds), got {period}")
    if trials < 1:
        raise ConnectError(f"--trials must be at least 1, got {trials}")
    if not isinstance(nodes, NodeMap):
        nodes = load_nodes(nodes, tuner.system)
    else:
        nodes.check(tuner.system)
    session = _Session(tuner, url, nodes, period, dry_run, echo or (lambda _: None))
    quiet = logging.getLogger("asyncua")  # its notes (a session timeout granted) are not ours
    level = quiet.level
    quiet.setLevel(max(level, logging.ERROR))
    try:
        return asyncio.run(session.run(trials))
    except (KeyboardInterrupt, asyncio.CancelledError):  # Ctrl-C; SIGTERM cancels the run
        said = f"{session.handed_back}; {session.trials_said()}"
        raise PlantInterrupted(said, session.signal_name) from None
    finally:
        quiet.setLevel(level)


class _Session:
    """One connection to the plant and the trials run over it."""

    def __init__(
        self,
        tuner: Tuner,
        url: str,
        nodes: NodeMap,
        period: float,
        dry_run: bool,
        echo: Callable[[str], None],
    ) -> None:
        self.tuner, self.nodes, self.period = tuner, nodes, period
        self.dry_run, self.echo = dry_run, echo
        self.client = PlantClient(url, nodes, tuner.system, dry_run)
        self.wrote = False  # whether this session has written to the plant
        self.handed_back = "nothing was written to the plant"
        self.in_progress: int | None = None  # the trial started and not yet told or aborted
        self.told: list[int] = []  # the trials this session told
        self.signal_name = "SIGINT"  # what stopped the run, if a signal did

    def trials_said(self) -> str:
        """What became of the trials, for a Ctrl-C's message."""
        told = f" (told: {', '.join(map(str, self.told))})" if self.told else ""
        if self.in_progress is None:
            return f"no trial was in progress{told}"
        where = self.tuner.run_dir.path / "trials" / str(self.in_progress)
        return (
            f"trial {self.in_progress}, in progress, is not told (its log is kept under "
            f"{where}); connect again to run it{told}"
        )

    def _on_sigterm(self, task: asyncio.Task) -> None:
        """SIGTERM (a service manager, ``kill``) stops the run as Ctrl-C does: the trial in
        progress is aborted and the plant handed back."""
        self.signal_name = "SIGTERM"
        task.cancel()

    async def run(self, trials: int) -> list[Outcome]:
        task = asyncio.current_task()
        if task is not None:  # a platform without signal handlers in the loop keeps SIGTERM's
            with contextlib.suppress(NotImplementedError, RuntimeError):
                asyncio.get_running_loop().add_signal_handler(
                    signal.SIGTERM, self._on_sigterm, task
                )
        await self.client.open()
        outcomes: list[Outcome] = []
        try:
            for _ in range(trials):
                if outcomes and self.tuner.episodes >= self.tuner.settings.episodes:
                    self.echo(
                        f"the tuner's budget of {self.tuner.settings.episodes} trials is spent"
                    )
                    break
                outcome = await self._trial(self.tuner.ask())
                outcomes.append(outcome)
                if outcome.status == "aborted":
                    return outcomes
            await self._let_go("")
            return outcomes
        except BaseException:  # Ctrl-C (cancelled), a log refused: hand the plant back first
            self.handed_back = (await self._let_go("")).lstrip("; ") or self.handed_back
            raise
        finally:
            await self.client.close()

    async def _trial(self, trial: Trial) -> Outcome:
        first = await self._start(trial)
        self.in_progress = trial.id
        outcome = await self._run(trial, first)
        self.in_progress = None
        if outcome.status == "told":
            self.told.append(trial.id)
        return outcome

    async def _run(self, trial: Trial, first: Reading) -> Outcome:
        trial.restart()
        self.echo(f"trial {trial.id}: {trial.steps} periods of {self.period:g} s")
        self.wrote = self.wrote or not self.dry_run
        try:
            log = await run_trial(self.client, trial, self.nodes, self.period, first)
        except Aborted as ab:
            handed = await self._let_go(ab.kind)  # the plant first, then the log to disk
            if ab.kind == "interrupted":
                self.handed_back = handed.lstrip("; ") or self.handed_back
                self._save(trial, ab.log, "aborted", f"{ab} ({self.signal_name})")
                raise asyncio.CancelledError from None
            path = self._save(trial, ab.log, "aborted", str(ab))
            message = f"trial {trial.id} aborted: {ab} (log so far: {path}); it is not told"
            return Outcome(trial.id, "aborted", path, message + handed, None, *_timing(ab.log))
        if self.dry_run:
            path = self._save(trial, log, "dry-run", "")
            return Outcome(trial.id, "dry-run", path, "", None, *_timing(log))
        path = self._save(trial, log, "log", "")
        names = [*self.tuner.system.state_names, *self.tuner.system.input_names, "fallback"]
        try:
            row = self.tuner.tell(trial, log.frame().reindex(columns=names))
        except TunerError as err:
            said = str(err)
            head = "" if said.startswith(f"trial {trial.id}") else f"trial {trial.id}: "
            raise TunerError(
                f"{head}{said} (the log {path} is kept; the trial stays pending: connect again "
                f"to run it anew, or tell that log with mpcmobo tell {self.tuner.run_dir.path} "
                f"{trial.id} {path} --force where the checks are wrong)"
            ) from None
        outcome = Outcome(trial.id, "told", path, "", float(row.f1), *_timing(log))
        self.echo(
            f"trial {trial.id} told: plant cost {row.plant_cost:.6g} (f1 {row.f1:.6g}); "
            f"{outcome.timing(self.period)}"
        )
        late = sum(latency > self.period for latency in outcome.latencies)
        if late:
            self.echo(
                f"warning: in {late} of trial {trial.id}'s periods the input was written more "
                f"than a period ({self.period:g} s) after the read: a longer period, or a "
                "smaller solve_budget (the previous plan's input sooner)"
            )
        return outcome

    async def _start(self, trial: Trial) -> Reading:
        """The plant's state at the trial's start, checked: the enable on and, under cycled
        starts, the plant at the trial's ``x0``."""
        try:
            first = await self.client.read()
        except PlantFault as fault:
            raise ConnectError(f"trial {trial.id} not started: {fault}") from None
        if not first.enabled:
            raise ConnectError(
                f"trial {trial.id} not started: the enable node {self.nodes.enable} is off "
                "(the operator has not handed the plant over)"
            )
        s = self.tuner.system
        implausible = reading_problem(s, first.x)
        if implausible is not None:
            raise ConnectError(
                f"trial {trial.id} not started: the plant's reading is not a state of the "
                f"system ({implausible}): check the node map's scale and offset of that state "
                "(a unit error?); nothing is written"
            )
        scale = np.asarray(s.x_scale, float)
        off = np.abs(first.x - trial.x0) / scale
        if self.tuner.settings.start_mode == "cycle" and np.any(off > START_TOLERANCE):
            j = int(np.argmax(off))
            raise ConnectError(
                f"trial {trial.id} not started: the plant is at {s.state_names[j]} = "
                f"{first.x[j]:.6g}, the trial starts at {trial.x0[j]:.6g}; the tuner compares "
                "thetas from the same starts (start_mode = 'cycle'), so bring the plant to the "
                f"trial's x0 (within {START_TOLERANCE:g} x_scale: {list(map(float, trial.x0))}) "
                "first, or tune with start_mode = 'random' (a new connect tuner's default)"
            )
        return first

    async def _let_go(self, kind: str) -> str:
        """Write the safe input (after a lost connection, once the server answers again);
        what the message should add if that fails."""
        if not self.wrote or self.dry_run:
            return ""
        if kind == "connection" and not await self._reconnect():
            return (
                f"; the server did not answer again within {self.nodes.reconnect_timeout:g} s: "
                "the safe input is NOT written (the plant holds the last input; its watchdog "
                "on the heartbeat node must take over)"
            )
        try:
            await self.client.write(self.nodes.safe(self.tuner.system), beat=False)
        except PlantFault as fault:
            return f"; writing the safe input failed too: {fault}"
        self.wrote = False
        return "; the safe input is written"

    async def _reconnect(self) -> bool:
        """Open the session again, retrying every period until ``reconnect_timeout``."""
        await self.client.close()
        loop = asyncio.get_running_loop()
        end = loop.time() + self.nodes.reconnect_timeout
        while True:
            try:
                await self.client.open()
                return True
            except ConnectError:
                if loop.time() >= end:
                    return False
                await asyncio.sleep(self.period)

    def _save(self, trial: Trial, log: TrialLog, status: str, message: str) -> Path:
        """Write the log (CSV, ``tell``'s format) and its note next to the trial."""
        where = self.tuner.run_dir.path / "trials" / str(trial.id)
        where.mkdir(parents=True, exist_ok=True)
        name = "log" if status == "log" else _free(where, status)
        path = storage.atomic_write_text(where / f"{name}.csv", log.frame().to_csv(index=False))
        note: dict[str, Any] = {
            "status": "complete" if status == "log" else status,
            "message": message,
            "url": public_url(self.client.url),
            "period": self.period,
            "dry_run": self.dry_run,
            "nodes": self.nodes.model_dump(mode="json", exclude={"security"}),
        }
        storage.atomic_write_text(where / f"{name}.json", json.dumps(note, indent=1) + "\n")
        return path


def _free(where: Path, stem: str) -> str:
    """The first ``stem-<n>`` without a log in ``where``."""
    n = 1
    while (where / f"{stem}-{n}.csv").exists():
        n += 1
    return f"{stem}-{n}"


def _timing(log: TrialLog) -> tuple[tuple[float, ...], int]:
    lat = tuple(float(v) for v in log.latencies())
    return lat, sum(int(r.get("fallback", 0) == 1.0) for r in log.rows)
