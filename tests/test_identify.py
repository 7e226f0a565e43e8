"""Identification (:mod:`mpcmobo.identify`) and the model switch that deploys its model.

The fit is least squares on the scaled one-step prediction error of the system's own model
structure: on transitions of the CSTR's true plant it recovers the true model parameters from
the nominal (imperfect) ones, its prior holds the nominal model as firmly as ``prior_std``
says, its robust loss shrugs off gross outliers, its covariance shrinks with the data, and its
held-out check tells a better model from the nominal one. The switch refits as the data grow
(ever more rarely) and resumes with the very fit it had. Last, a plant that runs away is
stopped, and its episode is a named failure.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from mpcmobo.experiment import loop, storage
from mpcmobo.experiment.settings import load_settings
from mpcmobo.experiment.study import run_study
from mpcmobo.identify import Identification, ModelFit, Transitions, identify, prediction_error
from mpcmobo.learners import EpisodeResult, Replay, Starts
from mpcmobo.learners.confidence import adjusted_confidence
from mpcmobo.learners.evidence import theta_key
from mpcmobo.learners.options import EvidenceDeploy
from mpcmobo.learners.prediction import JUDGE_STARTS
from mpcmobo.learners.switch import REFIT_GROWTH, ModelSwitch
from mpcmobo.mpc import PlantDiverged, rollout
from mpcmobo.systems import get_system
from mpcmobo.systems.plant import SystemPlant


def _identify_first(system, make):
    """``IdentifyFirst`` of MPC-RL learners made by ``make`` on ``system``, cycled over three
    starts, deploying on evidence."""
    from mpcmobo.learners.identified import IdentifyFirst

    return IdentifyFirst(
        make,
        system.search_space,
        np.asarray(system.parameterization.theta0, float),
        name="mpc-rl",
        starts=Starts("cycle", 3),
        model_fit=ModelFit(system),
        deploy=EvidenceDeploy(),
    )


def _episode(system, rng, steps=60):
    """States (steps+1, nx) and inputs (steps, nu) of the true plant under random inputs."""
    x = np.empty((steps + 1, system.nx))
    u = rng.uniform(system.u_lb, system.u_ub, size=(steps, system.nu))
    x[0] = system.sample_initial_state(rng)
    for k in range(steps):
        x[k + 1] = system.plant_step(x[k], u[k])
    return x, u


def _data(system, episodes, seed=0):
    rng = np.random.default_rng(seed)
    data = Transitions.empty(system.nx, system.nu)
    for _ in range(episodes):
        data.add_episode(*_episode(system, rng))
    return data


def test_one_episode_identifies_the_cstr_model(cstr):
    """One episode's 60 transitions: every multiplier within 0.5% of the true one (the nominal
    model is 10-20% off), a held-out error far below the nominal model's."""
    data = _data(cstr, 1)
    assert len(data) == 60
    fit = identify(cstr, data)
    assert fit.success and fit.better and fit.n == 60
    assert fit.names == cstr.param_names
    np.testing.assert_allclose(fit.estimate, cstr.true_params, rtol=5e-3)
    assert fit.holdout_error < 0.1 * fit.nominal_error
    assert prediction_error(cstr, data, fit.params) < 0.1 * prediction_error(
        cstr, data, cstr.models["imperfect"]
    )
    assert np.all(fit.std > 0) and np.all(np.isfinite(fit.cov))


def test_the_prior_holds_the_nominal_model_as_firmly_as_it_says(cstr):
    """With a prior spread of 1e-6 the estimate stays at the nominal model; with the default
    spread the data move it to the true one."""
    data = _data(cstr, 1)
    nominal = cstr.models["imperfect"]
    tight = ModelFit(cstr, prior_std=1e-6).fit(data)
    np.testing.assert_allclose(tight.estimate, nominal, rtol=1e-3)
    loose = ModelFit(cstr).fit(data)
    assert np.all(np.abs(loose.estimate - cstr.true_params) < np.abs(nominal - cstr.true_params))


def test_gross_outliers_barely_move_the_fit(cstr):
    """Three of 120 transitions corrupted by 50 x_scale: the soft-L1 loss keeps every estimate
    within 2% of the true model."""
    data = _data(cstr, 2, seed=1)
    data.x_next[[5, 40, 90]] += 50 * cstr.x_scale
    fit = identify(cstr, data)
    np.testing.assert_allclose(fit.estimate, cstr.true_params, rtol=2e-2)


def test_the_covariance_shrinks_with_the_data_and_a_subset_is_identified_alone(cstr):
    """Five episodes give smaller standard deviations than one; identifying two parameters
    leaves the others at the nominal model."""
    one, five = identify(cstr, _data(cstr, 1)), identify(cstr, _data(cstr, 5))
    assert np.all(five.std < one.std)
    sub = identify(cstr, _data(cstr, 1), names=["k0", "k1"])
    assert sub.names == ("k0", "k1") and sub.estimate.shape == (2,)
    nominal = cstr.models["imperfect"]
    np.testing.assert_array_equal(sub.params[[0, 3, 4]], nominal[[0, 3, 4]])
    with pytest.raises(ValueError, match="unknown model parameter"):
        ModelFit(cstr, names=["k9"])


