"""Start-adjusted deployment tests under random starts (issue 11, session 13).

Under random starts the candidate's and the deployed theta's episodes start from different
states, and how costly a start is explains most of an episode's cost (on `lq` nearly all of
it). ``deploy_adjust = "start_cost"`` (the default of bo, mobo, hybrid and MPC-RL) gives every
episode a covariate, ``EpisodeResult.start_cost``: theta0's closed loop from the episode's start
on the MPC's own model (:func:`~mpcmobo.mpc.model_rollout`, no plant episode), and compares the
two thetas' costs by the analysis of covariance
(:func:`~mpcmobo.learners.deploy.adjusted_confidence`). Checked: the test against an
independent least-squares fit of the ANCOVA model, its invariance to the covariate's units,
its fall-back to Welch, its power where Welch has none, the loop's covariate against the
model's own equations, and old checkpoints resuming unadjusted.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from mpcmobo.learners import EpisodeResult, make_learner
from mpcmobo.learners.deploy import adjusted_confidence, ancova_confidence, unpaired_confidence
from mpcmobo.systems import get_system

FAST = {"n_init": 3, "num_restarts": 2, "raw_samples": 32, "maxiter": 20}


@pytest.fixture(scope="module")
def lq():
    return get_system("lq")


def _ancova_by_lstsq(yd, yc, sd, sc):
    """The ANCOVA model y = a + delta [candidate] + b s + e fitted by least squares on the full
    design matrix: the one-sided confidence of delta < 0 from its covariance (n - 3 dof), and
    the diagonal of the hat matrix X (X'X)^-1 X'."""
    y = np.r_[yd, yc]
    g = np.r_[np.zeros(len(yd)), np.ones(len(yc))]
    X = np.column_stack([np.ones(len(y)), g, np.r_[sd, sc]])
    XtX_inv = np.linalg.inv(X.T @ X)
    coef = XtX_inv @ X.T @ y
    r = y - X @ coef
    dof = len(y) - 3
    cov = (r @ r / dof) * XtX_inv
    hat = np.einsum("ij,jk,ik->i", X, XtX_inv, X)
    return stats.t.cdf(-coef[1] / np.sqrt(cov[1, 1]), dof), hat


def _reference(yd, yc, sd, sc):
    """The smaller of the test on all episodes and without the highest-leverage one."""
    full, hat = _ancova_by_lstsq(yd, yc, sd, sc)
    i = int(np.argmax(hat))
    if i < len(yd):
        without, _ = _ancova_by_lstsq(np.delete(yd, i), yc, np.delete(sd, i), sc)
    else:
        k = i - len(yd)
        without, _ = _ancova_by_lstsq(yd, np.delete(yc, k), sd, np.delete(sc, k))
    return full, min(full, without)


@pytest.mark.parametrize("seed", range(5))
def test_adjusted_confidence_is_the_ancova_t_test(seed):
    rng = np.random.default_rng(seed)
    sd, sc = rng.uniform(1, 10, 6 + seed), rng.uniform(1, 10, 4 + seed)
    yd = 2.0 * sd + rng.normal(0, 1.0, len(sd))
    yc = 2.0 * sc - 0.8 + rng.normal(0, 1.0, len(sc))
    full, ref = _reference(yd, yc, sd, sc)
    assert ancova_confidence(yd, yc, sd, sc) == pytest.approx(full, rel=1e-9, abs=1e-12)
    assert adjusted_confidence(yd, yc, sd, sc) == pytest.approx(ref, rel=1e-9, abs=1e-12)


def test_no_decision_rests_on_one_episode():
    """Session 13, CSTR seed 8 (random starts), theta0 against a design point after six
    episodes each: one hot-spot start of theta0 (cost 979347, covariate 13428) sets the slope,
    and the candidate, which never met such a start, looked better on all episodes (0.924);
    it is 1.6 times worse than theta0 on 100 fresh starts. Without that episode it is not."""
    yd = np.array([1866.0, 979347.0, 41568.0, 14863.0, 2373.0, 7899.0])
    sd = np.array([3092.0, 13428.0, 3349.0, 3043.0, 2900.0, 2406.0])
    yc = np.array([1752.0, 36937.0, 2027.0, 954.0, 86879.0, 1023.0])
    sc = np.array([4012.0, 2615.0, 4272.0, 3095.0, 6304.0, 2313.0])
    assert ancova_confidence(yd, yc, sd, sc) > 0.9
    assert adjusted_confidence(yd, yc, sd, sc) < 0.7
    assert adjusted_confidence(yd, yc, sd, sc) == pytest.approx(_reference(yd, yc, sd, sc)[1])


@settings(max_examples=40, deadline=None)
@given(
    scale=st.floats(1e-3, 1e3),
    shift=st.floats(-1e3, 1e3),
    seed=st.integers(0, 2**16),
)
def test_the_covariates_units_do_not_matter(scale, shift, seed):
    rng = np.random.default_rng(seed)
    sd, sc = rng.uniform(1, 5, 6), rng.uniform(1, 5, 6)
    yd, yc = sd + rng.normal(0, 0.3, 6), sc - 0.2 + rng.normal(0, 0.3, 6)
    a = adjusted_confidence(yd, yc, sd, sc)
    b = adjusted_confidence(yd, yc, scale * sd + shift, scale * sc + shift)
    assert b == pytest.approx(a, abs=1e-6)


def test_it_sees_a_gain_the_starts_hide_from_welch():
    """Costs proportional to how costly the start is, the candidate 10% cheaper from every
    start, its starts happening to be costlier: Welch sees a dearer candidate, the adjusted
    test (also without any one episode) a cheaper one."""
    rng = np.random.default_rng(0)
    sd = rng.uniform(1, 3, 6)
    sc = rng.uniform(2, 4, 6)
    yd = sd * (1 + 0.01 * rng.normal(size=6))
    yc = 0.9 * sc * (1 + 0.01 * rng.normal(size=6))
    assert unpaired_confidence(yd, yc) < 0.1
    assert adjusted_confidence(yd, yc, sd, sc) > 0.99
    # and a candidate 10% dearer from every start with easier starts is refused
    assert unpaired_confidence(sc, 1.1 * sd) > 0.9
    assert adjusted_confidence(sc, 1.1 * sd, sc, sd) < 0.01


def test_falls_back_to_welch():
    yd, yc = np.array([2.0, 3.0, 4.0]), np.array([1.0, 1.5, 2.5])
    welch = unpaired_confidence(yd, yc)
    nan = np.full(3, np.nan)
    assert adjusted_confidence(yd, yc, nan, nan) == welch  # no covariate (old checkpoints)
    assert adjusted_confidence(yd, yc, np.ones(3), np.ones(3)) == welch  # no spread
    assert adjusted_confidence(yd, yc[:1], yd, yc[:1]) == unpaired_confidence(yd, yc[:1])
    # a failed episode (inf) is dropped with its covariate, as Welch drops it
    s = np.array([1.0, 2.0, 3.0])
    with_inf = adjusted_confidence(np.r_[yd, np.inf], yc, np.r_[s, 5.0], s)
    assert with_inf == adjusted_confidence(yd, yc, s, s)


def test_the_loop_gives_the_start_cost_of_theta0_on_the_model(lq):
    """EpisodeResult.start_cost is theta0's mean stage cost from the episode's start in a
    closed loop on the MPC's own model: checked against a loop written here with the model's
    equations (System.model_step) and the MPC's inputs; computed once per start; NaN for a
    learner that does not ask for it."""
    from mpcmobo.experiment.loop import LearningRun
    from mpcmobo.mpc import ParametricMPC

    mpc = ParametricMPC(lq)
    theta0 = lq.parameterization.theta0

    class Asks:
        name = "asks"

        def __init__(self, asks):
            self.space, self.theta0, self.asks, self.results = lq.search_space, theta0, asks, []

        def propose(self):
            return theta0.copy()

        def uses_start_cost(self):
            return self.asks

        def observe(self, theta, result):
            self.results.append(result)

        def incumbent(self):
            return theta0.copy()

    learner = Asks(True)
    run = LearningRun(
        lq,
        learner,
        mpc,
        seed=1,
        steps=8,
        exploration_std=[0.3],
        start_mode="cycle",
        n_cycle_starts=2,
    )
    for _ in range(3):
        run.run_episode()
    assert len(run._start_costs) == 2  # the third episode reuses the first start's value
    x = run.cycle_starts[0].copy()
    mpc.reset()
    costs = []
    for _ in range(8):
        u = lq.clip_input(mpc.solve(x, theta0, sensitivities=False).action)
        costs.append(lq.stage_cost(x, u))
        x = lq.model_step(x, u)
    ref = float(np.mean(costs))
    assert learner.results[0].start_cost == pytest.approx(ref, rel=1e-8)
    assert learner.results[2].start_cost == learner.results[0].start_cost
    plant = learner.results[0].stage_cost
    assert np.isfinite(plant) and plant != pytest.approx(
        ref, rel=1e-3
    )  # the model is not the plant

    quiet = Asks(False)
    LearningRun(lq, quiet, mpc, seed=1, steps=8, start_mode="cycle").run_episode()
    assert np.isnan(quiet.results[0].start_cost)


def _observe(lr, theta, f1, s):
    y = np.array([f1, 1.0, 0.0, 0.0])
    lr.observe(theta, EpisodeResult(y, np.zeros(len(theta)), True, start_id=-1, start_cost=s))


S0 = np.array([1.0, 3.0, 0.5, 2.0, 8.0, 1.5])  # start costs of theta0's six random starts
S1 = np.array([4.0, 6.0, 3.0, 9.0, 5.0, 7.0])  # the candidate's, costlier starts


@pytest.mark.parametrize("learner", ["bo", "mobo"])
def test_gp_learners_deploy_on_the_adjusted_test(lq, learner):
    """theta0's costs equal its start costs, the candidate's are 0.8 of theirs: the candidate
    looks dearer raw (Welch) but is cheaper from every start; deployed with the default,
    kept out with deploy_adjust = "none"."""
    space, theta0 = lq.search_space, lq.parameterization.theta0
    z0 = space.to_unit(theta0)
    good = z0.copy()
    good[0] += 0.1
    rng = np.random.default_rng(0)
    noise = 1 + 0.01 * rng.normal(size=12)
    decided = {}
    for adjust in ("start_cost", "none"):
        lr = make_learner(
            learner, space, theta0, seed=0, trust_region="off", deploy_adjust=adjust, **FAST
        )
        assert lr.uses_start_cost() == (adjust == "start_cost")
        for f, s in zip(S0 * noise[:6], S0, strict=True):
            _observe(lr, theta0, f, s)
        for f, s in zip(0.8 * S1 * noise[6:], S1, strict=True):
            _observe(lr, space.from_unit(good, base=theta0), f, s)
        decided[adjust] = lr._paired_cost(good, z0), lr._incumbent_z.copy()
    conf, deployed = decided["start_cost"]
    assert conf > 0.99
    np.testing.assert_allclose(deployed, good)
    conf, deployed = decided["none"]
    assert conf < 0.5
    np.testing.assert_array_equal(deployed, z0)


def test_gp_learner_state_keeps_the_start_costs_and_old_ones_resume_unadjusted(lq):
    space, theta0 = lq.search_space, lq.parameterization.theta0
    a = make_learner("bo", space, theta0, seed=0, **FAST)
    for f, s in zip(S0, S0, strict=True):
        _observe(a, theta0, f, s)
    state = a.state_dict()
    b = make_learner("bo", space, theta0, seed=0, **FAST)
    b.load_state_dict(state)
    np.testing.assert_array_equal(b.S0_, S0)
    assert b.deploy_adjust == "start_cost"
    old = {k: v for k, v in state.items() if k not in ("start_costs", "deploy_adjust")}
    c = make_learner("bo", space, theta0, seed=0, **FAST)
    c.load_state_dict(old)
    assert c.deploy_adjust == "none" and not c.uses_start_cost()
    assert np.all(np.isnan(c.S0_)) and len(c.S0_) == len(S0)


def test_bad_deploy_adjust_names_the_option(lq):
    for name in ("bo", "mpc-rl"):
        with pytest.raises(ValueError, match="deploy_adjust"):
            make_learner(name, lq.search_space, lq.parameterization.theta0, deploy_adjust="x0")


def _block_result(cost, s):
    return EpisodeResult(
        objectives=np.array([cost, 0.0, 0.0, 0.0]),
        grad=np.full(9, 0.5),
        critic_ok=True,
        start_id=-1,
        stage_cost=cost,
        start_cost=s,
    )


@pytest.mark.parametrize("adjust", ["start_cost", "none"])
def test_mpc_rl_blocks_use_the_adjusted_test(lq, adjust):
    """MPC-RL's verification blocks under random starts: theta0's block, then a candidate's
    whose starts were costlier and which is cheaper from each: deployed only when adjusted."""
    theta0 = lq.parameterization.theta0
    lr = make_learner(
        "mpc-rl",
        lq.search_space,
        theta0,
        deploy_min_runs=6,
        deploy_every=1,
        deploy_max_runs=6,
        deploy_adjust=adjust,
    )
    assert lr.uses_start_cost() == (adjust == "start_cost")
    for s in S0:
        lr.observe(lr.propose(), _block_result(s, s))
    lr.observe(lr.propose(), _block_result(1.0, 1.0))  # one gradient step: a new iterate
    cand = lr.propose()
    assert not np.allclose(cand, theta0)
    for s in S1:
        lr.observe(lr.propose(), _block_result(0.8 * s, s))
    conf = lr.block_conf_[-1]
    if adjust == "start_cost":
        assert conf == pytest.approx(adjusted_confidence(S0, 0.8 * S1, S0, S1)) and conf > 0.99
        np.testing.assert_allclose(lr.incumbent(), cand)
    else:
        assert conf == pytest.approx(unpaired_confidence(S0, 0.8 * S1)) and conf < 0.5
        np.testing.assert_array_equal(lr.incumbent(), theta0)
    state = lr.state_dict()
    assert state["deploy_adjust"] == adjust
    old = {k: v for k, v in state.items() if k not in ("block_C", "deploy_adjust")}
    again = make_learner("mpc-rl", lq.search_space, theta0, deploy_min_runs=6, deploy_every=1)
    again.load_state_dict(old)
    assert again.deploy_adjust == "none" and np.all(np.isnan(again.block_C_))


def test_the_gp_models_f1_relative_to_the_start_under_random_starts_only(lq):
    space, theta0 = lq.search_space, lq.parameterization.theta0
    rand = make_learner("bo", space, theta0, seed=0, **FAST)
    for f, s in zip(2.0 * S0, S0, strict=True):
        _observe(rand, theta0, f, s)
    np.testing.assert_allclose(rand._model_Y()[:, 0], 2.0)  # f1 / start cost
    np.testing.assert_array_equal(rand.Y_[:, 0], 2.0 * S0)  # the records keep f1 itself
    cyc = make_learner("bo", space, theta0, seed=0, **FAST)
    for k, (f, s) in enumerate(zip(2.0 * S0, S0, strict=True)):
        y = np.array([f, 1.0, 0.0, 0.0])
        cyc.observe(
            theta0, EpisodeResult(y, np.zeros(len(theta0)), True, start_id=k % 3, start_cost=s)
        )
    np.testing.assert_array_equal(cyc._model_Y(), cyc.Y_)  # cycled: per-start offsets instead
    none = make_learner("bo", space, theta0, seed=0, deploy_adjust="none", **FAST)
    for f, s in zip(2.0 * S0, S0, strict=True):
        _observe(none, theta0, f, s)
    np.testing.assert_array_equal(none._model_Y(), none.Y_)


def test_a_failing_covariate_never_ends_a_run(lq, monkeypatch):
    """The start cost of a learner without theta0 is that of the MPC's theta0; a closed loop
    on the model that fails gives NaN (the tests then fall back to Welch), and the episode is
    recorded as usual."""
    import mpcmobo.experiment.loop as loop
    from mpcmobo.mpc import ParametricMPC

    mpc = ParametricMPC(lq)

    class Bare:  # no theta0 attribute
        name = "bare"

        def __init__(self):
            self.space, self.results = lq.search_space, []

        def propose(self):
            return lq.parameterization.theta0.copy()

        def uses_start_cost(self):
            return True

        def observe(self, theta, result):
            self.results.append(result)

        def incumbent(self):
            return lq.parameterization.theta0.copy()

    bare = Bare()
    run = loop.LearningRun(lq, bare, mpc, seed=2, steps=5, start_mode="cycle", n_cycle_starts=1)
    run.run_episode()
    assert np.isfinite(bare.results[0].start_cost)

    def broken(*args, **kwargs):
        raise TypeError("no model")

    monkeypatch.setattr(loop, "model_rollout", broken)
    other = Bare()
    run = loop.LearningRun(lq, other, mpc, seed=2, steps=5, start_mode="cycle", n_cycle_starts=1)
    row, _ = run.run_episode()
    assert np.isnan(other.results[0].start_cost) and np.isnan(row["start_cost"])
    assert row["error"] == "" and np.isfinite(row["f1"])
    assert other.results[0].f1 == bare.results[0].f1  # the same episode as with a covariate
