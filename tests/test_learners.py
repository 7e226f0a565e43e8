"""CDPG direction on a linear-quadratic system, and the learners on the CSTR."""

import numpy as np
import pytest

from mpcmobo.bo import AcqfSearch, EHVIOptions
from mpcmobo.experiment.loop import LearningRun
from mpcmobo.learners import EpisodeResult, make_learner
from mpcmobo.mpc import ParametricMPC, rollout
from mpcmobo.rl import CompatibleCritic, GaussianExploration
from mpcmobo.systems import get_system


def test_cdpg_gradient_direction_matches_finite_differences_on_lq():
    """The compatible DPG estimate (eq. DPG) points where a finite-difference gradient of the
    expected discounted closed-loop cost points (cosine >= 0.9)."""
    s = get_system("lq")
    mpc = ParametricMPC(s, warm_start=False, tol=1e-10)
    th0 = mpc.theta0.copy()
    rng = np.random.default_rng(0)
    starts = [s.sample_initial_state(rng) for _ in range(8)]
    T = 30
    disc = mpc.gamma ** np.arange(T)

    def J(th):
        return np.mean([disc @ rollout(s, mpc, th, x0, T, sensitivities=False).L for x0 in starts])

    fd = np.zeros(mpc.n_theta)
    for i in range(1, mpc.n_theta):  # theta_c does not change the policy
        h = 1e-4 * max(1.0, abs(th0[i]))
        tp, tm = th0.copy(), th0.copy()
        tp[i] += h
        tm[i] -= h
        fd[i] = (J(tp) - J(tm)) / (2 * h)
    critic = CompatibleCritic(gamma=mpc.gamma, weighting="discounted")
    noise_rng = np.random.default_rng(1)
    expl = GaussianExploration(std=[0.3])
    grads = []
    for _ in range(8):
        for x0 in starts:
            rec = rollout(s, mpc, th0, x0, T, rng=noise_rng, exploration=expl)
            res = critic.fit(rec)
            assert res.ok
            grads.append(res.grad)
    g = np.mean(grads, axis=0)
    cos = g @ fd / (np.linalg.norm(g) * np.linalg.norm(fd))
    assert cos >= 0.9, f"cosine {cos:.3f}"


def _result(f, grad=None, ok=True):
    f = np.asarray(f, float)
    return EpisodeResult(objectives=f, grad=np.zeros(14) if grad is None else grad, critic_ok=ok)


@pytest.mark.parametrize("name", ["mpc-rl", "bo", "mobo", "hybrid"])
def test_proposals_inside_bounds_and_exact_resume(cstr, name):
    space = cstr.search_space
    theta0 = cstr.parameterization.theta0
    kw = (
        {"n_init": 3, "num_restarts": 2, "raw_samples": 32, "maxiter": 20}
        if name != "mpc-rl"
        else {}
    )
    a = make_learner(name, space, theta0, seed=3, **kw)
    rng = np.random.default_rng(0)
    for i in range(6):
        th = a.propose()
        assert space.contains(th)
        f = np.abs(rng.normal(size=4)) * [1000, 10, 1, 100]
        if i == 2:
            f[:] = np.nan  # a failed episode
        a.observe(th, _result(f, grad=rng.normal(size=14)))
    state = a.state_dict()
    b = make_learner(name, space, theta0, seed=99, **kw)
    b.load_state_dict(state)
    pa, pb = a.propose(), b.propose()
    np.testing.assert_array_equal(pa, pb)
    np.testing.assert_array_equal(a.incumbent(), b.incumbent())
    assert space.contains(pa)
    assert np.all(np.isfinite(a.incumbent()))


def test_bo_learners_never_fit_nan(cstr):
    space, theta0 = cstr.search_space, cstr.parameterization.theta0
    mobo = make_learner("mobo", space, theta0, seed=0, n_init=3, num_restarts=2, raw_samples=32)
    for i in range(5):
        th = mobo.propose()
        f = [np.nan] * 4 if i % 2 else [100.0 + i, 1.0, 0.0, 2.0]
        mobo.observe(th, _result(f))
    assert mobo.surrogate.train_Y.shape[0] == 3
    assert np.all(np.isfinite(mobo.surrogate.train_Y))
    assert mobo.ref_point_ is not None and np.all(np.isfinite(mobo.ref_point_))


