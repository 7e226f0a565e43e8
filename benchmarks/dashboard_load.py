"""Time until the page of ``mpcmobo dashboard`` is ready in headless Chromium, and until an
episode recorded while it is open is shown.

The records are generated from a real run (``--source DIR``; by default a CSTR run of the four
default learners, 6 episodes, made first): each job of the layout gets episodes resampled
from the real run's rows (its theta, f1..f4, costs, identified parameters), a change of the
deployed theta every 50 episodes, J_eval every 10 episodes, and the real run's stored
trajectories. Layouts: the default study (4 learners x 600 episodes, 1 seed) and 10 seeds x
5 learners x 50 episodes. For each, the server is started (it reads the runs once, as
``mpcmobo dashboard`` does), then Chromium opens the page ``--repeats`` times in a new
context (no cache) and once more in the same context (scripts from the browser's cache);
"ready" is the page's own clock (navigation start to the first complete drawing), "CPU" the
CPU seconds the browser's processes and the server used meanwhile (what the load of a shared
machine does not change). The baseline rows are pages that only load a plotting library from
the same server: uPlot (the page's) and, where the ``plotly`` package is installed, plotly.js
(the alternative it was chosen against).

    .venv/bin/python benchmarks/dashboard_load.py [--source DIR] [--repeats 5]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import tomli_w

from mpcmobo.dashboard import make_server
from mpcmobo.dashboard import server as dashboard_server
from mpcmobo.experiment import storage
from mpcmobo.experiment.settings import read_toml

CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
LAYOUTS = {
    "default study: 4 learners x 600 episodes": (["identify", "mpc-rl", "bo", "mobo"], 1, 600),
    "10 seeds x 5 learners x 50 episodes": (["identify", "mpc-rl", "bo", "mobo", "hybrid"], 10, 50),
}
BASELINE = """<!doctype html><html><body><script src="/static/{}"></script>
<script>document.body.dataset.readyMs = performance.now().toFixed(0);
document.body.dataset.ready = "1";</script></body></html>"""


def make_source(tmp: Path) -> Path:
    out = tmp / "source"
    cmd = [
        sys.executable,
        "-m",
        "mpcmobo.cli",
        "run",
        "--learner",
        "identify,mpc-rl,bo,mobo",
        "--episodes",
        "6",
        "--seeds",
        "0",
        "--out",
        str(out),
        "-q",
        "--no-plot",
    ]
    subprocess.run(cmd, check=True)
    return out


def generate(source: Path, out: Path, learners: list[str], seeds: int, episodes: int) -> Path:
    """A run directory of the layout, its rows and trajectories resampled from ``source``."""
    real = pd.read_parquet(source / "episodes.parquet")
    traj = pd.read_parquet(source / "trajectories.parquet")
    rng = np.random.default_rng(0)
    out.mkdir(parents=True)
    shutil.copy(source / "reference.pkl", out / "reference.pkl")
    config = read_toml(source / "config.toml")
    config.update(learners=learners, seeds=list(range(seeds)), episodes=episodes)
    (out / "config.toml").write_text(tomli_w.dumps(config))
    rows, trajs = [], [traj[traj.learner == ""]]
    for learner in learners:
        for seed in range(seeds):
            pick = real.iloc[rng.integers(0, len(real), episodes)].copy()
            pick["learner"], pick["seed"], pick["episode"] = learner, seed, np.arange(episodes)
            deployed = pick["theta"].iloc[(np.arange(episodes) // 50) * 50].to_numpy()
            pick["incumbent"] = list(deployed)
            pick["J_eval_incumbent"] = np.where(
                np.arange(episodes) % 10 == 0, pick["mean_stage_cost"] * 3, np.nan
            )
            rows.append(pick)
            t = traj[traj.learner == traj.learner[traj.learner != ""].iloc[0]].copy()
            t["learner"], t["seed"] = learner, seed
            t.loc[t.phase == "learning", "episode"] = t.loc[t.phase == "learning", "episode"].map(
                lambda e: 0 if e == 0 else episodes - 1
            )
            trajs.append(t)
    storage.write_parquet(out / "episodes.parquet", pd.concat(rows, ignore_index=True))
    storage.write_parquet(out / "trajectories.parquet", pd.concat(trajs, ignore_index=True))
    return out


def serve(directory: Path | None, library: str = "") -> tuple[str, object]:
    server = make_server([directory] if directory else [], port=0)
    dashboard_server.STATIC.pop("plotly.min.js", None)
    if directory is None:  # a page with the library alone
        server.dashboard._assets["index.html"] = BASELINE.format(library).encode()
        if library == "plotly.min.js":
            from plotly.offline import get_plotlyjs

            dashboard_server.STATIC[library] = dashboard_server.JS
            server.dashboard._assets[library] = get_plotlyjs().encode()
    server.warm()  # as mpcmobo dashboard does before it prints its address
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return f"http://127.0.0.1:{server.server_port}/", server


def browser_cpu_seconds() -> float:
    """CPU seconds (user + system) of every Chromium process under this one."""
    parent, cpu = {}, {}
    tick = os.sysconf("SC_CLK_TCK")
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        comm, rest = text[text.index("(") + 1 : text.rindex(")")], text[text.rindex(")") + 2 :]
        fields = rest.split()
        pid = int(stat.parent.name)
        parent[pid] = int(fields[1])
        if "chrom" in comm:
            cpu[pid] = (int(fields[11]) + int(fields[12])) / tick
    me, total = os.getpid(), 0.0
    for pid, seconds in cpu.items():
        p = pid
        while p > 1 and p != me:
            p = parent.get(p, 1)
        total += seconds if p == me else 0.0
    return total


def ready_ms(page, url: str) -> tuple[float, float]:
    """The page's own time to ready [ms], and the CPU seconds it took (browser and server)."""
    cpu = browser_cpu_seconds() + time.process_time()
    page.goto(url)
    page.wait_for_selector("body[data-ready='1']", state="attached", timeout=60_000)
    used = browser_cpu_seconds() + time.process_time() - cpu
    return float(page.evaluate("document.body.dataset.readyMs")), used