def test_transitions_leave_out_what_is_not_finite_and_hold_out_each_episodes_last_quarter(cstr):
    rng = np.random.default_rng(3)
    x, u = _episode(cstr, rng, steps=8)
    x[4, 1] = np.nan  # two transitions touch state 4
    data = Transitions.empty(cstr.nx, cstr.nu)
    data.add_episode(x, u)
    data.add_episode(*_episode(cstr, rng, steps=8))
    assert len(data) == 14 and np.all(np.isfinite(data.x))
    hold = data.holdout_mask()
    assert hold.sum() == 3  # floor(6/4) + floor(8/4)
    assert hold[5] and hold[12] and hold[13] and not hold[:5].any()
    assert identify(cstr, Transitions.empty(cstr.nx, cstr.nu)).success is False


def _switch(cstr, calls):
    """A model switch on the CSTR (with its model in theta) whose fits are counted."""
    system = get_system("cstr", identify=cstr.param_names)
    fit = ModelFit(system)
    original = fit.fit

    def counted(data, start=None):
        calls.append(len(data))
        return original(data, start)

    fit.fit = counted  # type: ignore[method-assign]
    theta0 = system.parameterization.theta0
    return ModelSwitch(fit, theta0, Starts("cycle", 3), EvidenceDeploy()), theta0


def test_the_switch_refits_as_the_data_grow_ever_more_rarely_and_resumes_its_fit(cstr):
    """40 episodes: a fit after each of the first ten, then after every 10% growth of the
    transitions (21 fits in all, not 40); a resumed switch has the very fit, without fitting."""
    calls: list[int] = []
    sw, theta0 = _switch(cstr, calls)
    rng = np.random.default_rng(0)
    for e in range(40):
        x, u = _episode(cstr, rng, steps=20)
        res = EpisodeResult(np.array([1.0, 0, 0, 0]), np.zeros(len(theta0)), True, start_id=e % 3)
        res.states, res.inputs = x, u
        sw.observe(sw.next_theta()[1], res, "deployed")
    assert calls[:10] == [20 * (e + 1) for e in range(10)]
    assert all(b >= (1 + REFIT_GROWTH) * a for a, b in zip(calls, calls[1:]))
    assert len(calls) == 21
    np.testing.assert_allclose(sw.identification_.estimate, cstr.true_params, rtol=5e-3)
    state = sw.state_dict()
    calls2: list[int] = []
    other, _ = _switch(cstr, calls2)
    other.load_state_dict(state)
    assert calls2 == []
    np.testing.assert_array_equal(other.identification_.estimate, sw.identification_.estimate)
    assert other.identification_.n == sw.identification_.n == calls[-1]


class _RunawayPlant(SystemPlant):
    """A system's plant whose last state jumps to 1e6 x_scale from x_ref at the fourth step."""

    def step(self, action):
        obs, r, term, trunc, info = super().step(action)
        self.k = getattr(self, "k", 0) + 1
        if self.k == 4:
            obs = obs.copy()
            obs[-1] = self.system.x_ref[-1] + 1e6 * self.system.x_scale[-1]
        return obs, r, term, trunc, info


def test_a_plant_that_runs_away_is_stopped_and_named(cstr, cstr_mpc):
    """A state more than RUNAWAY x_scale from x_ref ends the episode with an error that names
    the step and the state, and carries the violation of the steps the plant ran."""
    x0 = cstr.x_ref + np.array([7.0, 0.0, 0.0])  # V above its limit: a violation
    with pytest.raises(FloatingPointError, match=r"ran away at step 3: .*\(T more than 100") as e:
        rollout(cstr, cstr_mpc, None, x0, 10, plant=_RunawayPlant(cstr))
    assert isinstance(e.value, PlantDiverged) and e.value.step == 3
    full = rollout(cstr, cstr_mpc, None, x0, 10)  # the same four steps, then on
    assert float(np.sum(full.violation[:4])) > 0
    assert e.value.violation == pytest.approx(float(np.sum(full.violation[:4])))


def test_a_runaway_episode_is_a_recorded_failure_of_the_study(tmp_path, monkeypatch):
    """In a study the runaway episode's row says why it failed, its objectives are NaN, and
    the run goes on to the end."""
    calls = {"n": 0}
    original = loop.rollout

    def flaky(system, mpc, theta, x0, steps, **kw):
        calls["n"] += 1
        if calls["n"] == 2:
            kw["plant"] = _RunawayPlant(system)
        return original(system, mpc, theta, x0, steps, **kw)

    monkeypatch.setattr(loop, "rollout", flaky)
    settings = load_settings(
        None,
        system={"name": "lq"},
        learners=["mpc-rl"],
        episodes=3,
        steps=8,
        workers=1,
        evaluation={"n_starts": 2},
    )
    summary = run_study(settings, tmp_path / "run")
    assert summary["complete"] is True
    df = storage.read_episodes(tmp_path / "run")
    assert len(df) == 3
    assert "ran away at step 3" in df.loc[1, "error"] and np.isnan(df.loc[1, "f1"])
    assert np.isfinite(df.loc[1, "violation"])  # the violation of the steps the plant ran
    assert (df.loc[[0, 2], "error"] == "").all() and np.isfinite(df.loc[[0, 2], "f1"]).all()


