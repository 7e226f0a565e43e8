"""Runs written by mpcmobo 0.1.0 (commit 9ff9153, before the issue-10 refactor) resume exactly.

``tests/data/checkpoints_v0.1`` holds an LQ study (mpc-rl and mobo, 8 episodes) interrupted after
4 episodes by that version, with the records of the same study run uninterrupted by that version
(``make_fixture.py`` made both, run with the old code). Resuming the old checkpoints with today's
code must give the old uninterrupted records: the checkpoint, reference and learner-state formats
stay readable, and the learners continue exactly.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pandas as pd

from mpcmobo.experiment import run_study, storage

DATA = Path(__file__).parent / "data" / "checkpoints_v0.1"


def _drop_wall(df: pd.DataFrame) -> pd.DataFrame:
    return df.drop(columns=[c for c in df.columns if c.endswith("time_s")]).reset_index(drop=True)


def test_resuming_a_v0_1_run_gives_its_uninterrupted_records(tmp_path):
    out = tmp_path / "run"
    shutil.copytree(DATA / "run", out)
    summary = run_study(None, out, resume=True)
    assert summary["complete"] is True
    expected = pd.read_parquet(DATA / "expected_episodes.parquet")
    got = storage.read_episodes(out)
    assert len(got) == 16
    pd.testing.assert_frame_equal(_drop_wall(got), _drop_wall(expected), check_exact=True)
    pd.testing.assert_frame_equal(
        storage.read_trajectories(out).reset_index(drop=True),
        pd.read_parquet(DATA / "expected_trajectories.parquet").reset_index(drop=True),
        check_exact=True,
    )
