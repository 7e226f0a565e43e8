"""One learning run: a learner, a seed, episodes on the plant, one record per episode."""

from __future__ import annotations

import hashlib
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import gymnasium
import numpy as np

from mpcmobo.experiment.price import ExplorationPrice
from mpcmobo.learners.base import EpisodeResult, Learner, episode_result
from mpcmobo.mpc import (
    EpisodeRecord,
    ParametricMPC,
    PlantDiverged,
    model_plant,
    model_rollout,
    rollout,
    rollouts,
)
from mpcmobo.rl import CompatibleCritic, GaussianExploration
from mpcmobo.rl.objectives import mean_stage_cost
from mpcmobo.systems.base import System
from mpcmobo.systems.plant import SystemPlant

START_MODES = ("random", "cycle")
# what a closed loop that fails raises (a plant that runs away or raises, a broken episode):
# recorded as a failed episode or evaluation, never the end of a run
EPISODE_FAILURES = (FloatingPointError, ValueError, RuntimeError)
# how a refused candidate's row says that the learner learned from its simulation
SIMULATED_NOTE = "the learner learns from its episode simulated on the model"
# a simulated episode's spread (EpisodeResult.spread): the model's predictions of plant costs
# trusted within this many RMS log errors (ExplorationPrice.error)
SPREAD_ERRORS = 2.0


@dataclass
class EpisodePlan:
    """What one episode runs (:meth:`LearningRun.plan`): its theta, initial state, exploration
    noise per step (T, nu; zero where the learner asked for a noise-free episode), the plant's
    seed, the start's index in the cycle (-1: random), the proposal's error if it failed and the
    theta deployed when it was planned (what the episode's excess cost is measured against).
    With an exploration budget (:mod:`mpcmobo.experiment.price`): the predicted cost of the
    theta that runs and of the deployed one from ``x0`` with ``noise`` (NaN: not predicted),
    why the learner's candidate was refused ("": it was not) and that candidate, whether the
    learner learns from that candidate's episode simulated on the model (``simulated``), else
    the bound on the refused candidate's cost as a multiple of the deployed theta's from the
    same start (``refused_bound``: its predicted ratio times ``SPREAD_ERRORS`` of the model's
    ratio errors; NaN: none), and whether tuning has converged (the deployed theta runs without
    noise and the learner does not observe it)."""

    episode: int
    theta: np.ndarray
    x0: np.ndarray
    noise: np.ndarray
    explore: bool
    plant_seed: int
    start_id: int = -1
    error: str = ""
    propose_time: float = 0.0
    deployed: list[float] | None = None
    predicted_cost: float = math.nan
    predicted_deployed: float = math.nan
    refused: str = ""
    refused_theta: list[float] | None = None
    simulated: bool = False
    refused_bound: float = math.nan
    converged: bool = False

    def to_dict(self) -> dict:
        """Plain data (a pending trial in a checkpoint)."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__}

    @classmethod
    def from_dict(cls, d: dict) -> EpisodePlan:
        """The inverse of :meth:`to_dict`."""
        return cls(**d)


def model_costs(
    system: System,
    mpc: ParametricMPC,
    theta: np.ndarray,
    starts: np.ndarray,
    steps: int | None,
    plant: gymnasium.Env,
    noise: np.ndarray | None = None,
) -> np.ndarray:
    """The mean stage cost of ``theta``'s closed loop of ``steps`` steps (None: the system's)
    from each start (n, nx) on ``plant`` (a model's, :func:`mpcmobo.mpc.model_plant`),
    noise-free or with the exploration ``noise`` (steps, nu) replayed; NaN where that closed
    loop fails. What a start covariate and the twin's evaluations and predictions are made
    of. Several closed loops on a noise-free plant of the system's equations run together
    (:func:`mpcmobo.mpc.rollouts`, the same records), others one after the other."""
    starts = np.atleast_2d(starts)
    if (
        len(starts) > 1
        and type(plant) is SystemPlant
        and plant.process_noise is None
        and plant.measurement_noise is None
    ):
        try:
            params = plant.system.true_params
            recs = rollouts(system, mpc, theta, starts, steps, plant_params=params, noise=noise)
        except Exception:  # noqa: BLE001 - a failed closed loop is a NaN cost, never an end
            return np.full(len(starts), np.nan)
        return np.array(
            [mean_stage_cost(r) if isinstance(r, EpisodeRecord) else np.nan for r in recs], float
        )
    out = []
    for x0 in starts:
        try:
            rec = model_rollout(system, mpc, theta, x0, steps, plant=plant, noise=noise)
            out.append(mean_stage_cost(rec))
        except Exception:  # noqa: BLE001 - a failed closed loop is a NaN cost, never an end
            out.append(float("nan"))
    return np.array(out, float)


def _start_key(x0: np.ndarray, theta: np.ndarray, p: np.ndarray, e: np.ndarray | None) -> bytes:
    """The cache key of a start cost: its start, theta, model parameters and exploration."""
    return b"".join(np.asarray(v, float).tobytes() for v in (x0, theta, p, () if e is None else e))


def starts_of_cycle(
    system: System, seed: int, n: int, given: Sequence[Sequence[float]] | None = None
) -> np.ndarray:
    """The fixed cycle of initial states (n, nx) that ``seed``'s cycled episodes start from:
    the ``given`` ones (the settings' ``cycle_starts``), else ``n`` drawn from the system's
    initial-state distribution (a stream of its own: ``[seed, 7]``'s third child)."""
    if given is not None:
        return np.array(given, float).reshape(-1, system.nx)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7]).spawn(3)[2])
    return np.array([system.sample_initial_state(rng) for _ in range(max(1, int(n)))])


