"""Read-to-write time of ``mpcmobo connect`` on the simulated CSTR behind an OPC UA server.

The plant (tests/opcua_plant.py: the CSTR's true model behind an asyncua server, stepping every
``--period`` seconds, the CSTR's 3 s sampling accelerated 20x at 0.15 s) runs in a process of
its own, as a real server would. ``run_plant`` runs ``--trials`` trials of an mpc-rl tuner of
60 steps each, and every period's time from the start of the batched read of the states to the
end of the batched write of the inputs is taken from the trials' logs (the ``latency``
column): the read, the checks, the MPC's warm solve in its worker thread, the write.

The baseline, measured in the same run against the same server: a bare asyncua loop that per
period reads the same state nodes in one call and writes the same input nodes in one call,
with no solve (``--baseline-periods`` periods). Reported per trial and over all: the median,
p99 and max read-to-write time, p99 as a share of the period (the target: at most 20%), the
periods whose input is the previous plan's (``fallback``), and p99 over the baseline's p99.

    .venv/bin/python benchmarks/connect_latency.py                  # 3 trials x 60 steps, 0.15 s
    .venv/bin/python benchmarks/connect_latency.py --steps 20 --trials 1
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _serve(period: float, urls: mp.Queue, stop: mp.Event) -> None:  # type: ignore[type-arg]
    sys.path.insert(0, str(ROOT / "tests"))
    from opcua_plant import SimPlant

    from mpcmobo.systems import get_system

    system = get_system("cstr")
    plant = SimPlant(system, system.x_ref, period)
    urls.put(plant.url)
    stop.wait()
    plant.close()


async def _baseline(url: str, periods: int, period: float) -> np.ndarray:
    """Per period: one batched read of the states, one batched write of the inputs."""
    from asyncua import Client, ua

    client = Client(url, timeout=4)
    await client.connect()
    try:
        reads = [client.get_node(f"ns=2;s=CSTR.{n}") for n in ("V", "Ca", "T", "Enable")]
        writes = [client.get_node(f"ns=2;s=CSTR.{n}") for n in ("qs", "qc")]
        out = []
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        for k in range(periods):
            await asyncio.sleep(max(0.0, t0 + k * period - loop.time()))
            t = time.perf_counter()
            await client.read_attributes(reads, ua.AttributeIds.Value)
            dvs = [ua.DataValue(ua.Variant(v, ua.VariantType.Double)) for v in (100.0, 110.0)]
            await client.write_values(writes, dvs)
            out.append(time.perf_counter() - t)
        return np.array(out)
    finally:
        await client.disconnect()


def _row(
    name: str, lat: np.ndarray, period: float, parts: str, fallbacks: str, base_p99: float
) -> str:
    p50, p99, top = (float(np.percentile(lat, q)) * 1e3 for q in (50, 99, 100))
    share = p99 / (period * 1e3)
    ratio = "" if not base_p99 else f"{p99 / base_p99:.1f}"
    return (
        f"| {name} | {len(lat)} | {p50:.1f} | {p99:.1f} | {top:.1f} | {share:.0%} | {parts} | "
        f"{fallbacks} | {ratio} |"
    )


def _parts(frames: list) -> str:
    """The medians of the read, the solve and the write (ms) in the logs ``frames``."""
    import pandas as pd

    df = pd.concat(frames).dropna(subset=["latency"])
    cols = ("read_time", "solve_time", "write_time")
    return " / ".join(f"{float(np.nanmedian(df[c])) * 1e3:.1f}" for c in cols)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--period", type=float, default=0.15)
    parser.add_argument("--trials", type=int, default=3)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--learner", default="mpc-rl")
    parser.add_argument("--baseline-periods", type=int, default=120)
    args = parser.parse_args()

    sys.path.insert(0, str(ROOT / "tests"))
    import pandas as pd
    from opcua_plant import node_map

    from mpcmobo.connect import run_plant
    from mpcmobo.experiment.tuner import Tuner

    load_before = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    ctx = mp.get_context("spawn")
    urls, stop = ctx.Queue(), ctx.Event()
    server = ctx.Process(target=_serve, args=(args.period, urls, stop), daemon=True)
    server.start()
    url = urls.get(timeout=120)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            nodes = Path(tmp) / "nodes.toml"
            nodes.write_text(node_map())
            tuner = Tuner(
                "cstr",
                args.learner,
                Path(tmp) / "tuner",
                episodes=args.trials + 1,
                steps=args.steps,
                start_mode="random",
                evaluation={"n_starts": 1, "eval_every": 1000},
            )
            base = asyncio.run(_baseline(url, args.baseline_periods, args.period))
            outcomes = run_plant(tuner, url, nodes, args.period, trials=args.trials)
            frames = [pd.read_csv(o.log) for o in outcomes]
    finally:
        stop.set()
        server.join(10)
    base_p99 = float(np.percentile(base, 99)) * 1e3
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    print(f"period {args.period} s, {args.trials} trials x {args.steps} steps, {args.learner}")
    print(f"load average before and after: {load_before}; {load}")
    print(
        "| loop | periods | median [ms] | p99 [ms] | max [ms] | p99 / period "
        "| read / solve / write median [ms] | fallbacks | p99 / baseline p99 |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    print(_row("baseline (read + write, no solve)", base, args.period, "", "", 0.0))
    for o, df in zip(outcomes, frames):
        lat = np.array(o.latencies)
        name = f"trial {o.trial} ({o.status})"
        print(_row(name, lat, args.period, _parts([df]), str(o.fallbacks), base_p99))
    every = np.concatenate([np.array(o.latencies) for o in outcomes])
    fb = str(sum(o.fallbacks for o in outcomes))
    print(_row("all trials", every, args.period, _parts(frames), fb, base_p99))


if __name__ == "__main__":
    main()
