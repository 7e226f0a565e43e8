"""What ``Tuner.status()`` says beyond the deployed theta: the trials, their cost, what to do.

:func:`trial_table` gives one entry per told trial: its ``role`` (``deployed``: it ran the
theta deployed before it; ``verification``: it ran a theta an earlier trial ran, to measure it
again; ``candidate``: a new theta), its start, its plant cost (the episode's mean stage cost),
its excess over the deployed controller from the same start (``None`` until it is predicted),
its verdict (whether its theta was deployed, or is still under verification) and the checks
its log was told despite (``forced``, with ``--force``). :func:`recommendation` says whether
to go on.
:func:`saved_status` reads ``status.json`` (what the tuner wrote after its last ask, tell or
retract) without loading the tuner, if it is as new as the tuner's checkpoint and settings;
a trial whose log is accepted and not learned from yet is said to be learned from only where a
process is (the caller asks the tuner's process, ``mpcmobo serve``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mpcmobo.experiment.price import UNPRICED
from mpcmobo.experiment.records import EpisodeRow


def _same(a: Any, b: Any) -> bool:
    """Whether two thetas are the same (to round-off: a theta through the unit cube and back)."""
    return bool(np.allclose(np.asarray(a, float), np.asarray(b, float), rtol=1e-9, atol=1e-12))


def _finite(v: float) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None


def trial_table(
    rows: Sequence[EpisodeRow],
    theta0: np.ndarray,
    start_mode: str,
    n_cycle_starts: int,
    forced: dict[int, list[str]] | None = None,
    verifying: np.ndarray | None = None,
) -> list[dict[str, Any]]:
    """One entry per told trial (module docstring); ``forced``: per trial whose log was told
    with ``--force``, the checks it was accepted despite (``forced`` in its entry, and said in
    its verdict); ``verifying``: the candidate the learner is still gathering episodes of (its
    trials' verdict: under verification)."""
    forced = forced or {}
    out = []
    before = np.asarray(theta0, float)
    for i, row in enumerate(rows):
        theta = np.asarray(row.theta, float)
        after = np.asarray(row.incumbent, float)
        if _same(theta, before):
            role = "deployed"
        elif any(_same(theta, r.theta) for r in rows[:i]):
            role = "verification"
        else:
            role = "candidate"
        later = next((r.episode for r in rows[i:] if _same(r.incumbent, theta)), None)
        if role == "deployed":
            verdict = "ran the deployed theta"
        elif later == row.episode:
            verdict = "deployed"
        elif later is not None:
            verdict = f"deployed after trial {later}"
        elif verifying is not None and _same(theta, verifying):
            verdict = "under verification"
        else:
            verdict = "not deployed"
        if row.error:
            verdict = f"{verdict}; error: {row.error}"
        despite = forced.get(int(row.episode), [])
        if despite:
            verdict = f"{verdict}; its log accepted with --force despite: {', '.join(despite)}"
        out.append(
            {
                "id": int(row.episode),
                "role": role,
                "start": int(row.episode % n_cycle_starts) if start_mode == "cycle" else None,
                "x0": [float(v) for v in row.x0],
                "plant_cost": _finite(row.plant_cost),
                "excess_cost": _finite(row.excess_cost),
                "verdict": verdict,
                "forced": list(despite),
            }
        )
        before = after
    return out


def cumulative(trials: list[dict[str, Any]], key: str) -> float | None:
    """The sum of ``key`` over the trials (None if a trial has none, or there is no trial)."""
    values = [t[key] for t in trials]
    if not values or any(v is None for v in values):
        return None
    return float(sum(values))


def recommendation(
    told: int,
    budget: int,
    pending: int | None,
    quarantined: list[int],
    directory: str,
    converged: str = "",
    learning: int | None = None,
    verifying: bool = False,
    learns: bool = True,
) -> dict[str, str]:
    """``action`` (``continue`` or ``stop``) and ``reason``; ``converged``: why tuning stopped
    exploring ("": it has not; :mod:`mpcmobo.experiment.price`); ``learning``: the told trial
    whose accepted log the learner has not learned from yet, None if none, and ``learns``:
    whether a process is learning from it now (:func:`learning_reason`); ``verifying``: a
    candidate is under verification (not yet deployed or dropped)."""
    if learning is not None:
        return learning_reason(learning, budget, directory, learns)
    if converged and (pending is None or pending not in quarantined):
        # a model that cannot price a candidate stopped exploring; it did not converge
        stopped, theta = (
            ("stopped exploring", "kept") if UNPRICED in converged else ("converged", "the result")
        )
        return {
            "action": "stop",
            "reason": (
                f"tuning has {stopped}: {converged}. The deployed theta is {theta} (mpcmobo "
                f"export {directory}); further trials run it without exploration (another "
                f"exploration budget opens exploring again: mpcmobo ask {directory} "
                "--exploration-budget B)"
            ),
        }
    if told >= budget and verifying:
        return {
            "action": "stop",
            "reason": (
                f"the budget of {budget} trials is spent while a candidate is under "
                f"verification: it is not deployed yet, and a larger budget lets its "
                f"verification finish (mpcmobo ask {directory} --episodes N); without it the "
                f"deployed theta is the result (mpcmobo export {directory})"
            ),
        }
    if told >= budget:
        return {
            "action": "stop",
            "reason": (
                f"the budget of {budget} trials is spent: the deployed theta is the result "
                f"(mpcmobo export {directory}); a larger budget goes on (mpcmobo ask "
                f"{directory} --episodes N)"
            ),
        }
    if pending is not None and pending in quarantined:
        reason = (
            f"trial {pending}'s log is quarantined (quarantine/trial-{pending}.json says why): "
            f"tell a corrected log, or accept it with mpcmobo tell {directory} {pending} --force"
        )
    elif pending is not None:
        reason = f"trial {pending} is pending: run it on the plant and tell its log"
    else:
        reason = f"{told} of {budget} trials told: ask for the next trial"
    return {"action": "continue", "reason": reason}


def learning_reason(learning: int, budget: int, directory: str, learns: bool) -> dict[str, str]:
    """The recommendation while trial ``learning``'s log is accepted and not learned from yet:
    a process learns from it now (``learns``: the tuner's, ``mpcmobo serve``), or none does
    (the command that told it stopped before it learned) and the next command that loads the
    tuner learns from it, named."""
    last = learning + 1 >= budget
    result = (
        f"then the deployed theta is the result (mpcmobo export {directory}); a larger budget "
        f"goes on (mpcmobo ask {directory} --episodes N)"
    )
    if learns:
        told = f"trial {learning} is told and the tuner's process is learning from it"
        if last:
            told = (
                f"trial {learning}, the last of the budget of {budget} trials, is told and the "
                "tuner's process is learning from it"
            )
        then = result if last else f"mpcmobo ask {directory} prints the next trial when it is ready"
        return {"action": "stop" if last else "continue", "reason": f"{told}: {then}"}
    told = (
        f"trial {learning} is told: its log is accepted (accepted/trial-{learning}.pkl) and not "
        "learned from yet, and no process is learning from it (the command that told it "
        "stopped before it learned, or Tuner.accept() without Tuner.learn()); Tuner.learn() or "
        "the next command that loads the tuner (ask, tell, serve) learns from it"
    )
    if last:
        then = f"mpcmobo ask {directory} learns from it and says the budget is spent; {result}"
    else:
        then = f"mpcmobo ask {directory} learns from it and prints the next trial"
    return {"action": "continue", "reason": f"{told}: {then}"}


# the keys of Tuner.status() that ``mpcmobo status`` reads
STATUS_KEYS = frozenset(
    (
        "learner",
        "told",
        "budget",
        "pending",
        "trials",
        "quarantined",
        "plant_cost",
        "excess_cost",
        "recommendation",
        "exploration",
        "deployed",
        "deployed_episodes",
        "evidence",
        "changes_of_deployed",
        "J_eval",
        "J_star",
        "J_initial",
        "identification",
    )
)


def saved_status(
    directory: str | Path, learns: Callable[[Path], bool] | None = None
) -> dict[str, Any] | None:
    """``Tuner.status()`` of the tuner in ``directory`` as its ``status.json`` holds it (NaN
    as None), with the recommendation naming ``directory`` as given; None where the file is
    missing, unreadable, of other keys, or older than the tuner's settings or a checkpoint of
    its job (written by an interrupted tell, or the budget extended since): then the tuner must
    be loaded to say it. Where it names a trial whose accepted log is not learned from yet (or
    the pending trial's log is in ``accepted/``: kept by a process killed before it wrote the
    file again), ``learns(directory)`` says whether a process is learning from it now (None:
    none is; the file cannot tell a process that learns from one that was killed)."""
    path = Path(directory)
    status, mark = path / "status.json", path / "tuner.json"
    if not (status.is_file() and mark.is_file()):
        return None
    try:
        written = status.stat().st_mtime_ns
        newer = [path / "config.toml", *path.glob("jobs/*/checkpoint*.pkl")]
        if any(p.stat().st_mtime_ns > written for p in newer):
            return None
        st = json.loads(status.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(st, dict) or not STATUS_KEYS <= set(st):
        return None
    kept = kept_unsaid(st, path)
    if kept is not None:
        st["learning"] = kept
    return with_recommendation(st, path, learns)


def kept_unsaid(st: dict[str, Any], path: Path) -> int | None:
    """The pending trial of the status ``st`` (``status.json``'s) where its log is in
    ``accepted/`` of the tuner in ``path`` and ``st`` does not say so: kept by a process killed
    before it wrote the file again (the next load learns from it). None otherwise."""
    pending = st.get("pending")
    if st.get("learning") is not None or pending is None:
        return None
    return int(pending) if (path / "accepted" / f"trial-{pending}.pkl").is_file() else None


def with_recommendation(
    st: dict[str, Any], path: Path, learns: Callable[[Path], bool] | None
) -> dict[str, Any]:
    """The status ``st`` (``status.json``'s) with its recommendation made again for the tuner
    in ``path`` as given; where it names a log accepted and not learned from yet,
    ``learns(path)`` says whether a process learns from it now (None: none does)."""
    converged = (st["exploration"] or {}).get("converged") or ""
    learning = st.get("learning")
    st["recommendation"] = recommendation(
        st["told"],
        st["budget"],
        st["pending"],
        st["quarantined"],
        str(path),
        converged,
        learning,
        bool(st.get("verifying")),
        learning is not None and learns is not None and learns(path),
    )
    return st
