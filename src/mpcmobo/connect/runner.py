"""One trial on the plant, period by period: read the states, compute the input, write it, log.

Every period starts on the clock (``t0 + k * period``): one batched read (the states and the
enable node), the checks (the enable on, every state's source timestamp advancing), the
controller's input plus the trial's exploration noise, clipped to the input bounds, one batched
write, a row of the log. The MPC is solved in a worker thread, warm-started from its previous
solve; a solve that is not done ``solve_budget * period`` after the read is not waited for: the
input written is the last plan's input for this period (the MPC's fallback, its previous plan
shifted), and the next period solves again once the worker is free. After the last input, one
more period later, the last state is read. A fault raises :class:`Aborted` with the log so far.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import numpy as np

from mpcmobo.connect.client import PlantClient, PlantFault, Reading
from mpcmobo.connect.nodes import NodeMap
from mpcmobo.experiment.tuner import Trial
from mpcmobo.systems.base import System

__all__ = ["Aborted", "Controller", "TrialLog", "run_trial"]


@dataclass
class TrialLog:
    """The log of a trial: per step the state read, the input written (none after the last
    state), the time of the read from the trial's start, the read-to-write latency and its
    parts (the read, the solve, the write; seconds) and whether the input is the previous
    plan's (``fallback``)."""

    system: System
    rows: list[dict[str, float]] = field(default_factory=list)

    def add(self, x: np.ndarray, u: np.ndarray | None, **extra: float) -> None:
        """One step's row."""
        row = dict(zip(self.system.state_names, map(float, x)))
        nan = np.full(self.system.nu, np.nan)
        row.update(zip(self.system.input_names, map(float, nan if u is None else u)))
        row.update(extra)
        self.rows.append(row)

    @property
    def complete(self) -> bool:
        """Whether the log holds the whole episode a tuner can take (``steps + 1`` states)."""
        return bool(self.rows) and np.isnan(self.rows[-1][self.system.input_names[0]])

    def frame(self) -> Any:
        """The log as a DataFrame in the format ``tell`` reads, with the extra columns."""
        import pandas as pd

        return pd.DataFrame(self.rows)

    def latencies(self) -> np.ndarray:
        """The read-to-write times of the periods that wrote an input (seconds)."""
        return np.array([r["latency"] for r in self.rows if np.isfinite(r.get("latency", np.nan))])


class Aborted(Exception):
    """The trial stopped before its end: ``kind`` (a :class:`PlantFault`'s, ``interrupted``,
    or ``error`` for any other exception, chained), the message and the log so far."""

    def __init__(self, kind: str, message: str, log: TrialLog) -> None:
        super().__init__(message)
        self.kind, self.log = kind, log


class Controller:
    """The trial's MPC with a deadline: :meth:`action` gives the input for period ``k`` within
    ``budget`` seconds (the default for :meth:`action`), or the last plan's input for period
    ``k`` (``fallback``)."""

    def __init__(self, trial: Trial, system: System, budget: float) -> None:
        self.trial, self.system, self.budget = trial, system, budget
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mpcmobo-solve")
        self._busy: Future[Any] | None = None
        self._plan: np.ndarray | None = None
        self._plan_step = 0

    def _solve(self, x: np.ndarray, k: int) -> tuple[np.ndarray, float]:
        t = time.perf_counter()
        sol = self.trial.mpc.solve(x, self.trial.theta, sensitivities=False)
        if sol.plan_u is not None and not sol.fallback:
            self._plan, self._plan_step = np.asarray(sol.plan_u, float), k
        return np.asarray(sol.action, float), time.perf_counter() - t

    def prime(self, x: np.ndarray) -> None:
        """Solve once at ``x`` before the clock starts (the first solve is a cold one)."""
        self._solve(x, 0)

    def fallback(self, k: int) -> np.ndarray:
        """The last plan's input for period ``k`` (the MPC's fallback: its plan, shifted)."""
        if self._plan is None:
            return self.trial.mpc.fallback_action()
        age = min(k - self._plan_step, len(self._plan) - 1)
        return self.system.clip_input(self._plan[age])

    def action(
        self, x: np.ndarray, k: int, budget: float | None = None
    ) -> tuple[np.ndarray, bool, float]:
        """(input, whether it is the fallback, solve seconds or NaN) for period ``k``. It
        blocks the event loop for at most ``budget`` seconds (None: the controller's): between
        the read and the write there is nothing else to do, and a thread's wake-up is faster
        than the loop's."""
        budget = self.budget if budget is None else budget
        if self._busy is not None and not self._busy.done():
            return self.fallback(k), True, np.nan
        self._busy = self._pool.submit(self._solve, x, k)
        try:
            u, took = self._busy.result(timeout=max(budget, 0.0))
        except FutureTimeout:
            return self.fallback(k), True, np.nan
        return u, False, took

    def close(self) -> None:
        """Let the worker finish its solve in the background."""
        self._pool.shutdown(wait=False)