def test_mpc_rl_ignores_failed_episodes(cstr):
    space, theta0 = cstr.search_space, cstr.parameterization.theta0
    lr = make_learner("mpc-rl", space, theta0, deploy="iterate")  # no verification block
    th = lr.propose()
    lr.observe(th, _result([np.nan] * 4, grad=np.full(14, np.nan), ok=False))
    np.testing.assert_array_equal(lr.propose(), th)
    lr.observe(th, _result([1, 1, 1, 1], grad=np.ones(14)))
    assert not np.array_equal(lr.propose(), th)  # a good episode moves theta


def test_unknown_learner():
    s = get_system("lq")
    with pytest.raises(ValueError, match="unknown learner 'nope'"):
        make_learner("nope", s.search_space, s.parameterization.theta0)


def _short_cstr_run(cstr, cstr_mpc, name, seed):
    """16 episodes of 40 steps from 2 cycled starts; returns the learner and the rows."""
    kw = (
        {"n_init": 4, "num_restarts": 2, "raw_samples": 64, "maxiter": 30}
        if name != "mpc-rl"
        else {"lr": 0.05}
    )
    learner = make_learner(name, cstr.search_space, cstr_mpc.theta0, seed=seed, **kw)
    run = LearningRun(
        cstr,
        learner,
        cstr_mpc,
        seed=seed,
        steps=40,
        exploration_std=[2, 2],
        start_mode="cycle",
        n_cycle_starts=2,
    )
    return learner, [run.run_episode()[0] for _ in range(16)]


def _lowered(rows) -> bool:
    """A later pair of episodes (one from each start) costs less than the first pair (theta0
    for mpc-rl; theta0 and the design for mobo)."""
    f1 = np.array([r["f1"] for r in rows])
    return min(f1[10:12].mean(), f1[12:14].mean(), f1[14:16].mean()) < f1[:2].mean()


# mpc-rl on most of these seeds: one seed's outcome depends on the machine's floating point
# (the CSTR's closed loop amplifies it: seed 0 lowered f1 on the machine of session 10, not on
# that of session 11, where seeds 1 and 2 did); mobo on seed 0
SHORT_RUN_SEEDS = {"mpc-rl": (0, 1, 2), "mobo": (0,)}


@pytest.mark.parametrize("name", ["mpc-rl", "mobo"])
def test_learner_lowers_f1_on_short_cstr_run(cstr, cstr_mpc, name):
    """Short seeded CSTR runs: the learner's later episodes cost less than theta0's, on most
    seeds."""
    runs = [_short_cstr_run(cstr, cstr_mpc, name, seed) for seed in SHORT_RUN_SEEDS[name]]
    lowered = [_lowered(rows) for _, rows in runs]
    assert sum(lowered) > len(lowered) / 2, lowered
    for _, rows in runs:
        for r in rows:
            assert cstr.search_space.contains(np.array(r["theta"]))
    learner = runs[0][0]
    if name == "mobo":  # cycled starts reach the GP as groups: one f1 offset per start
        np.testing.assert_array_equal(learner.starts_, np.arange(16) % 2)
        offsets = learner.surrogate.group_offsets
        assert sorted(offsets) == [0, 1]
        assert offsets[0][0] == pytest.approx(-offsets[1][0]) and offsets[0][0] != 0


# the incumbent rule (random starts: these tests give no start_id; since session 11 "auto" would
# verify there)
OLD_RULE = {
    "violation_budget": "off",
    "deploy_confidence": 0.0,
    "deploy_min_runs": 1,
    "deploy": "incumbent",
}


