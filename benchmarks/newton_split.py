"""Where the default MPC step's time goes: the steps the Newton steps, the barrier path and IPOPT solve.

On the states of ``benchmarks/step_time.py`` (4 closed-loop CSTR episodes of 60 steps, initial
states from ``default_rng(0)``), the default :class:`mpcmobo.mpc.ParametricMPC` (Newton steps
at tau first, IPOPT when they do not converge; with ``--barrier-steps 30`` the barrier path
between them) is timed step by step, with both sensitivities; the steps are split by the path
that solved them. The warm steps that fall back to IPOPT are also split by their warm start:
whether the new state makes rows of the shifted plan violated (``H >= 0``, so the Newton steps
at tau cannot start) and at which stages, or the start is interior and the Newton steps did not
converge (too slow a residual decrease, or out of steps).

    PYTHONPATH=src .venv/bin/python benchmarks/newton_split.py [--codegen] [--barrier-steps 30]
        [--no-barrier-push]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mpcmobo.mpc import ParametricMPC
from mpcmobo.systems import get_system


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--codegen", action="store_true")
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--barrier-steps", type=int, default=None, help="default: the MPC's")
    ap.add_argument(
        "--no-barrier-push",
        action="store_true",
        help="the barrier path only from interior warm starts (barrier_push=False)",
    )
    args = ap.parse_args(argv)
    s = get_system("cstr")
    opts: dict = {} if args.barrier_steps is None else {"barrier_steps": args.barrier_steps}
    if args.no_barrier_push:
        opts["barrier_push"] = False
    mpc = ParametricMPC(s, "imperfect", codegen=args.codegen, **opts)
    rng = np.random.default_rng(0)
    x0s = [s.sample_initial_state(rng) for _ in range(args.episodes)]
    mpc.solve(x0s[0], mpc.theta0)  # first-call allocations
    paths: dict[str, list[float]] = {
        "newton": [],
        "barrier": [],
        "ipopt warm": [],
        "ipopt cold": [],
    }
    newton_steps, barrier_steps = [], []
    why: dict[str, int] = {}  # the warm IPOPT steps by their warm start
    m = mpc.nin // (mpc.N + 1)  # general rows per stage (stage i: rows i*m .. (i+1)*m - 1)
    for x0 in x0s:
        mpc.reset()
        x = x0.copy()
        for k in range(60):
            start = None
            if mpc._prev is not None:  # which rows of the shifted plan the new state violates
                p = np.concatenate([x, mpc.theta0])
                H = np.asarray(mpc._h_call(mpc._prev["w_shift"], p)[0]).reshape(-1)[: mpc.nin]
                stages = sorted({int(r) // m for r in np.flatnonzero(H >= 0)})
                start = f"violated rows at stages {stages}" if stages else "interior start"
            t0 = time.perf_counter()
            sol = mpc.solve(x, mpc.theta0, sensitivities=True)
            dt = time.perf_counter() - t0
            if sol.status == "Newton_Succeeded":
                paths["newton"].append(dt)
                newton_steps.append(sol.iterations)
            elif sol.status == "Barrier_Succeeded":
                paths["barrier"].append(dt)
                barrier_steps.append(sol.iterations)
            else:
                paths["ipopt cold" if k == 0 else "ipopt warm"].append(dt)
                if start is not None:
                    why[start] = why.get(start, 0) + 1
            x = s.plant_step(x, sol.action)
    n = sum(len(v) for v in paths.values())
    everything = np.concatenate([np.array(v) for v in paths.values()])
    print(f"codegen={args.codegen}: {n} steps, median step {1e3 * np.median(everything):.2f} ms")
    for name, v in paths.items():
        if v:
            print(
                f"  {name:<11} {len(v):>4} steps ({100 * len(v) / n:4.1f} %), median "
                f"{1e3 * np.median(v):6.2f} ms, mean {1e3 * np.mean(v):6.2f} ms"
            )
    print(f"  Newton steps per Newton-path solve: mean {np.mean(newton_steps):.2f}")
    if barrier_steps:
        print(f"  Newton steps per barrier-path solve: mean {np.mean(barrier_steps):.2f}")
    for start, count in sorted(why.items()):
        print(f"  warm IPOPT steps, {start}: {count}")


if __name__ == "__main__":
    main()