def test_identify_first_tunes_once_the_switch_has_settled(cstr):
    """The tuning learner starts at once after a deployment that the fit has not moved away
    from; after a drop, once no new candidate has come for a verification's worth of episodes
    (a cycle of 3 here); or after MAX_DECISIONS decisions once a model is deployed, never on
    drops alone while candidates come."""
    from mpcmobo.learners.switch import MAX_DECISIONS

    sw, theta0 = _switch(cstr, [])
    for _ in range(5):
        sw.decide()  # no fit, no decision yet: the switch goes on
    assert not sw.settled()
    sw.candidate_ = theta0.copy()
    sw._decided()
    assert not sw.settled()
    for _ in range(sw.policy.min_runs - 1):
        sw.decide()  # no fit: no new candidate
        assert not sw.settled()
    sw.decide()
    assert sw.settled()
    deployed, _ = _switch(cstr, [])
    deployed.candidate_ = theta0.copy()
    deployed.deployed_params_ = np.ones(3)  # a deployment (its identified model)
    assert not deployed.settled()  # a candidate is being verified
    deployed._decided()
    assert deployed.settled()
    other, _ = _switch(cstr, [])
    for _ in range(MAX_DECISIONS + 2):
        other.candidate_ = theta0.copy()  # a candidate from the fit, dropped
        other._decided()
        other.candidate_ = theta0.copy()  # and the fit has brought a new one
        assert not other.settled()  # the nominal model: identification goes on
    other._decided()
    other.deployed_params_ = np.ones(3)  # a model deployed at some decision
    assert other.settled()


def _fit_of(estimate, std=0.01):
    """A successful fit at ``estimate`` with standard deviations ``std`` (better than nominal)."""
    q = np.asarray(estimate, float)
    return Identification(
        ("a",) * len(q), q, np.full(len(q), std), np.eye(len(q)), q, 0.1, 1.0, 100, True
    )


def test_a_deployment_settles_the_switch_unless_the_fit_has_moved_on(cstr):
    """The decision that deploys a candidate looks at the fit at once: if it has moved more
    than MOVED standard deviations from the deployed model, a new candidate runs and the
    switch is not settled; if not, the switch has settled."""
    from mpcmobo.learners.switch import MOVED

    for shift, settles in ((0.5 * MOVED * 0.01, True), (2 * MOVED * 0.01, False)):
        sw, theta0 = _switch(cstr, [])
        sw.policy.runs = lambda *a: 100  # type: ignore[method-assign]
        sw.policy.confidence_of = lambda *a: 1.0  # type: ignore[method-assign]
        sw.identification_ = _fit_of(cstr.true_params)
        sw.decide()  # the fit beats the nominal model: a candidate
        assert sw.candidate_ is not None and not sw.settled()
        y = np.array([1.0])
        sw.evidence_.append(sw.candidate_, y, np.zeros(len(theta0)), 0, 0.0, "verify")
        sw.identification_ = _fit_of(np.asarray(cstr.true_params) + shift)
        sw.decide()  # the evidence deploys it
        assert sw.decisions_ == 1 and sw.deployed_params_ is not None
        assert sw.settled() is settles
        assert (sw.candidate_ is None) is settles


def test_a_candidate_follows_the_fit_until_it_first_runs(cstr):
    """A candidate that has not run yet is replaced by the fit once the fit moves away from
    it; once it has run, a moved fit waits for its decision."""

    sw, theta0 = _switch(cstr, [])
    sw.identification_ = _fit_of(cstr.true_params)
    sw.decide()
    first = sw.candidate_.copy()
    sw.identification_ = _fit_of(np.asarray(cstr.true_params) * 1.1)
    sw.decide()
    assert sw.decisions_ == 0 and theta_key(sw.candidate_) != theta_key(first)
    np.testing.assert_allclose(sw.tried_, np.asarray(cstr.true_params) * 1.1)
    moved = sw.candidate_.copy()
    sw.evidence_.append(moved, np.array([1.0]), np.zeros(len(theta0)), 0, 0.0, "verify")
    sw.identification_ = _fit_of(np.asarray(cstr.true_params) * 1.2)
    sw.decide()
    assert theta_key(sw.candidate_) == theta_key(moved)


def _ident_settings(learners):
    cheap = {"n_init": 3, "search": {"num_restarts": 1, "raw_samples": 16, "maxiter": 10}}
    return load_settings(
        None,
        system={"name": "lq", "identify": True},
        learners=learners,
        episodes=22,
        seeds=[0],
        evaluation={"n_starts": 3, "eval_every": 4},
        learner_options={"bo": cheap},
        workers=1,
    )