def test_incumbent_prefers_supported_points_when_risk_averse(cstr):
    """Ten noisy episodes of one theta (z = 0.3) against one lucky episode elsewhere: with
    kappa = 0 the incumbent is the lowest predicted f1, with kappa = 3 the well-supported
    point."""
    space = cstr.search_space
    rng = np.random.default_rng(0)
    a = np.full(space.dim, 0.3)
    Z = np.vstack([np.tile(a, (10, 1)), np.full(space.dim, 0.9)])
    f1 = np.r_[1000 * np.exp(0.5 * rng.normal(size=10)), 700.0]
    picks = {}
    for kappa in (0.0, 3.0):
        # the old incumbent rule (no deployment rule: the safe default needs runs and evidence)
        bo = make_learner(
            "bo", space, cstr.parameterization.theta0, incumbent_kappa=kappa, **OLD_RULE
        )
        for z, f in zip(Z, f1, strict=True):
            bo.observe(space.from_unit(z, base=bo.theta0), _result([f, 0, 0, 0]))
        picks[kappa] = space.to_unit(bo.incumbent())
    np.testing.assert_allclose(picks[0.0], Z[-1], atol=1e-9)
    np.testing.assert_allclose(picks[3.0], a, atol=1e-9)
    with pytest.raises(ValueError, match="incumbent_kappa"):
        make_learner("bo", space, cstr.parameterization.theta0, incumbent_kappa=-1)


@pytest.mark.parametrize("name", ["bo", "mobo"])
def test_removed_options_load_at_their_old_defaults_only(cstr, name):
    """confirm_runs, replicate_every, max_replicates and noise_floor were removed (issue 10):
    old settings that leave them at their defaults still build the learner; one switched on,
    or a name that was never an option, is refused with a message naming it."""
    space, theta0 = cstr.search_space, cstr.parameterization.theta0
    old = {"confirm_runs": 1, "replicate_every": 0, "max_replicates": 3, "noise_floor": None}
    make_learner(name, space, theta0, **old)
    for key, on in [("confirm_runs", 2), ("replicate_every", 3), ("noise_floor", 0.2)]:
        with pytest.raises(ValueError, match=f"{key} = .*removed in the issue-10 clean-up"):
            make_learner(name, space, theta0, **{**old, key: on})
    with pytest.raises(TypeError, match="unexpected learner option 'confirm'"):
        make_learner(name, space, theta0, confirm=2)


def test_learner_state_from_before_the_clean_up_resumes_exactly(cstr):
    """A state dict whose GP state still has the removed keys (num_threads, noise_floor at its
    default) resumes to the same next proposal; a noise floor switched on is refused."""
    space, theta0 = cstr.search_space, cstr.parameterization.theta0
    kw = {"n_init": 2, "num_restarts": 2, "raw_samples": 32, "maxiter": 10}
    a = make_learner("mobo", space, theta0, seed=1, **kw)
    for k in range(4):
        a.observe(a.propose(), _result([1000.0 + 100 * k, 10.0 - k, k % 2, 0]))
    state = a.state_dict()
    state["surrogate_pre_fit"] = {
        **state["surrogate_pre_fit"],
        "num_threads": 1,
        "noise_floor": None,
    }
    b = make_learner("mobo", space, theta0, seed=7, **kw)
    b.load_state_dict(state)
    np.testing.assert_array_equal(a.propose(), b.propose())
    state["surrogate_pre_fit"]["noise_floor"] = 0.2
    with pytest.raises(ValueError, match="noise_floor"):
        make_learner("mobo", space, theta0, **kw).load_state_dict(state)


