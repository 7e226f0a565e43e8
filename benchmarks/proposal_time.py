"""Wall time of one EHVI proposal (GP fit + acquisition optimisation), 4 objectives, d = 13.

Compares ``GPSurrogate.fit`` + ``propose_ehvi`` (warm-started state, as inside a learner loop)
with a plain BoTorch loop: a fresh ``fit_gpytorch_mll`` of a ``ModelListGP`` of default
``SingleTaskGP``s, ``qLogNoisyExpectedHypervolumeImprovement`` with default settings except
``prune_baseline=True`` (as in BoTorch's tutorials; it makes the plain loop faster, not slower)
and ``optimize_acqf(num_restarts=10, raw_samples=512)``.

Synthetic data: ``f_j(x) = |x - a_j|^2 + 0.3 sin(3 w_j . x) + 0.05 eps`` with random anchors
``a_j`` (conflicting objectives) on uniform random x in [0,1]^13, costs minimised. With
``--starts K`` (default 6, as the learners' default cycle of starts) the rows cycle through K
groups, f1 and f2 get one offset per group, and our surrogate fits those offsets (start effects,
as inside ``mobo``); the plain loop gets the same data without groups. ``--starts 0``: none.

Threads: our proposals run with one torch thread, as inside a study's worker process (which sets
it once at start); the plain loop runs with torch's default thread count.

    .venv/bin/python benchmarks/proposal_time.py            # full: n in {50, 200, 600}
    .venv/bin/python benchmarks/proposal_time.py --quick    # n in {50, 200}, fewer repetitions
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import numpy as np
import torch
from botorch.acquisition.multi_objective.logei import qLogNoisyExpectedHypervolumeImprovement
from botorch.fit import fit_gpytorch_mll
from botorch.models import ModelListGP, SingleTaskGP
from botorch.optim import optimize_acqf
from gpytorch.mlls import SumMarginalLogLikelihood

from mpcmobo.bo import AcqfSearch, EHVIOptions, GPSurrogate, propose_ehvi, reference_point
from mpcmobo.learners.mobo import search_effort
from mpcmobo.learners.options import MOBOOptions

D, M = 13, 4
# the mobo learner's EHVI options and search effort at its defaults, halved from
# reduce_effort_after observations on (search_effort, as in MOBOLearner)
_SEARCH = MOBOOptions().search
OPTIONS = EHVIOptions(mc_samples=_SEARCH.mc_samples)
SEARCH = AcqfSearch(_SEARCH.num_restarts, _SEARCH.raw_samples, _SEARCH.maxiter)
REDUCE_AFTER = _SEARCH.reduce_effort_after


def make_problem(seed: int = 0):
    rng = np.random.default_rng(seed)
    A = rng.uniform(0.2, 0.8, size=(M, D))
    W = rng.normal(size=(M, D))

    def f(X: np.ndarray) -> np.ndarray:
        Y = np.stack([((X - A[j]) ** 2).sum(1) + 0.3 * np.sin(3 * X @ W[j]) for j in range(M)], 1)
        return Y + 0.05 * rng.normal(size=Y.shape)

    return f, rng


def time_fast(X, Y, ref, n, warmup, reps, groups=None):
    """Consecutive proposals at n, n+1, ... as in a loop; returns the timed ones (s)."""
    flags = None if groups is None else [True, True, False, False]
    sur = GPSurrogate(M, group_outputs=flags)  # as in the mobo learner
    times, full = [], []
    for i in range(warmup + reps):
        Xi, Yi = X[: n + i], Y[: n + i]
        t0 = time.perf_counter()
        sur.fit(Xi, Yi, groups=None if groups is None else groups[: n + i])
        options, search = search_effort(n + i, OPTIONS, SEARCH, REDUCE_AFTER)
        x = propose_ehvi(sur, Xi, Yi, ref, seed=i, options=options, search=search)
        dt = time.perf_counter() - t0
        assert x.shape == (D,) and np.all((x >= 0) & (x <= 1))
        if i >= warmup:
            times.append(dt)
            full.append(sur.last_fit_was_full)
    return times, sum(full)


def time_plain(X, Y, ref, n, reps):
    times = []
    bounds = torch.stack([torch.zeros(D), torch.ones(D)]).double()
    for i in range(reps):
        tX = torch.as_tensor(X[: n + i])
        tY = -torch.as_tensor(Y[: n + i])  # BoTorch maximises
        t0 = time.perf_counter()
        model = ModelListGP(*[SingleTaskGP(tX, tY[:, j : j + 1]) for j in range(M)])
        fit_gpytorch_mll(SumMarginalLogLikelihood(model.likelihood, model))
        acq = qLogNoisyExpectedHypervolumeImprovement(
            model, ref_point=(-torch.as_tensor(ref)).tolist(), X_baseline=tX, prune_baseline=True
        )
        optimize_acqf(acq, bounds=bounds, q=1, num_restarts=10, raw_samples=512)
        times.append(time.perf_counter() - t0)
    return times


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="n in {50, 200}, fewer repetitions")
    p.add_argument("--sizes", type=int, nargs="*", default=None)
    p.add_argument("--reps", type=int, default=None, help="timed fast proposals per n")
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--plain-reps", type=int, default=None)
    p.add_argument("--starts", type=int, default=6, help="groups (cycled starts); 0: none")
    args = p.parse_args()
    sizes = args.sizes or ([50, 200] if args.quick else [50, 200, 600])
    reps = args.reps or (4 if args.quick else 10)
    plain_reps = args.plain_reps or (1 if args.quick else 2)

    f, rng = make_problem(0)
    nmax = max(sizes) + args.warmup + reps + plain_reps + 1
    X = rng.uniform(size=(nmax, D))
    Y = f(X)
    groups = None
    if args.starts > 0:
        groups = np.arange(nmax) % args.starts
        Y[:, :2] += rng.normal(scale=0.5, size=(args.starts, 2))[groups]
    ref = reference_point(Y[:20])  # fixed rule: from the initial design only

    default_threads = torch.get_num_threads()
    print(
        f"torch {torch.__version__}, threads 1 (mpcmobo) and {default_threads} (plain), "
        f"{os.cpu_count()} cpus, {platform.processor() or platform.machine()}, "
        f"load avg {os.getloadavg()[0]:.1f}, starts {args.starts}, mobo effort {OPTIONS} "
        f"{SEARCH} halved from {REDUCE_AFTER}"
    )
    rows = []
    for n in sizes:
        torch.set_num_threads(1)  # as in a study's worker (mpcmobo.experiment.study)
        ft, nfull = time_fast(X, Y, ref, n, args.warmup, reps, groups)
        torch.set_num_threads(default_threads)
        pt = time_plain(X, Y, ref, n, plain_reps)
        fmed, pmed = statistics.median(ft), statistics.median(pt)
        rows.append((n, fmed, statistics.mean(ft), max(ft), len(ft), nfull, pmed, len(pt)))
        print(f"n={n}: fast {ft}  plain {pt}  load {os.getloadavg()[0]:.1f}", flush=True)

    print()
    print(
        "| n | mpcmobo median [s] | mpcmobo mean [s] | mpcmobo max [s] | timed (full refits) "
        "| plain BoTorch median [s] | plain reps | speed-up (median) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for n, fmed, fmean, fmax, k, nfull, pmed, kp in rows:
        print(
            f"| {n} | {fmed:.2f} | {fmean:.2f} | {fmax:.2f} | {k} ({nfull}) | {pmed:.1f} | {kp} "
            f"| {pmed / fmed:.0f}x |"
        )


if __name__ == "__main__":
    main()