class _Staleness:
    """Counts the periods since each state's source timestamp last advanced."""

    def __init__(self, names: Sequence[str], limit: int) -> None:
        self.names, self.limit = names, limit
        self.last: list[datetime | None] = [None] * len(names)
        self.same = [0] * len(names)

    def check(self, stamps: tuple[datetime | None, ...]) -> None:
        for j, stamp in enumerate(stamps):
            if stamp is None:  # a server without timestamps cannot be checked
                continue
            self.same[j] = self.same[j] + 1 if stamp == self.last[j] else 0
            self.last[j] = stamp
            if self.same[j] >= self.limit:
                raise PlantFault(
                    "stale",
                    f"state {self.names[j]} is stale: its source timestamp ({stamp:%H:%M:%S.%f}) "
                    f"has not advanced for {self.same[j]} periods",
                )


async def _sleep_until(loop: asyncio.AbstractEventLoop, t: float) -> None:
    delay = t - loop.time()
    if delay > 0:
        await asyncio.sleep(delay)


async def _period(
    client: PlantClient, ctrl: Controller, stale: _Staleness, log: TrialLog, k: int, at: float
) -> None:
    """Period ``k`` (``at`` seconds into the trial): read, check, compute, write, log; after
    the last input, read and log the last state."""
    t_read = time.perf_counter()
    reading = await client.read()
    read_s = time.perf_counter() - t_read
    if not reading.enabled:
        raise PlantFault("enable", "the operator withdrew the enable: plant handed back")
    stale.check(reading.stamps)
    trial = ctrl.trial
    if k == trial.steps:
        log.add(reading.x, None, time=at, read_time=read_s)
        return
    base, fallback, took = ctrl.action(reading.x, k)
    u = ctrl.system.clip_input(base + trial.noise[k])
    t_write = time.perf_counter()
    u = await client.write(u)  # as written: an integer node rounds it
    done = time.perf_counter()
    log.add(
        reading.x,
        u,
        time=at,
        latency=done - t_read,
        read_time=read_s,
        solve_time=took,
        write_time=done - t_write,
        fallback=float(fallback),
    )


async def run_trial(
    client: PlantClient, trial: Trial, nodes: NodeMap, period: float, first: Reading
) -> TrialLog:
    """Run ``trial`` from the state ``first`` (read at its start); the complete log, or
    :class:`Aborted` with the log so far."""
    system = client.system
    log = TrialLog(system)
    ctrl = Controller(trial, system, nodes.solve_budget * period)
    stale = _Staleness(system.state_names, nodes.stale_periods)
    loop = asyncio.get_running_loop()
    try:
        stale.check(first.stamps)
        ctrl.prime(first.x)
        t0 = loop.time()
        for k in range(trial.steps + 1):
            await _sleep_until(loop, t0 + k * period)
            await _period(client, ctrl, stale, log, k, loop.time() - t0)
    except PlantFault as fault:
        raise Aborted(fault.kind, str(fault), log) from None
    except asyncio.CancelledError:
        raise Aborted("interrupted", "interrupted", log) from None
    except Exception as err:  # a bug or an MPC error: the plant is handed back all the same
        raise Aborted("error", f"{type(err).__name__}: {err}", log) from err
    finally:
        ctrl.close()
    return log
