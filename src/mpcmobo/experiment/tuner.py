"""Ask and tell: tune a plant whose episodes run outside mpcmobo (a DCS, a PLC, a simulator).

A :class:`Tuner` is one job of a study (one learner, one seed) in its own run directory,
driven by the user's loop instead of ``mpcmobo run``: :meth:`Tuner.ask` gives the next
:class:`Trial` (its theta, its controller ``trial.policy(x)``, the exploration noise to add at
every step, and where a simulated study would start it), the episode runs on the plant, and
:meth:`Tuner.tell` takes the logged episode: the MPC is solved again on the logged states
(it is deterministic given x and theta), so its actions, values and sensitivities, the critic
and f1..f4 are what a simulated episode would have had; the stage cost and violation are the
system's where the log has none. Each tell is recorded as ``mpcmobo run`` records an episode
(``episodes.parquet``, ``trajectories.parquet``, ``summary.json``, a checkpoint after every ask
and tell), so :meth:`Tuner.load` continues after a crash, also between ask and tell. Where the
system's plant can be simulated (its true parameters, or a plant of the settings), the
deployed theta is evaluated as in a study (J_eval); on a real plant it is not.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from mpcmobo.experiment import storage
from mpcmobo.experiment.build import build_system, needs_plant
from mpcmobo.experiment.job import Job
from mpcmobo.experiment.loop import EpisodePlan
from mpcmobo.experiment.records import EpisodeRow, Reference
from mpcmobo.experiment.reference import compute_reference, system_info
from mpcmobo.experiment.rundir import RunDirectory, open_run
from mpcmobo.experiment.settings import Settings, load_settings
from mpcmobo.experiment.summary import write_records
from mpcmobo.mpc import ParametricMPC, replay
from mpcmobo.systems.registry import is_factory_path

__all__ = ["Trial", "Tuner", "TunerError"]

# a logged state further than this many widths of its bounds outside them is not a state
STATE_RANGE = 10.0
# a logged first state within this fraction of x_scale of the trial's x0 started there
START_TOLERANCE = 0.05


class TunerError(ValueError):
    """A trial or a log the tuner cannot take; the message says what is wrong. Nothing
    recorded is changed."""


@dataclass(frozen=True)
class Trial:
    """One episode to run on the plant: its ``id`` (the episode's index), ``theta``, the
    ``noise`` (T, nu) to add to the controller's input at step k (zero where the learner wants a
    noise-free episode), ``steps`` T, and ``x0``, where a simulated study would start it (on a
    real plant, start where the plant is and log it). ``policy(x)`` is the MPC's first input
    with theta at the measured state x, warm-started from the previous call: call it at every
    step, in order."""

    id: int
    theta: np.ndarray
    noise: np.ndarray
    steps: int
    x0: np.ndarray
    theta_names: tuple[str, ...]
    mpc: ParametricMPC = field(repr=False, compare=False)

    def policy(self, x: np.ndarray) -> np.ndarray:
        """The input to apply at ``x`` before the noise: ``pi_theta(x)`` (eq. Policy), or the
        MPC's safe fallback where its solve fails."""
        return self.mpc.solve(x, self.theta, sensitivities=False).action

    def restart(self) -> None:
        """Forget the controller's warm start (a new episode of the same trial)."""
        self.mpc.reset()

    def to_json(self) -> dict[str, Any]:
        """The trial as plain data (what ``mpcmobo ask`` prints)."""
        return {
            "id": self.id,
            "theta": dict(zip(self.theta_names, map(float, self.theta))),
            "steps": self.steps,
            "x0": [float(v) for v in self.x0],
            "noise": np.asarray(self.noise).tolist(),
        }


