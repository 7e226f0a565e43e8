"""MPC-RL's verified deployment (``deploy = "verified"``, :class:`VerifiedBlocks`).

Every ``every`` gradient steps the iterate is frozen for a block of ``runs`` noise-free
episodes, and the block's candidate is deployed only when its own episode costs beat the
deployed theta's block: paired by cycled start, else adjusted for the starts' cost (Welch's
test without a covariate). Checked: the schedule, the block's one step along its mean
gradient, the decisions against scipy's tests, pairing by start, a failed episode, the
extension of a promising block under random starts only, the return of the iterate after a
confidently worse block, exact resume, the options, and the noise-free episodes in the loop.
"""

from __future__ import annotations

import copy
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import ttest_ind, ttest_rel

from mpcmobo.learners import EpisodeResult, Starts, make_learner
from mpcmobo.learners.confidence import adjusted_confidence, unpaired_confidence
from mpcmobo.learners.mpc_rl import VerifiedBlocks
from mpcmobo.learners.registry import LearnerOptionError
from mpcmobo.systems import get_system

B, EVERY = 6, 4  # block length and steps between blocks in these tests


@pytest.fixture(scope="module")
def lq():
    return get_system("lq")


def _learner(lq, starts=None, optimizer=None, **deploy):
    """MPC-RL with blocks of B episodes every EVERY steps (and the given deploy options)."""
    options = {"deploy": {"runs": B, "every": EVERY, **deploy}}
    if optimizer is not None:
        options["optimizer"] = optimizer
    space, theta0 = lq.search_space, lq.parameterization.theta0
    return make_learner("mpc-rl", space, theta0, starts=starts, **options)


CYCLE = Starts("cycle", B)


def _result(f1, start_id=-1, grad=None, ok=True, stage_cost=float("nan"), start_cost=float("nan")):
    n = 9  # lq's theta
    return EpisodeResult(
        objectives=np.array([f1, 0.0, 0.0, 0.0]),
        grad=np.full(n, 0.5) if grad is None else np.asarray(grad, float),
        critic_ok=ok,
        start_id=start_id,
        stage_cost=stage_cost,
        start_cost=start_cost,
    )


def _cost_stream(episode, theta, theta0):
    """A deterministic cost: lower the further theta moved from theta0 (down the gradient),
    different per cycled start."""
    s = episode % B
    return 1.0 + 0.1 * s - 0.05 * float(np.abs(theta - theta0).sum()), s


def test_schedule_freezes_the_iterate_for_each_block(lq):
    lr = _learner(lq, CYCLE)
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
    assert all(not np.array_equal(a, b) for a, b in zip(steps[:-1], steps[1:]))
    block = proposals[B + EVERY : 2 * B + EVERY]  # a frozen block at the iterate
    assert all(np.array_equal(block[0], p) for p in block)
    assert not np.array_equal(proposals[-1], block[0])  # one step at the block's end


def test_block_makes_one_step_along_its_mean_gradient(lq):
    """The paper's plain step (in theta) after theta0's block: theta0 - lr * the mean of the
    block's gradients."""
    lr = _learner(lq, CYCLE, optimizer={"rule": "gd", "lr": 1e-3})
    space, theta0 = lq.search_space, lq.parameterization.theta0
    grads = np.random.default_rng(0).normal(size=(B, 9))
    for k in range(B):
        lr.observe(lr.propose(), _result(1.0, k, grad=grads[k]))
    expected = theta0.copy()
    expected[space.free] -= 1e-3 * grads.mean(0)[space.free]
    assert space.contains(expected)
    np.testing.assert_allclose(space.from_unit(lr.z_, base=theta0), expected, atol=1e-12)
    assert lr.rule.t == 1  # one step for the whole block


