"""Time from SIGINT (a Ctrl-C to the process group) to the exit of ``mpcmobo run``.

Starts an lq study (mpc-rl, 400 episodes x 30 steps, seeds 0 and 1, J_eval on 2 starts) with 1
and with 2 workers, sends SIGINT to its process group 2 s after the first checkpoint, and
prints the exit code and the seconds until the process has exited.

    .venv/bin/python benchmarks/stop_time.py
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CONFIG = """system = { name = "lq" }
learners = ["mpc-rl"]
episodes = 400
steps = 30
evaluation = { n_starts = 2 }
"""


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "stop.toml"
        config.write_text(CONFIG)
        for workers in ("1", "2"):
            out = Path(tmp) / f"w{workers}"
            cmd = [sys.executable, "-m", "mpcmobo.cli", "run", "--config", str(config),
                   "--seeds", "0", "1", "--workers", workers, "--out", str(out), "-q",
                   "--no-plot"]  # fmt: skip
            p = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, start_new_session=True)
            while not list(out.glob("jobs/*/checkpoint.pkl")):
                time.sleep(0.05)
            time.sleep(2)
            t = time.monotonic()
            os.killpg(p.pid, signal.SIGINT)
            err = p.stderr.read()
            p.wait()
            print(f"{workers} worker(s): exit code {p.returncode} after "
                  f"{time.monotonic() - t:.2f} s: {err.strip()[:60]}")  # fmt: skip


if __name__ == "__main__":
    main()