class Tuner:
    """One learner tuning a plant by ask and tell, recorded in ``out`` (module docstring).

    ``system``: a system name or factory path (as ``--system``), or the settings' ``[system]``
    table as a mapping (``{"name": "cstr", "identify": False}``); ``learner``: one of the
    learners; ``config``: a settings file; ``overrides``: settings as in
    :func:`~mpcmobo.experiment.settings.load_settings` (``episodes``, ``start_mode``,
    ``learner_options``, ...). ``out`` must be a new or empty directory; :meth:`load` opens an
    existing one.
    """

    def __init__(
        self,
        system: str | Mapping[str, Any] | None = None,
        learner: str = "mobo",
        out: str | Path = "tuning",
        *,
        config: str | Path | None = None,
        seed: int = 0,
        **overrides: Any,
    ) -> None:
        per_job = sorted(k for k in ("learners", "seeds", "workers") if k in overrides)
        if per_job:
            raise TunerError(
                f"a tuner runs one learner with one seed in one process: give learner= and "
                f"seed=, not {', '.join(per_job)}"
            )
        if RunDirectory(out).holds_run():
            raise TunerError(
                f"{out} holds a run already: continue it with Tuner.load({str(out)!r}) "
                f"(mpcmobo ask {out}), or give a new directory"
            )
        if isinstance(system, Mapping):
            sys_table = dict(system)
        else:
            sys_table = (
                {} if system is None else {"factory" if is_factory_path(system) else "name": system}
            )
        settings = load_settings(
            config,
            system=sys_table or None,
            learners=[learner],
            seeds=[seed],
            workers=1,
            **overrides,
        )
        existed = Path(out).exists()
        run_dir, settings = open_run(out, settings, resume=False)
        try:
            self._open(run_dir, settings, new=True)
            storage.atomic_write_text(
                run_dir.tuner_mark, json.dumps({"learner": learner, "seed": seed}) + "\n"
            )
        except BaseException:  # a system or learner that cannot be built: leave no tuner
            for path in [*run_dir.path.iterdir()] if existed else [run_dir.path]:
                if path.is_dir():
                    shutil.rmtree(path, ignore_errors=True)
                else:
                    path.unlink(missing_ok=True)
            raise

    @classmethod
    def load(cls, out: str | Path, episodes: int | None = None) -> Tuner:
        """The tuner recorded in ``out``, where it stopped (also between ask and tell);
        ``episodes``: a larger budget of trials from now on (saved with its settings)."""
        run_dir = RunDirectory(out)
        if not run_dir.holds_run():
            raise TunerError(f"{out} holds no tuner (no config.toml)")
        run_dir.check_schema()
        settings = run_dir.saved_settings()
        if len(settings.learners) != 1 or len(settings.seeds) != 1:
            raise TunerError(
                f"{out} holds a study of {len(settings.learners)} learners and "
                f"{len(settings.seeds)} seeds; a tuner has one of each"
            )
        if episodes is not None and episodes != settings.episodes:
            if episodes < settings.episodes:
                raise TunerError(
                    f"episodes: the tuner in {out} has a budget of {settings.episodes} trials; "
                    f"it can be extended, not shortened (got {episodes})"
                )
            settings = run_dir.reopen(settings.model_copy(update={"episodes": int(episodes)}))
        tuner = cls.__new__(cls)
        tuner._open(run_dir, settings, new=False)
        return tuner

    def _open(self, run_dir: RunDirectory, settings: Settings, new: bool) -> None:
        self.run_dir, self.settings = run_dir, settings
        self.learner, self.seed = settings.learners[0], settings.seeds[0]
        system = build_system(settings, self.learner)  # the learner's: its identify checked
        self.evaluates = system.has_true_plant or needs_plant(settings)
        reference = run_dir.reference()
        if reference is None:
            reference = self._reference(settings)
            run_dir.save_reference(reference)
        self.reference = reference
        J0 = reference.J_initial if math.isfinite(reference.J_initial) else None
        self.job = Job(settings, run_dir, self.learner, self.seed, J0, evaluates=self.evaluates)
        if not new:
            self.job.restore()
        self.system = self.job.run.system
        self._policy_mpc = ParametricMPC(self.system, model="imperfect", **settings.mpc.options())

    def _reference(self, settings: Settings) -> Reference:
        """J* and J_eval(theta0) where the plant can be simulated; else neither."""
        if self.evaluates:
            return compute_reference(settings)
        system = build_system(settings)
        return Reference(
            J_star=None,
            J_initial=math.nan,
            theta0=system.parameterization.theta0.copy(),
            system=system_info(system),
            J_star_missing="the plant is not simulated: the tuner runs on a real plant",
        )

    # ------------------------------------------------------------------ the loop
    @property
    def deployed(self) -> np.ndarray:
        """The theta deployed now (the learner's incumbent)."""
        return np.asarray(self.job.run.learner.incumbent(), dtype=float)

    @property
    def episodes(self) -> int:
        """Trials told so far."""
        return self.job.run.episode

    def ask(self) -> Trial:
        """The next trial (the pending one again if it has not been told)."""
        if self.job.done:
            raise TunerError(
                f"the tuner's budget of {self.settings.episodes} trials is spent; give it a "
                f"larger one to go on: Tuner.load(out, episodes=N), or mpcmobo ask "
                f"{self.run_dir.path} --episodes N"
            )
        if self.job.pending is None:
            plan = self.job.run.plan()
            self.job.pending = plan.to_dict()
            self.job.save()  # the learner's state after the proposal, with the trial
        return self._trial(EpisodePlan.from_dict(self.job.pending))

    def _trial(self, plan: EpisodePlan) -> Trial:
        self._policy_mpc.reset()
        return Trial(
            id=plan.episode,
            theta=np.array(plan.theta, float),
            noise=np.array(plan.noise, float),
            steps=self.job.run.steps,
            x0=np.array(plan.x0, float),
            theta_names=tuple(self._policy_mpc.theta_names),
            mpc=self._policy_mpc,
        )

    def tell(
        self,
        trial: Trial | int,
        states: Any,
        inputs: Any | None = None,
        stage_costs: Any | None = None,
        violations: Any | None = None,
    ) -> EpisodeRow:
        """Take the logged episode of ``trial``: ``states`` (T+1, nx), the last the state after
        the last input; ``inputs`` (T, nu), the inputs actually applied; ``stage_costs`` and
        ``violations`` (T,) if the plant measured them. Arrays, or one DataFrame with the
        system's state and input names as columns (inputs empty in the last row) and
        optionally ``stage_cost`` and ``violation``. Returns the episode's row."""
        plan = self._pending(_trial_id(trial))
        X, U, L, V = self._log(states, inputs, stage_costs, violations)
        plan = self._started(plan, X[0])
        t0 = time.perf_counter()
        record = replay(self.system, self.job.run.mpc, plan.theta, X, U, L, V)
        mpc_time = time.perf_counter() - t0
        try:
            row = self.job.complete(plan, record, "", mpc_time)
        except BaseException:
            # the learner may have observed the episode in part (an interrupt, an error):
            # back to the last checkpoint, where the trial is pending, so it can be told again
            self._open(self.run_dir, self.settings, new=False)
            raise
        self.job.pending = None
        self.job.save()
        write_records(self.run_dir.path, self.settings, self.reference)
        return row

    def _started(self, plan: EpisodePlan, x_first: np.ndarray) -> EpisodePlan:
        """The plan with the episode's logged initial state: the trial's ``x0`` if the log
        starts within ``START_TOLERANCE`` x_scale of it (a measurement of that start), else
        the logged state; under cycled starts an episode must start at its trial's ``x0``."""
        scale = np.asarray(self.system.x_scale, float)
        if np.all(np.abs(x_first - plan.x0) <= START_TOLERANCE * scale):
            return plan
        if self.settings.start_mode == "cycle":
            j = int(np.argmax(np.abs(x_first - plan.x0) / scale))
            raise TunerError(
                f"the log starts at {self.system.state_names[j]} = {x_first[j]:.6g}, the trial "
                f"at {plan.x0[j]:.6g}: under start_mode = 'cycle' thetas are compared from the "
                "same starts, so an episode must start at its trial's x0 (within "
                f"{START_TOLERANCE:g} x_scale); on a plant that cannot be brought there, use "
                "start_mode = 'random'"
            )
        return replace(plan, x0=np.array(x_first, float))

    def _pending(self, tid: int) -> EpisodePlan:
        """The pending trial's plan, if ``tid`` is its id."""
        pending = self.job.pending
        if pending is not None and int(pending["episode"]) == tid:
            return EpisodePlan.from_dict(pending)
        if tid < self.job.run.episode:
            raise TunerError(
                f"trial {tid} was told already (the tuner is at trial {self.episodes})"
            )
        if pending is None:
            raise TunerError(f"unknown trial {tid}: no trial is pending; ask for one first")
        raise TunerError(f"unknown trial {tid}: the pending trial is {pending['episode']}")

    def _log(
        self, states: Any, inputs: Any, stage_costs: Any, violations: Any
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """The log as arrays, checked: shapes, finite values, states in range."""
        s, T = self.system, self.job.run.steps
        if hasattr(states, "columns"):  # a DataFrame
            states, inputs, stage_costs, violations = _frame(states, s)
        X = _numbers(states, "states")
        if inputs is None:
            raise TunerError("the log needs the inputs applied (inputs, or input columns)")
        U = _numbers(inputs, "inputs")
        if X.shape != (T + 1, s.nx):
            raise TunerError(
                f"states must be ({T + 1}, {s.nx}): the {T + 1} states of the episode "
                f"({', '.join(s.state_names)}), the last after the last input; got {X.shape}"
            )
        if U.shape != (T, s.nu):
            raise TunerError(
                f"inputs must be ({T}, {s.nu}): the {T} inputs applied "
                f"({', '.join(s.input_names)}); got {U.shape}"
            )
        for name, arr in (("states", X), ("inputs", U)):
            if not np.all(np.isfinite(arr)):
                k = int(np.flatnonzero(~np.all(np.isfinite(arr.reshape(len(arr), -1)), 1))[0])
                raise TunerError(f"{name} has a value that is not finite at step {k}: {arr[k]}")
        span = np.where(np.isfinite(s.x_ub - s.x_lb), s.x_ub - s.x_lb, np.inf)
        far = (X < s.x_lb - STATE_RANGE * span) | (X > s.x_ub + STATE_RANGE * span)
        if np.any(far):
            k, j = (int(v[0]) for v in np.nonzero(far))
            raise TunerError(
                f"state {s.state_names[j]} = {X[k, j]} at step {k} is far outside its bounds "
                f"[{s.x_lb[j]}, {s.x_ub[j]}]: check the log's units and columns"
            )
        outside = (U < s.u_lb - 1e-9 * np.abs(s.u_lb) - 1e-12) | (
            U > s.u_ub + 1e-9 * np.abs(s.u_ub) + 1e-12
        )
        if np.any(outside):
            k, j = (int(v[0]) for v in np.nonzero(outside))
            raise TunerError(
                f"input {s.input_names[j]} = {U[k, j]} at step {k} is outside its bounds "
                f"[{s.u_lb[j]}, {s.u_ub[j]}]: log the inputs actually applied"
            )
        out: list[np.ndarray | None] = []
        for name, arr in (("stage_costs", stage_costs), ("violations", violations)):
            if arr is None:
                out.append(None)
                continue
            a = _numbers(arr, name).reshape(-1)
            if a.shape != (T,):
                raise TunerError(f"{name} must be {T} numbers, one per input; got {a.shape}")
            if not np.all(np.isfinite(a)):
                k = int(np.flatnonzero(~np.isfinite(a))[0])
                raise TunerError(f"{name} has a value that is not finite at step {k}: {a[k]}")
            if name == "violations" and np.any(a < 0):
                k = int(np.flatnonzero(a < 0)[0])
                raise TunerError(f"violations cannot be negative; step {k} has {a[k]}")
            out.append(a)
        return X, U, out[0], out[1]

    # ------------------------------------------------------------------ status
    def status(self) -> dict[str, Any]:
        """What is deployed and on what evidence: the deployed theta, the trials so far and how
        many ran the deployed theta and how often it changed from theta0, the deployed theta's
        last J_eval (a simulated plant; None until it is evaluated), the pending trial,
        and with identification the last fit (``identification``: per parameter its nominal
        value, estimate and standard deviation; the RMS scaled one-step errors on held-out
        transitions of the fit and of the nominal model; the transitions fitted)."""
        rows = self.job.rows
        deployed = self.deployed
        ran = sum(1 for r in rows if np.allclose(r.theta, deployed, rtol=0, atol=1e-12))
        J = [  # the deployed theta's own evaluations
            r.J_eval_incumbent
            for r in rows
            if math.isfinite(r.J_eval_incumbent) and np.array_equal(r.incumbent, deployed)
        ]
        incumbents = [self.job.run.learner.theta0, *(np.asarray(r.incumbent) for r in rows)]
        return {
            "learner": self.learner,
            "trials": len(rows),
            "budget": self.settings.episodes,
            "pending": None if self.job.pending is None else int(self.job.pending["episode"]),
            "deployed": dict(zip(self._policy_mpc.theta_names, map(float, deployed))),
            "deployed_episodes": ran,
            "changes_of_deployed": sum(
                1 for a, b in zip(incumbents, incumbents[1:]) if not np.array_equal(a, b)
            ),
            "J_eval": J[-1] if J else None,
            "J_star": self.reference.J_star,
            "J_initial": None
            if not math.isfinite(self.reference.J_initial)
            else self.reference.J_initial,
            "identification": self._identification(),
        }

    def _identification(self) -> dict[str, Any] | None:
        """The learner's last fit of the model, as :meth:`status` reports it (None without)."""
        fit = self.job.run.learner.identification()
        if fit is None:
            return None
        nominal = dict(zip(self.system.param_names, self.system.models["imperfect"]))
        return {
            "parameters": {
                name: {"nominal": float(nominal[name]), "estimate": float(q), "std": float(sd)}
                for name, q, sd in zip(fit.names, fit.estimate, fit.std)
            },
            "holdout_error": fit.holdout_error,
            "nominal_error": fit.nominal_error,
            "transitions": fit.n,
        }


def _trial_id(trial: Any) -> int:
    """A trial's id: a :class:`Trial`'s, or an integer."""
    if isinstance(trial, Trial):
        return trial.id
    if isinstance(trial, (int, np.integer)) and not isinstance(trial, bool):
        return int(trial)
    raise TunerError(f"a trial is a Trial or its integer id, not {trial!r}")


def _numbers(values: Any, name: str) -> np.ndarray:
    """``values`` as an array of floats, or a :class:`TunerError` naming what is not a
    number."""
    try:
        return np.asarray(values, dtype=float)
    except (TypeError, ValueError) as err:
        raise TunerError(f"{name} holds a value that is not a number: {err}") from None


def _frame(df: Any, system: Any) -> tuple[Any, Any, Any, Any]:
    """States, inputs, stage costs and violations from a DataFrame with the system's state and
    input names as columns (the inputs' last row empty)."""
    import pandas as pd

    missing = [c for c in (*system.state_names, *system.input_names) if c not in df.columns]
    if missing:
        raise TunerError(
            f"the log has no column {missing[0]!r}; it needs the states "
            f"{list(system.state_names)} and the inputs {list(system.input_names)}"
        )
    optional = [c for c in ("stage_cost", "violation") if c in df.columns]
    for c in (*system.state_names, *system.input_names, *optional):
        try:
            pd.to_numeric(df[c])
        except (TypeError, ValueError) as err:
            msg = f"the log's column {c!r} holds a value that is not a number: {err}"
            raise TunerError(msg) from None
    X = df[list(system.state_names)].to_numpy(float)
    U = df[list(system.input_names)].to_numpy(float)[:-1]
    L = df["stage_cost"].to_numpy(float)[:-1] if "stage_cost" in df.columns else None
    V = df["violation"].to_numpy(float)[:-1] if "violation" in df.columns else None
    return X, U, L, V


def write_log(path: str | Path, states: np.ndarray, inputs: np.ndarray, system: Any) -> Path:
    """A logged episode as a CSV or Parquet file of the tuner's format (``mpcmobo tell``)."""
    import pandas as pd

    X, U = np.asarray(states, float), np.asarray(inputs, float)
    data = {n: X[:, i] for i, n in enumerate(system.state_names)}
    pad = np.full((len(X), U.shape[1]), np.nan)
    pad[: len(U)] = U
    data.update({n: pad[:, i] for i, n in enumerate(system.input_names)})
    df = pd.DataFrame(data)
    path = Path(path)
    if path.suffix == ".parquet":
        storage.write_parquet(path, df)
    else:
        df.to_csv(path, index=False)
    return path