def test_a_simulated_episode_steps_outside_blocks_only_and_starts_no_block(lq):
    """A refused candidate's simulated episode: inside a block nothing (the block's evidence
    is the plant's), after it one plain step along its valid gradient that does not count
    towards the next block; an invalid gradient makes none."""
    lr = _learner(lq, CYCLE, optimizer={"rule": "gd", "lr": 1e-3})
    space = lq.search_space
    assert not lr.learns_in_simulation()  # theta0's block comes first
    z = lr.z_.copy()
    lr.observe_simulated(lr.propose(), _result(1.0, 0))
    np.testing.assert_array_equal(lr.z_, z)
    for k in range(B):
        lr.observe(lr.propose(), _result(1.0, k))
    assert lr.learns_in_simulation()
    theta, since, t = lr.propose(), lr.blocks_.since_, lr.rule.t
    lr.observe_simulated(theta, _result(1.0, 0, ok=False))
    assert lr.rule.t == t
    grad = np.random.default_rng(1).normal(size=9)
    lr.observe_simulated(theta, _result(1.0, 0, grad=grad))
    expected = space.clip(theta).copy()
    expected[space.free] -= 1e-3 * grad[space.free]
    np.testing.assert_allclose(
        space.from_unit(lr.z_, base=lq.parameterization.theta0), expected, atol=1e-12
    )
    assert lr.rule.t == t + 1 and lr.blocks_.since_ == since


def test_an_invalid_gradient_makes_no_step_and_the_block_averages_the_valid_ones(lq):
    lr = _learner(lq, CYCLE, optimizer={"rule": "gd", "lr": 1e-3})
    space, theta0 = lq.search_space, lq.parameterization.theta0
    grads = np.random.default_rng(1).normal(size=(B, 9))
    for k in range(B):
        ok = k != 2
        lr.observe(lr.propose(), _result(1.0, k, grad=grads[k], ok=ok))
    expected = theta0.copy()
    expected[space.free] -= 1e-3 * np.delete(grads, 2, axis=0).mean(0)[space.free]
    np.testing.assert_allclose(space.from_unit(lr.z_, base=theta0), expected, atol=1e-12)
    z = lr.z_.copy()  # a step episode without a valid gradient: no step
    lr.observe(lr.propose(), _result(np.nan, 0, grad=np.full(9, np.nan), ok=False))
    np.testing.assert_array_equal(lr.z_, z)


def _run_blocks(lr, costs_of_block, start_ids):
    """Run blocks; ``costs_of_block[b]`` gives the B costs of block b, steps cost 1."""
    b = 0
    while b < len(costs_of_block):
        th = lr.propose()
        if lr.blocks_.in_block():
            for k in range(B):
                lr.observe(lr.propose(), _result(costs_of_block[b][k], start_ids[k]))
            b += 1
        else:
            lr.observe(th, _result(1.0, -1 if start_ids[0] < 0 else 0))
    return lr


BASE = np.array([1.0, 2.0, 3.0, 1.5, 2.5, 0.5])


@pytest.mark.parametrize("cycled", [True, False])
def test_a_clearly_better_block_is_deployed_and_a_worse_one_is_not(lq, cycled):
    theta0 = lq.parameterization.theta0
    starts, ids = (CYCLE, list(range(B))) if cycled else (None, [-1] * B)
    better = BASE * 0.4 + np.array([0.01, -0.01, 0.02, 0.0, -0.02, 0.01])
    worse = BASE * 1.2
    lr = _run_blocks(_learner(lq, starts), [BASE, worse], ids)
    np.testing.assert_array_equal(lr.incumbent(), theta0)
    assert lr.blocks_.conf_[0] < 0.5 and lr.blocks_.deployed_ == 0
    lr = _run_blocks(_learner(lq, starts), [BASE, better], ids)
    assert lr.blocks_.conf_[0] >= 0.9 and lr.blocks_.deployed_ == 1
    np.testing.assert_array_equal(lr.incumbent(), lr.theta_of(lr.blocks_.candidates_[1]))
    assert not np.array_equal(lr.incumbent(), theta0)


