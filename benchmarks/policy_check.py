"""Whose policy? Each MPC variant and IPOPT under other options, from the SAME warm start.

On the closed loop of the step-time benchmark (4 CSTR episodes of 60 steps, initial states from
``default_rng(0)``), driven by ``--driver`` (``default``: the default MPC, as in the step-time
runs; ``ipopt``: the reference itself), the reference, the IPOPT-only MPC
(``ParametricMPC(newton_steps=0)``), solves every state from its own warm start (its shifted
previous solution and multipliers), and every candidate solves it from that same warm start, so a difference is the candidate's choice at that state and
not carried over from its own earlier steps (as in ``benchmarks/step_time.py``, where each
variant keeps its own warm start). Printed per candidate: how the steps were solved, the
states where its action differs from the reference's by more than 1e-4 (episode, step, |du|,
value against the reference's), and the largest |du|.

Candidates: the MPC's paths (``default``: Newton steps, then IPOPT; ``barrier``:
``barrier_steps=30``; ``barrier_interior``: with ``barrier_push=False``) and IPOPT itself with
one option changed (``ipopt_max_soc_0``: no second-order corrections; ``ipopt_alpha_y_full``;
``ipopt_mu_init_1e-4``; ``ipopt_cold``: no warm start): what "IPOPT's policy" means where two
local minima compete. ``--options NAME=JSON`` adds a candidate with those ParametricMPC options;
``--log EPISODE STEP`` prints the reference IPOPT's iteration log (``print_level`` 5) at that
state, from the same warm start.

    PYTHONPATH=src .venv/bin/python benchmarks/policy_check.py [--driver ipopt] [--codegen]
        [--options 'relax={"barrier_steps": 30, "barrier_relax": true}']
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from mpcmobo.mpc import ParametricMPC
from mpcmobo.systems import get_system

CANDIDATES: dict[str, dict] = {
    "default": {},
    "barrier": {"barrier_steps": 30},
    "barrier_interior": {"barrier_steps": 30, "barrier_push": False},
    "ipopt_max_soc_0": {"newton_steps": 0, "warm_options": {"max_soc": 0}},
    "ipopt_alpha_y_full": {"newton_steps": 0, "warm_options": {"alpha_for_y": "full"}},
    "ipopt_mu_init_1e-4": {"newton_steps": 0, "warm_options": {"mu_init": 1e-4}},
    "ipopt_cold": {"newton_steps": 0, "warm_options": {"warm_start_init_point": "no"}},
}
PATHS = {"Newton_Succeeded": "newton", "Barrier_Succeeded": "barrier"}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--codegen", action="store_true", help="every MPC with codegen=True")
    ap.add_argument("--driver", choices=["default", "ipopt"], default="default")
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--options", action="append", default=[], help="NAME=JSON: another candidate")
    ap.add_argument("--log", type=int, nargs=2, metavar=("EPISODE", "STEP"), default=None)
    args = ap.parse_args(argv)
    cands = dict(CANDIDATES)
    for item in args.options:
        name, sep, text = item.partition("=")
        if not sep:
            ap.error(f"--options {item!r}: expected NAME=JSON")
        cands[name] = json.loads(text)
    s = get_system("cstr")
    ref = ParametricMPC(s, "imperfect", newton_steps=0, codegen=args.codegen)
    logger = None
    if args.log is not None:  # the reference with IPOPT's iteration log
        logger = ParametricMPC(
            s, "imperfect", newton_steps=0, codegen=args.codegen, warm_options={"print_level": 5}
        )
    drv = ref if args.driver == "ipopt" else ParametricMPC(s, "imperfect", codegen=args.codegen)
    mpcs = {n: ParametricMPC(s, "imperfect", codegen=args.codegen, **o) for n, o in cands.items()}
    rng = np.random.default_rng(0)
    x0s = [s.sample_initial_state(rng) for _ in range(args.episodes)]
    paths = {n: {"newton": 0, "barrier": 0, "ipopt": 0, "failed": 0} for n in mpcs}
    differs: dict[str, list] = {n: [] for n in mpcs}
    max_du = dict.fromkeys(mpcs, 0.0)
    for e, x0 in enumerate(x0s):
        ref.reset()
        drv.reset()
        x = x0.copy()
        for k in range(args.steps):
            prev = ref._prev
            sr = ref.solve(x, ref.theta0, sensitivities=False)
            if logger is not None and prev is not None and [e, k] == args.log:
                logger._prev = {
                    key: (v.copy() if hasattr(v, "copy") else v) for key, v in prev.items()
                }
                logger.solve(x, logger.theta0, sensitivities=False)
            if prev is not None:  # warm steps only: the cold first step has no warm start
                for n, m in mpcs.items():
                    m._prev = {
                        key: (v.copy() if hasattr(v, "copy") else v) for key, v in prev.items()
                    }
                    sol = m.solve(x, m.theta0, sensitivities=False)
                    if not sol.success:
                        paths[n]["failed"] += 1
                        continue
                    paths[n][PATHS.get(sol.status, "ipopt")] += 1
                    if not sr.success:
                        continue
                    du = float(np.max(np.abs(sol.action - sr.action)))
                    max_du[n] = max(max_du[n], du)
                    if du > 1e-4:
                        differs[n].append((e, k, round(du, 2), round(sol.value), round(sr.value)))
            if drv is not ref:
                sr_drv = drv.solve(x, drv.theta0, sensitivities=False)
                x = s.plant_step(x, sr_drv.action)
            else:
                x = s.plant_step(x, sr.action)
    print(
        f"driver {args.driver}; reference: IPOPT only (newton_steps=0) on its own warm starts, "
        f"codegen={args.codegen}; warm steps only"
    )
    for n in mpcs:
        print(
            f"{n:<20} paths {paths[n]}  du>1e-4: {len(differs[n])}  max du {max_du[n]:.1e}  "
            f"(episode, step, |du|, value, reference value): {differs[n]}"
        )


if __name__ == "__main__":
    main()
