"""MPC-RL's verified deployment (``deploy = "verified"``): the iterate is frozen
for a block of episodes every ``deploy_every`` steps, and the block's candidate is deployed only
when its own episode costs beat the deployed theta's (paired by cycled start, else Welch)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.stats import ttest_ind, ttest_rel

from mpcmobo.learners import EpisodeResult, make_learner
from mpcmobo.rl.steps import STEP_RULES
from mpcmobo.systems import get_system

B, EVERY = 6, 4  # block length and steps between blocks in these tests


@pytest.fixture(scope="module")
def lq():
    return get_system("lq")


def _learner(lq, **kw):
    options = {"deploy": "verified", "deploy_min_runs": B, "deploy_every": EVERY} | kw
    return make_learner("mpc-rl", lq.search_space, lq.parameterization.theta0, **options)


def _result(f1, start_id=-1, grad=None, ok=True):
    n = 9  # lq's theta
    return EpisodeResult(
        objectives=np.array([f1, 0.0, 0.0, 0.0]),
        grad=np.full(n, 0.5) if grad is None else np.asarray(grad, float),
        critic_ok=ok,
        start_id=start_id,
    )


def _cost_stream(episode, theta, theta0):
    """A deterministic cost: lower the further theta moved from theta0 (down the gradient),
    different per cycled start."""
    s = episode % B
    return 1.0 + 0.1 * s - 0.05 * float(np.abs(theta - theta0).sum()), s


def test_schedule_freezes_the_iterate_for_each_block(lq):
    lr = _learner(lq)
    theta0 = lq.parameterization.theta0
    proposals = []
    for k in range(B + EVERY + B + 1):
        th = lr.propose()
        proposals.append(th)
        f, s = _cost_stream(k, th, theta0)
        lr.observe(th, _result(f, s))
    for k in range(B):  # the first block is theta0 itself, exactly (not its round trip)
        np.testing.assert_array_equal(proposals[k], theta0)
    steps = proposals[B : B + EVERY + 1]  # then the iterate moves after every episode
    assert all(not np.array_equal(a, b) for a, b in zip(steps[:-1], steps[1:], strict=True))
    block = proposals[B + EVERY : 2 * B + EVERY]  # a frozen block at the iterate
    assert all(np.array_equal(block[0], p) for p in block)
    assert not np.array_equal(proposals[-1], block[0])  # one step at the block's end


def test_block_makes_one_step_along_its_mean_gradient(lq):
    lr = _learner(lq, optimizer="sgd", max_step=10.0, lr=0.01)
    space, theta0 = lq.search_space, lq.parameterization.theta0
    rng = np.random.default_rng(0)
    grads = rng.normal(size=(B, 9))
    for k in range(B):
        lr.observe(lr.propose(), _result(1.0, k, grad=grads[k]))
    rule = STEP_RULES["sgd"](lr=0.01, max_step=10.0)
    gz = grads.mean(0)[space.free] * space.dtheta_dz(theta0)
    expected = np.clip(space.to_unit(theta0) - rule.step(gz), 0, 1)
    np.testing.assert_allclose(lr.z, expected, rtol=0, atol=1e-15)


def _run_blocks(lr, theta0, costs_of_block, start_ids):
    """Run blocks; ``costs_of_block(b)`` gives the B costs of block b, steps cost 1."""
    b = 0
    while b < len(costs_of_block):
        th = lr.propose()
        if lr._in_block():
            for k in range(B):
                lr.observe(lr.propose(), _result(costs_of_block[b][k], start_ids[k]))
            b += 1
        else:
            lr.observe(th, _result(1.0, -1 if start_ids[0] < 0 else 0))
    return lr


@pytest.mark.parametrize("cycled", [True, False])
def test_a_clearly_better_block_is_deployed_and_a_worse_one_is_not(lq, cycled):
    theta0 = lq.parameterization.theta0
    starts = list(range(B)) if cycled else [-1] * B
    base = np.array([1.0, 2.0, 3.0, 1.5, 2.5, 0.5])
    better = base * 0.4 + np.array([0.01, -0.01, 0.02, 0.0, -0.02, 0.01])
    worse = base * 1.2
    lr = _run_blocks(_learner(lq), theta0, [base, worse], starts)
    np.testing.assert_array_equal(lr.incumbent(), theta0)
    assert lr.block_conf_[0] < 0.5
    lr = _run_blocks(_learner(lq), theta0, [base, better], starts)
    assert lr.block_conf_[0] >= 0.9
    np.testing.assert_array_equal(lr.incumbent(), lq.search_space.from_unit(lr.block_Z_[1], theta0))
    assert not np.array_equal(lr.incumbent(), theta0)


def test_confidence_is_scipys_paired_or_welch_test(lq):
    theta0 = lq.parameterization.theta0
    rng = np.random.default_rng(3)
    base, cand = rng.uniform(1, 3, B), rng.uniform(0.8, 2.6, B)
    one = {"deploy_max_runs": B}  # one block of evidence, no extension
    lr = _run_blocks(_learner(lq, **one), theta0, [base, cand], list(range(B)))
    p = ttest_rel(base, cand, alternative="greater").pvalue
    assert lr.block_conf_[0] == pytest.approx(1 - p, rel=1e-12)
    lr = _run_blocks(_learner(lq, **one), theta0, [base, cand], [-1] * B)
    p = ttest_ind(base, cand, equal_var=False, alternative="greater").pvalue
    assert lr.block_conf_[0] == pytest.approx(1 - p, rel=1e-12)


def test_paired_by_start_not_by_position(lq):
    """Blocks see the cycled starts in a different order: the pairs follow the start ids."""
    theta0 = lq.parameterization.theta0
    lr = _learner(lq)
    base = np.array([1.0, 5.0, 2.0, 4.0, 3.0, 6.0])
    for k in range(B):
        lr.observe(lr.propose(), _result(base[k], k))
    for _ in range(EVERY):
        lr.observe(lr.propose(), _result(1.0, 0))
    order = [3, 4, 5, 0, 1, 2]  # the cycle continued: the next block starts at start 3
    for s in order:
        lr.observe(lr.propose(), _result(base[s] - 0.1 * (1 + 0.01 * s), s))
    assert lr.block_conf_[0] > 0.99  # better from every start by about 0.1
    assert not np.array_equal(lr.incumbent(), theta0)


def test_a_failed_episode_rules_the_candidate_out(lq):
    theta0 = lq.parameterization.theta0
    lr = _learner(lq)
    base = np.full(B, 2.0) + np.arange(B)
    _run_blocks(lr, theta0, [base], list(range(B)))
    for _ in range(EVERY):
        lr.observe(lr.propose(), _result(1.0, 0))
    for k in range(B):
        f = np.nan if k == 2 else 0.1
        lr.observe(lr.propose(), _result(f, k, ok=k != 2))
    assert lr.block_conf_[0] == 0.0
    np.testing.assert_array_equal(lr.incumbent(), theta0)


@pytest.mark.parametrize("at", [B + EVERY + 2, 2 * B + EVERY + 2], ids=["in-block", "in-steps"])
def test_resume_is_exact(lq, at):
    a = _learner(lq)
    rng = np.random.default_rng(1)
    n = B + EVERY + B + EVERY + B
    costs = rng.uniform(0.5, 2.0, n)
    grads = rng.normal(size=(n, 9))
    b = None
    for k in range(n):
        if k == at:  # inside the second block, or in the steps after it
            b = _learner(lq)
            b.load_state_dict(copy.deepcopy(a.state_dict()))
        for lr in (a,) if b is None else (a, b):
            lr.observe(lr.propose(), _result(costs[k] * (1 + 0.1 * lr.n_observed), k % B, grads[k]))
        if b is not None:
            np.testing.assert_array_equal(a.propose(), b.propose())
            np.testing.assert_array_equal(a.incumbent(), b.incumbent())
    np.testing.assert_array_equal(a.block_conf_, b.block_conf_)


@pytest.mark.parametrize(
    "bad", [{"deploy_min_runs": 1}, {"deploy_every": -1}, {"deploy_confidence": 1.0}]
)
def test_bad_settings_name_the_option(lq, bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        _learner(lq, **bad)


def test_blocks_ask_for_noise_free_episodes(lq):
    lr = _learner(lq)
    asked = []
    for k in range(B + EVERY + B):
        th = lr.propose()
        asked.append(lr.explores())
        lr.observe(th, _result(1.0 + 0.1 * (k % B), k % B))
    assert asked == [False] * B + [True] * EVERY + [False] * B
    noisy = _learner(lq, deploy_explore=True)
    assert noisy.explores()
    default = make_learner("mpc-rl", lq.search_space, lq.parameterization.theta0)
    assert not default.explores()  # the default's first block measures theta0
    pooled = make_learner("mpc-rl", lq.search_space, lq.parameterization.theta0, deploy="pooled")
    assert pooled.explores()


def test_the_loop_runs_a_noise_free_episode_on_the_same_random_stream(lq):
    """An episode the learner asks to measure has zero exploration noise (its inputs are the
    MPC's, as in an evaluation), and the noise stream advances as if it had explored: the next
    episode's noise is that of a run whose learner always explores. EpisodeResult.stage_cost is
    the episode's plain mean stage cost."""
    from mpcmobo.experiment.evaluation import Evaluator
    from mpcmobo.experiment.loop import LearningRun
    from mpcmobo.mpc import ParametricMPC
    from mpcmobo.rl import mean_stage_cost

    mpc = ParametricMPC(lq)
    theta0 = lq.parameterization.theta0

    class Quiet:  # explores from the second episode on; records what it observed
        name = "quiet"

        def __init__(self, quiet_first: bool):
            self.space, self.n, self.quiet_first, self.results = lq.search_space, 0, quiet_first, []

        def propose(self):
            return theta0.copy()

        def explores(self):
            return not (self.quiet_first and self.n == 0)

        def observe(self, theta, result):
            self.n += 1
            self.results.append(result)

        def incumbent(self):
            return theta0.copy()

    runs = []
    for quiet in (True, False):
        learner = Quiet(quiet)
        run = LearningRun(lq, learner, mpc, seed=3, exploration_std=[0.5], start_mode="cycle")
        recs = [run.run_episode()[1] for _ in range(2)]
        runs.append((learner, recs))
    (ql, (q0, q1)), (nl, (n0, n1)) = runs
    ev = Evaluator(lq, n_starts=1)
    ev.starts = q0.x[:1].copy()
    clean = ev.episodes(theta0)[0]
    np.testing.assert_allclose(q0.u, clean.u, rtol=0, atol=1e-9)  # no noise
    assert not np.allclose(n0.u, clean.u)  # the exploring run's first episode had noise
    np.testing.assert_array_equal(q1.u, n1.u)  # the stream is the same afterwards
    assert ql.results[0].stage_cost == mean_stage_cost(q0)
    assert not ql.results[0].critic_ok and nl.results[0].critic_ok  # no noise, no critic


def test_the_metric_is_the_stage_cost_unless_asked_for_f1(lq):
    lr, lf = _learner(lq), _learner(lq, deploy_metric="f1")
    r = EpisodeResult(np.array([2.0, 0, 0, 0]), np.zeros(9), True, stage_cost=3.0)
    assert lr._block_cost(r) == 3.0 and lf._block_cost(r) == 2.0
    r_old = EpisodeResult(np.array([2.0, 0, 0, 0]), np.zeros(9), True)  # no stage cost reported
    assert lr._block_cost(r_old) == 2.0
    with pytest.raises(ValueError, match="deploy_metric"):
        _learner(lq, deploy_metric="J_eval")


def test_a_promising_candidate_is_extended_only_where_reruns_bring_new_starts(lq):
    theta0 = lq.parameterization.theta0
    base = np.array([1.0, 2.0, 3.0, 1.5, 2.5, 0.5])
    cand = base * np.array([0.8, 1.1, 0.9, 1.05, 0.85, 1.1])  # better on average, not clearly
    for starts, extended in ((list(range(B)), False), ([-1] * B, True)):
        lr = _run_blocks(_learner(lq), theta0, [base], starts)
        for _ in range(EVERY):
            lr.observe(lr.propose(), _result(1.0, starts[0]))
        for k in range(B):
            lr.observe(lr.propose(), _result(cand[k], starts[k]))
        assert lr._block_open() == extended
        if extended:  # six more episodes of the same candidate, then one decision
            z = lr.block_Z_[-1].copy()
            for k in range(B):
                assert np.array_equal(lr._open_block_z(), z)
                lr.observe(lr.propose(), _result(0.5 * cand[k], -1))
            assert not lr._block_open() and len(lr.block_conf_) == 1
            assert np.count_nonzero(lr.block_id_ == 1) == 2 * B


@pytest.mark.parametrize("reset", [True, False])
def test_a_confidently_worse_candidate_sends_the_iterate_back(lq, reset):
    theta0 = lq.parameterization.theta0
    lr = _learner(lq, deploy_reset=reset)
    base = np.array([1.0, 2.0, 3.0, 1.5, 2.5, 0.5])
    _run_blocks(lr, theta0, [base], list(range(B)))
    for _ in range(EVERY):
        lr.observe(lr.propose(), _result(1.0, 0))
    t = lr.rule.t
    for k in range(B):
        lr.observe(lr.propose(), _result(base[k] * 1.5, k))  # worse from every start
    assert lr.block_conf_[0] < 0.1
    back = np.array_equal(lr.z, lr.deployed_z_)
    assert back == reset
    assert lr.rule.t == t + 1  # the block's own step; the rule keeps its state on a reset


def test_a_checkpoint_of_the_pooled_judge_resumes_with_it(lq):
    """A run checkpointed with the pooled judge (``deploy = "pooled"``) keeps it when resumed
    by a learner built with the default ``deploy``."""
    theta0 = lq.parameterization.theta0
    old = make_learner("mpc-rl", lq.search_space, theta0, deploy="pooled")
    rng = np.random.default_rng(4)
    for k in range(5):
        old.observe(old.propose(), _result(rng.uniform(1, 2), k, grad=rng.normal(size=9)))
    new = make_learner("mpc-rl", lq.search_space, theta0)  # deploy left at its default
    new.load_state_dict(copy.deepcopy(old.state_dict()))
    assert new.deploy == "pooled" and new.explores()
    for k in range(5, 9):
        g = rng.normal(size=9)
        for lr in (old, new):
            lr.observe(lr.propose(), _result(1.0 + 0.1 * k, k % B, grad=g))
        np.testing.assert_array_equal(old.propose(), new.propose())
        np.testing.assert_array_equal(old.incumbent(), new.incumbent())