def test_identify_first_deploys_the_identified_model_and_resumes_exactly(tmp_path):
    """lq with identification, cycled starts: bo's deployed theta takes the identified model
    (the true one) after one cycle of candidate episodes, its episodes those of ``identify``
    until then, and bo proposes from there at once (the fit has not moved);
    runs interrupted before and after the deployment and in the tuning phase give the
    uninterrupted records."""
    full = tmp_path / "full"
    assert run_study(_ident_settings(["bo", "identify"]), full)["complete"] is True
    df = storage.read_episodes(full)
    lq = get_system("lq", identify=get_system("lq").param_names)
    names = list(lq.parameterization.names)
    idx = [names.index(f"model_{n}") for n in lq.param_names]
    bo, ident = (df[df.learner == n].sort_values("episode") for n in ("bo", "identify"))
    assert bo.theta.iloc[:12].map(tuple).tolist() == ident.theta.iloc[:12].map(tuple).tolist()
    # bo tunes: its candidate runs, or the budget refuses it and the deployed theta runs
    tried = bo.refused_theta.iloc[12] if bo.refused.iloc[12] else bo.theta.iloc[12]
    assert tuple(tried) != tuple(ident.theta.iloc[12])
    for learner in ("bo", "identify"):
        rows = df[df.learner == learner].sort_values("episode")
        final = np.asarray(rows.incumbent.iloc[-1], float)
        np.testing.assert_allclose(final[idx], lq.true_params, rtol=1e-3)
        assert len(rows.identified.iloc[-1]) == len(lq.param_names)
    out = tmp_path / "resumed"
    run_study(_ident_settings(["bo", "identify"]), out, max_episodes_this_call=5)
    run_study(None, out, resume=True, max_episodes_this_call=6)  # at 11: the candidate runs
    run_study(None, out, resume=True, max_episodes_this_call=4)  # at 15: bo tunes
    assert run_study(None, out, resume=True)["complete"] is True
    wall = ["mpc_time_s", "learner_time_s", "eval_time_s"]
    pd.testing.assert_frame_equal(
        storage.read_episodes(full).drop(columns=wall),
        storage.read_episodes(out).drop(columns=wall),
    )


def test_the_twin_tunes_theta_on_the_model_and_skips_what_fails():
    """tune_on_twin: the bo learner on a cost of theta alone (here a bowl off theta0 in the
    unit cube) finds a theta cheaper than the one it started from within its budget; a
    closed loop that fails (NaN) is never the result."""
    from mpcmobo.learners.twin import TWIN_EPISODES, tune_on_twin

    lq = get_system("lq", identify=get_system("lq").param_names)
    space, theta0 = lq.search_space, np.asarray(lq.parameterization.theta0, float)
    target = np.clip(space.to_unit(theta0) + 0.05, 0, 1)
    seen = []

    def costs(starts, theta, params):
        z = space.to_unit(np.asarray(theta, float))
        seen.append(z)
        c = 1.0 + float(np.sum((z - target) ** 2))
        bad = len(seen) % 4 == 0  # every fourth evaluation fails
        return np.full(len(starts), np.nan if bad else c)

    res = tune_on_twin(space, theta0, lq.true_params, costs, np.zeros((3, lq.nx)), seed=0)
    assert res.evaluations == TWIN_EPISODES == len(seen)
    assert res.better and res.cost < res.base_cost
    assert np.isfinite(res.cost) and res.cost == min(
        1.0 + float(np.sum((z - target) ** 2)) for i, z in enumerate(seen) if (i + 1) % 4
    )


def test_an_offered_candidate_is_judged_before_the_switch_settles(cstr):
    """A candidate offered on the deployed model (the twin's) keeps the switch unsettled,
    even after MAX_DECISIONS decisions, and a moving fit does not replace it; once decided,
    the switch has settled. Offering needs a deployed identified model."""
    from mpcmobo.learners.switch import MAX_DECISIONS

    sw, theta0 = _switch(cstr, [])
    with pytest.raises(ValueError, match="deployed identified model"):
        sw.offer(theta0)
    sw.deployed_params_ = np.asarray(cstr.true_params, float)
    sw.decisions_ = MAX_DECISIONS
    offered = theta0 * 1.01
    sw.offer(offered)
    assert not sw.settled()
    q = np.asarray(cstr.true_params, float) * 1.3
    sw.identification_ = _fit_of(q)
    sw.decide()  # it has not run: an offered candidate does not follow the fit
    assert theta_key(sw.candidate_) == theta_key(offered) and not sw.settled()
    state = sw.state_dict()
    other, _ = _switch(cstr, [])
    other.load_state_dict(state)
    assert not other.settled() and not other.follows_fit_
    sw._decided()
    assert sw.settled() and sw.follows_fit_


def _offered_switch(cstr):
    """A settled switch (cycle of 3 starts) whose deployed theta ran from every start at cost
    10, with the twin's theta offered; (switch, deployed theta, offered theta)."""
    from mpcmobo.learners.switch import MAX_DECISIONS

    sw, theta0 = _switch(cstr, [])
    sw.deployed_params_ = np.asarray(cstr.true_params, float)
    sw.decisions_ = MAX_DECISIONS
    for start in range(3):
        sw.observe(theta0.copy(), _cost(10.0, start), "deployed")
    offered = theta0 * 1.01
    sw.offer(offered)
    return sw, theta0, offered


