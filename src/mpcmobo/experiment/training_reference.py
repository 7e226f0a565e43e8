"""J~*: the like-for-like reference of the training curve J~ (f1, eq. cl_perf) of Fig. 1.

J* (:mod:`mpcmobo.experiment.evaluation`) is the reference of J_eval: the same undiscounted mean
stage cost, on the same fixed evaluation starts, without exploration, of the perfect-model MPC.
J~ of a learning episode is something else: discounted, with exploration noise, from a training
start. Its reference J~* is computed the same way: f1 of the perfect-model MPC (theta0) on the
first training episodes of each seed, whose initial states and exploration noise are drawn by the
job's own :class:`~mpcmobo.experiment.loop.LearningRun`, so that they are exactly those of every
learner's first episodes on that seed. It is computed once per study, with J*, and stored in the
study's :class:`~mpcmobo.experiment.records.Reference` (``training``) and in ``summary.json``
(``J_tilde_star``, ``J_tilde_star_per_seed``, ``J_tilde_star_episodes``).

With an exploration ``decay`` below 1 the reference has the noise level of the first episodes.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mpcmobo.experiment import interrupts
from mpcmobo.experiment.build import build_plant, needs_plant
from mpcmobo.experiment.job import _learning_run
from mpcmobo.experiment.loop import EPISODE_FAILURES
from mpcmobo.experiment.records import Reference, TrainingReference
from mpcmobo.experiment.settings import Settings
from mpcmobo.mpc import ParametricMPC, rollout
from mpcmobo.rl.objectives import f1_closed_loop_cost
from mpcmobo.systems.base import System


def training_reference_episodes(settings: Settings) -> int:
    """How many perfect-model training episodes make J~* of a seed (also the window of the
    figure's moving mean of J~): one cycle of the starts (``n_cycle_starts``) with cycled
    starts, else as many as J* has evaluation starts (``evaluation.n_starts``)."""
    if settings.start_mode == "cycle":
        return int(settings.n_cycle_starts)
    return int(settings.evaluation.n_starts)


def training_reference(
    settings: Settings, system: System, seed: int, mpc: ParametricMPC, n_episodes: int
) -> TrainingReference:
    """J~ (f1) of the perfect-model MPC ``mpc`` with theta0 on the first ``n_episodes``
    training episodes of ``seed``: the same initial states and exploration noise as a learner's
    episodes 0..n-1 on that seed, and the same function,
    :func:`~mpcmobo.rl.objectives.f1_closed_loop_cost`, that gives the learners' J~. A diverged
    episode counts as NaN, as it does for a learner."""
    plant = build_plant(settings, system) if needs_plant(settings) else None
    run = _learning_run(settings, system, settings.learners[0], seed, plant)  # starts, noise
    values, starts = [], []
    for episode in range(n_episodes):
        x0 = run.next_start()
        run.exploration.episode = episode
        try:
            record = rollout(
                system,
                mpc,
                None,
                x0,
                run.steps,
                rng=run.rng_noise,
                exploration=run.exploration,
                sensitivities=False,
                plant=plant,
                plant_seed=run.plant_seed(),
            )
            values.append(f1_closed_loop_cost(record))
        except EPISODE_FAILURES:
            values.append(math.nan)
        starts.append([float(v) for v in x0])
        run.episode += 1
    return TrainingReference(int(seed), values, starts)


def training_references(settings: Settings, system: System) -> list[TrainingReference]:
    """J~* of every seed of the study (the ``training`` field of its reference)."""
    mpc = ParametricMPC(system, model="perfect", **settings.mpc.options())
    interrupts.guard_solves(mpc)  # an interrupt ends a solve, never fails it
    n = training_reference_episodes(settings)
    return [training_reference(settings, system, s, mpc, n) for s in settings.seeds]


def training_summary(reference: Reference) -> dict[str, Any]:
    """The keys of ``summary.json`` for J~*: ``J_tilde_star`` (the median over the seeds of
    their J~*), ``J_tilde_star_per_seed`` and ``J_tilde_star_episodes``; in a run whose
    reference predates J~*, ``J_tilde_star`` is null and ``J_tilde_star_reason`` says why."""
    if not reference.training:
        reason = (
            f"no reference model: {reference.J_star_missing}"
            if reference.J_star is None
            else "the run's reference.pkl was computed before J~* existed"
        )
        return {"J_tilde_star": None, "J_tilde_star_reason": reason}
    per_seed = {str(t.seed): t.mean for t in reference.training}
    finite = [v for v in per_seed.values() if math.isfinite(v)]
    out: dict[str, Any] = {
        "J_tilde_star": float(np.median(finite)) if finite else None,
        "J_tilde_star_per_seed": per_seed,
        "J_tilde_star_episodes": len(reference.training[0].J_tilde),
    }
    failed = [seed for seed, v in per_seed.items() if not math.isfinite(v)]
    if failed:
        out["J_tilde_star_reason"] = (
            f"an episode of the perfect-model MPC failed (the plant diverged or returned a "
            f"state that is not finite) on the training starts of seed(s) {', '.join(failed)}: "
            "their J~* is null" + ("" if finite else ", and so is the median")
        )
    return out