def episode_latency(page, run: Path) -> float:
    """Seconds from writing the records with one more episode per job to the page showing it."""
    ep = pd.read_parquet(run / "episodes.parquet")
    last = ep[ep.episode == ep.episode.max()].copy()
    last["episode"] += 1
    n = int(last.episode.iloc[0]) + 1
    t = time.perf_counter()
    storage.write_parquet(run / "episodes.parquet", pd.concat([ep, last], ignore_index=True))
    page.wait_for_function(
        f"() => [...document.querySelectorAll('#jobs tr')].slice(1)"
        f".every(r => r.cells[3].textContent.startsWith('{n} '))",
        timeout=30_000,
    )
    return time.perf_counter() - t


def measure(browser, directory: Path | None, repeats: int, library: str = "") -> dict[str, float]:
    url, server = serve(directory, library)
    cold, cold_cpu = [], []
    for _ in range(repeats):
        context = browser.new_context(viewport={"width": 1400, "height": 900})
        page = context.new_page()
        ms, cpu = ready_ms(page, url)
        cold.append(ms)
        cold_cpu.append(cpu)
        context.close()
    context = browser.new_context(viewport={"width": 1400, "height": 900})
    page = context.new_page()
    ready_ms(page, url)
    warm, warm_cpu = ready_ms(page, url)
    drawing = page.evaluate("window.renderTimes || {}")
    latency = [episode_latency(page, directory) for _ in range(3)] if directory else []
    context.close()
    server.shutdown()
    return {
        "cold": statistics.median(cold),
        "cold_max": max(cold),
        "cold_cpu": statistics.median(cold_cpu),
        "warm_cpu": warm_cpu,
        "warm": warm,
        "latency": max(latency) if latency else float("nan"),
        "drawing": drawing,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", type=Path, help="a real run to resample (default: make one)")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as pw:
        source = args.source or make_source(Path(tmp))
        chromium = shutil.which("chromium") or shutil.which("chromium-browser")
        browser = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
        results = {
            "baseline: uPlot alone": measure(browser, None, args.repeats, "uPlot.iife.min.js")
        }
        if importlib.util.find_spec("plotly"):
            results["plotly.js alone"] = measure(browser, None, args.repeats, "plotly.min.js")
        for name, (learners, seeds, episodes) in LAYOUTS.items():
            run = generate(
                source, Path(tmp) / name.split(":")[0].replace(" ", "_"), learners, seeds, episodes
            )
            results[name] = measure(browser, run, args.repeats)
        browser.close()
    print(
        f"| page | ready, new context (median of {args.repeats}) | its CPU | worst | ready, "
        "cached scripts | its CPU | new episode shown (worst of 3) |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, r in results.items():
        if r["drawing"]:
            print(f"{name}: drawing (ms, cached load) {r['drawing']}", file=sys.stderr)
        lat = "" if np.isnan(r["latency"]) else f"{r['latency']:.2f} s"
        print(
            f"| {name} | {r['cold'] / 1000:.2f} s | {r['cold_cpu']:.2f} s | "
            f"{r['cold_max'] / 1000:.2f} s | {r['warm'] / 1000:.2f} s | {r['warm_cpu']:.2f} s | "
            f"{lat} |"
        )


if __name__ == "__main__":
    main()
