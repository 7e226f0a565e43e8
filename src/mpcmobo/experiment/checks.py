"""A told log checked before it is believed: units, time order, the model, the controller.

A log that parses is not yet an episode of the trial. :func:`box_problems` compares each state
column with the system's box (a column far outside it, or one that a factor 10, 100 or 1000
or another temperature scale brings into it, is a unit error); :func:`order_problems` looks
for a log in reverse time order (a ``time`` column that decreases, or that repeats a row next
to a missing one, or transitions the model explains far better read backwards);
:func:`input_problems` compares the applied inputs with the trial's controller plus its
exploration noise, clipped, at the logged states (an operator override, shuffled rows, another
trial's log); :func:`model_problems` compares the episode's one-step prediction error under
the current model (the identified one, else the MPC's nominal model) with the episodes told
before (a robust z-score of the per-episode RMS scaled residuals). Each finding is a
:class:`Problem` naming the check, the column or the steps; the tuner quarantines the episode
(:mod:`mpcmobo.experiment.tuner`), or refuses it outright where the finding is not
``forceable`` (a state it is sure is in the wrong unit, or far outside its box).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mpcmobo.experiment.plantlog import describe_gaps, time_gaps
from mpcmobo.mpc import EpisodeRecord, ParametricMPC, replay
from mpcmobo.mpc.export import controller_inputs
from mpcmobo.systems.base import System

# a state more than this many box widths outside its box is not a state of the plant
FAR_WIDTHS = 3.0
# a state this many box widths outside its box that a power of ten brings into it: a unit error
UNIT_OUTSIDE = 0.5
UNIT_FACTORS = (10.0, 100.0, 1000.0)
# the factors a unit error is looked for at: the powers of ten above and their inverses
POWERS_OF_TEN = (*UNIT_FACTORS, *(1 / f for f in UNIT_FACTORS))
# an applied input further than this fraction of its span from the controller plus its noise
INPUT_TOLERANCE = 0.005
# an episode whose one-step error exceeds this many times the median of the episodes before it
# (and by ROBUST_Z robust standard deviations) is not explained by the model
EPISODE_RATIO = 5.0
ROBUST_Z = 5.0
MIN_HISTORY = 3  # episodes told before the comparison is made
RESIDUAL_FLOOR = 1e-3  # scaled one-step errors below this are never an outlier
# a log whose one-step error read backwards is below this fraction of its error as given
REVERSE_RATIO = 0.2
STEP_RATIO = 20.0  # a step whose error exceeds this many times the episode's median


@dataclass(frozen=True)
class Problem:
    """One finding: the ``check`` ("range", "time_order", "inputs", "model", "start"), the
    ``message`` naming what is wrong, the log's ``steps`` (rows from 0) it concerns, and
    whether ``force`` may accept the log despite it (not: a state the tool is sure is in the
    wrong unit, or far outside its box)."""

    check: str
    message: str
    steps: tuple[int, ...] = ()
    forceable: bool = True

    def to_dict(self) -> dict[str, Any]:
        """The finding as plain data (a quarantined trial's json)."""
        return {"check": self.check, "message": self.message, "steps": list(self.steps)}


def describe_steps(steps: Sequence[int]) -> str:
    """``[3, 4, 5, 9]`` as ``"3-5, 9"``."""
    out: list[str] = []
    for run in _runs(steps):
        out.append(str(run[0]) if len(run) == 1 else f"{run[0]}-{run[-1]}")
    return ", ".join(out)


def _runs(steps: Sequence[int]) -> list[list[int]]:
    """The consecutive runs of the sorted ``steps``."""
    runs: list[list[int]] = []
    for k in sorted(int(s) for s in steps):
        if runs and k == runs[-1][-1] + 1:
            runs[-1].append(k)
        else:
            runs.append([k])
    return runs


def _box(system: System) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each state's box (lower, upper) and its width (twice x_scale where it is infinite)."""
    lo, hi = np.asarray(system.x_lb, float), np.asarray(system.x_ub, float)
    width = hi - lo
    scale = np.asarray(system.x_scale, float)
    width = np.where(np.isfinite(width) & (width > 0), width, 2 * scale)
    return lo, hi, width


def box_problems(
    system: System, states: np.ndarray, start: np.ndarray | None = None
) -> list[Problem]:
    """Each state column against the system's box: far outside it, or outside it by a factor
    that a power of ten undoes, or in another temperature scale (the column's unit is named as
    the likely error; ``start``, the trial's initial state, tells apart the factors that all
    bring the column into the box: :func:`unit_factor`). A finding the tool is sure of (the
    column far outside its box, or a conversion that brings it into its box and its first
    value to the trial's start) is not ``forceable``: the log is refused, the conversion
    named."""
    X = np.asarray(states, float)
    lo, hi, width = _box(system)
    problems = []
    for j, name in enumerate(system.state_names):
        x = X[:, j]
        out = _widths_outside(x, lo[j], hi[j], width[j])
        worst = int(np.argmax(out))
        if out[worst] <= UNIT_OUTSIDE:
            continue
        where = (
            f"state {name} = {x[worst]:.6g} at step {worst} is outside its bounds "
            f"[{lo[j]:.6g}, {hi[j]:.6g}] by {out[worst]:.3g} box widths"
        )
        steps = tuple(int(k) for k in np.flatnonzero(out > UNIT_OUTSIDE))
        found = _column_unit(name, x, (lo[j], hi[j], width[j]), None if start is None else start[j])
        if found is None and out[worst] <= FAR_WIDTHS:
            continue
        far = bool(out[worst] > FAR_WIDTHS)
        if found is None:
            message = (
                f"{where}, far outside its bounds (more than {FAR_WIDTHS:g} widths), not a state "
                f"of the plant: check the log's units and columns (is {name} the right column?), "
                f"correct the log and tell it again; {NOT_FORCED}"
            )
            problems.append(Problem("range", message, steps, forceable=False))
            continue
        text, sure = found
        sure = sure or far
        then = f"; {NOT_FORCED}" if sure else ""
        problems.append(Problem("range", f"{where}; {text}{then}", steps, forceable=not sure))
    return problems


def reading_problem(system: System, x: np.ndarray) -> str | None:
    """What makes one reading of the plant's states ``x`` (a live plant's, before anything is
    written to it) not a state of the system, as :func:`box_problems` judges a log's column:
    a state outside its bounds by more than half its box's width that a unit error explains,
    or one more than :data:`FAR_WIDTHS` widths outside; None where every state is plausible."""
    lo, hi, width = _box(system)
    found = []
    for j, name in enumerate(system.state_names):
        out = float(_widths_outside(np.asarray(x[j], float), lo[j], hi[j], width[j]))
        if out <= UNIT_OUTSIDE:
            continue
        unit = unit_factor(np.array([x[j]], float), lo[j], hi[j], width[j])
        if unit is None and out <= FAR_WIDTHS:
            continue
        hint = "" if unit is None else f" ({unit_fix(unit)} it lies in its box)"
        found.append(
            f"{name} = {x[j]:.6g} is outside its bounds [{lo[j]:.6g}, {hi[j]:.6g}] by "
            f"{out:.3g} box widths{hint}"
        )
    return "; ".join(found) or None


# what a refusal the tool is sure of says of --force
NOT_FORCED = (
    "--force does not accept a log with a state in the wrong unit or far outside its box "
    "(if the plant was there, the system's bounds x_lb, x_ub do not hold it: widen them)"
)


def _column_unit(
    name: str, x: np.ndarray, box: tuple[float, float, float], start: float | None
) -> tuple[str, bool] | None:
    """The unit error of the state column ``x`` named ``name`` outside its ``box`` (lower,
    upper, width): another temperature scale (:func:`temperature_scale`, which the trial's
    ``start`` confirms) or a power of ten (:func:`unit_factor`), in words with the conversion
    to apply, and whether the tool is sure of it (the converted column starts within 5% of the
    box's width of ``start``); None: neither brings the column into its box."""
    lo, hi, width = box
    scale = None if start is None else temperature_scale(x, lo, hi, width, start)
    if scale is not None:
        return (
            f"the log's {name} looks like {scale[0]} ({scale[1]} brings the column into its "
            f"box and to the trial's start): a unit error; convert the column ({scale[1]}) "
            "and tell the log again",
            True,
        )
    unit = unit_factor(x, lo, hi, width, start)
    if unit is None:
        return None
    fix = unit_fix(unit)
    sure = start is not None and abs(x[0] / unit - start) <= 0.05 * width
    text = (
        f"{fix}, the column lies in its box: a unit error? (the log's {name} looks "
        f"{looks_off_by(unit)}, e.g. mm for cm, or in another unit or with an offset, e.g. "
        "kelvin or Fahrenheit for Celsius; far outside its bounds as logged)"
    )
    if sure:
        text = (
            f"{fix}, the column lies in its box and starts at the trial's start: a unit error "
            f"(the log's {name} looks {looks_off_by(unit)}, e.g. mm for cm); convert the "
            f"column ({fix}) and tell the log again"
        )
    return text, sure


def _widths_outside(x: np.ndarray, lo: float, hi: float, width: float) -> np.ndarray:
    """How far each value of ``x`` lies outside [lo, hi], in box ``width``s (0 inside)."""
    return np.maximum(np.maximum(lo - x, x - hi), 0.0) / width


def unit_fix(unit: float) -> str:
    """The conversion that undoes the power of ten ``unit`` (:func:`unit_factor`), in words:
    "divided by 10", "multiplied by 100"."""
    return f"divided by {unit:g}" if unit > 1 else f"multiplied by {1 / unit:g}"


def _inside(y: np.ndarray, lo: float, hi: float, width: float) -> float:
    """The fraction of ``y`` in [lo, hi] with a tenth of its ``width`` to spare."""
    return float(np.mean((y >= lo - 0.1 * width) & (y <= hi + 0.1 * width)))


def unit_factor(
    x: np.ndarray, lo: float, hi: float, width: float, start: float | None = None
) -> float | None:
    """The power of ten (10, 100, 1000 or their inverses) that ``x`` is off by: of those that
    bring 90% of ``x`` into [lo, hi] (with a tenth of its width to spare), the one that brings
    its first value nearest the trial's start ``start`` (where given, of the same sign and
    not 0), else the one that brings the most of ``x`` in (the smaller on a tie). A column of
    small values a thousand times too large is brought in by 100 and 1000 alike: the start
    decides. None: no power of ten brings it in."""
    fits = []
    for f in POWERS_OF_TEN:
        inside = _inside(x / f, lo, hi, width)
        if inside >= 0.9:
            fits.append((f, inside))
    if not fits:
        return None
    if start is not None and start * x[0] > 0:
        return min(fits, key=lambda fit: abs(np.log(x[0] / fit[0] / start)))[0]
    return max(fits, key=lambda fit: fit[1])[0]


# temperature scales a log may be in instead of the system's: what it looks like, how the
# system's value follows from the logged one, and that in words
# (every pair of kelvin, Celsius and Fahrenheit, both ways)
TEMPERATURE_SCALES: tuple[tuple[str, Any, str], ...] = (
    ("kelvin for Celsius", lambda t: t - 273.15, "minus 273.15"),
    ("Celsius for kelvin", lambda t: t + 273.15, "plus 273.15"),
    ("Fahrenheit for Celsius", lambda t: (t - 32.0) * 5.0 / 9.0, "(T - 32) 5/9"),
    ("Celsius for Fahrenheit", lambda t: t * 9.0 / 5.0 + 32.0, "T 9/5 + 32"),
    ("Fahrenheit for kelvin", lambda t: (t - 32.0) * 5.0 / 9.0 + 273.15, "(T - 32) 5/9 + 273.15"),
    ("kelvin for Fahrenheit", lambda t: (t - 273.15) * 9.0 / 5.0 + 32.0, "(T - 273.15) 9/5 + 32"),
)


def temperature_scale(
    x: np.ndarray, lo: float, hi: float, width: float, start: float
) -> tuple[str, str] | None:
    """The temperature scale (:data:`TEMPERATURE_SCALES`) that brings 90% of ``x`` into
    [lo, hi] (a tenth of its width to spare) and its first value within 5% of the width of the
    trial's ``start``, of those that do the one that brings it nearest: what the column looks
    like and the conversion, in words (None: none)."""
    found: list[tuple[float, str, str]] = []
    for looks, convert, words in TEMPERATURE_SCALES:
        y = convert(np.asarray(x, float))
        miss = abs(float(y[0]) - start)
        if _inside(y, lo, hi, width) >= 0.9 and miss <= 0.05 * width:
            found.append((miss, looks, words))
    if not found:
        return None
    _, looks, words = min(found, key=lambda f: f[0])
    return looks, words


def looks_off_by(unit: float) -> str:
    """A column off by the power of ten ``unit``, in words: "10 times too large"."""
    return f"{unit:g} times too large" if unit > 1 else f"{1 / unit:g} times too small"


def start_factor(logged: float, start: float) -> float | None:
    """The power of ten (10, 100, 1000 or their inverses) that a log's first value ``logged``
    is, within 2%, times the trial's start ``start``: a unit error that may keep the column
    inside its box (None: none is)."""
    if start * logged <= 0:
        return None
    for f in POWERS_OF_TEN:
        if abs(logged / start / f - 1.0) <= 0.02:
            return f
    return None


def residuals(system: System, states: np.ndarray, inputs: np.ndarray, params: Any) -> np.ndarray:
    """Per step the RMS over the states of the one-step prediction error of the model with
    ``params``, scaled by x_scale: (T,)."""
    X, U = np.asarray(states, float), np.asarray(inputs, float)
    T = len(U)
    F = system.discrete_step.map(T)
    p = np.repeat(np.asarray(params, float).reshape(-1, 1), T, axis=1)
    pred = np.asarray(F(X[:-1].T, U.T, p), float).T
    scaled = (X[1:] - pred) / np.asarray(system.x_scale, float)
    with np.errstate(over="ignore", invalid="ignore"):
        r = np.sqrt(np.mean(scaled**2, axis=1))
    return np.where(np.isfinite(r), r, np.inf)


def episode_error(system: System, states: np.ndarray, inputs: np.ndarray, params: Any) -> float:
    """The episode's RMS scaled one-step prediction error under the model with ``params``."""
    r = residuals(system, states, inputs, params)
    return float(np.sqrt(np.mean(r**2)))


def order_problems(
    system: System, states: np.ndarray, inputs: np.ndarray, params: Any, time: Any = None
) -> list[Problem]:
    """A log in reverse time order: its ``time`` column (if it has one) decreases or is out of
    order, or repeats a row and misses another (:func:`time_problems`), or the model explains
    its transitions far better read backwards."""
    if time is not None:
        found = time_problems(np.asarray(time, float))
        if found:
            return found
    forward = episode_error(system, states, inputs, params)
    backward = episode_error(system, states[::-1], inputs[::-1], params)
    if forward > RESIDUAL_FLOOR and backward < REVERSE_RATIO * forward:
        return [
            Problem(
                "time_order",
                (
                    f"the log seems to be in reverse time order: the model explains it read backwards "
                    f"(one-step error {backward:.3g}) far better than as given ({forward:.3g}); the "
                    "first row is the episode's start, the last the state after the last input"
                ),
            )
        ]
    return []


def time_problems(t: np.ndarray) -> list[Problem]:
    """A log's time column ``t`` that decreases (a reversed log), does not increase somewhere
    (rows out of order), or repeats a time next to a step about twice the usual one (a row
    written twice and another missing, so the rows between are a step off: the inputs and the
    states there do not belong together). A repeated time alone passes: a coarse clock writes
    one."""
    dt = np.diff(t)
    if len(dt) and np.all(dt < 0):
        return [
            Problem(
                "time_order",
                (
                    "the log is in reverse time order (its time column decreases): sort it by time, "
                    "the first row the episode's start"
                ),
            )
        ]
    if np.any(dt < 0):
        bad = tuple(int(k) + 1 for k in np.flatnonzero(dt < 0))
        return [
            Problem(
                "time_order",
                (
                    f"the log's rows are out of time order at rows {describe_steps(bad)} (its time "
                    "column does not increase there): sort it by time"
                ),
                bad,
            )
        ]
    repeated = [int(k) + 1 for k in np.flatnonzero(dt == 0)]
    gaps = time_gaps(t)
    if not (repeated and gaps):
        return []
    first, last = min(repeated + gaps), max(repeated + gaps)
    return [
        Problem(
            "time_order",
            (
                f"the log's time repeats at row{'s' if len(repeated) > 1 else ''} "
                f"{describe_steps(repeated)} (a row written twice) and a row is missing "
                f"{describe_gaps(t, gaps)}: the rows between are a step off, "
                "their states and inputs do not belong together; drop the repeated row, restore "
                "the missing one from the plant's records and tell the log again"
            ),
            tuple(range(first, last + 1)),
        )
    ]


def input_problems(
    system: System,
    inputs: np.ndarray,
    pi: np.ndarray,
    noise: np.ndarray,
    trial: int,
    exported: Sequence[np.ndarray] = (),
    fallback: np.ndarray | None = None,
) -> list[Problem]:
    """The applied inputs against the trial's controller ``pi`` (at the logged states) plus its
    ``noise``, clipped to the input bounds: the steps that differ by more than
    ``INPUT_TOLERANCE`` of the input's span, and what that suggests. ``exported``: the inputs
    of the trial's exported controller at the logged states (NaN where it failed), one array
    per way of calling it, which may stop at another local minimum: a step that matches any is
    the trial's, and one where the exported controller failed is the user's fallback; so is a
    step the log marks as the controller's fallback (``fallback``: the previous plan's input,
    applied where a solve missed its deadline)."""
    U, pi, noise = (np.asarray(a, float) for a in (inputs, pi, noise))
    lb, ub = np.asarray(system.u_lb, float), np.asarray(system.u_ub, float)
    span = np.where(np.isfinite(ub - lb), ub - lb, 2 * np.asarray(system.u_scale, float))
    expected = np.clip(pi + noise, lb, ub)
    off = np.max(np.abs(U - expected) / span, axis=1)
    for other in exported:
        failed = ~np.all(np.isfinite(other), axis=1)
        differs = np.max(np.abs(U - np.clip(other + noise, lb, ub)) / span, axis=1)
        off = np.where(failed, 0.0, np.minimum(off, differs))
    if fallback is not None:
        off = np.where(fallback, 0.0, off)
    bad = np.flatnonzero(off > INPUT_TOLERANCE)
    if not len(bad):
        return []
    T, steps = len(U), tuple(int(k) for k in bad)
    head = (
        f"the applied inputs differ from trial {trial}'s controller plus its noise (by more "
        f"than {INPUT_TOLERANCE:.1%} of an input's span, up to {np.max(off):.1%})"
    )
    no_noise = np.max(np.abs(U - np.clip(pi, lb, ub)) / span, axis=1) <= INPUT_TOLERANCE
    held = _saturated(U, expected, bad, span)
    if np.any(np.abs(noise) > 0) and np.mean(no_noise) > 0.9:
        why = "the inputs are the controller's without the trial's noise: add trial.noise[k]"
    elif held is not None:
        j, value, side = held
        why = (
            f"at steps {describe_steps(steps)} the applied {system.input_names[j]} stays at "
            f"{value:g} where the controller asked {side}: an actuator that saturates there, "
            f"inside the input's bounds [{lb[j]:g}, {ub[j]:g}] (give the system that bound), "
            "or an operator override?"
        )
    elif len(bad) > T / 2:
        why = (
            f"at {len(bad)} of {T} steps: is this another trial's log, or the inputs of "
            "another controller?"
        )
    elif len(runs := _runs(steps)) == 1 and len(runs[0]) >= 3:
        why = f"at steps {describe_steps(steps)}: an operator override?"
    else:
        why = (
            f"at steps {describe_steps(steps)}: rows out of order (swapped or shuffled), or an "
            "operator override?"
        )
    return [Problem("inputs", f"{head} {why}", steps)]


def _saturated(
    applied: np.ndarray, expected: np.ndarray, bad: np.ndarray, span: np.ndarray
) -> tuple[int, float, str] | None:
    """The input that, at the steps ``bad`` where ``applied`` differs from ``expected`` (the
    controller's plus its noise), stays at one value where the controller asked beyond it, on
    the same side at every one of them, and never passes that value at any step (an actuator
    that saturates inside the input's bounds, not an operator's setting); its index, that value
    and "more" or "less" (None: no input does so)."""
    for j in range(applied.shape[1]):
        u, e = applied[bad, j], expected[bad, j]
        if len(u) < 2 or np.ptp(u) > 1e-9 * span[j]:
            continue
        gap, tiny = INPUT_TOLERANCE * span[j], 1e-9 * span[j]
        if np.all(e > u[0] + gap) and np.all(applied[:, j] <= u[0] + tiny):
            return j, float(u[0]), "more"
        if np.all(e < u[0] - gap) and np.all(applied[:, j] >= u[0] - tiny):
            return j, float(u[0]), "less"
    return None


def model_problems(
    system: System,
    states: np.ndarray,
    inputs: np.ndarray,
    params: Any,
    history: Sequence[float],
    model: str,
    confirmed: bool = False,
) -> list[Problem]:
    """The episode's one-step error under the ``model`` (its ``params``: "identified" or
    "nominal") against the errors of the episodes told before (``history``, under the same
    model): far worse is a finding (with fewer than ``MIN_HISTORY`` episodes before it, none
    is made, unless the ``history`` is ``confirmed``: it starts at an episode the user told
    despite this check, e.g. at a new sensor's noise). An identified model also judges the
    episode's steps: a few steps it explains far worse than the rest (``STEP_RATIO`` times the
    median) are rows out of order."""
    r = residuals(system, states, inputs, params)
    e = float(np.sqrt(np.mean(r**2)))
    limit = max(STEP_RATIO * float(np.median(r)), RESIDUAL_FLOOR)
    steps = tuple(int(k) for k in np.flatnonzero(r > limit))
    h = np.asarray([v for v in history if np.isfinite(v)], float)
    if len(h) >= (1 if confirmed else MIN_HISTORY):
        med = float(np.median(h))
        scale = max(1.4826 * float(np.median(np.abs(h - med))), 0.1 * med, 1e-12)
        z = (e - med) / scale
        if e > RESIDUAL_FLOOR and e > EPISODE_RATIO * med and z > ROBUST_Z:
            where = f"; worst at steps {describe_steps(steps)}" if steps else ""
            return [
                Problem(
                    "model",
                    (
                        f"the {model} model explains this episode far worse than the {len(h)} told "
                        f"before (RMS scaled one-step error {e:.3g}, theirs {med:.3g} in the median, "
                        f"robust z {z:.1f}){where}: more measurement noise than in the episodes told "
                        "before (a new or noisier sensor: if so, accept the log with --force "
                        "(force=True), and the later checks compare with it), a sensor fault, rows out of "
                        "order, or not this plant's log?"
                    ),
                    steps,
                )
            ]
    if model == "identified" and steps and len(steps) <= max(3, len(r) // 10):
        return [
            Problem(
                "model",
                (
                    f"the identified model explains steps {describe_steps(steps)} far worse than the "
                    f"episode's other steps (one-step error up to {float(np.max(r)):.3g}, the median "
                    f"{float(np.median(r)):.3g}): rows out of order (swapped or shuffled), a "
                    "disturbance or a measurement fault at those steps, or states where the "
                    "model is poor (where it is not smooth, e.g. a square root at zero)?"
                ),
                steps,
            )
        ]
    return []


def review(
    system: System,
    mpc: ParametricMPC,
    plan: Any,
    log: Any,
    params: np.ndarray,
    model: str,
    history: Sequence[float],
    confirmed: bool = False,
) -> tuple[list[Problem], EpisodeRecord | None, float]:
    """Every check of a told ``log`` (a :class:`~mpcmobo.experiment.plantlog.PlantLog`) of
    the trial ``plan``, in order: the box (a unit error stops there), the time order (a
    reversed log stops there), then the MPC replayed on the logged states and the inputs and
    the model's one-step error checked against the ``history`` (``confirmed``:
    :func:`model_problems`). The problems, the replay's record (None if the checks stopped
    before it) and its time."""
    X, U = log.states, log.inputs
    problems = box_problems(system, X, plan.x0)
    if problems:
        return problems, None, 0.0
    problems = order_problems(system, X, U, params, log.time)
    if problems:
        return problems, None, 0.0
    t0 = time.perf_counter()
    record = replay(system, mpc, plan.theta, X, U, log.stage_costs, log.violations)
    mpc_time = time.perf_counter() - t0
    marked = log.fallback
    problems = input_problems(system, U, record.pi, plan.noise, plan.episode, (), marked)
    if problems and len(problems[0].steps) > len(U) / 2 and _reversed(system, mpc, plan, log):
        return [Problem("time_order", REVERSED)], record, mpc_time
    if problems:  # the episode may have run on the trial's exported controller
        exported = controller_inputs(mpc, plan.theta, X[:-1])
        problems = input_problems(system, U, record.pi, plan.noise, plan.episode, exported, marked)
    problems += model_problems(system, X, U, params, history, model, confirmed)
    return problems, record, mpc_time


REVERSED = (
    "the log is in reverse time order: read backwards, its inputs are the trial's controller "
    "plus its noise; the first row is the episode's start, the last the state after the last "
    "input"
)


def _reversed(system: System, mpc: ParametricMPC, plan: Any, log: Any) -> bool:
    """Whether the log read backwards is the trial's controller plus its noise (at most a
    tenth of its steps off)."""
    X, U = log.states[::-1], log.inputs[::-1]
    record = replay(system, mpc, plan.theta, X, U)
    found = input_problems(system, U, record.pi, plan.noise, plan.episode)
    return not found or len(found[0].steps) <= len(U) / 10
