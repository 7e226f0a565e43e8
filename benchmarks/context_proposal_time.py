"""Wall time of one mobo learner step with the issue-11 safe design (contextual GP over (z, x0),
constrained EHVI over the contexts, the deployment rule: ``benchmarks/configs/safe_context.toml``,
opt-in), at n synthetic observations, on the CSTR's search space and initial-state box.

Synthetic data as in ``benchmarks/proposal_time.py`` (4 conflicting objectives of z) with a
context effect ``+ 0.5 |c - 0.5|^2`` on every objective, positive costs, and a violation
``exp(3 (z_0 - 0.7)) * u`` (u uniform): a fitted step (observe: GP fit + deployment rule) and a
proposal (constrained EHVI + safety filter) are timed separately, ``--reps`` times each at every
n (the fits after the first are conditioning fits, as in a learner loop). Three learners on the
same data in the same run: the safe design (8 contexts), the same with 16 contexts (session
4's number), and the defaults (no context, no budget, no deployment rule; since session 7 all
three with the trust region, the default). CPU time
(``time.process_time``, one torch thread) is reported besides wall time: on the shared
machine the wall time moves with the load, the CPU time much less.

    .venv/bin/python benchmarks/context_proposal_time.py --n 100 400 600
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from mpcmobo.bo.context import ContextSpec
from mpcmobo.learners.base import EpisodeResult
from mpcmobo.learners.bo import MOBOLearner
from mpcmobo.systems import get_system

SAFE = dict(context="x0", violation_budget=1.0, deploy_confidence=0.9)
VARIANTS = {
    "safe design": SAFE,
    "safe design, 16 contexts": {**SAFE, "n_contexts": 16},
    "defaults": {},
}


def synthetic(rng, Z, C):
    d = Z.shape[1]
    A = np.random.default_rng(0).uniform(0.2, 0.8, size=(4, d))
    ctx = 0.5 * ((C - 0.5) ** 2).sum(1)
    Y = np.stack(
        [((Z - A[j]) ** 2).sum(1) + ctx + 0.05 * rng.normal(size=len(Z)) for j in range(4)], 1
    )
    V = np.exp(3 * (Z[:, 0] - 0.7)) * rng.uniform(size=len(Z))
    return np.abs(Y) + 0.01, V


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[100, 400])
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)  # as in a study's worker
    system = get_system("cstr")
    spec = ContextSpec.from_system(system)
    for n in args.n:
        for label, options in VARIANTS.items():
            run(label, options, n, args.reps, system, spec)


def run(label, options, n, reps, system, spec) -> None:
    space, theta0 = system.search_space, system.parameterization.theta0
    rng = np.random.default_rng(n)
    learner = MOBOLearner(space, theta0, seed=0, contexts=spec, **options)
    Z = rng.uniform(size=(n, space.dim))
    X0 = np.array([system.sample_initial_state(rng) for _ in range(n)])
    Y, V = synthetic(rng, Z, spec.unit(X0))
    learner.Z_, learner.Y_ = Z, Y
    learner.grads_ = np.zeros((n, space.n_theta))
    learner.starts_ = np.full(n, -1)
    learner.C_, learner.V_ = spec.unit(X0)[:, : learner._dc], V
    learner.n_observed = n
    learner.ref_point_ = np.quantile(Y, 0.9, axis=0)
    learner._fit()
    fits, props, cfits, cprops = [], [], [], []
    for _ in range(reps):
        t0, c0 = time.perf_counter(), time.process_time()
        z = learner.propose()
        props.append(time.perf_counter() - t0)
        cprops.append(time.process_time() - c0)
        zu = space.to_unit(space.clip(z))[None, :]
        x0 = system.sample_initial_state(rng)
        y, v = synthetic(rng, zu, spec.unit(x0)[None, :])
        res = EpisodeResult(
            objectives=y[0], grad=np.zeros(space.n_theta), critic_ok=True, x0=x0, violation=v[0]
        )
        t0, c0 = time.perf_counter(), time.process_time()
        learner.observe(z, res)
        fits.append(time.perf_counter() - t0)
        cfits.append(time.process_time() - c0)
    med = statistics.median
    print(
        f"n={n} {label}: proposal median {med(props):.2f} s wall, {med(cprops):.2f} s CPU; "
        f"observe median {med(fits):.2f} s wall, {med(cfits):.2f} s CPU",
        flush=True,
    )


if __name__ == "__main__":
    main()
