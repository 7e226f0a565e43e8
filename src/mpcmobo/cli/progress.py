"""Progress of a running study on the terminal: rich progress bars, or plain lines for a log."""

from __future__ import annotations

import math
import time
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
)

__all__ = ["Bars", "Lines", "WorkProgress", "fmt", "progress_bars"]


def fmt(x: float | None, digits: int = 5) -> str:
    """A number for a table or a line (``-`` for none)."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.{digits}g}"


def progress_bars(console: Console) -> Progress:
    """Progress bars, one line per job (fed by :class:`Bars`)."""
    return Progress(
        TextColumn("{task.description:<14}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("f1 {task.fields[f1]:>10}"),
        TextColumn("best J_eval {task.fields[best]:>10}"),
        TimeElapsedColumn(),
        console=console,
        transient=False,
    )


class Lines:
    """Plain progress lines for a log (stdout not a terminal: CI, nohup, a scheduler): the
    start, J*, and one line per job every ``every`` episodes and at its last episode."""

    def __init__(self, console: Console, every: int | None = None) -> None:
        self.console = console
        self.every = every
        self.printed: dict[tuple[str, int], int] = {}
        self.t0 = time.perf_counter()

    def _print(self, text: str) -> None:
        elapsed = time.perf_counter() - self.t0
        self.console.print(
            f"[{elapsed:7.0f} s] {text}", markup=False, highlight=False, soft_wrap=True
        )
        self.console.file.flush()

    def __call__(self, event: dict) -> None:
        """Show one of the study's progress events."""
        kind = event.get("kind")
        if kind == "start":
            total = event["episodes"]
            if self.every is None:
                self.every = max(1, min(10, total // 10))
            jobs = ", ".join(f"{n} s{s}" for n, s in event["jobs"])
            self._print(f"study in {event['out_dir']}: {jobs}; {total} episodes each")
        elif kind == "reference":
            if event["status"] == "running":
                self._print("computing J* and J(theta0)")
            else:
                self._print(f"J* = {fmt(event['J_star'])}, J(theta0) = {fmt(event['J_initial'])}")
        elif kind == "episode":
            job, n = (event["learner"], event["seed"]), event["episode"]
            last = self.printed.get(job)
            every = self.every or 1
            due = last is None or n // every > last // every or n == event["episodes"]
            if n == last or not due:
                return
            self.printed[job] = n
            stopped = "" if event.get("exploring", True) else ", exploring stopped"
            self._print(
                f"{event['learner']} s{event['seed']}: episode {n}/{event['episodes']}, "
                f"f1 {fmt(event['f1'])}, best J_eval {fmt(event['best_J_eval'])}{stopped}"
            )


class Bars:
    """Rich progress bars, one per (learner, seed) job, fed by the study's progress events."""

    def __init__(self, progress: Progress) -> None:
        self.progress = progress
        self.tasks: dict[tuple[str, int], TaskID] = {}
        self.ref_task: TaskID | None = None

    def __call__(self, event: dict) -> None:
        """Show one of the study's progress events."""
        kind = event.get("kind")
        if kind == "start":
            for n, s in event["jobs"]:
                self.tasks[(n, s)] = self.progress.add_task(
                    f"{n} s{s}", total=event["episodes"], f1="-", best="-"
                )
        elif kind == "reference":
            if event["status"] == "running":
                self.ref_task = self.progress.add_task("J*, J(theta0)", total=1, f1="", best="")
            elif self.ref_task is not None:
                self.progress.update(self.ref_task, completed=1, best=f"J*={fmt(event['J_star'])}")
        elif kind == "episode":
            task = self.tasks.get((event["learner"], event["seed"]))
            if task is not None:
                name = f"{event['learner']} s{event['seed']}"
                self.progress.update(
                    task,
                    completed=event["episode"],
                    f1=fmt(event["f1"]),
                    best=fmt(event["best_J_eval"]),
                    description=name if event.get("exploring", True) else f"{name} (stopped)",
                )


class WorkProgress:
    """A learner's long work, ``(what, done, total)`` (``Learner.use_progress``), as a rich
    progress line per ``what`` on a terminal, else as a plain line at every tenth of it; a
    context manager (the line is finished on exit)."""

    def __init__(self, console: Console) -> None:
        self.console = console
        self.live = console.is_terminal
        self.progress = Progress(
            TextColumn("{task.description:<14}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=console,
            transient=False,
        )
        self.tasks: dict[str, TaskID] = {}
        self.shown: dict[str, int] = {}

    def __enter__(self) -> WorkProgress:
        if self.live:
            self.progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.live:
            self.progress.stop()

    def __call__(self, what: str, done: int, total: int) -> None:
        """Show that ``done`` of the ``total`` steps of ``what`` are done."""
        if self.live:
            if what not in self.tasks:
                self.tasks[what] = self.progress.add_task(what, total=total)
            self.progress.update(self.tasks[what], completed=done, total=total)
            return
        tenth = done * 10 // max(total, 1)
        if self.shown.get(what) != tenth:
            self.shown[what] = tenth
            self.console.print(f"{what}: {done}/{total}", markup=False, highlight=False)


class Waiting:
    """What a command waits for (the tuner's process learning, ``mpcmobo serve``): a spinner
    with the latest text on a terminal, else a plain line each time the text changes; a
    context manager, called with the text."""

    def __init__(self, console: Console) -> None:
        self.console = console
        self.status: Any = None
        self.last = ""

    def __enter__(self) -> Waiting:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.status is not None:
            self.status.stop()

    def __call__(self, text: str) -> None:
        """Show that the process is doing ``text``."""
        if text == self.last:
            return
        self.last = text
        if not self.console.is_terminal:
            self.console.print(f"waiting: {text}", markup=False, highlight=False)
        elif self.status is None:
            self.status = self.console.status(text)
            self.status.start()
        else:
            self.status.update(text)