def _cost(f1, start, spread=float("nan")):
    return EpisodeResult(
        np.array([f1, 0, 0, 0]),
        np.zeros(1),  # the switch keeps no gradient
        True,
        start_id=start,
        stage_cost=f1 / 60,
        spread=spread,
    )


def test_an_offered_candidate_kept_off_a_start_is_judged_there_on_its_bounded_simulation(cstr):
    """The twin's theta, simulated instead of run from a start (refused there, or not paying
    for itself), is judged from that start on its simulated cost times the model's spread (a
    "bounded" row): with the plant episodes of the other starts it is deployed where the
    bound still shows it cheaper, and not where the spread makes it dearer. Kept off from more
    than a third of the starts, or without a finite spread, it is dropped unrun; the count
    survives a resume; another theta leaves it, as does a fitted candidate."""
    from mpcmobo.learners.evidence import BOUNDED
    from mpcmobo.learners.switch import MAX_DECISIONS

    for spread, deployed in ((1.5, True), (3.0, False)):
        sw, theta0, offered = _offered_switch(cstr)
        sw.kept_off(theta0 * 1.02, _cost(6.0, 0, spread))  # not the candidate
        assert sw.offered() and len(sw.evidence_) == 3
        for start in (1, 2):
            sw.observe(offered.copy(), _cost(5.0, start), "verify")
        assert sw.offered()  # two of three starts: not judged yet
        sw.kept_off(offered.copy(), _cost(6.0, 0, spread))
        assert sw.evidence_.kinds[-1] == BOUNDED and sw.evidence_.Y[-1, 0] == 6.0 * spread
        assert sw.evidence_.costs[-1] == pytest.approx(6.0 / 60 * spread)
        if deployed:  # 10 - 9 = 1, 5, 5 cheaper from every start
            assert theta_key(sw.deployed_) == theta_key(offered) and not sw.offered()
            continue
        assert sw.offered() and theta_key(sw.deployed_) == theta_key(theta0)  # 10 - 18 = -8
        again, _ = _switch(cstr, [])
        again.load_state_dict(sw.state_dict())
        again.kept_off(offered.copy(), _cost(6.0, 0, spread))  # a second start of three
        assert not again.offered() and again.settled()
        assert again.decisions_ == MAX_DECISIONS + 1
        assert theta_key(again.deployed_) == theta_key(theta0)
    sw, theta0, offered = _offered_switch(cstr)
    sw.kept_off(offered.copy(), _cost(6.0, 0, float("inf")))  # the model not calibrated
    assert not sw.offered() and sw.settled() and len(sw.evidence_) == 3
    sw, theta0, offered = _offered_switch(cstr)
    gradless = _cost(6.0, 0, 1.5)
    gradless.objectives[1:] = np.nan  # no critic on the simulation: the cost still bounds it
    sw.kept_off(offered.copy(), gradless)
    assert sw.offered() and sw.evidence_.kinds[-1] == BOUNDED and len(sw.evidence_) == 4
    sw, theta0, offered = _offered_switch(cstr)
    sw.kept_off(offered.copy(), _cost(float("nan"), 0, 1.5))  # no cost: dropped unrun
    assert not sw.offered() and len(sw.evidence_) == 3
    fitted, _ = _switch(cstr, [])
    fitted.identification_ = _fit_of(np.asarray(cstr.true_params, float))
    fitted.decide()
    assert fitted.candidate_ is not None and not fitted.offered()
    fitted.kept_off(fitted.candidate_.copy(), _cost(6.0, 0, 1.0))
    assert fitted.candidate_ is not None and len(fitted.evidence_) == 0  # judged on the plant


def _fitted_switch(cstr, starts=6):
    """A switch (cycle of ``starts``) whose theta0 ran from every start at cost 10, with the
    fit's candidate made; (switch, theta0, candidate)."""
    system = get_system("cstr", identify=cstr.param_names)
    theta0 = system.parameterization.theta0
    sw = ModelSwitch(ModelFit(system), theta0, Starts("cycle", starts), EvidenceDeploy())
    for start in range(starts):
        sw.observe(theta0.copy(), _cost(10.0, start), "deployed")
    sw.identification_ = _fit_of(np.asarray(cstr.true_params, float))
    sw.decide()
    assert sw.candidate_ is not None and not sw.offered()
    return sw, theta0, sw.candidate_.copy()


