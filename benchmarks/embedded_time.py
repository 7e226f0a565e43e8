"""Per-step time and inputs of the embedded controller (``mpcmobo export --format embedded``).

Exports the CSTR's MPC at theta0 as C that needs only libc and libm
(:mod:`mpcmobo.mpc.embedded`), compiles it (``cc -O2``), and runs its ``main.c``, which times
each step with ``clock_gettime``:

* cold: 100 states drawn from the CSTR's initial-state box, each after a reset, against
  ``ParametricMPC.solve`` after a reset (IPOPT from the cold guess);
* warm: the states of 4 closed-loop episodes of 60 steps of ``ParametricMPC`` (its own closed
  loop), fed in order, against its actions.

Reported: the linked libraries (``ldd``), the paths (Newton steps, continuation, continuation
restarted from the shifted plan, cold continuation, fallback), the steps whose input is within
1e-6 of the MPC's, and the median, 95th percentile and largest step time in microseconds. The
controller runs ``--repeats`` times on the same states (a new process each time: the same
inputs and paths, checked); a step's time is its fastest over the repeats, as ``timeit``
takes it (one pass's median moves by a quarter between passes on an idle machine); the
first pass's median is printed beside it.

    .venv/bin/python benchmarks/embedded_time.py
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from mpcmobo.mpc import ParametricMPC
from mpcmobo.mpc.embedded import embedded_compile_command, export_embedded
from mpcmobo.systems import get_system

PATHS = ("fallback", "Newton", "continuation", "cold", "restart")


def run_controller(program: Path, states, *args: str) -> np.ndarray:
    text = "".join(" ".join(repr(float(v)) for v in x) + "\n" for x in states)
    out = subprocess.run([str(program), *args], input=text, capture_output=True, text=True)
    return np.array([[float(v) for v in line.split()] for line in out.stdout.splitlines()])


def repeated(run, repeats: int) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``run()`` with each step's fastest time over ``repeats`` runs (their inputs
    and paths checked to be the same), and the first run's step times."""
    passes = [run() for _ in range(max(1, repeats))]
    first = passes[0]
    for other in passes[1:]:
        if not np.array_equal(other[:, :-1], first[:, :-1]):
            raise SystemExit("the controller's inputs or paths differ between repeats")
    rows = first.copy()
    rows[:, -1] = np.min([p[:, -1] for p in passes], axis=0)
    return rows, first[:, -1]


def report(name: str, rows: np.ndarray, actions: np.ndarray, nu: int, first: float) -> None:
    du = np.max(np.abs(rows[:, :nu] - actions), axis=1)
    paths = np.bincount(rows[:, nu].astype(int), minlength=len(PATHS))
    t = rows[:, nu + 1]
    print(
        f"{name:<5} {len(rows):>5} {int(np.sum(du <= 1e-6)):>9} "
        f"{' / '.join(f'{PATHS[i]} {paths[i]}' for i in (1, 2, 4, 3, 0)):<64} "
        f"{np.median(t):>8.1f} {np.percentile(t, 95):>8.1f} {t.max():>8.1f} {first:>10.1f}"
    )


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--states", type=int, default=100)
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=5, help="runs of the controller per state set")
    args = ap.parse_args(argv)
    s = get_system("cstr")
    mpc = ParametricMPC(s, "imperfect")
    with tempfile.TemporaryDirectory() as tmp:
        d = export_embedded(mpc, None, Path(tmp) / "embedded")
        t0 = time.perf_counter()
        subprocess.run(embedded_compile_command(d), check=True)
        print(f"compiled with -O2 in {time.perf_counter() - t0:.1f} s")
        ldd = subprocess.run(["ldd", str(d / "controller")], capture_output=True, text=True)
        print("ldd:", ", ".join(line.split()[0] for line in ldd.stdout.splitlines()))
        rng = np.random.default_rng(args.seed)
        cold = np.array([s.sample_initial_state(rng) for _ in range(args.states)])
        acts = []
        for x in cold:
            mpc.reset()
            acts.append(mpc.solve(x, sensitivities=False).action)
        program = d / "controller"
        rows_cold, first_cold = repeated(
            lambda: run_controller(program, cold, "--cold"), args.repeats
        )
        episodes, warm_acts = [], []
        for _ in range(args.episodes):  # one run of the controller per episode: a fresh start
            mpc.reset()
            x, states = s.sample_initial_state(rng), []
            for _ in range(args.steps):
                sol = mpc.solve(x, sensitivities=False)
                states.append(x)
                warm_acts.append(sol.action)
                x = s.plant_step(x, sol.action)
            episodes.append(np.array(states))
        warm = [repeated(lambda x=x: run_controller(program, x), args.repeats) for x in episodes]
        rows_warm = np.vstack([r for r, _ in warm])
        first_warm = np.concatenate([t for _, t in warm])
        print(
            f"{'':<5} {'steps':>5} {'u <= 1e-6':>9} {'paths':<64} {'median':>8} {'p95':>8} "
            f"{'max':>8} {'1st median':>10}"
        )
        report("cold", rows_cold, np.array(acts), s.nu, float(np.median(first_cold)))
        report("warm", rows_warm, np.array(warm_acts), s.nu, float(np.median(first_warm)))
        print(
            f"times in microseconds per step (controller_step, clock_gettime), each step's "
            f"fastest of {args.repeats} runs; 1st median: the first run's"
        )


if __name__ == "__main__":
    main()