def test_an_episode_the_budget_ran_instead_of_the_candidate_is_no_evidence_of_it(lq):
    """Where the exploration budget keeps a block's candidate off the plant, the deployed theta
    runs instead: its cheap episodes do not enter the candidate's block, which waits for the
    candidate's own (dearer) episodes and so does not deploy it."""
    lr = _learner(lq, CYCLE)
    for k in range(B):  # theta0's block
        lr.observe(lr.propose(), _result(BASE[k], k))
    for _ in range(EVERY):  # steps: the iterate moves, a new block is due
        lr.observe(lr.propose(), _result(1.0, 0))
    candidate = lr.propose()
    assert lr.blocks_.in_block() and not np.array_equal(candidate, lr.incumbent())
    for k in range(3):  # refused: the deployed theta ran, far cheaper than either block
        lr.observe(lr.incumbent(), _result(0.01, k))
        np.testing.assert_array_equal(lr.propose(), candidate)  # asked again
    for k in [3, 4, 5, 0, 1, 2]:  # the candidate's own episodes, 20% dearer
        lr.observe(lr.propose(), _result(1.2 * BASE[k], k))
    ev = lr.blocks_.evidence_
    block = ev.group(1)
    assert len(block) == B
    np.testing.assert_allclose(ev.Y[block, 0], 1.2 * BASE[[3, 4, 5, 0, 1, 2]])
    assert lr.blocks_.conf_[0] < 0.5 and lr.blocks_.deployed_ == 0
    np.testing.assert_array_equal(lr.incumbent(), lq.parameterization.theta0)


def test_confidence_is_scipys_paired_or_welch_test(lq):
    rng = np.random.default_rng(3)
    base, cand = rng.uniform(1, 3, B), rng.uniform(0.8, 2.6, B)
    lr = _run_blocks(_learner(lq, CYCLE, max_runs=B), [base, cand], list(range(B)))
    p = ttest_rel(base, cand, alternative="greater").pvalue
    assert lr.blocks_.conf_[0] == pytest.approx(1 - p, rel=1e-12)
    lr = _run_blocks(_learner(lq, max_runs=B), [base, cand], [-1] * B)
    p = ttest_ind(base, cand, equal_var=False, alternative="greater").pvalue
    assert lr.blocks_.conf_[0] == pytest.approx(1 - p, rel=1e-12)


def test_paired_by_start_not_by_position(lq):
    """Blocks see the cycled starts in a different order: the pairs follow the start ids."""
    theta0 = lq.parameterization.theta0
    lr = _learner(lq, CYCLE)
    base = np.array([1.0, 5.0, 2.0, 4.0, 3.0, 6.0])
    for k in range(B):
        lr.observe(lr.propose(), _result(base[k], k))
    for _ in range(EVERY):
        lr.observe(lr.propose(), _result(1.0, 0))
    order = [3, 4, 5, 0, 1, 2]  # the cycle continued: the next block starts at start 3
    for s in order:
        lr.observe(lr.propose(), _result(base[s] - 0.1 * (1 + 0.01 * s), s))
    assert lr.blocks_.conf_[0] > 0.99  # better from every start by about 0.1
    assert not np.array_equal(lr.incumbent(), theta0)


def test_a_failed_episode_rules_the_candidate_out(lq):
    theta0 = lq.parameterization.theta0
    lr = _learner(lq, CYCLE)
    _run_blocks(lr, [np.full(B, 2.0) + np.arange(B)], list(range(B)))
    for _ in range(EVERY):
        lr.observe(lr.propose(), _result(1.0, 0))
    for k in range(B):
        f = np.nan if k == 2 else 0.1
        lr.observe(lr.propose(), _result(f, k, ok=k != 2))
    assert lr.blocks_.conf_[0] == 0.0
    assert np.isinf(lr.blocks_.evidence_.Y[:, 0][B + 2])  # a failed episode costs inf
    np.testing.assert_array_equal(lr.incumbent(), theta0)