def _paired_excess(plant_cost: float, predicted: float, predicted_deployed: float) -> float:
    """The excess of an episode that cost ``plant_cost`` over the deployed controller from the
    same start, where the model predicted ``predicted`` for it and ``predicted_deployed`` for
    the deployed controller: the plant cost times ``1 - predicted_deployed / predicted``
    (:meth:`LearningRun.excess_cost`); the plain difference ``plant_cost -
    predicted_deployed`` where the ratio is not defined; NaN where neither is known."""
    if math.isfinite(predicted) and math.isfinite(predicted_deployed) and predicted > 0:
        return float(plant_cost * (1.0 - predicted_deployed / predicted))
    return float(plant_cost - predicted_deployed)


def _as_list(values: np.ndarray | None) -> list[float]:
    """A learner's identified parameters as a record's list (empty: none)."""
    return [] if values is None else [float(v) for v in np.asarray(values).reshape(-1)]


class LearningRun:
    """Episodes of one learner on one seed; resumable through ``state_dict``.

    Each episode: the learner proposes theta, the MPC with theta runs ``steps`` steps on the
    true plant with exploration noise, the compatible critic is fitted to the episode, the four
    objectives are computed, and the learner observes them. Initial states are drawn at random
    (``start_mode="random"``, the paper's setting) or cycle through a fixed seeded set
    (``"cycle"``) so that candidates are compared on common starts. The plant is a gymnasium
    environment (default: the system's equations with ``true_params``), reset at the start of
    each episode with a seed that depends only on (seed, episode), so a resumed run sees the
    same plant.
    """

    def __init__(
        self,
        system: System,
        learner: Learner,
        mpc: ParametricMPC,
        *,
        seed: int = 0,
        steps: int | None = None,
        exploration_std: Sequence[float] | None = None,
        exploration_decay: float = 1.0,
        start_mode: str = "random",
        n_cycle_starts: int = 6,
        cycle_starts: Sequence[Sequence[float]] | None = None,
        critic_ridge: float = 1e-6,
        critic_method: str = "lstd",
        critic_q_target: str | None = None,
        critic_min_valid_steps: int = 2,
        critic_weighting: str = "uniform",
        beta: float = 1.0,
        plant: gymnasium.Env | None = None,
        price: ExplorationPrice | None = None,
    ) -> None:
        if start_mode not in START_MODES:
            raise ValueError(f"start_mode must be one of {START_MODES}, got '{start_mode}'")
        self.system, self.learner, self.mpc = system, learner, mpc
        self.plant = plant  # None: the system's own equations (SystemPlant)
        self.price = ExplorationPrice(math.inf, 0) if price is None else price
        self.seed = int(seed)
        self.steps = int(system.episode_steps if steps is None else steps)
        std = np.zeros(system.nu) if exploration_std is None else exploration_std
        self.exploration = GaussianExploration(std=np.asarray(std, float), decay=exploration_decay)
        self.critic = CompatibleCritic(
            gamma=mpc.gamma,
            ridge=critic_ridge,
            method=critic_method,
            q_target=critic_q_target,
            min_valid_steps=critic_min_valid_steps,
            weighting=critic_weighting,
        )
        self.beta = float(beta)
        self.start_mode = start_mode
        # separate streams: initial states, exploration noise
        s_start, s_noise, _ = np.random.SeedSequence([self.seed, 7]).spawn(3)
        self.rng_start = np.random.default_rng(s_start)
        self.rng_noise = np.random.default_rng(s_noise)
        self.cycle_starts = starts_of_cycle(system, self.seed, n_cycle_starts, cycle_starts)
        self.episode = 0
        self.previous_Vc: float | None = None
        self._start_costs: dict[bytes, float] = {}  # start_cost per initial state (a cache)
        self._model_plants: dict[bytes, gymnasium.Env] = {}  # a model as a plant, per parameters
        learner.use_start_costs(self.start_costs)

    def plant_seed(self) -> int:
        """The plant's seed of this episode (its own noise, if any): a function of (seed,
        episode), so it draws nothing from the other streams."""
        return int(np.random.SeedSequence([self.seed, 7, 3, self.episode]).generate_state(1)[0])

    def next_start(self) -> np.ndarray:
        """The initial state of the next episode (the cycle of fixed starts, or a random one)."""
        if self.start_mode == "cycle":
            return self.cycle_starts[self.episode % len(self.cycle_starts)].copy()
        return self.system.sample_initial_state(self.rng_start)

    def plan(self) -> EpisodePlan:
        """What the next episode runs: the learner's proposal, whether it explores, its initial
        state and its exploration noise, drawn now (the random streams advance as if the
        episode ran), judged by the exploration budget (:meth:`_priced`). Once tuning has
        converged the deployed theta runs without noise and the learner is not asked.
        :meth:`finish` completes the episode from its record."""
        t0 = time.perf_counter()
        deployed = np.asarray(self.learner.incumbent(), float)
        converged = self.price.converged
        if converged:
            theta, proposal_error, explore = deployed.copy(), "", False
        else:
            theta, proposal_error = self._propose()
            explore = bool(self.learner.explores())
        t_prop = time.perf_counter() - t0
        x0 = self.next_start()
        self.exploration.episode = self.episode
        exploration = self.exploration
        if not explore:  # zero noise, drawn all the same: the stream does not depend on it
            exploration = GaussianExploration(np.zeros(exploration.nu), episode=self.episode)
        noise = np.array([exploration.sample(self.rng_noise, k) for k in range(self.steps)])
        plan = EpisodePlan(
            episode=self.episode,
            theta=theta,
            x0=x0,
            noise=noise.reshape(self.steps, self.system.nu),
            explore=explore,
            plant_seed=self.plant_seed(),
            start_id=self.episode % len(self.cycle_starts) if self.start_mode == "cycle" else -1,
            error=proposal_error,
            propose_time=t_prop,
            deployed=[float(v) for v in deployed],
            converged=converged,
        )
        return self._priced(plan) if self.price.active and not converged else plan

    def _priced(self, plan: EpisodePlan) -> EpisodePlan:
        """``plan`` with its predicted cost and the deployed theta's, on the learner's model of
        the plant (:meth:`prediction_params`) from its start with its noise; a candidate the
        budget refuses (:mod:`mpcmobo.experiment.price`; exploring or not, as MPC-RL's
        noise-free verification of its iterate) is replaced by the deployed theta (same
        noise), and simulated for the learner where the price says so (:meth:`finish`)."""
        t0 = time.perf_counter()
        deployed = np.asarray(plan.deployed, float)
        params = self.prediction_params(deployed)
        self.price.use_model(
            hashlib.sha1(params.tobytes()).hexdigest(), lambda eps: self._predicted(eps, params)
        )
        d = self.start_cost(plan.x0, deployed, params, plan.noise)
        if np.array_equal(plan.theta, deployed):
            plan.predicted_cost = plan.predicted_deployed = d
        else:
            c = self.start_cost(plan.x0, plan.theta, params, plan.noise)
            plan.predicted_cost, plan.predicted_deployed = c, d
            theta = plan.theta

            def gain() -> tuple[float, float]:
                return self._saving(theta, deployed, params)

            learns = self.learner.learns_in_simulation()
            verdict = self.price.judge(c, d, plan.episode, gain, learns)
            if not verdict.run:
                plan.refused, plan.refused_theta = verdict.reason, _as_list(plan.theta)
                plan.theta, plan.predicted_cost = deployed.copy(), d
                plan.simulated = verdict.simulated
                if verdict.simulated:
                    plan.refused += f"; {SIMULATED_NOTE}"
                elif c > 0 and d > 0:
                    plan.refused_bound = c / d * math.exp(SPREAD_ERRORS * self.price.ratio_error())
        plan.propose_time += time.perf_counter() - t0
        return plan

    def restarted(self, plan: EpisodePlan, x0: np.ndarray) -> EpisodePlan:
        """``plan`` as its episode ran from ``x0`` (a real plant starts where it is, under random
        starts): its predicted costs (:meth:`_priced`) from there, on the same model, so that
        the excess cost and the budget's calibration compare costs from the same start. Its
        verdict stays as it was made."""
        plan = replace(plan, x0=np.array(x0, float))
        if plan.deployed is None or not np.isfinite(plan.predicted_deployed):
            return plan
        deployed = np.asarray(plan.deployed, float)
        params = self.prediction_params(deployed)
        d = self.start_cost(plan.x0, deployed, params, plan.noise)
        plan.predicted_deployed = d
        plan.predicted_cost = (
            d
            if np.array_equal(plan.theta, deployed)
            else self.start_cost(plan.x0, plan.theta, params, plan.noise)
        )
        return plan

    def _predicted(self, episodes: list[dict], params: np.ndarray) -> np.ndarray:
        """The costs of past ``episodes`` (their ``x0``, ``theta`` and ``noise``) predicted on
        the model with ``params``: a new model's calibration."""
        return np.array(
            [
                self.start_cost(np.asarray(e["x0"]), np.asarray(e["theta"]), params, e["noise"])
                for e in episodes
            ]
        )

    def _saving(
        self, theta: np.ndarray, deployed: np.ndarray, params: np.ndarray
    ) -> tuple[float, float]:
        """What ``theta`` would save per episode were it deployed instead of ``deployed``: the
        mean over the starts where the learner's deployment test measures a theta
        (:meth:`~mpcmobo.learners.Learner.judge_starts`: the twin's), else over the run's fixed
        starts, of the deployed theta's noise-free cost on the model with ``params`` less its
        own (NaN where its closed loop fails and the deployed theta's does not), and the
        deployed theta's mean cost there."""
        starts = self.learner.judge_starts()
        if starts is None:
            starts = self.cycle_starts
        d = self.start_costs(starts, deployed, params)
        c = self.start_costs(starts, theta, params)
        ok = np.isfinite(d)
        if not ok.any():
            return np.nan, np.nan
        if not np.all(np.isfinite(c[ok])):
            return np.nan, float(np.mean(d[ok]))
        return float(np.mean(d[ok] - c[ok])), float(np.mean(d[ok]))

    def prediction_params(self, deployed: np.ndarray) -> np.ndarray:
        """The model parameters the loop predicts plant episodes with: the model of the
        learner's last identification, else the deployed theta's own model."""
        fit = self.learner.identification()
        if fit is not None:
            return np.asarray(fit.params, float)
        return self._model_of(deployed)

    def run_episode(self) -> tuple[dict, EpisodeRecord | None]:
        """Run one episode; return its row of records (the fields of :class:`EpisodeRow` except
        ``J_eval_incumbent`` and ``eval_time_s``, which the study's job adds) and the episode."""
        plan = self.plan()
        t1 = time.perf_counter()
        try:
            record: EpisodeRecord | None = rollout(
                self.system,
                self.mpc,
                plan.theta,
                plan.x0,
                self.steps,
                noise=plan.noise,
                plant=self.plant,
                plant_seed=plan.plant_seed,
            )
            error, stopped_violation = "", np.nan
        except EPISODE_FAILURES as err:
            record, error = None, f"{type(err).__name__}: {err}"
            stopped_violation = err.violation if isinstance(err, PlantDiverged) else np.nan
        deployed_cost = self._deployed_on_plant(plan) if record is not None else np.nan
        return self.finish(
            plan,
            record,
            error,
            time.perf_counter() - t1,
            violation=stopped_violation,
            deployed_cost=deployed_cost,
        )

    def _deployed_on_plant(self, plan: EpisodePlan) -> float:
        """The mean stage cost the deployed theta (when the episode was planned) has on the
        simulated plant from the episode's start with its exploration noise and plant seed:
        what the episode would have cost without tuning (NaN if that closed loop fails). Run
        only where the episode ran another theta; it touches no random stream."""
        if plan.deployed is None or np.array_equal(plan.deployed, plan.theta):
            return np.nan  # the same controller: finish() records no excess
        try:
            rec = rollout(
                self.system,
                self.mpc,
                np.asarray(plan.deployed, float),
                plan.x0,
                self.steps,
                noise=plan.noise,
                plant=self.plant,
                plant_seed=plan.plant_seed,
                sensitivities=False,
            )
        except EPISODE_FAILURES:
            return np.nan
        return mean_stage_cost(rec)

    def finish(
        self,
        plan: EpisodePlan,
        record: EpisodeRecord | None,
        error: str = "",
        mpc_time: float = 0.0,
        violation: float = np.nan,
        deployed_cost: float = np.nan,
    ) -> tuple[dict, EpisodeRecord | None]:
        """Complete the episode of ``plan`` from its ``record`` (None: it failed, ``error``
        says why; ``violation``: the violation of the steps a stopped plant ran, else NaN):
        the critic and the objectives, the learner's observation, the row. ``deployed_cost``:
        the deployed theta's cost on the plant from the same start with the same noise, where it
        was measured (a simulated plant); else the MPC's own model predicts it
        (:meth:`excess_cost`)."""
        if plan.episode != self.episode:
            raise ValueError(f"the plan is of episode {plan.episode}, the run is at {self.episode}")
        t1 = time.perf_counter()
        result, error2 = self._result(plan.theta, record)
        if error2:
            record, error = None, "; ".join(e for e in (error, error2) if e)
        error = "; ".join(e for e in (plan.error, error) if e)
        theta, x0 = plan.theta, plan.x0
        result.start_id = plan.start_id
        result.x0 = x0.copy()
        if self.learner.uses_start_cost():
            result.start_cost = self.start_cost(x0)
        plant_cost = mean_stage_cost(record) if record is not None else np.nan
        excess = self.excess_cost(plan, plant_cost, result, deployed_cost)
        t_mpc = mpc_time + time.perf_counter() - t1
        if self.price.active:
            noise = np.asarray(plan.noise, float).tolist()
            ran = {"x0": x0.tolist(), "theta": theta.tolist(), "noise": noise}
            self.price.calibrate(plan.predicted_cost, plant_cost, {**ran, "cost": plant_cost})
        t2 = time.perf_counter()
        self._observe(plan, result)
        incumbent = np.asarray(self.learner.incumbent(), dtype=float)
        t_learn = plan.propose_time + time.perf_counter() - t2
        if np.isfinite(result.Vc):
            self.previous_Vc = result.Vc
        f = result.objectives
        row = {
            "learner": self.learner.name,
            "seed": self.seed,
            "episode": self.episode,
            "theta": theta.tolist(),
            "f1": float(f[0]),
            "f2": float(f[1]),
            "f3": float(f[2]),
            "f4": float(f[3]),
            "J_tilde": float(f[0]),
            "mean_stage_cost": mean_stage_cost(record) if record is not None else np.nan,
            "mean_abs_A": float(result.mean_abs_advantage),
            "critic_ok": bool(result.critic_ok),
            "violation": float(np.sum(record.violation)) if record is not None else violation,
            "solver_failures": int(result.failures) if record is not None else self.steps + 1,
            "x0": x0.tolist(),
            "mpc_time_s": t_mpc,
            "learner_time_s": t_learn,
            "incumbent": incumbent.tolist(),
            "error": error,
            "start_cost": float(result.start_cost),
            "identified": _as_list(self.learner.identified()),
            "plant_cost": float(plant_cost),
            "excess_cost": float(excess),
            "predicted_cost": float(plan.predicted_cost),
            "refused": plan.refused,
            "refused_theta": list(plan.refused_theta or []),
        }
        self.episode += 1
        return row, record

    def _observe(self, plan: EpisodePlan, result: EpisodeResult) -> None:
        """The learner's observations of the episode: the refused candidate's simulation
        first, where the plan has one, else the refusal with its bound (the plant's episode of
        the deployed theta, :meth:`~mpcmobo.learners.Learner.observe_refused`), then the
        plant's episode; nothing once tuning has converged."""
        if plan.converged:
            return
        if plan.simulated:
            self._observe_simulated(plan)
        elif plan.refused and math.isfinite(plan.refused_bound):
            bounded = replace(result, spread=plan.refused_bound)
            self.learner.observe_refused(np.asarray(plan.refused_theta, float), bounded)
        self.learner.observe(plan.theta, result)

    def _observe_simulated(self, plan: EpisodePlan) -> None:
        """The refused candidate's episode on the learner's model of the plant
        (:meth:`prediction_params`) from the plan's start with its noise, as the learner's
        simulated observation (:meth:`~mpcmobo.learners.Learner.observe_simulated`), with the
        factor within which the model's costs are trusted (``spread``: ``SPREAD_ERRORS`` RMS
        log errors of its predictions so far); a closed loop that fails is observed as a
        failed episode."""
        theta = np.asarray(plan.refused_theta, float)
        params = self.prediction_params(np.asarray(plan.deployed, float))
        record: EpisodeRecord | None
        try:
            record = rollout(
                self.system,
                self.mpc,
                theta,
                plan.x0,
                self.steps,
                noise=plan.noise,
                plant=self._model_plant(params),
                plant_seed=plan.plant_seed,
            )
        except EPISODE_FAILURES:
            record = None
        result, _ = self._result(theta, record)
        result.start_id = plan.start_id
        result.x0 = plan.x0.copy()
        result.spread = math.exp(SPREAD_ERRORS * self.price.error())
        if self.learner.uses_start_cost():
            result.start_cost = self.start_cost(plan.x0)
        self.learner.observe_simulated(theta, result)

    def _model_plant(self, params: np.ndarray) -> gymnasium.Env:
        """The model with ``params`` as a noise-free plant (cached per parameters)."""
        key = np.asarray(params, float).tobytes()
        plant = self._model_plants.get(key)
        if plant is None:
            plant = model_plant(self.system, self.mpc, np.asarray(params, float))
            self._model_plants[key] = plant
        return plant

    def excess_cost(
        self,
        plan: EpisodePlan,
        plant_cost: float,
        result: EpisodeResult,
        deployed_cost: float = np.nan,
    ) -> float:
        """What the episode cost the plant beyond the deployed controller from the same start:
        0 where it ran the deployed theta; else its plant cost minus ``deployed_cost`` where
        that was measured. Where it was not (a real plant), the model's two predictions from
        the episode's start with its exploration, the episode's theta's ``c`` and the deployed
        theta's ``d``, give the ratio of the two costs, and the excess is the plant cost times
        ``1 - d / c``: a bias of the model common to both predictions cancels, as in the
        exploration budget (a structurally wrong model that under-predicts every closed loop
        by a third would otherwise put the excess of a candidate as good as the deployed
        controller at minus a third of its cost). The predictions are the budget's, made
        before the episode ran (:meth:`_priced`), else the closed loops of both thetas on the
        deployed theta's own model (the MPC's model with its learned model parameters); NaN
        where neither is known."""
        if plan.deployed is None or not np.isfinite(plant_cost):
            return np.nan
        deployed = np.asarray(plan.deployed, float)
        if np.array_equal(deployed, plan.theta):
            return 0.0
        if np.isfinite(deployed_cost):
            return float(plant_cost - deployed_cost)
        if np.isfinite(plan.predicted_deployed):
            return _paired_excess(plant_cost, plan.predicted_cost, plan.predicted_deployed)
        if result.exploration is None or result.x0 is None:
            return np.nan
        params = self._model_of(deployed)
        d = self.start_cost(result.x0, deployed, params, result.exploration)
        c = self.start_cost(result.x0, plan.theta, params, result.exploration)
        return _paired_excess(plant_cost, c, d)

    def _model_of(self, theta: np.ndarray) -> np.ndarray:
        """The model parameters the MPC with ``theta`` predicts with: its own, with the
        learnable ones theta holds."""
        p = np.array(self.mpc.model_params, float)
        param = self.mpc.param
        if "model" in param.blocks:
            p[list(param.model_param_index)] = np.asarray(theta, float)[param.blocks["model"]]
        return p

    def start_cost(
        self,
        x0: np.ndarray,
        theta: np.ndarray | None = None,
        params: np.ndarray | None = None,
        noise: np.ndarray | None = None,
    ) -> float:
        """The start covariate of ``x0``: the mean stage cost of ``theta`` (default the
        learner's ``start_model()``, else its theta0) from ``x0`` in a noise-free closed loop on
        the model with ``params`` (default the MPC's own model), the episode's length; NaN if
        that closed loop fails; with ``noise`` (an episode's exploration, (steps, nu)), that
        episode's exploration replayed (the twin's prediction of the episode). Cached; a
        function of its arguments alone, so the random streams and a resumed run are
        unaffected."""
        if theta is None:
            model = self.learner.start_model()
            if model is not None:
                theta, params = model
            else:
                theta = self.learner.theta0
        theta = self.mpc.check_theta(theta)
        p = np.asarray(self.mpc.model_params if params is None else params, float)
        e = None if noise is None else np.asarray(noise, float)
        if e is not None and e.shape != (self.steps, self.system.nu):
            raise ValueError(
                f"exploration of shape {e.shape}, not ({self.steps}, {self.system.nu})"
            )
        key = _start_key(x0, theta, p, e)
        if key not in self._start_costs:
            plant = self._model_plant(p)
            cost = model_costs(self.system, self.mpc, theta, x0, self.steps, plant, e)
            self._start_costs[key] = float(cost[0])  # NaN if it failed: the tests fall back
        return self._start_costs[key]

    def start_costs(
        self,
        starts: np.ndarray,
        theta: np.ndarray,
        params: np.ndarray,
        noise: np.ndarray | None = None,
    ) -> np.ndarray:
        """:meth:`start_cost` of every start in ``starts`` (n, nx) (what a learner asks for when
        its covariate's model changes); ``noise``: one start's exploration, replayed. The
        closed loops not cached yet run together (:func:`model_costs`)."""
        starts = np.atleast_2d(starts)
        if theta is not None and params is not None and len(starts) > 1:
            th, p = self.mpc.check_theta(theta), np.asarray(params, float)
            e = None if noise is None else np.asarray(noise, float)
            new = {_start_key(x0, th, p, e): x0 for x0 in starts}
            new = {k: x0 for k, x0 in new.items() if k not in self._start_costs}
            if len(new) > 1 and (e is None or e.shape == (self.steps, self.system.nu)):
                plant = self._model_plant(p)
                costs = model_costs(
                    self.system, self.mpc, th, np.array(list(new.values())), self.steps, plant, e
                )
                self._start_costs.update(zip(new, (float(c) for c in costs)))
        return np.array([self.start_cost(x0, theta, params, noise) for x0 in starts])

    def _propose(self) -> tuple[np.ndarray, str]:
        """The learner's proposal; if the learner fails (an exception, or a theta that is not
        finite), the episode runs its incumbent instead and the error is recorded."""
        try:
            theta = np.asarray(self.learner.propose(), dtype=float)
            if theta.shape != (self.learner.space.n_theta,) or not np.all(np.isfinite(theta)):
                raise ValueError(f"the proposal is not a finite theta: {theta!r}")
            return theta, ""
        except Exception as err:  # noqa: BLE001 - a learner's failure never ends a run
            theta = np.asarray(self.learner.incumbent(), dtype=float)
            return theta, f"proposal failed, ran the incumbent: {type(err).__name__}: {err}"

    def _result(self, theta: np.ndarray, record: EpisodeRecord | None) -> tuple[EpisodeResult, str]:
        """What the learner observes of an episode (the critic fitted to its record, the
        objectives); a missing or broken episode is all NaN, with its error."""
        if record is not None:
            try:
                result, _ = episode_result(record, self.critic, self.previous_Vc, self.beta)
                return result, ""
            except EPISODE_FAILURES as err:
                error = f"{type(err).__name__}: {err}"
        else:
            error = ""
        nan = EpisodeResult(
            objectives=np.full(4, np.nan), grad=np.zeros(len(theta)), critic_ok=False
        )
        return nan, error

    def state_dict(self) -> dict:
        """Everything needed to continue the run exactly: episode, random streams, learner state."""
        return {
            "episode": self.episode,
            "previous_Vc": self.previous_Vc,
            "rng_start": self.rng_start.bit_generator.state,
            "rng_noise": self.rng_noise.bit_generator.state,
            "learner": self.learner.state_dict(),
            "price": self.price.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict`."""
        self.episode = int(state["episode"])
        self.previous_Vc = state["previous_Vc"]
        self.rng_start.bit_generator.state = state["rng_start"]
        self.rng_noise.bit_generator.state = state["rng_noise"]
        self.learner.load_state_dict(state["learner"])
        self.price.load_state_dict(state.get("price"))
