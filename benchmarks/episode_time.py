"""Per-episode MPC time on the CSTR, as in a study: what the MPC costs a learner per episode.

For each variant of :class:`mpcmobo.mpc.ParametricMPC`, on the same starts and noise, it times
a learning episode (``rollout`` of 60 steps with sensitivities and the study's default Gaussian
exploration, std 2 % of each input's range) and an evaluation episode (60 steps, no
sensitivities, no exploration), interleaved episode by episode. Reported: median seconds per
episode and the ratio ``ipopt`` median / variant median (``ipopt``: IPOPT only, the MPC of the
default study before issue 13's second part, apart from lam_p).

    PYTHONPATH=src .venv/bin/python benchmarks/episode_time.py [--starts 6] [--repeats 2]
"""

from __future__ import annotations

import argparse
import time

import casadi as ca
import numpy as np

from mpcmobo.mpc import ParametricMPC, rollout
from mpcmobo.rl import GaussianExploration
from mpcmobo.systems import get_system

VARIANTS = {
    "ipopt": {"newton_steps": 0},
    "default": {},
    "codegen": {"codegen": True},
}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--starts", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
    s = get_system("cstr")
    mpcs = {n: ParametricMPC(s, "imperfect", **o) for n, o in VARIANTS.items()}
    expl = GaussianExploration(std=0.02 * (s.u_ub - s.u_lb))
    rng = np.random.default_rng(0)
    starts = [s.sample_initial_state(rng) for _ in range(args.starts)]
    learn = {n: [] for n in mpcs}
    evals = {n: [] for n in mpcs}
    for _rep in range(args.repeats):
        for i, x0 in enumerate(starts):
            for n, mpc in mpcs.items():
                theta = mpc.theta0
                mpc.reset()
                t0 = time.perf_counter()
                rollout(s, mpc, theta, x0, 60, rng=np.random.default_rng(i), exploration=expl)
                learn[n].append(time.perf_counter() - t0)
                mpc.reset()
                t0 = time.perf_counter()
                rollout(s, mpc, theta, x0, 60, sensitivities=False)
                evals[n].append(time.perf_counter() - t0)
    print(f"CSTR, {args.starts} starts x {args.repeats} repeats, casadi {ca.__version__}")
    print(
        f"{'variant':<10} {'learning ep. [s]':>17} {'ratio':>6} {'eval ep. [s]':>13} {'ratio':>6}"
    )
    for n in mpcs:
        lm, em = np.median(learn[n]), np.median(evals[n])
        print(
            f"{n:<10} {lm:>17.3f} {np.median(learn['ipopt']) / lm:>6.2f} {em:>13.3f} "
            f"{np.median(evals['ipopt']) / em:>6.2f}"
        )


if __name__ == "__main__":
    main()
