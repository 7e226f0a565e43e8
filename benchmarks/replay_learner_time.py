"""CPU time of a GP learner's steps replayed on a real run's episodes (issue 11, session 9).

``benchmarks/context_proposal_time.py`` times a learner step on synthetic data; this script
replays the episodes a real run recorded in a job's checkpoint (``DIR/jobs/<job>/checkpoint.pkl``:
the learner's thetas, objectives, violations, initial states and starts), so that the data
have the structure a study produces (repeated thetas from verification episodes, a trust
region that has shrunk, cycled starts). For each ``n`` a learner with the run's options is
given the first ``n`` episodes and fitted, then ``--steps`` steps are timed: a proposal, then
the observation of the run's next episode (its recorded theta and outcomes, not the proposal,
so every learner variant sees the same data). ``--profile`` prints the cProfile of those steps
(cumulative time, top functions).

    .venv/bin/python benchmarks/replay_learner_time.py --run runs/study-safe-mobo --n 400 590
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pickle
import pstats
import time
from pathlib import Path

import numpy as np

from mpcmobo.experiment.job import make_study_learner
from mpcmobo.experiment.settings import build_system, load_settings
from mpcmobo.learners.base import EpisodeResult


def load_state(run: Path, job: str | None) -> tuple[str, int, dict]:
    """The learner name, seed and learner state of a job's checkpoint."""
    jobs = sorted((run / "jobs").iterdir()) if job is None else [run / "jobs" / job]
    ck = pickle.loads((jobs[0] / "checkpoint.pkl").read_bytes())
    return ck["learner"], int(ck["seed"]), ck["state"]["learner"]


def make(run: Path, name: str, seed: int, options: dict):
    settings = load_settings(run / "config.toml")
    if options:
        lo = dict(settings.learner_options)
        lo[name] = {**lo.get(name, {}), **options}
        settings = settings.model_copy(update={"learner_options": lo})
    system = build_system(settings)
    theta0 = system.parameterization.theta0
    return make_study_learner(settings, system, name, theta0, seed), system


def result_of(state: dict, i: int, learner) -> EpisodeResult:
    spec = learner.context_spec
    c = np.asarray(state["contexts_x0"], float)[i]
    x0 = None if spec is None or c.size == 0 else spec.lb + c * (spec.ub - spec.lb)
    return EpisodeResult(
        objectives=np.asarray(state["Y"], float)[i],
        grad=np.asarray(state["grads"], float)[i],
        critic_ok=True,
        start_id=int(state["starts"][i]),
        x0=x0,
        violation=float(state["violations"][i]),
    )