S0 = np.array([1.0, 3.0, 0.5, 2.0, 8.0, 1.5])  # start costs of theta0's block
S1 = np.array([4.0, 6.0, 3.0, 9.0, 5.0, 7.0])  # the candidate's block: costlier starts


def test_random_starts_use_the_start_adjusted_test(lq):
    """theta0's block, then a candidate's whose starts were costlier and which is cheaper
    from each: deployed on the adjusted test (Welch's would refuse it)."""
    theta0 = lq.parameterization.theta0
    lr = _learner(lq, every=1, max_runs=B)
    assert lr.uses_start_cost()
    for s in S0:
        lr.observe(lr.propose(), _result(s, stage_cost=s, start_cost=s))
    lr.observe(lr.propose(), _result(1.0, stage_cost=1.0, start_cost=1.0))  # one step
    cand = lr.propose()
    assert not np.allclose(cand, theta0)
    for s in S1:
        lr.observe(lr.propose(), _result(0.8 * s, stage_cost=0.8 * s, start_cost=s))
    conf = lr.blocks_.conf_[-1]
    assert conf == pytest.approx(adjusted_confidence(S0, 0.8 * S1, S0, S1)) and conf > 0.99
    assert unpaired_confidence(S0, 0.8 * S1) < 0.5
    np.testing.assert_allclose(lr.incumbent(), cand)


def test_the_block_cost_is_the_stage_cost_else_f1():
    """What J_eval averages, the plain mean stage cost; f1 for an episode that reports none;
    inf for a failed one."""
    blocks = VerifiedBlocks(
        make_learner("mpc-rl", *_lq_space()).options.deploy, Starts(), dim=8, n_theta=9
    )
    z = np.full(8, 0.5)
    blocks.observe(z, _result(2.0, stage_cost=3.0), None)
    blocks.observe(z, _result(2.0), None)
    blocks.observe(z, _result(np.nan), None)
    np.testing.assert_array_equal(blocks.evidence_.Y[:, 0], [3.0, 2.0, np.inf])


def _lq_space():
    s = get_system("lq")
    return s.search_space, s.parameterization.theta0


@pytest.mark.parametrize("at", [B + EVERY + 2, 2 * B + EVERY + 2], ids=["in-block", "in-steps"])
@pytest.mark.parametrize("starts", [CYCLE, Starts("random")], ids=["cycle", "random"])
def test_resume_is_exact(lq, at, starts):
    a = _learner(lq, starts)
    rng = np.random.default_rng(1)
    n = B + EVERY + B + EVERY + B
    costs = rng.uniform(0.5, 2.0, n)
    grads = rng.normal(size=(n, 9))
    b = None
    for k in range(n):
        if k == at:  # inside the second block, or in the steps after it
            b = _learner(lq, starts)
            b.load_state_dict(copy.deepcopy(a.state_dict()))
        s = k % B if starts.mode == "cycle" else -1
        for lr in (a,) if b is None else (a, b):
            f = costs[k] * (1 + 0.1 * lr.n_observed)
            lr.observe(lr.propose(), _result(f, s, grads[k], start_cost=costs[k]))
        if b is not None:
            np.testing.assert_array_equal(a.propose(), b.propose())
            np.testing.assert_array_equal(a.incumbent(), b.incumbent())
            assert a.explores() == b.explores()
    np.testing.assert_array_equal(a.blocks_.conf_, b.blocks_.conf_)
    assert len(a.blocks_.conf_) >= 1
    np.testing.assert_array_equal(a.rule.m, b.rule.m)


