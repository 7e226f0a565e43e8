"""``deploy = "auto"``, the default of bo, mobo and hybrid since session 10 (issue 11, item 3):
with cycled starts the learner deploys a candidate only after it was run from every start of
the cycle and is better on the mean episode cost (``deploy = "verified"``,
``deploy_paired = "cost"``, ``deploy_min_runs`` = the cycle's length, known after its first
wrap); with random starts it keeps the incumbent rule.

Checked: the resolution by start mode, options set by the user kept, the same decisions as the
explicit options, exact resume, and checkpoints from before "auto" resuming with their rule.
"""

from __future__ import annotations

import numpy as np
import pytest

from mpcmobo.learners import EpisodeResult, make_learner
from mpcmobo.learners.bo import CYCLE_UNKNOWN
from mpcmobo.systems import get_system

FAST = {"n_init": 3, "num_restarts": 2, "raw_samples": 32, "maxiter": 20}
BASE = np.exp([0.0, 1.0, -1.0, 0.5, -0.5])  # theta0's cost from each of the 5 cycled starts


@pytest.fixture(scope="module")
def lq():
    s = get_system("lq")
    return s.search_space, s.parameterization.theta0


def _observe(lr, theta, f1, start):
    y = np.array([f1, 1.0, 0.0, 0.0])
    lr.observe(theta, EpisodeResult(y, np.zeros(len(theta)), True, start_id=start))


def test_auto_resolves_by_the_start_mode(lq):
    space, theta0 = lq
    cyc = make_learner("mobo", space, theta0, seed=0, **FAST)
    assert cyc.deploy_option == "auto" and cyc.deploy == "incumbent"  # nothing seen yet
    for s in range(5):
        _observe(cyc, theta0, BASE[s], s)
    assert (cyc.deploy, cyc.deploy_paired) == ("verified", "cost")
    assert cyc.deploy_rule.model_confidence == 0.5
    assert cyc.deploy_rule.min_runs == CYCLE_UNKNOWN  # the cycle has not wrapped yet
    _observe(cyc, theta0, BASE[0], 0)
    assert (cyc.deploy_rule.min_runs, cyc.deploy_rule.run_cap) == (5, 10)
    assert not cyc.safe_mode  # the default search; only the deployment changes
    rnd = make_learner("mobo", space, theta0, seed=0, **FAST)
    for _ in range(4):
        _observe(rnd, theta0, 1.0, -1)
    assert rnd.deploy == "incumbent" and not rnd.safe_mode


def test_options_set_by_the_user_are_kept(lq):
    space, theta0 = lq
    lr = make_learner("bo", space, theta0, seed=0, deploy="auto", deploy_min_runs=3,
                      deploy_paired="every", **FAST)  # fmt: skip
    for s in (0, 1, 2, 0):
        _observe(lr, theta0, BASE[s], s)
    assert (lr.deploy, lr.deploy_paired, lr.deploy_rule.min_runs) == ("verified", "every", 3)
    assert lr.deploy_rule.model_confidence is None  # 0.5 only with the paired cost test
    fixed = make_learner("bo", space, theta0, seed=0, deploy="incumbent", **FAST)
    for s in (0, 1, 2, 0):
        _observe(fixed, theta0, BASE[s], s)
    assert fixed.deploy == "incumbent"


@pytest.mark.parametrize("factors", [(0.5, 0.5, 1.3, 0.5, 0.5), (0.3, 4.0, 0.3, 0.3, 0.3)])
def test_auto_decides_as_the_explicit_full_cycle_cost_rule(lq, factors):
    """theta0 from the five starts, then a candidate from each: the default learner deploys
    exactly what deploy = "verified", deploy_min_runs = 5, deploy_paired = "cost" deploys
    (the candidate when it is cheaper on average, theta0 when it is dearer on average)."""
    space, theta0 = lq
    z0 = space.to_unit(theta0)
    good = z0.copy()
    good[0] = z0[0] + 0.1
    cand = space.from_unit(good, base=theta0)
    got = []
    explicit = {"deploy": "verified", "deploy_min_runs": 5, "deploy_paired": "cost",
                "deploy_model_confidence": 0.5}  # fmt: skip
    for opts in ({}, explicit):
        lr = make_learner("bo", space, theta0, seed=0, trust_region="off", **opts, **FAST)
        for s in range(5):
            _observe(lr, theta0, BASE[s], s)
        for s in range(5):
            _observe(lr, cand, BASE[s] * factors[s], s)
        got.append(lr._incumbent_z.copy())
    np.testing.assert_array_equal(got[0], got[1])
    expected = good if np.mean(BASE * np.asarray(factors)) < np.mean(BASE) else z0
    np.testing.assert_allclose(got[0], expected)


def test_auto_resumes_exactly(lq):
    space, theta0 = lq
    a = make_learner("hybrid", space, theta0, seed=2, **FAST)
    rng = np.random.default_rng(3)
    for k in range(9):
        th = a.propose()
        _observe(a, th, float(np.exp(rng.normal() + 0.3 * k % 3)), k % 3)
    state = a.state_dict()
    assert (state["deploy_option"], state["deploy"], state["deploy_paired"]) == (
        "auto", "verified", "cost")  # fmt: skip
    b = make_learner("hybrid", space, theta0, seed=99, **FAST)
    b.load_state_dict(state)
    assert (b.deploy, b.deploy_paired, b.deploy_rule.min_runs) == ("verified", "cost", 3)
    assert b.deploy_rule.model_confidence == a.deploy_rule.model_confidence == 0.5
    np.testing.assert_array_equal(b.incumbent(), a.incumbent())
    np.testing.assert_array_equal(b.propose(), a.propose())


def test_a_checkpoint_from_before_auto_keeps_its_rule(lq):
    """A learner state without "deploy_option" (written before session 10) made with the
    incumbent rule under cycled starts continues with the incumbent rule."""
    space, theta0 = lq
    old = make_learner("bo", space, theta0, seed=0, deploy="incumbent", **FAST)
    for s in (0, 1, 2, 0):
        _observe(old, theta0, BASE[s], s)
    state = {
        k: v for k, v in old.state_dict().items() if k not in ("deploy_option", "deploy_paired")
    }
    new = make_learner("bo", space, theta0, seed=0, **FAST)
    new.load_state_dict(state)
    _observe(new, space.from_unit(space.to_unit(theta0) * 0.95, base=theta0), 0.5, 1)
    assert (new.deploy_option, new.deploy) == ("incumbent", "incumbent")