def test_a_fitted_candidate_refused_from_a_start_is_judged_there_on_the_budgets_bound(cstr):
    """Under cycled starts the budget's refusal of the fit's candidate from a start (no
    simulation) stands in for its episode there: the deployed theta's plant cost from that
    start times the bound (a "bounded" row), so that the cycle's paired test decides. Cheaper
    from the other starts by more than the bound costs, the candidate is deployed; refused
    from more than a third of the cycle's starts, it is dropped unrun there. Another theta, a
    result without a finite bound of at least 1, an offered candidate and random starts leave
    it as it was."""
    from mpcmobo.learners.evidence import BOUNDED

    sw, theta0, cand = _fitted_switch(cstr)
    sw.refused(theta0 * 1.02, _cost(10.0, 0, 2.0))  # not the candidate
    sw.refused(cand.copy(), _cost(10.0, 0, float("inf")))  # the model not calibrated
    sw.refused(cand.copy(), _cost(float("nan"), 0, 2.0))  # the deployed episode failed
    assert len(sw.evidence_) == 6 and sw.kept_off_ == 0
    for start in (0, 1, 2, 4, 5):
        sw.observe(cand.copy(), _cost(1.0, start), "verify")
    assert sw.candidate_ is not None  # five starts of six: not judged yet
    sw.refused(cand.copy(), _cost(10.0, 3, 2.0))
    assert sw.evidence_.kinds[-1] == BOUNDED and sw.evidence_.Y[-1, 0] == 20.0
    assert sw.evidence_.costs[-1] == pytest.approx(10.0 / 60 * 2.0)
    assert theta_key(sw.deployed_) == theta_key(cand)  # -9 x 5 and +10: cheaper, paired
    sw, theta0, cand = _fitted_switch(cstr)
    for start in (0, 1, 2):
        sw.refused(cand.copy(), _cost(10.0, start, 1.2))
    assert sw.candidate_ is None and sw.decisions_ == 1  # 3 of 6 starts: dropped
    assert theta_key(sw.deployed_) == theta_key(theta0)
    assert list(sw.evidence_.kinds).count(BOUNDED) == 2
    sw, theta0, cand = _fitted_switch(cstr)
    sw.refused(cand.copy(), _cost(10.0, 0, 0.5))  # a bound below 1 is no bound
    assert len(sw.evidence_) == 6
    sw, theta0, offered = _offered_switch(cstr)
    sw.refused(offered.copy(), _cost(6.0, 0, 1.5))  # offered: its simulations bound it
    assert len(sw.evidence_) == 3 and sw.offered()
    system = get_system("cstr", identify=cstr.param_names)
    rand = ModelSwitch(ModelFit(system), theta0, Starts("random", 3), EvidenceDeploy())
    rand.identification_ = _fit_of(np.asarray(cstr.true_params, float))
    rand.decide()
    rand.refused(rand.candidate_.copy(), _cost(10.0, -1, 2.0))
    assert len(rand.evidence_) == 0  # random starts: the test counts episodes from any start


def test_the_twins_candidate_is_judged_by_the_deployed_models_twin_and_resumes_so(cstr):
    """A fitted candidate (a model of its own) is judged by the plain tests; the twin's theta,
    offered on the deployed identified model, by that model's twin (its simulated starts drawn
    with the switch's seed), also after a resume; without the loop's closed loops, plainly."""

    def costs(starts, theta, params):
        return np.ones(len(starts))

    q = np.asarray(cstr.true_params, float)
    for service in (None, costs):
        sw, theta0 = _switch(cstr, [])
        sw.seed, sw.start_costs = 3, service
        sw.identification_ = _fit_of(q)
        sw.decide()
        assert sw.candidate_ is not None and sw.policy.twin is None  # a model of its own
        sw.deployed_, sw.deployed_params_ = sw.candidate_, q
        sw._decided()
        sw.offer(theta0 * 1.01)
        if service is None:
            assert sw.policy.twin is None
            continue
        twin = sw.policy.twin
        assert twin is not None and twin.costs is costs
        np.testing.assert_array_equal(twin.params, q)
        other, _ = _switch(cstr, [])
        other.seed, other.start_costs = 3, costs
        other.load_state_dict(sw.state_dict())
        np.testing.assert_array_equal(other.policy.twin.params, q)
        np.testing.assert_array_equal(other.policy.twin.starts, twin.starts)


def test_a_dropped_model_is_tried_again_when_the_fit_moves_a_deployed_one_not():
    """Noise-free data: standard deviations near zero. A fit 1e-6 away from a dropped model
    (more than two standard deviations, less than RESOLUTION) is a new candidate; the same
    move away from the deployed model is not."""

    cstr = get_system("cstr")
    q0 = np.asarray(cstr.true_params, float)

    for deployed in (False, True):
        sw, _ = _switch(cstr, [])
        sw.identification_ = _fit_of(q0, std=1e-9)
        sw.decide()
        first = sw.candidate_.copy()
        if deployed:
            sw.deployed_ = first
            sw.deployed_params_ = q0
        sw._decided()
        sw.identification_ = _fit_of(q0 + 1e-6, std=1e-9)
        sw.decide()
        assert (sw.candidate_ is None) is deployed


