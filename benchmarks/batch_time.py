"""Time of the twin's judgement of a theta: 64 closed loops on the model, batched or not.

The twin judges a theta by the mean stage cost of its noise-free closed loops on the identified
model from ``JUDGE_STARTS`` (64) starts (``mpcmobo.learners.twin.Twin.simulate``, through
``mpcmobo.experiment.loop.model_costs``). This script measures, in one run and interleaved
(sequential, then batched, ``--repeats`` times, the median kept), on the CSTR of
``--config`` (default ``benchmarks/configs/ident.toml``: identification, generated code) with
the identified model equal to the true one (as in ``benchmarks/twin.py``), the system's
episode length, and the twin's 64 starts of ``--seed``:

- ``sequential``: the 64 closed loops one after the other (``model_rollout`` per start);
- ``batched``: ``model_costs``, the 64 closed loops in lock-step (``mpcmobo.mpc.rollouts``);
- ``one loop``: a sequential closed loop's mean time (sequential / 64), the unit of the target
  "judging a theta costs at most 5 closed loops".

for two thetas: theta0 with the identified parameters, and a theta tuned on the twin (a
short ``tune_on_twin`` from it, ``--tune-episodes``, batched). Times are CPU seconds of this
process (``time.process_time``: the machine is shared, wall times are given too). Also: the
largest difference of the costs (0: the batch gives the sequential records bit for bit), the
solves per closed loop that left the batched Newton path (each loop alone: IPOPT, or first the
continuation with ``--continuation N``) and their share of the batch's CPU time (one more
batched run).

    .venv/bin/python benchmarks/batch_time.py            # 3 repeats
    .venv/bin/python benchmarks/batch_time.py --repeats 1 --tune-episodes 4
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from mpcmobo.experiment.build import build_system, identified_parameters
from mpcmobo.experiment.loop import model_costs
from mpcmobo.experiment.settings import load_settings
from mpcmobo.identify import ModelFit
from mpcmobo.learners.twin import TWIN_STARTS, Twin, tune_on_twin
from mpcmobo.mpc import ParametricMPC, model_plant, model_rollout, rollouts
from mpcmobo.rl.objectives import mean_stage_cost


def _timed(fn: Callable[[np.ndarray], Any], theta: np.ndarray) -> tuple[Any, float, float]:
    """``fn(theta)``, its CPU and its wall seconds."""
    c, w = time.process_time(), time.perf_counter()
    out = fn(theta)
    return out, time.process_time() - c, time.perf_counter() - w


def _own_share(
    system: Any, mpc: ParametricMPC, theta: np.ndarray, starts: np.ndarray, steps: int, p: Any
) -> tuple[list, float]:
    """The batched closed loops' records and the share of their CPU time in the loops' own
    solves (``ParametricMPC.solve``: IPOPT, each loop alone)."""
    own, solve = [0.0], mpc.solve

    def timed_solve(*a: Any, **k: Any) -> Any:
        c = time.process_time()
        try:
            return solve(*a, **k)
        finally:
            own[0] += time.process_time() - c

    mpc.solve = timed_solve  # type: ignore[method-assign]
    try:
        c = time.process_time()
        recs = rollouts(system, mpc, theta, starts, steps, plant_params=p)
        return recs, own[0] / (time.process_time() - c)
    finally:
        mpc.solve = solve  # type: ignore[method-assign]


def steps_of(mpc: ParametricMPC) -> int:
    """The continuation's most steps per path in ``mpc``'s solver (0: none)."""
    interior = mpc.solver.interior
    return 0 if interior is None else interior.max_steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="benchmarks/configs/ident.toml")
    ap.add_argument("--seed", type=int, default=0, help="the twin's starts (Twin.make)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--tune-episodes", type=int, default=10)
    ap.add_argument(
        "--continuation",
        type=int,
        default=None,
        help="the MPC's continuation_steps (default: the config's)",
    )
    args = ap.parse_args()
    settings = load_settings(args.config)
    system = build_system(settings, "bo")
    fit = ModelFit(system, identified_parameters(settings, system, "bo"))
    t0 = time.perf_counter()
    options = settings.mpc.options()
    if args.continuation is not None:
        options["continuation_steps"] = args.continuation
    mpc = ParametricMPC(system, model="imperfect", **options)
    build = time.perf_counter() - t0
    true = np.asarray(system.true_params, float)
    plant = model_plant(system, mpc, true)
    steps = system.episode_steps if settings.steps is None else settings.steps

    def costs(starts: np.ndarray, theta: np.ndarray, params: np.ndarray) -> np.ndarray:
        return model_costs(system, mpc, theta, starts, steps, plant)

    twin = Twin.make(system, true, costs, args.seed)

    def sequential(theta: np.ndarray) -> list[float]:  # model_costs' closed loops one by one
        return [
            mean_stage_cost(model_rollout(system, mpc, theta, x0, steps, plant=plant))
            for x0 in twin.starts
        ]

    def batched(theta: np.ndarray) -> np.ndarray:
        return costs(twin.starts, theta, true)

    start = fit.theta_with(mpc.theta0, true[fit.index])
    rng = np.random.default_rng(np.random.SeedSequence([args.seed, 11]))
    tuned_on = np.array([system.sample_initial_state(rng) for _ in range(TWIN_STARTS)])
    space = system.search_space
    tuned = tune_on_twin(space, start, true, costs, tuned_on, args.seed, args.tune_episodes)
    print(
        f"{system.name}, {len(twin.starts)} starts x {steps} steps, codegen "
        f"{settings.mpc.codegen}, continuation_steps {steps_of(mpc)} "
        f"(MPC built in {build:.1f} s), {args.repeats} repeats; tuned "
        f"theta: {tuned.cost / tuned.base_cost:.3f} of theta0's cost on its {TWIN_STARTS} starts"
    )
    print(
        "| theta | sequential, 64 loops (CPU s) | batched (CPU s) | one loop (CPU s) "
        "| batched / one loop | sequential / batched | wall: sequential, batched (s) "
        "| largest cost difference | own solves per loop | their share of the batch |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, theta in (("theta0", start), ("tuned", tuned.theta)):
        seq_t, bat_t, seq_w, bat_w = [], [], [], []
        for _ in range(args.repeats):
            seq, c, w = _timed(sequential, theta)
            seq_t.append(c)
            seq_w.append(w)
            bat, c, w = _timed(batched, theta)
            bat_t.append(c)
            bat_w.append(w)
        recs, share = _own_share(system, mpc, theta, twin.starts, steps, true)
        own = [sum(s != "Newton_Succeeded" for s in r.status) for r in recs if hasattr(r, "status")]
        diff = float(np.nanmax(np.abs(np.asarray(seq) - np.asarray(bat))))
        S, B = float(np.median(seq_t)), float(np.median(bat_t))
        one = S / len(twin.starts)
        print(
            f"| {name} | {S:.2f} | {B:.2f} | {one:.3f} | {B / one:.1f} | {S / B:.2f} "
            f"| {np.median(seq_w):.2f}, {np.median(bat_w):.2f} | {diff:.1e} "
            f"| {np.mean(own):.2f} | {share:.0%} |"
        )


if __name__ == "__main__":
    main()
