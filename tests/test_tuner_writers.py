"""One writer at a time: a tuner changed by another process since a ``Tuner`` loaded it is
not overwritten by that object (the other's trials would be lost), and two processes that
change one tuner take turns (``tuner.lock``)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

import pytest
from test_interrupts import same_source_env
from test_tuner_checks import episode

from mpcmobo.experiment.tuner import Tuner, TunerError
from mpcmobo.experiment.tunerfiles import LOCK_FILE, TunerFiles

SETTINGS = {"episodes": 6, "steps": 12, "start_mode": "cycle", "n_cycle_starts": 2}

HOLD = """
import sys
from pathlib import Path
from mpcmobo.experiment.tunerfiles import TunerFiles
with TunerFiles(Path(sys.argv[1])).lock():
    print("held", flush=True)
    sys.stdin.readline()  # held until a line comes (or the process is killed)
"""


def _holder(d) -> subprocess.Popen:
    """Another process holding the tuner's lock until it reads a line."""
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(d)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=same_source_env(),
    )
    assert proc.stdout.readline().strip() == "held"
    return proc


@pytest.fixture
def told_twice(tmp_path):
    d = tmp_path / "t"
    tuner = Tuner("lq", "mpc-rl", d, **SETTINGS)
    for _ in range(2):
        trial = tuner.ask()
        tuner.tell(trial, *episode(tuner, trial))
    return d


def test_a_stale_tuner_does_not_overwrite_another_process_s_trials(told_twice):
    """Two loads of one tuner: the first tells a trial; the second, which has not seen it,
    may not retract or tell over it, and the told trial stays; loaded again, it may."""
    first, second = Tuner.load(told_twice), Tuner.load(told_twice)
    trial = first.ask()
    first.tell(trial, *episode(first, trial))
    for change in (
        lambda: second.retract(0, later=True),
        lambda: second.tell(trial, *episode(second, trial)),
        second.ask,
    ):
        with pytest.raises(TunerError, match="changed by another process since this one"):
            change()
    st = Tuner.load(told_twice).status()
    assert st["told"] == 3 and [t["id"] for t in st["trials"]] == [0, 1, 2]
    again = Tuner.load(told_twice)
    assert again.retract(2) == [2] and again.status()["told"] == 2
    with pytest.raises(TunerError, match="changed by another process"):
        first.ask()  # the first is stale now too: the retract changed the tuner


def test_a_process_changing_the_tuner_is_waited_for(told_twice, capsys):
    """While another process holds ``tuner.lock`` a load and a change wait for it, saying
    so, and go on once it is released; the lock is the system's, so a killed holder releases
    it."""
    tuner = Tuner.load(told_twice)
    holder = _holder(told_twice)
    done: list = []
    threads = [
        threading.Thread(target=lambda w=work: done.append(w()), daemon=True)
        for work in (lambda: Tuner.load(told_twice), tuner.ask)
    ]
    for thread in threads:
        thread.start()
    threads[0].join(timeout=1.0)
    assert all(t.is_alive() for t in threads) and not done  # waiting: a free lock is at once
    holder.communicate("go\n", timeout=30)
    for thread in threads:
        thread.join(timeout=60)
    assert f"waiting for another process (process {holder.pid})" in capsys.readouterr().err
    assert sorted(type(d).__name__ for d in done) == ["Trial", "Tuner"]
    assert next(d for d in done if not isinstance(d, Tuner)).id == 2
    killed = _holder(told_twice)
    with pytest.raises(TunerError, match=f"process {killed.pid}.* has been changing the tuner"):
        with TunerFiles(told_twice).lock(timeout=0.3):
            pass
    killed.kill()
    killed.wait(timeout=30)
    with TunerFiles(told_twice).lock(timeout=5):  # gone with the killed process
        assert (told_twice / LOCK_FILE).read_text().strip() == str(os.getpid())