def test_mpc_rl_learning_rate_decay(cstr):
    """lr_decay = c: the k-th step (k = 0, 1, ...) is lr / (1 + c k) times the gradient."""
    space = cstr.search_space
    g = np.zeros(14)
    g[2] = 1e-6  # a small gradient on one weight: no clipping, no bound reached
    lr = make_learner("mpc-rl", space, cstr.parameterization.theta0, optimizer="sgd",
                      lr=0.01, lr_decay=1.0, deploy="iterate")  # fmt: skip
    zs = [space.to_unit(lr.propose())]
    for _ in range(3):
        lr.observe(lr.propose(), _result([1, 1, 1, 1], grad=g))
        zs.append(space.to_unit(lr.propose()))
    steps = np.linalg.norm(np.diff(zs, axis=0), axis=1)
    # (d theta / d z changes slightly as the log-scaled weight moves: 1% tolerance)
    np.testing.assert_allclose(steps / steps[0], [1, 1 / 2, 1 / 3], rtol=1e-2)
    with pytest.raises(ValueError, match="lr_decay"):
        make_learner("mpc-rl", space, cstr.parameterization.theta0, lr_decay=-1)


def test_mobo_halves_its_ehvi_search_after_reduce_effort_after(cstr, monkeypatch):
    import mpcmobo.learners.bo as bo_module

    seen = []

    def fake_ehvi(surrogate, X, Y, ref, *, seed, options, search, box=None):
        seen.append((X.shape[0], options.mc_samples, search.num_restarts, search.raw_samples))
        return np.full(X.shape[1], 0.5)

    monkeypatch.setattr(bo_module, "propose_ehvi", fake_ehvi)
    space = cstr.search_space
    # the non-contextual EHVI path (the old defaults); the contextual one calls search_effort
    # through _safe_effort
    mobo = make_learner("mobo", space, cstr.parameterization.theta0, n_init=2,
                        reduce_effort_after=4, **OLD_RULE)  # fmt: skip
    for k in range(6):
        th = mobo.propose()
        mobo.observe(th, _result([1000.0 + 100 * k, 10.0 - k, k % 2, 0]))
    # the design (n < 2) needs no search; full effort at n = 2, 3; halved from n = 4
    assert seen == [(2, 64, 4, 256), (3, 64, 4, 256), (4, 32, 2, 128), (5, 32, 2, 128)]
    options, search = bo_module.reduced_effort(EHVIOptions(mc_samples=1), AcqfSearch(1, 1))
    assert (options.mc_samples, search.num_restarts, search.raw_samples) == (1, 1, 1)
    with pytest.raises(ValueError, match="reduce_effort_after"):
        make_learner("mobo", space, cstr.parameterization.theta0, reduce_effort_after=-1)

    # direct_samples (issue 13, speed): off by default, reaches the EHVI options and survives
    # the halving of the search
    assert not mobo.ehvi.direct_samples
    fast = make_learner("mobo", space, cstr.parameterization.theta0, direct_samples=True)
    assert fast.ehvi.direct_samples and fast.search_effort(10**6)[0].direct_samples


@pytest.mark.parametrize("name", ["bo", "mobo", "hybrid"])
def test_gp_learners_run_and_deploy_theta0_itself(cstr, name):
    """The first design point and the incumbent before any data are theta0 exactly, not its
    round trip through the unit cube (4e-12 away, which moved J_eval by 2.8% on the CSTR);
    a checkpoint written before this rule (no "exact_theta0" in its state) keeps its round
    trip, so that it resumes as it would have run."""
    space, theta0 = cstr.search_space, cstr.parameterization.theta0
    kw = {"n_init": 3, "num_restarts": 2, "raw_samples": 32, "maxiter": 20}
    a = make_learner(name, space, theta0, seed=3, **kw)
    round_trip = space.from_unit(space.to_unit(theta0), base=theta0)
    assert not np.array_equal(round_trip, theta0)  # else this test would test nothing
    np.testing.assert_array_equal(a.incumbent(), theta0)
    th = a.propose()
    np.testing.assert_array_equal(th, theta0)
    a.observe(th, _result([1000.0, 10.0, 1.0, 100.0], grad=np.zeros(14)))
    old = a.state_dict()
    del old["exact_theta0"]
    b = make_learner(name, space, theta0, seed=3, **kw)
    b.load_state_dict(old)
    np.testing.assert_array_equal(b.incumbent(), round_trip)