@pytest.mark.parametrize(
    "options, match",
    [
        ({"deploy": {"runs": 1}}, r"^deploy\.runs: "),
        ({"deploy": {"every": -1}}, r"^deploy\.every: "),
        ({"deploy": {"confidence": 1.0}}, r"^deploy\.confidence: "),
        ({"deploy": {"runs": 8, "max_runs": 6}}, r"^deploy: max_runs \(6\) must be at least runs"),
        ({"deploy": {"rule": "iterate", "runs": 6}}, r"^deploy\.runs: unknown option"),
        ({"deploy": "pooled"}, r"^deploy: .*'verified', 'iterate'"),
        ({"optimizer": "sgd"}, r"^optimizer: .*'adam', 'gd'"),
        ({"optimizer": {"lr": 0}}, r"^optimizer\.lr: "),
        ({"optimizer": {"rule": "gd", "max_step": 0.1}}, r"^optimizer\.max_step: unknown option"),
        ({"lr": 0.05}, r"^lr: unknown option"),
        ({"lr_decay": 1.0}, r"^lr_decay: unknown option"),
        ({"deploy_min_runs": 6}, r"^deploy_min_runs: unknown option"),
    ],
)
def test_bad_settings_name_the_option(lq, options, match):
    with pytest.raises(LearnerOptionError, match=match) as err:
        make_learner("mpc-rl", lq.search_space, lq.parameterization.theta0, **options)
    assert "the options of 'mpc-rl'" in str(err.value)


def test_the_options_reach_the_learner(lq):
    space, theta0 = lq.search_space, lq.parameterization.theta0
    lr = make_learner("mpc-rl", space, theta0, optimizer={"lr": 0.05, "max_step": 0.2})
    assert (lr.rule.name, lr.rule.lr, lr.rule.max_step) == ("adam", 0.05, 0.2)
    lr = make_learner("mpc-rl", space, theta0, optimizer="gd")
    assert (lr.rule.name, lr.rule.lr, lr.rule.coordinates) == ("gd", 0.003, "theta")
    lr = make_learner("mpc-rl", space, theta0, deploy={"every": 4, "runs": 3})
    o = lr.blocks_.options
    assert (o.every, o.runs, o.max_runs, o.confidence) == (4, 3, 12, 0.9)
    assert lr.blocks_.target_ == 3
    it = make_learner("mpc-rl", space, theta0, deploy="iterate")
    assert it.blocks_ is None and not it.uses_start_cost() and it.explores()


def test_blocks_ask_for_noise_free_episodes(lq):
    lr = _learner(lq, CYCLE)
    asked = []
    for k in range(B + EVERY + B):
        th = lr.propose()
        asked.append(lr.explores())
        lr.observe(th, _result(1.0 + 0.1 * (k % B), k % B))
    assert asked == [False] * B + [True] * EVERY + [False] * B
    default = make_learner("mpc-rl", lq.search_space, lq.parameterization.theta0)
    assert not default.explores()  # the default's first block measures theta0
    iterate = make_learner("mpc-rl", lq.search_space, lq.parameterization.theta0, deploy="iterate")
    assert iterate.explores()


def test_the_iterate_rule_deploys_the_iterate(lq):
    space, theta0 = lq.search_space, lq.parameterization.theta0
    lr = make_learner("mpc-rl", space, theta0, deploy="iterate")
    for k in range(3):
        lr.observe(lr.propose(), _result(1.0, grad=np.linspace(-1, 1, 9) * (k + 1)))
        np.testing.assert_array_equal(lr.incumbent(), lr.propose())
    assert not np.allclose(lr.incumbent(), theta0)


