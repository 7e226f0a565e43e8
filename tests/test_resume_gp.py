"""Study-level resume of the GP learners past a hyperparameter refit.

``tests/test_study.py`` resumes mpc-rl at study level; the GP learners are resumed there only
inside their first episodes, where every fit is a full refit (fewer observations than the
surrogate's ``min_refit_n`` = 20). Here mobo and hybrid run 24 episodes with ``refit_every = 2``:
from the 20th observation on, fits alternate between full refits and fits that reuse the
hyperparameters (a full refit at 22 observations), and the run is interrupted after 21, 22 and
23 episodes, i.e. after fits of both kinds. The resumed records must equal the uninterrupted
run's. Random starts: the deployment policy's baseline and verification episodes and its
start costs are part of what is resumed, and no per-start offsets are fitted (two more
likelihood fits per refit under cycled starts; their resume is tested in test_learners.py).
The learners tune the nominal model, so that every episode is the GP's (identify-first's
resume is tested in test_identify.py).
"""

from __future__ import annotations

import math

import pandas as pd
import pytest

from mpcmobo.experiment import storage
from mpcmobo.experiment.settings import load_settings
from mpcmobo.experiment.study import run_study

WALL = ["mpc_time_s", "learner_time_s", "eval_time_s"]
EPISODES = 24
SEARCH = {"num_restarts": 1, "raw_samples": 16, "maxiter": 10, "mc_samples": 8}
CHEAP = {"n_init": 4, "refit_every": 2, "search": SEARCH}  # the resume, not the search


def _settings():
    return load_settings(
        None,
        system={"name": "lq", "identify": False},
        learners=["mobo", "hybrid"],
        episodes=EPISODES,
        steps=6,
        seeds=[0],
        start_mode="random",
        evaluation={"n_starts": 2, "eval_every": 5},
        records={"trajectory_every": 5},
        learner_options={"mobo": CHEAP, "hybrid": CHEAP},
        workers=2,
        # every episode the GP's, past the refit (the nominal model, an exploration budget
        # would refuse most candidates and stop the learner early)
        exploration={"budget": math.inf},
    )


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    out = tmp_path_factory.mktemp("gp") / "full"
    summary = run_study(_settings(), out)
    assert summary["complete"] is True
    return out


def test_gp_learners_resume_past_a_refit_with_identical_records(uninterrupted, tmp_path):
    out = tmp_path / "resumed"
    # interrupted after 21 (a warm fit), 22 (a full refit) and 23 episodes (a warm fit)
    part = run_study(_settings(), out, max_episodes_this_call=21)
    assert part["complete"] is False
    run_study(None, out, resume=True, max_episodes_this_call=1)
    run_study(None, out, resume=True, max_episodes_this_call=1)
    done = run_study(None, out, resume=True)
    assert done["complete"] is True
    a = storage.read_episodes(uninterrupted).drop(columns=WALL)
    b = storage.read_episodes(out).drop(columns=WALL)
    assert len(a) == 2 * EPISODES and set(a.learner) == {"mobo", "hybrid"}
    pd.testing.assert_frame_equal(a, b)
    pd.testing.assert_frame_equal(
        storage.read_trajectories(uninterrupted), storage.read_trajectories(out)
    )
    # past the refit threshold: the last fit (24 observations) reused the hyperparameters, the
    # second time since the refit at 22; the state holds the GP after it, loaded without a fit
    for learner in ("mobo", "hybrid"):
        state = storage.load_checkpoint(out, learner, 0)["state"]["learner"]
        assert len(state["evidence"]["Z"]) == EPISODES
        assert "baseline" in state["evidence"]["kinds"]  # the policy's episodes are resumed
        surrogate = state["surrogate"]
        assert surrogate["min_refit_n"] == 20
        assert surrogate["calls_since_refit"] == 2 and not surrogate["last_fit_was_full"]