def test_unsure_model_candidates_pool_their_evidence_until_one_is_decided():
    """Random starts: a fitted candidate the test leaves unsure after ``2 min_runs`` episodes
    is dropped into the pool, and the next fitted candidate is judged on its own episodes and
    the pool's. Here neither candidate's episodes alone are sure, both together are: the
    second is deployed after its ``min_runs`` episodes. A pooled test that finds the candidate
    more likely worse empties the pool; the pool survives a state round trip."""
    cstr = get_system("cstr")
    system = get_system("cstr", identify=cstr.param_names)
    theta0 = system.parameterization.theta0
    q0 = np.asarray(cstr.true_params, float)
    zeros = np.zeros(len(theta0))
    base = np.array([1.0, 1.3, 0.8, 1.2, 0.9, 1.1])
    c1 = np.array([0.71, 1.05, 0.75, 0.72, 1.03, 1.18])
    c2 = np.array([0.73, 1.08, 0.81])
    nan = np.full(9, np.nan)

    def conf(y):
        return adjusted_confidence(base, y, nan[: len(base)], nan[: len(y)])

    assert conf(c1) < 0.9 and conf(c2) < 0.9 <= conf(np.r_[c1, c2])

    def switch():
        sw = ModelSwitch(ModelFit(system), theta0, Starts("random"), EvidenceDeploy(min_runs=3))
        for y in base:
            sw.evidence_.append(theta0, np.array([y]), zeros, -1, np.nan, "baseline")
        sw.identification_ = _fit_of(q0)
        sw.decide()
        first = sw.candidate_.copy()
        for y in c1:
            sw.evidence_.append(first, np.array([y]), zeros, -1, np.nan, "verify")
        sw.decide()  # unsure after 2 min_runs episodes: dropped into the pool
        assert sw.candidate_ is None and sw.decisions_ == 1 and len(sw.pool_) == 1
        sw.identification_ = _fit_of(q0 * 1.05)
        sw.decide()  # the fit has moved: a new candidate
        assert sw.candidate_ is not None and theta_key(sw.candidate_) != theta_key(first)
        return sw

    sw = switch()
    restored = ModelSwitch(ModelFit(system), theta0, Starts("random"), EvidenceDeploy(min_runs=3))
    restored.load_state_dict(sw.state_dict())
    for s in (sw, restored):
        second = s.candidate_.copy()
        for y in c2:
            s.evidence_.append(second, np.array([y]), zeros, -1, np.nan, "verify")
        s.decide()
        assert theta_key(s.deployed_) == theta_key(second) and s.pool_ == []

    sw = switch()
    for y in (1.5, 1.6, 1.4):  # the new candidate is dearer: the pooled test says worse
        sw.evidence_.append(sw.candidate_, np.array([y]), zeros, -1, np.nan, "verify")
    sw.decide()
    assert theta_key(sw.deployed_) == theta_key(theta0) and sw.pool_ == []


def test_identify_first_offers_the_twins_theta_before_it_tunes():
    """Settled on a deployed identified model, identify-first tunes on the twin once and
    offers its theta to the switch; the tuning learner is built only after that candidate is
    decided, and its deployments are judged by the deployed model's twin. Without the loop's
    closed loops on a model there is no twin, and it tunes at once."""
    from mpcmobo.learners.mpc_rl import MPCRL

    lq = get_system("lq", identify=get_system("lq").param_names)
    space, theta0 = lq.search_space, np.asarray(lq.parameterization.theta0, float)
    target = np.clip(space.to_unit(theta0) + 0.05, 0, 1)

    def costs(starts, theta, params):
        c = 1.0 + float(np.sum((space.to_unit(np.asarray(theta, float)) - target) ** 2))
        return np.full(len(starts), c)

    for service in (costs, None):
        built: list[np.ndarray] = []

        def make(th, built=built):
            built.append(th)
            return MPCRL(space, th)

        learner = _identify_first(lq, make)
        assert not built  # the inner learner is built once, when the switch has settled
        if service is not None:
            learner.use_start_costs(service)
        sw = learner.switch_
        sw.deployed_params_ = np.asarray(lq.true_params, float)
        sw.decisions_ = 1  # a deployed model the fit has not left: settled
        assert sw.settled()
        assert learner.judge_starts() is None  # the plant's episodes judge the switch's models
        learner._advance()
        inner = learner.inner_
        if service is None:
            assert inner is not None and learner.twin_ is None and len(built) == 1
            assert learner.judge_starts() is None  # no twin without the loop's closed loops
            continue
        assert inner is None and not built and learner.twin_ is not None
        assert learner.twin_.better
        assert theta_key(sw.candidate_) == theta_key(learner.twin_.theta)
        assert sw.policy.twin is not None  # the offered candidate is judged by the twin
        # ... on its simulated starts, where the budget's payback is judged too
        np.testing.assert_array_equal(learner.judge_starts(), sw.policy.twin.starts)
        assert learner.judge_starts().shape == (JUDGE_STARTS, lq.nx)
        sw._decided()  # the plant's evidence decides the twin's theta
        learner._advance()
        inner = learner.inner_
        assert inner is not None and len(built) == 1
        assert inner.blocks_.twin is not None
        np.testing.assert_array_equal(inner.blocks_.twin.params, sw.deployed_params_)
        np.testing.assert_array_equal(learner.judge_starts(), inner.blocks_.twin.starts)