def test_a_promising_candidate_is_extended_only_where_reruns_bring_new_starts(lq):
    """Better on average, not clearly: under random starts the block runs B more episodes
    (new starts, new evidence), once (max_runs 2 B), then decides; under cycled starts the
    same starts would come again, so it decides at once."""
    cand = BASE * np.array([0.8, 1.1, 0.9, 1.05, 0.85, 1.1])
    for starts, ids, extended in ((CYCLE, list(range(B)), False), (None, [-1] * B, True)):
        lr = _run_blocks(_learner(lq, starts), [BASE], ids)
        for _ in range(EVERY):
            lr.observe(lr.propose(), _result(1.0, ids[0]))
        for k in range(B):
            lr.observe(lr.propose(), _result(cand[k], ids[k]))
        blocks = lr.blocks_
        assert blocks.is_open() == extended
        if not extended:
            assert 0.5 <= blocks.conf_[0] < 0.9  # promising, not convincing: not deployed
            assert blocks.deployed_ == 0
            continue
        assert len(blocks.conf_) == 0 and blocks.target_ == 2 * B
        z = blocks.candidates_[-1].copy()
        for k in range(B):  # the same candidate, noise-free
            np.testing.assert_array_equal(blocks.candidate(lr.z_), z)
            assert not lr.explores()
            lr.observe(lr.propose(), _result(cand[k], -1))
        assert not blocks.is_open() and len(blocks.conf_) == 1  # decided after 2 B
        assert len(blocks.evidence_.group(1)) == 2 * B


def test_a_confidently_worse_candidate_sends_the_iterate_back(lq):
    lr = _learner(lq, CYCLE)
    _run_blocks(lr, [BASE], list(range(B)))
    for _ in range(EVERY):
        lr.observe(lr.propose(), _result(1.0, 0))
    t = lr.rule.t
    for k in range(B):
        lr.observe(lr.propose(), _result(BASE[k] * 1.5, k))  # worse from every start
    b = lr.blocks_
    assert b.conf_[0] < 0.1 and b.deployed_ == 0
    np.testing.assert_array_equal(lr.z_, b.candidates_[b.deployed_])  # back at the deployed theta
    assert lr.rule.t == t + 1  # the block's own step; the rule keeps its state


def test_a_block_worse_but_not_confidently_leaves_the_iterate(lq):
    lr = _learner(lq, CYCLE)
    _run_blocks(lr, [BASE], list(range(B)))
    for _ in range(EVERY):
        lr.observe(lr.propose(), _result(1.0, 0))
    noise = np.array([0.3, -0.25, 0.2, -0.3, 0.25, -0.1])
    for k in range(B):
        lr.observe(lr.propose(), _result(BASE[k] * 1.02 + noise[k], k))
    conf = lr.blocks_.conf_[0]
    assert 0.1 < conf < 0.5
    assert not np.array_equal(lr.z_, lr.blocks_.candidates_[0])  # it keeps walking


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

    from mpcmobo.learners import Learner

    class Quiet(Learner):  # explores from the second episode on; records what it observed
        name = "quiet"

        def __init__(self, quiet_first: bool):
            super().__init__(lq.search_space, theta0)
            self.n, self.quiet_first, self.results = 0, quiet_first, []

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


def test_the_open_blocks_candidate_is_under_verification(lq):
    """``verifying()`` is the open block's candidate while the block gathers its episodes,
    None between blocks and without blocks; the tuner's status calls its trials so."""
    from mpcmobo.experiment.tunerstatus import trial_table

    lr = _learner(lq, CYCLE)
    seen = []
    for k in range(B + EVERY + 2):
        th = lr.propose()
        lr.observe(th, _result(1.0 + 0.1 * (k % B), k % B))
        v = lr.verifying()
        seen.append(v is not None)
        if v is not None:
            np.testing.assert_array_equal(v, th)
    # theta0's block, then steps outside blocks, then the next block's first episodes
    assert seen == [True] * (B - 1) + [False] * (EVERY + 1) + [True] * 2
    iterate = make_learner("mpc-rl", lq.search_space, lq.parameterization.theta0, deploy="iterate")
    assert iterate.verifying() is None
    theta0 = lq.parameterization.theta0
    rows = [
        SimpleNamespace(
            episode=k,
            theta=th,
            incumbent=theta0,
            x0=[0.0],
            error="",
            plant_cost=1.0,
            excess_cost=0.0,
        )
        for k, th in enumerate([theta0, lr.propose()])
    ]
    table = trial_table(rows, theta0, "cycle", B, None, lr.verifying())
    assert [t["verdict"] for t in table] == ["ran the deployed theta", "under verification"]