def prime(learner, state: dict, n: int) -> None:
    """The learner after the first ``n`` episodes of ``state`` (fitted from scratch)."""
    Z = np.asarray(state["Z"], float)[:n]
    learner.Z_, learner.Y_ = Z, np.asarray(state["Y"], float)[:n]
    learner.grads_ = np.asarray(state["grads"], float)[:n]
    learner.starts_ = np.asarray(state["starts"], int)[:n]
    learner.C_ = np.asarray(state["contexts_x0"], float)[:n, : learner._dc]
    learner.V_ = np.asarray(state["violations"], float)[:n]
    learner.n_observed = n
    learner.proposal_kinds_ = list(state["proposal_kinds"][:n])
    if hasattr(learner, "ref_point_") and state.get("ref_point") is not None:
        learner.ref_point_ = np.asarray(state["ref_point"], float)
    learner._fit()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, required=True)
    ap.add_argument("--job", default=None)
    ap.add_argument("--n", type=int, nargs="+", default=[400, 590])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument(
        "--trace",
        type=Path,
        default=None,
        help="write the proposals and deployed thetas of every step to this .npz (to compare "
        "two versions of the code: same file contents = same decisions)",
    )
    ap.add_argument(
        "--force-search",
        action="store_true",
        help="every timed proposal is an acquisition search (a pending verification is "
        "dropped), and the job's learner CPU is estimated from the run's own share of "
        "searches (summary line)",
    )
    ap.add_argument("--top", type=int, default=30)
    ap.add_argument("--sort", default="cumulative")
    ap.add_argument(
        "--option",
        action="append",
        default=[],
        help="KEY=VALUE learner option on top of the run's (a Python literal or a string)",
    )
    args = ap.parse_args()
    import ast

    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(1)  # as in a study's job: one torch and one BLAS thread
    threadpool_limits(1)
    options = {}
    for kv in args.option:
        k, v = kv.split("=", 1)
        try:
            options[k] = ast.literal_eval(v)
        except (ValueError, SyntaxError):
            options[k] = v
    name, seed, state = load_state(args.run, args.job)
    total = len(state["Z"])
    trace: dict[str, np.ndarray] = {}
    per_step: list[tuple[int, float, float]] = []  # n, observe, search proposal (CPU s)
    for n in args.n:
        learner, _ = make(args.run, name, seed, options)
        prime(learner, state, n)
        prof = cProfile.Profile() if args.profile else None
        cp, co = [], []
        kinds, proposals, deployed = [], [], []
        for i in range(n, min(total, n + args.steps)):
            if prof:
                prof.enable()
            if args.force_search:
                learner._verify_z = None
            c0 = time.process_time()
            proposals.append(learner.propose())
            c1 = time.process_time()
            theta = learner._theta(np.asarray(state["Z"], float)[i])
            learner.observe(theta, result_of(state, i, learner))
            c2 = time.process_time()
            if prof:
                prof.disable()
            deployed.append(learner.incumbent())
            cp.append(c1 - c0)
            co.append(c2 - c1)
            kinds.append(learner.proposal_kinds_[-1] if learner.proposal_kinds_ else "")
        print(
            f"n={n} {options or 'run options'}: {len(cp)} steps, CPU s per step: proposal "
            f"mean {np.mean(cp):.3f} (max {np.max(cp):.3f}), observe mean {np.mean(co):.3f} "
            f"(max {np.max(co):.3f}); total {np.sum(cp) + np.sum(co):.2f}; kinds {kinds}",
            flush=True,
        )
        trace[f"proposals_{n}"], trace[f"deployed_{n}"] = np.array(proposals), np.array(deployed)
        per_step.append((n, float(np.mean(co)), float(np.mean(cp))))
        if prof:
            s = io.StringIO()
            pstats.Stats(prof, stream=s).sort_stats(args.sort).print_stats(args.top)
            print(s.getvalue())
    if args.trace is not None:
        np.savez(args.trace, **trace)
    if args.force_search and len(per_step) > 1:
        print(estimate(per_step, state, total))


def estimate(per_step: list[tuple[int, float, float]], state: dict, total: int) -> str:
    """The learner CPU of the run's episodes ``n_0 .. total`` estimated from the timed steps:
    per episode, the observe time plus the search time if the run's proposal was a search
    (``proposal_kinds`` "search" or "safe"), both interpolated linearly in n."""
    ns = np.array([p[0] for p in per_step], float)
    obs = np.array([p[1] for p in per_step])
    srch = np.array([p[2] for p in per_step])
    kinds = list(state["proposal_kinds"])
    eps = np.arange(int(ns[0]), total)
    searched = np.array([kinds[i] in ("search", "safe") for i in eps], float)
    cpu = np.interp(eps, ns, obs) + searched * np.interp(eps, ns, srch)
    return (
        f"estimated learner CPU of episodes {int(ns[0])}-{total - 1}: {cpu.sum():.0f} s "
        f"(observe {np.interp(eps, ns, obs).sum():.0f} s, searches "
        f"{(searched * np.interp(eps, ns, srch)).sum():.0f} s over {int(searched.sum())} "
        f"searches)"
    )


if __name__ == "__main__":
    main()