def test_a_fit_held_by_its_bounds_is_reported_and_drawn(tmp_path):
    """lq's plant lies outside bounds of e^(+-0.2) around its nominal model: every identified
    parameter ends on a bound, and the summary, ``mpcmobo run`` and figure 5 say which and
    where; with the default bounds none does. ``at_bounds`` tells a bound within 1e-3 from
    one further away, for parameters of either sign."""
    from typer.testing import CliRunner

    from mpcmobo.cli import app
    from mpcmobo.identify.fit import at_bounds, identification_bounds

    lq = get_system("lq")
    lo, hi = identification_bounds(lq)
    np.testing.assert_allclose(lo, np.asarray(lq.models["imperfect"]) * np.exp(-0.7))
    on_lo, on_hi = at_bounds(np.array([lo[0] * 1.0005, lo[1] * 1.01, hi[2]]), lo, hi)
    assert on_lo.tolist() == [True, False, False] and on_hi.tolist() == [False, False, True]
    on_lo, on_hi = at_bounds(np.array([-2.0, -1.9]), np.array([-2.0, -2.0]), np.array([1.0, 1.0]))
    assert on_lo.tolist() == [True, False] and not on_hi.any()

    args = [
        "run",
        "--system",
        "lq",
        "--learner",
        "identify",
        "--episodes",
        "2",
        "--seeds",
        "0",
        "1",
        "--workers",
        "1",
        "-q",
    ]
    cfg = tmp_path / "narrow.toml"
    cfg.write_text("[system]\nmodel_log_range = 0.2\n[evaluation]\nn_starts = 2\n")
    res = CliRunner().invoke(app, [*args, "--config", str(cfg), "--out", str(tmp_path / "n")])
    assert res.exit_code == 0, res.output
    summary = storage.read_json(tmp_path / "n" / "summary.json")
    held = summary["learners"]["identify"]["identified_at_bound"]
    sides = {"stiffness": "lower", "damping": "upper", "gain": "upper"}  # true 1, 0.5, 1
    assert {b["name"]: b["bound"] for b in held} == sides
    assert all(b["seeds"] == [0, 1] for b in held)
    bounds = summary["learners"]["identify"]["identified_bounds"]
    assert bounds["damping"][1] == pytest.approx(0.3 * np.exp(0.2))
    for name, side in sides.items():
        assert f"'{name}' ends on its {side} bound" in res.output
    assert "model_log_range" in res.output
    assert (tmp_path / "n" / "figures" / "fig5_identified.png").exists()
    res = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "d"), "--no-plot"])
    assert res.exit_code == 0 and "ends on its" not in res.output
    plain = storage.read_json(tmp_path / "d" / "summary.json")["learners"]["identify"]
    assert plain["identified_at_bound"] == []


def test_the_twin_of_the_right_model_predicts_a_plant_episode_exactly_by_replaying_it():
    """The twin predicts an episode by replaying its exploration (the inputs applied minus the
    MPC's) in the closed loop on the model from its start: with the true model that is the
    plant's episode itself, where the noise-free closed loop from the same start is off by
    the exploration's share of the cost."""
    from mpcmobo.experiment.build import build_system
    from mpcmobo.experiment.job import _learning_run
    from mpcmobo.learners.twin import Twin
    from mpcmobo.rl.objectives import mean_stage_cost

    s = load_settings(
        None, system={"name": "cstr"}, learners=["bo"], steps=20, exploration={"std": [5.0, 5.0]}
    )
    system = build_system(s, "bo")
    run = _learning_run(s, system, "bo", 0)
    _, record = run.run_episode()
    twin = Twin(np.asarray(system.true_params, float), run.start_costs, np.zeros((1, system.nx)))
    replay = Replay(record.x[0], record.u - record.pi)
    plant = mean_stage_cost(record)
    assert twin.predict(record.theta, [replay])[0] == pytest.approx(plant, rel=1e-8)
    assert abs(twin.predict(record.theta, [Replay(record.x[0])])[0] / plant - 1) > 0.01


def test_identify_first_records_the_last_fit_once_the_switch_gave_up():
    """The switch dropped its candidates and the tuning learner tunes the nominal model: the
    record's identified parameters are the last fit, not the nominal model the deployed theta
    holds (which figure 5 and identified_final would show as identified); once an identified
    model is deployed, they are the deployed theta's."""
    from mpcmobo.learners.mpc_rl import MPCRL

    lq = get_system("lq", identify=get_system("lq").param_names)
    space, theta0 = lq.search_space, np.asarray(lq.parameterization.theta0, float)
    learner = _identify_first(lq, lambda th: MPCRL(space, th))
    sw = learner.switch_
    nominal = sw.fit.estimate_of(theta0)
    sw.identification_ = _fit_of(nominal * 0.8)
    sw.decisions_, sw.waiting_ = 1, sw.policy.min_runs  # a drop, and no candidate since
    assert sw.settled() and sw.deployed_params_ is None
    learner._advance()
    assert learner.inner_ is not None
    np.testing.assert_array_equal(learner.identified(), nominal * 0.8)
    deployed = theta0.copy()
    deployed[sw.fit.theta_index] = nominal * 0.9  # an identified model deployed
    sw.deployed_ = deployed
    np.testing.assert_array_equal(learner.identified(), nominal * 0.9)
