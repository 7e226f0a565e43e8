"""The exploration budget: which candidates run on the plant, and when tuning stops exploring."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mpcmobo.experiment.loop import LearningRun
from mpcmobo.experiment.price import (
    PATIENCE,
    RECENT,
    SIMULATED_PATIENCE,
    SIMULATION_ERROR,
    ExplorationPrice,
)
from mpcmobo.experiment.settings import SettingsError, load_settings
from mpcmobo.experiment.tunerstatus import recommendation
from mpcmobo.learners.base import Learner
from mpcmobo.mpc import ParametricMPC
from mpcmobo.systems import get_system


def _no_saving():
    return -0.05, 1.0


def _unasked():
    raise AssertionError("the saving is asked only of a costlier candidate within the budget")


def _calibrated(budget: float, errors: list[float], episodes: int = 50) -> ExplorationPrice:
    """A gate whose model predicted past episodes with these log errors."""
    price = ExplorationPrice(budget, episodes)
    for e in errors:
        price.calibrate(1.0, math.exp(e), {"cost": math.exp(e)})
    return price


def test_before_the_model_is_calibrated_only_the_deployed_controller_runs():
    price = ExplorationPrice(0.5, episodes=50)
    assert price.error() == math.inf
    v = price.judge(0.5, 1.0, 0, _unasked)
    assert not v.run and "not calibrated" in v.reason


def test_a_candidate_within_the_budget_runs_one_over_it_does_not():
    price = _calibrated(0.5, [0.0, 0.0])
    assert price.judge(1.4, 1.0, 0, lambda: (1.0, 1.0)).run
    assert price.judge(0.8, 1.0, 1, _unasked).run  # cheaper: no payback to judge
    v = price.judge(1.6, 1.0, 2, _unasked)
    assert not v.run and "1.600x" in v.reason and "1.500x" in v.reason


def test_an_uncertain_model_bounds_even_a_cheaper_prediction():
    """A model whose log errors spread by a standard deviation of sqrt(2) (errors +-1) trusts
    a prediction of 0.8x the deployed controller only up to 0.8 e^sqrt(2) = 3.3x: over a
    budget of 1.5x."""
    price = _calibrated(0.5, [1.0, -1.0])
    assert price.error() == pytest.approx(1.0)
    assert price.ratio_error() == pytest.approx(math.sqrt(2))
    v = price.judge(0.8, 1.0, 0, _unasked)
    assert not v.run and "within a factor 4.113" in v.reason
    assert price.judge(0.35, 1.0, 1, _unasked).run  # 0.35 e^sqrt(2) = 1.44x: within it


def test_a_bias_common_to_both_predictions_does_not_refuse():
    """A structurally wrong model that under-predicts every closed loop by about a factor 4
    (log errors near 1.4): its RMS error is large and it simulates nothing, but a candidate it
    predicts at 0.8x the deployed controller runs, since the ratio of two of its predictions
    is as good as the spread of its errors (a common bias cancels)."""
    price = _calibrated(0.5, [1.3, 1.5, 1.4, 1.35])
    assert price.error() > 1.3 and not price.simulates()
    assert price.ratio_error() == pytest.approx(np.std([1.3, 1.5, 1.4, 1.35], ddof=1))
    assert price.judge(0.8, 1.0, 0, _unasked).run
    assert not price.judge(1.4, 1.0, 1, _unasked).run  # 1.4 e^0.087 = 1.53x: over 1.5x


def test_a_failing_prediction_is_refused_and_no_basis_runs():
    price = _calibrated(0.5, [0.0, 0.0])
    assert not price.judge(math.nan, 1.0, 0, _unasked).run
    assert price.judge(5.0, math.nan, 1, _unasked).run  # the deployed's prediction failed
    assert not price.judge(1.1, 1.0, 2, lambda: (math.nan, 1.0)).run  # fails from a start


def test_an_excess_that_does_not_pay_back_runs_and_counts_towards_convergence():
    price = _calibrated(0.5, [0.02, -0.02, 0.0])
    s = price.error()
    assert s == pytest.approx(np.sqrt(2 * 0.02**2 / 3))
    # 10% more from this start, 5% worse on the fixed starts: beyond the model's error
    v = price.judge(1.1, 1.0, 10, _no_saving)
    assert v.run and not v.pays and "pay back" in v.reason and price.unpaid_ == 1
    # better on the fixed starts (a saving of 0.01 per episode): 39 episodes pay it back
    assert price.judge(1.1, 1.0, 10, lambda: (0.01, 1.0)).pays and price.unpaid_ == 0
    assert not price.judge(1.1, 1.0, 46, lambda: (0.01, 1.0)).pays  # but not 3 of them
    assert not price.judge(1.01, 1.0, 49, lambda: (1.0, 1.0)).pays  # nor none
    for k in range(PATIENCE - 2):
        assert not price.converged
        price.judge(1.1, 1.0, 20 + k, _no_saving)
    assert price.converged and "could not pay back" in price.converged_


def test_a_new_model_is_calibrated_on_the_last_episodes():
    price = ExplorationPrice(0.5, episodes=50)
    for k in range(8):
        price.calibrate(1.0, 2.0, {"x0": [k], "cost": 2.0})
    assert price.error() == pytest.approx(math.log(2.0))
    seen = []

    def predict(episodes):
        seen.extend(e["x0"][0] for e in episodes)
        return np.full(len(episodes), 2.0)

    price.use_model("the identified model", predict)
    assert seen == list(range(8))[-RECENT:]  # the last ones, predicted by the new model
    assert price.error() == 0.0
    price.use_model("the identified model", predict)
    assert len(seen) == RECENT  # the same model: no new calibration


def test_tuning_converges_after_refusals_in_a_row_and_a_larger_budget_reopens_it():
    price = _calibrated(0.2, [0.0, 0.0], episodes=20)
    for k in range(PATIENCE - 1):
        assert not price.judge(2.0, 1.0, k, _unasked).run
    assert price.judge(1.0, 1.0, PATIENCE, _unasked).run  # a run breaks the row
    for k in range(PATIENCE):
        assert not price.converged
        price.judge(2.0, 1.0, 10 + k, _unasked)
    assert price.converged and "in a row" in price.converged_
    again = ExplorationPrice(0.2, episodes=20)
    again.load_state_dict(price.state_dict())
    assert again.converged and again.state_dict() == price.state_dict()
    extended = ExplorationPrice(0.2, episodes=40)
    extended.load_state_dict(price.state_dict())
    assert not extended.converged and extended.errors_ == price.errors_


def test_a_model_too_wrong_to_price_a_candidate_says_so_when_tuning_stops():
    """The MPC's own model without identification: its errors vary between starts by more than
    the budget, so every candidate is refused; tuning stops exploring, and the reason says the
    model cannot price a candidate and what to do, not that exploring no longer pays."""
    price = _calibrated(0.5, [0.0, 2.9, 0.1, 2.0])  # e.g. the CSTR's wrong model, 19x off
    for k in range(PATIENCE):
        assert not price.judge(1.0, 1.0, k, _unasked).run
    assert price.converged
    assert "cannot price a candidate" in price.converged_
    assert "[system] identify" in price.converged_ and "[exploration] budget" in price.converged_
    assert "no longer pays" not in price.converged_
    rec = recommendation(6, 50, None, [], "tuning", price.converged_)["reason"]
    assert rec.startswith("tuning has stopped exploring") and "theta is kept" in rec
    fresh = ExplorationPrice(0.5, episodes=50)  # never calibrated: no prediction is trusted
    for k in range(PATIENCE):
        fresh.judge(1.0, 1.0, k, _unasked)
    assert "it is not calibrated" in fresh.converged_
    priced = _calibrated(0.5, [0.0, 0.0])  # a model that prices: the refusals are verdicts
    for k in range(PATIENCE):
        priced.judge(2.0, 1.0, k, _unasked)
    assert "exploring no longer pays" in priced.converged_


def test_an_identified_model_too_wrong_to_price_a_candidate_is_not_told_to_identify():
    """Where the learner identifies the model already (its predictions are the identified
    model's, a structurally wrong one), a model too wrong to price a candidate does not advise
    to tune again with the model identified: the cure is a model with the plant's physics, or
    a larger budget. The tuner's learning run knows whether its learner identifies."""
    errors = [0.0, 0.9, -0.1, 0.3]  # a first-order model of a second-order batch reactor
    price = ExplorationPrice(0.5, episodes=50, identifies=True)
    for e in errors:
        price.calibrate(1.0, math.exp(e), {"cost": math.exp(e)})
    for k in range(PATIENCE):
        assert not price.judge(1.0, 1.0, k, _unasked).run
    assert "cannot price a candidate" in price.converged_
    assert "[system] identify" not in price.converged_
    assert "identified already" in price.converged_ and "[exploration] budget" in price.converged_


def test_the_learning_run_says_whether_its_learner_identifies(tmp_path):
    from mpcmobo.experiment.job import _learning_run
    from mpcmobo.experiment.settings import load_settings as load

    lq = get_system("lq")
    for identify, expected in ((True, True), (False, False)):
        s = load(None, system={"name": "lq", "identify": identify}, episodes=4).resolved()
        assert _learning_run(s, lq, "bo", 0).price.identifies is expected


def test_a_refusal_is_simulated_only_on_a_model_within_its_error_and_converges_later():
    """A learner that learns in simulation sees a refused candidate, or one that does not pay
    back, on the model where the model's error is at most SIMULATION_ERROR (it does not run);
    tuning converges only after SIMULATED_PATIENCE of them in a row, and a candidate that runs
    and pays back resets the count."""
    assert ExplorationPrice(0.5, 50).judge(0.5, 1.0, 0, _unasked, True).simulated is False
    rough = _calibrated(0.5, [2 * SIMULATION_ERROR, -2 * SIMULATION_ERROR])
    v = rough.judge(2.0, 1.0, 0, _unasked, True)
    assert not v.run and not v.simulated and rough.unpaid_ == 1
    price = _calibrated(0.5, [0.01, -0.01], episodes=100)
    assert not price.judge(2.0, 1.0, 0, _unasked, False).simulated  # a learner that does not
    assert price.unpaid_ == 1
    v = price.judge(1.1, 1.0, 1, _no_saving, True)  # within the budget, does not pay back
    assert not v.run and v.simulated and "pay back" in v.reason
    for k in range(SIMULATED_PATIENCE - 2):
        v = price.judge(2.0, 1.0, 2 + k, _unasked, True)
        assert not v.run and v.simulated and not price.converged
    assert price.unpaid_ == 1 and price.simulated_ == SIMULATED_PATIENCE - 1
    assert price.judge(0.9, 1.0, 40, _unasked, True).run  # cheaper: runs, resets both
    assert price.unpaid_ == 0 and price.simulated_ == 0
    for k in range(SIMULATED_PATIENCE):
        price.judge(2.0, 1.0, 41 + k, _unasked, True)
    assert price.converged and "on the model only" in price.converged_
    state = price.state_dict()
    again = ExplorationPrice(0.5, 100)
    again.load_state_dict(state)
    assert again.simulated_ == SIMULATED_PATIENCE and again.converged


def test_the_budget_setting_is_checked_and_inf_means_none():
    assert load_settings(exploration={"budget": math.inf}).exploration.budget == math.inf
    assert not ExplorationPrice(math.inf, 10).active
    for bad in (-0.1, math.nan):
        with pytest.raises(SettingsError, match="exploration.budget"):
            load_settings(exploration={"budget": bad})


def test_a_converged_tuning_recommends_to_stop_and_says_why():
    rec = recommendation(12, 50, None, [], "tuning", "5 candidates in a row were refused")
    assert rec["action"] == "stop" and "converged" in rec["reason"]
    assert "5 candidates" in rec["reason"] and "mpcmobo export tuning" in rec["reason"]
    assert recommendation(12, 50, None, [], "tuning")["action"] == "continue"
    spent = recommendation(8, 8, None, [], "tuning")["reason"]
    assert "budget of 8 trials is spent: the deployed theta is the result" in spent
    verifying = recommendation(8, 8, None, [], "tuning", verifying=True)["reason"]
    assert "under verification" in verifying and "--episodes N" in verifying


# ---------------------------------------------------------------------- in the loop
@pytest.fixture(scope="module")
def lq():
    return get_system("lq")


class FarAway(Learner):
    """Proposes the same far-away candidate; deploys theta0; counts its calls."""

    name = "far-away"

    def __init__(self, system, candidate):
        super().__init__(system.search_space, system.parameterization.theta0)
        self.candidate = np.asarray(candidate, float)
        self.proposed, self.observed = 0, []

    def propose(self):
        self.proposed += 1
        return self.candidate.copy()

    def observe(self, theta, result):
        self.observed.append(np.array(theta))

    def incumbent(self):
        return self.theta0.copy()


def _run(lq, budget, candidate, episodes=12):
    mpc = ParametricMPC(lq, model="imperfect")
    learner = FarAway(lq, candidate)
    run = LearningRun(
        lq,
        learner,
        mpc,
        seed=3,
        steps=10,
        exploration_std=[0.05],
        price=ExplorationPrice(budget, episodes),
    )
    return run, learner


def _expensive(lq):
    theta = lq.parameterization.theta0.copy()
    theta[lq.search_space.names.index("R_f")] = lq.search_space.upper[-1]  # a sluggish input
    return lq.search_space.clip(theta)


class Judging(FarAway):
    """FarAway whose deployment test measures a theta on ``starts``."""

    name = "judging"

    def __init__(self, system, candidate, starts):
        super().__init__(system, candidate)
        self.starts = starts

    def judge_starts(self):
        return self.starts.copy()


def test_the_payback_is_judged_on_the_starts_where_the_deployment_is_decided(lq):
    """A candidate's saving were it deployed is its mean over the starts of the learner's
    deployment test (the twin's), not over the run's fixed starts, where it may differ."""
    run, learner = _run(lq, 0.5, _expensive(lq))
    deployed, candidate = learner.theta0, learner.candidate
    params = run.prediction_params(deployed)
    on_cycle = run._saving(candidate, deployed, params)
    d, c = (run.start_costs(run.cycle_starts, t, params) for t in (deployed, candidate))
    assert on_cycle == pytest.approx((np.mean(d - c), np.mean(d)))
    rng = np.random.default_rng(5)
    starts = np.array([lq.sample_initial_state(rng) for _ in range(7)])
    run.learner = Judging(lq, candidate, starts)
    judged = run._saving(candidate, deployed, params)
    d, c = (run.start_costs(starts, t, params) for t in (deployed, candidate))
    assert judged == pytest.approx((np.mean(d - c), np.mean(d)))
    assert judged[1] != pytest.approx(on_cycle[1])


def test_the_loop_refuses_an_expensive_candidate_runs_the_deployed_and_converges(lq):
    run, learner = _run(lq, 0.0, _expensive(lq))
    rows = []
    for _ in range(PATIENCE + 2):
        plan = run.plan()
        rows.append(run.finish(plan, _episode(lq, run, plan))[0])
    refused = [r for r in rows if r["refused"]]
    assert len(refused) == PATIENCE  # each ran the deployed theta, with the noise
    for r in refused:
        np.testing.assert_array_equal(r["theta"], learner.theta0)
        assert r["excess_cost"] == 0.0 and np.isfinite(r["predicted_cost"])
    assert run.price.converged
    frozen = rows[PATIENCE:]
    assert all(not r["refused"] and math.isnan(r["predicted_cost"]) for r in frozen)
    assert learner.proposed == PATIENCE  # a converged tuning does not ask the learner
    assert len(learner.observed) == PATIENCE  # nor shows it the deployed theta's episodes
    plan = run.plan()
    assert plan.converged and not plan.explore and not np.any(plan.noise)


def _episode(lq, run, plan):
    from mpcmobo.mpc import rollout

    return rollout(lq, run.mpc, plan.theta, plan.x0, run.steps, noise=plan.noise)


def test_a_real_plants_excess_is_the_plant_cost_times_the_predicted_ratio(lq):
    """On a real plant (the deployed controller's episode is not measured) a candidate's excess
    is its plant cost times the model's predicted ratio of the two costs less one, so that a
    bias of the model common to both cancels: a candidate that is the deployed controller but
    for 1e-9 in a weight costs the plant nothing more, though the MPC's imperfect model of
    `lq` predicts each closed loop off by percents; with the budget's predictions, and
    without a budget (the closed loops of both on the deployed theta's model)."""
    theta0 = lq.parameterization.theta0
    near = theta0.copy()
    near[lq.search_space.names.index("R_f")] *= 1 + 1e-9
    for budget in (10.0, math.inf):
        run, _ = _run(lq, budget, near)
        rows = []
        for _ in range(4):
            plan = run.plan()
            rows.append(run.finish(plan, _episode(lq, run, plan))[0])
        ran = [r for r in rows if not np.array_equal(r["theta"], theta0)]
        assert len(ran) == (2 if budget == 10.0 else 4)
        for r in ran:
            d = run.start_cost(np.asarray(r["x0"]), theta0, run.mpc.model_params, None)
            assert abs(d / r["plant_cost"] - 1) > 1e-3  # the model is biased
            assert abs(r["excess_cost"]) < 1e-6 * r["plant_cost"]


def test_the_prediction_is_that_of_the_episode_on_an_exact_model(lq):
    """With the true model, the predicted cost of an episode is its plant cost; the first two
    episodes, before the model is calibrated, run the deployed controller."""
    run, learner = _run(lq, 10.0, lq.parameterization.theta0 * 1.05)
    run.mpc = ParametricMPC(lq, model="perfect")
    rows = []
    for _ in range(3):
        plan = run.plan()
        rows.append(run.finish(plan, _episode(lq, run, plan))[0])
    assert [bool(r["refused"]) for r in rows] == [True, True, False]
    assert "not calibrated" in rows[0]["refused"]
    np.testing.assert_array_equal(rows[0]["refused_theta"], learner.candidate)
    np.testing.assert_array_equal(rows[2]["theta"], learner.candidate)
    for r in rows:
        assert r["predicted_cost"] == pytest.approx(r["plant_cost"], rel=1e-6)
    assert run.price.error() < 1e-6


def test_without_a_budget_nothing_is_predicted_and_the_streams_are_those_of_the_budget(lq):
    a, learner = _run(lq, math.inf, _expensive(lq))
    b, _ = _run(lq, 0.0, _expensive(lq))
    pa, pb = a.plan(), b.plan()
    assert math.isnan(pa.predicted_cost) and not pa.refused
    np.testing.assert_array_equal(pa.theta, learner.candidate)
    np.testing.assert_array_equal(pa.x0, pb.x0)
    np.testing.assert_array_equal(pa.noise, pb.noise)


class Rehearsing(FarAway):
    """FarAway that learns in simulation, keeping what it is shown."""

    name = "rehearsing"

    def __init__(self, system, candidate):
        super().__init__(system, candidate)
        self.simulated = []

    def learns_in_simulation(self):
        return True

    def observe_simulated(self, theta, result):
        self.simulated.append((np.array(theta), result))


def test_a_refused_candidate_is_simulated_on_the_model_for_a_learner_that_learns_there(lq):
    """On the exact model, a refused candidate reaches the learner as its episode on the
    model from the plan's start with its noise (the plant's own episode, there), before the
    deployed theta's plant episode; the row records the refusal and says so."""
    from mpcmobo.mpc import model_plant, rollout
    from mpcmobo.rl.objectives import mean_stage_cost

    run, _ = _run(lq, 0.0, _expensive(lq))
    run.mpc = ParametricMPC(lq, model="perfect")
    learner = Rehearsing(lq, _expensive(lq))
    run.learner = learner
    rows, plans = [], []
    for _ in range(4):
        plan = run.plan()
        plans.append(plan)
        rows.append(run.finish(plan, _episode(lq, run, plan))[0])
    # the first two refusals precede the model's calibration: nothing is simulated
    assert [p.simulated for p in plans] == [False, False, True, True]
    assert all(r["refused"] for r in rows) and "simulated on the model" in rows[3]["refused"]
    assert len(learner.simulated) == 2 and len(learner.observed) == 4
    theta, result = learner.simulated[0]
    np.testing.assert_array_equal(theta, learner.candidate)
    plan = plans[2]
    params = run.prediction_params(np.asarray(plan.deployed))
    record = rollout(
        lq,
        run.mpc,
        theta,
        plan.x0,
        run.steps,
        noise=plan.noise,
        plant=model_plant(lq, run.mpc, params),
    )
    np.testing.assert_allclose(result.stage_cost, mean_stage_cost(record), rtol=1e-9)
    np.testing.assert_array_equal(result.x0, plan.x0)
    assert result.start_id == plan.start_id
    np.testing.assert_array_equal(learner.observed[2], learner.theta0)  # the plant's episode


class Bounded(FarAway):
    """FarAway that keeps the refusals it is told of with their bounds."""

    name = "bounded"

    def __init__(self, system, candidate):
        super().__init__(system, candidate)
        self.refused = []

    def observe_refused(self, theta, result):
        self.refused.append((np.array(theta), result))


def test_a_refusal_without_a_simulation_reaches_the_learner_with_its_bound(lq):
    """A candidate the budget refuses on a calibrated model, for a learner that does not learn
    in simulation, reaches the learner as the deployed theta's plant episode from that start
    with the bound on the candidate's cost ratio (its predicted ratio times SPREAD_ERRORS of
    the model's ratio errors), before that episode itself; before the calibration there is
    no bound, and nothing reaches it."""
    from mpcmobo.experiment.loop import SPREAD_ERRORS

    run, _ = _run(lq, 0.0, _expensive(lq))
    learner = Bounded(lq, _expensive(lq))
    run.learner = learner
    plans, rows, spreads = [], [], []
    for _ in range(4):
        plan = run.plan()
        spreads.append(math.exp(SPREAD_ERRORS * run.price.ratio_error()))
        plans.append(plan)
        rows.append(run.finish(plan, _episode(lq, run, plan))[0])
    assert all(r["refused"] and not p.simulated for r, p in zip(rows, plans, strict=True))
    assert [math.isfinite(p.refused_bound) for p in plans] == [False, False, True, True]
    assert len(learner.refused) == 2 and len(learner.observed) == 4
    for (theta, result), plan, row, spread in zip(
        learner.refused, plans[2:], rows[2:], spreads[2:], strict=True
    ):
        np.testing.assert_array_equal(theta, learner.candidate)
        params = run.prediction_params(np.asarray(plan.deployed))
        c = run.start_cost(plan.x0, learner.candidate, params, plan.noise)
        assert plan.refused_bound == pytest.approx(c / plan.predicted_deployed * spread)
        assert result.spread == plan.refused_bound > 1
        assert result.stage_cost == pytest.approx(row["plant_cost"])  # the deployed's episode
        assert result.start_id == plan.start_id
        np.testing.assert_array_equal(result.x0, plan.x0)


def test_the_gate_resumes_from_the_run_state(lq):
    run, _ = _run(lq, 0.0, _expensive(lq))
    for _ in range(3):
        plan = run.plan()
        run.finish(plan, _episode(lq, run, plan))
    state = run.state_dict()
    other, _ = _run(lq, 0.0, _expensive(lq))
    other.load_state_dict(state)
    assert other.price.state_dict() == run.price.state_dict()
    assert other.price.unpaid_ == 3


def test_a_tuner_converges_hands_out_the_deployed_controller_and_says_so(tmp_path):
    """bo on ``lq`` with no budget at all: its design's candidates are refused until tuning
    has converged; then each trial is the deployed theta without noise (from a start told
    before, the same log, which is no longer taken for a repeat), and status says to stop.
    Another exploration budget given to the tuner (``ask --exploration-budget``) is saved and
    opens exploring again; an invalid one is refused, naming the key, and changes nothing."""
    from test_tuner import FAST, _episode
    from typer.testing import CliRunner

    from mpcmobo import Tuner
    from mpcmobo.cli import app

    out = tmp_path / "t"
    tuner = Tuner(
        {"name": "lq", "identify": False},
        "bo",
        out,
        episodes=16,
        steps=6,
        exploration={"budget": 0.0},
        learner_options={"bo": FAST},
        evaluation={"n_starts": 2, "eval_every": 50},
    )
    refused = []
    for _ in range(14):
        converged = tuner.status()["exploration"]["converged"] is not None
        trial = tuner.ask()
        if converged:
            assert not np.any(trial.noise)
            np.testing.assert_array_equal(trial.theta, tuner.deployed)
        row = tuner.tell(trial, *_episode(tuner, trial))
        refused += [row.episode] if row.refused else []
    st = tuner.status()
    assert st["exploration"]["refused"] == refused and len(refused) >= PATIENCE
    assert st["exploration"]["converged"] and st["recommendation"]["action"] == "stop"
    res = CliRunner().invoke(app, ["status", str(out)])
    # a budget of 0 leaves no room for the model's error: the reason says it cannot price one
    assert res.exit_code == 0 and "tuning has stopped exploring" in res.output
    assert "([system] identify)" in " ".join(res.output.split())  # printed, not taken for markup
    assert "refused" in res.output
    # the next trial planned while converged, as `mpcmobo tell` leaves it (it prepares it)
    assert not np.any(tuner.ask().noise)
    # another exploration budget on the tuner: saved, and exploring opens again at the next ask
    res = CliRunner().invoke(app, ["ask", str(out), "--exploration-budget", "inf"])
    assert res.exit_code == 0, res.output
    assert np.any(json.loads(res.stdout[res.stdout.index("{") :])["noise"]), res.output
    tuner = Tuner.load(out)
    assert tuner.settings.exploration.budget == math.inf and tuner.settings.episodes == 16
    st = tuner.status()
    assert st["exploration"]["converged"] is None and st["recommendation"]["action"] == "continue"
    trial = tuner.ask()  # the pending trial, planned again under the new budget: the learner's
    assert np.any(trial.noise) and trial.id == 14
    res = CliRunner().invoke(app, ["ask", str(out), "--exploration-budget", "-1"])
    assert res.exit_code == 2 and "exploration.budget" in res.output, res.output
    assert Tuner.load(out).settings.exploration.budget == math.inf  # nothing changed


def test_a_run_that_could_not_price_its_candidates_warns_at_its_end():
    """The summary keeps why each job stopped exploring; ``mpcmobo run`` warns of the jobs
    that stopped because the model could not price a candidate, not of the others."""
    from mpcmobo.cli import unpriced_warnings
    from mpcmobo.experiment.summary import stopped_exploring

    wrong = _calibrated(0.5, [0.0, 2.9, 0.1, 2.0])
    right = _calibrated(0.5, [0.0, 0.0])
    for k in range(PATIENCE):
        wrong.judge(1.0, 1.0, k, _unasked)
        right.judge(2.0, 1.0, k, _unasked)
    ckpts = [
        {"learner": "bo", "seed": 0, "state": {"price": wrong.state_dict()}},
        {"learner": "bo", "seed": 1, "state": {"price": right.state_dict()}},
        {"learner": "mobo", "seed": 0, "state": {"price": ExplorationPrice(0.5, 50).state_dict()}},
        {"learner": "identify", "seed": 0, "state": {}},
    ]
    stops = stopped_exploring(ckpts)
    assert sorted(stops) == ["bo"] and [s["seed"] for s in stops["bo"]] == [0, 1]
    assert [s["episode"] for s in stops["bo"]] == [PATIENCE - 1] * 2
    (line,) = unpriced_warnings({"stopped_exploring": stops})
    assert line.startswith(
        f"1 job(s) stopped exploring (bo seed 0 at episode {PATIENCE - 1}): the model cannot price"
    )
    assert "bo seed 1" not in line and "[system] identify" in line
    assert unpriced_warnings({"stopped_exploring": {"bo": stops["bo"][1:]}}) == []
    assert unpriced_warnings({}) == []  # a summary written before the key existed


def test_the_progress_lines_say_when_a_job_stops_exploring():
    """A run's progress lines (and bars) show that a job has stopped exploring, from its run's
    saved state, so a user does not wait for a run that no longer learns."""
    import io

    from rich.console import Console

    from mpcmobo.cli.progress import Lines
    from mpcmobo.experiment.job import explores, progress_event

    stopped = _calibrated(0.5, [0.0, 0.0])
    for k in range(PATIENCE):
        stopped.judge(2.0, 1.0, k, _unasked)
    assert not explores({"price": stopped.state_dict()})
    assert explores({"price": ExplorationPrice(0.5, 50).state_dict()}) and explores({})
    out = io.StringIO()
    lines = Lines(Console(file=out, width=200), every=1)
    lines(progress_event("bo", 0, [], 10, exploring=True) | {"episode": 1})
    lines(progress_event("bo", 0, [], 10, exploring=False) | {"episode": 2})
    first, second = out.getvalue().splitlines()
    assert "exploring stopped" not in first and second.endswith("exploring stopped")
