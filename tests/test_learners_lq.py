"""Learners against a known optimum on the lq system, and the sign of their updates (issue 16,
item 4).

On ``lq`` (a linear plant, quadratic stage cost, no active constraint) the best closed loop is
known independently of the MPC code: the discounted LQR of the true plant
(``scipy.linalg.solve_discrete_are``), simulated here from the evaluation starts, gives
J_LQR. The study's J* (the perfect-model MPC with theta0) lies just above it.

Measured (``/tmp`` scripts of the issue-16 branch, evaluation on 6 starts, 30-step episodes,
default settings otherwise): J_initial = 0.6698, J* = 0.6337, J_LQR = 0.6041. MPC-RL with
``lr = 0.003`` closed 97%, 94%, 92%, 93% and 67% of J_initial - J_LQR after 30 episodes on seeds
0-4 (with its default ``lr = 0.03`` and its iterate deployed: 94%, 40%, 29% after 20 episodes
and worse than theta0 on three of four seeds after 40). Issue 11 made the deployed theta MPC-RL's
best verified iterate (the pooled judge) by default. At its defaults it kept theta0 on seed 0
(closed 0%), so the gap test keeps the tuned step with the iterate deployed, and the defaults are
tested for what the judge promises: never worse than theta0. A random search with the same budget, deploying its best
episode, ended at theta0 or worse (0%, -158%, 0%). bo and mobo at their defaults ended worse
than theta0 on lq (bo: 0% and -439% after 20 episodes on seeds 0, 1; mobo: -148% on seed 0),
so they have no such test yet (issue 11 works on them). Session 6 measured why (docs/benchmarks.md,
"GP learners on `lq`"): no point of a Sobol design of the declared box beats theta0, and under
random starts the start effect is 30x the theta effect per episode; ``search_radius`` (tested
below) fixes the search half, not the deployment half. Session 7 (``trust_region``, a box around
the deployed theta that grows with successes): fed the noise-free cost J_eval as f1, bo at its
defaults and mobo and hybrid with the trust region close a stated fraction of the gap in 15
evaluations and beat a random search (the test at the end; mobo at its defaults ended worse
than theta0 there). With single noisy episodes they still do not deploy reliably better thetas
within 30 episodes (docs/benchmarks.md, "A trust region for the GP learners (session 7)"), so
the episode-loop version of that test is not added for them. The hybrid gets no gradient there
(its gradient step is tested by sign, above), so its proposals are the GP's.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from mpcmobo.experiment.evaluation import Evaluator
from mpcmobo.experiment.loop import LearningRun
from mpcmobo.experiment.settings import load_settings
from mpcmobo.learners import EpisodeResult, make_learner
from mpcmobo.learners.base import Learner
from mpcmobo.mpc import ParametricMPC
from mpcmobo.systems import get_system

BUDGET = 30  # episodes
SEEDS = (0, 1, 2)
MPC_RL = {"lr": 0.003, "deploy": "iterate"}  # a tuned step, the iterate deployed
FRACTION = 0.5  # of J_initial - J_LQR, closed by each seed within the budget


def _lq_matrices(dt=0.1):
    """x+ = A x + B u of one RK4 step of the true lq plant dx/dt = [[0, 1], [-1, -0.5]] x +
    [0, 1] u (u held over the step), written out."""
    Ac = np.array([[0.0, 1.0], [-1.0, -0.5]])
    Bc = np.array([[0.0], [1.0]])
    h = Ac * dt
    I = np.eye(2)
    A = I + h + h @ h / 2 + h @ h @ h / 6 + h @ h @ h @ h / 24
    B = dt * (I + h / 2 + h @ h / 6 + h @ h @ h / 24) @ Bc
    return A, B


class RandomSearch(Learner):
    """theta0, then uniform points of the search box (seeded); deploys the theta of its best
    episode (lowest f1)."""

    name = "random-search"

    def __init__(self, space, theta0, seed=0):
        super().__init__(space, theta0, seed)
        self.best_f1, self.best = np.inf, self.theta0.copy()

    def propose(self):
        if self.n_observed == 0:
            return self.theta0.copy()
        return self.space.from_unit(self.rng.uniform(size=self.space.dim), base=self.theta0)

    def observe(self, theta, result):
        self.n_observed += 1
        if np.isfinite(result.f1) and result.f1 < self.best_f1:
            self.best_f1, self.best = result.f1, np.array(theta, dtype=float)

    def incumbent(self):
        return self.best.copy()


@pytest.fixture(scope="module")
def lq_study():
    settings = load_settings(None, system={"name": "lq"}).resolved()
    system = get_system("lq")
    evaluator = Evaluator(system, n_starts=6, seed=2025, steps=settings.steps)
    return settings, system, evaluator


@pytest.fixture(scope="module")
def J_lqr(lq_study):
    settings, system, evaluator = lq_study
    A, B = _lq_matrices(system.dt)
    np.testing.assert_allclose(
        np.column_stack([system.plant_step(e, [0.0]) for e in np.eye(2)]), A, rtol=1e-12
    )
    gamma, Q, R = system.mpc_spec.gamma, np.diag(system.Q), np.diag(system.R)
    P = scipy.linalg.solve_discrete_are(np.sqrt(gamma) * A, np.sqrt(gamma) * B, Q, R)
    K = gamma * np.linalg.solve(R + gamma * B.T @ P @ B, B.T @ P @ A)
    costs = []
    for x in evaluator.starts:
        c = 0.0
        for _ in range(evaluator.steps):
            u = -K @ x
            c += x @ Q @ x + u @ R @ u
            x = A @ x + B @ u
        costs.append(c / evaluator.steps)
    return float(np.mean(costs))


def _learn(lq_study, learner, seed):
    settings, system, evaluator = lq_study
    mpc = ParametricMPC(system, model="imperfect", **settings.mpc.options())
    run = LearningRun(
        system,
        learner,
        mpc,
        seed=seed,
        steps=settings.steps,
        exploration_std=settings.exploration.std,
        start_mode=settings.start_mode,
        n_cycle_starts=settings.n_cycle_starts,
    )
    for _ in range(BUDGET):
        run.run_episode()
    return evaluator.J_eval(learner.incumbent())


def test_reference_optimum(lq_study, J_lqr):
    """J_LQR is below the imperfect MPC, and the study's J* (perfect-model MPC) lies within 6%
    above it (a finite horizon with terminal weight Q, not the Riccati one)."""
    _, _, evaluator = lq_study
    J0, J_star = evaluator.J_eval(None), evaluator.J_star()
    assert J_lqr < J_star < 1.06 * J_lqr
    assert J0 > J_star


@pytest.mark.parametrize("seed", SEEDS)
def test_mpc_rl_at_its_defaults_never_deploys_worse_than_theta0(lq_study, seed):
    """MPC-RL at its defaults (Adam, lr 0.03, the pooled judge) deploys nothing worse than
    theta0 after the budget (the default's iterate alone ended worse than theta0 on three of
    four seeds, see the module docstring)."""
    settings, system, evaluator = lq_study
    space, theta0 = system.search_space, system.parameterization.theta0
    J0 = evaluator.J_eval(None)
    J_rl = _learn(lq_study, make_learner("mpc-rl", space, theta0, seed=seed), seed)
    assert J_rl <= J0 * (1 + 1e-9), (J_rl, J0)


@pytest.mark.parametrize("seed", SEEDS)
def test_mpc_rl_closes_the_gap_and_beats_random_search(lq_study, J_lqr, seed):
    settings, system, evaluator = lq_study
    space, theta0 = system.search_space, system.parameterization.theta0
    J0 = evaluator.J_eval(None)
    J_rl = _learn(lq_study, make_learner("mpc-rl", space, theta0, seed=seed, **MPC_RL), seed)
    J_rs = _learn(lq_study, RandomSearch(space, theta0, seed=seed), seed)
    closed = (J0 - J_rl) / (J0 - J_lqr)
    assert closed >= FRACTION, (closed, J_rl, J0, J_lqr)
    assert J_rl < J_rs, (J_rl, J_rs)


# ----------------------------------------------------------------------------- update signs


def _result(grad, f=(1.0, 1.0, 0.0, 0.0), start_id=-1):
    return EpisodeResult(np.asarray(f, float), np.asarray(grad, float), True, start_id=start_id)


@pytest.mark.parametrize("optimizer", ["sgd", "adam", "trust", None])
def test_mpc_rl_steps_against_the_gradient(optimizer):
    """theta <- theta - alpha grad J (eq. theta) in the unit coordinates z: plain SGD moves by
    -lr * dJ/dz, Adam's first step (also the default) by -lr * sign(dJ/dz), the trust step by
    -lr * dJ/dz / |dJ/dz|."""
    s = get_system("lq")
    space, theta0 = s.search_space, s.parameterization.theta0
    lr = 1e-3
    opts = {} if optimizer is None else {"optimizer": optimizer, "lr": lr}
    # the iterate deployed: the default's verification blocks freeze the first episodes
    learner = make_learner("mpc-rl", space, theta0, deploy="iterate", **opts)
    lr = lr if optimizer else 0.03  # Adam's default
    g = np.array([0.0, 0.3, -0.2, 0.1, -0.4, 0.05, 0.2, -0.1, 0.3])
    z0 = space.to_unit(learner.propose())
    learner.observe(learner.propose(), _result(g))
    dz = space.to_unit(learner.propose()) - z0
    gz = g[space.free] * space.dtheta_dz(theta0)
    assert dz @ gz < 0  # downhill
    expected = {
        "sgd": -lr * gz,
        "adam": -lr * np.sign(gz),
        None: -lr * np.sign(gz),
        "trust": -lr * gz / np.linalg.norm(gz),
    }[optimizer]
    np.testing.assert_allclose(dz, expected, rtol=1e-6, atol=1e-12)


def test_mpc_rl_paper_rule_steps_in_theta():
    """``optimizer = "gd"`` (the paper's eq. theta): theta moves by -lr * dJ/dtheta in theta's
    own units, whatever the scaling of the search space (here a step small enough to stay
    inside the bounds)."""
    s = get_system("lq")
    space, theta0 = s.search_space, s.parameterization.theta0
    lr = 1e-3
    learner = make_learner("mpc-rl", space, theta0, optimizer="gd", lr=lr, deploy="iterate")
    g = np.array([0.0, 0.3, -0.2, 0.1, -0.4, 0.05, 0.2, -0.1, 0.3])
    learner.observe(learner.propose(), _result(g))
    dtheta = learner.propose() - theta0
    np.testing.assert_allclose(dtheta[space.free], -lr * g[space.free], rtol=1e-9, atol=1e-12)
    assert not np.any(dtheta[~space.free])


def test_hybrid_gradient_step_goes_downhill_from_the_incumbent():
    """The hybrid's CDPG proposal (every 3rd) is a step of length hybrid_step (in the largest
    coordinate) from the incumbent against the gradient observed there."""
    s = get_system("lq")
    space, theta0 = s.search_space, s.parameterization.theta0
    hybrid = make_learner("hybrid", space, theta0, seed=0, n_init=2)
    g = np.array([0.0, -0.3, 0.2, 0.1, -0.4, 0.05, 0.2, -0.1, 0.3])
    for k in range(2):  # the design: theta0 and one Sobol point, the same gradient observed
        hybrid.observe(hybrid.propose(), _result(g, f=(1.0 + k, 2.0 - k, 0.0, 0.0)))
    z_inc = space.to_unit(hybrid.incumbent())
    z = space.to_unit(hybrid.propose())  # the 3rd proposal: the gradient step
    gz = g[space.free] * space.dtheta_dz(hybrid.incumbent())
    step = z - z_inc
    assert step @ gz < 0  # downhill
    inside = (z > 1e-12) & (z < 1 - 1e-12)  # coordinates not clipped at the box
    np.testing.assert_allclose(
        step[inside], (-hybrid.hybrid_step * gz / np.abs(gz).max())[inside], rtol=1e-9
    )
    assert inside.sum() >= space.dim - 2


def _hybrid_with_incumbent_runs(grads, **options):
    """A hybrid learner after its design (theta0 best, one Sobol point worse) with theta0 run
    once per gradient of ``grads``; the next proposal is due to be a gradient step."""
    s = get_system("lq")
    space, theta0 = s.search_space, s.parameterization.theta0
    hybrid = make_learner("hybrid", space, theta0, seed=0, n_init=2, **options)
    for k, g in enumerate(grads[:2]):  # the design: theta0 and a Sobol point
        hybrid.observe(hybrid.propose(), _result(g, f=(1.0 + k, 2.0 - k, 0.0, 0.0)))
    for g in grads[2:]:  # theta0 again (as baseline episodes would)
        hybrid.observe(theta0, _result(g, f=(1.0, 2.0, 0.0, 0.0)))
    hybrid.n_proposals_ = 2  # the next proposal is the third: a gradient step
    return hybrid, space


def test_hybrid_gradient_step_averages_the_incumbents_episodes_and_is_not_repeated():
    """Session 17 (opt-in): the step is taken from the mean gradient of the incumbent's episodes (here
    theta0's two, with gradients g1 and g2; the Sobol point's gradient is not theta0's), and
    once that step has been run and the incumbent has not changed, the next due gradient step
    (the same theta) is not taken again: the GP proposes instead (``hybrid_gradient =
    "mean"``). The default, ``"first"``, steps from the first episode's gradient, and repeats
    it."""
    g1 = np.array([0.0, -0.3, 0.2, 0.1, -0.4, 0.05, 0.2, -0.1, 0.3])
    g2 = np.array([0.0, 0.5, 0.4, -0.3, 0.0, 0.25, -0.2, 0.3, 0.1])
    other = np.array([0.0, 9.0, -9.0, 9.0, 9.0, -9.0, 9.0, 9.0, -9.0])
    hybrid, space = _hybrid_with_incumbent_runs([g1, other, g2], hybrid_gradient="mean")
    z_inc = space.to_unit(hybrid.incumbent())
    theta = hybrid.propose()
    assert hybrid.proposal_kinds_[-1] == "gradient"
    gz = (g1 + g2)[space.free] / 2 * space.dtheta_dz(hybrid.incumbent())
    step = space.to_unit(theta) - z_inc
    inside = (step != 0) & (space.to_unit(theta) > 1e-12) & (space.to_unit(theta) < 1 - 1e-12)
    assert inside.sum() >= space.dim - 2
    np.testing.assert_allclose(
        step[inside], (-hybrid.hybrid_step * gz / np.abs(gz).max())[inside], rtol=1e-9
    )
    hybrid.observe(theta, _result(g1, f=(50.0, 50.0, 0.0, 0.0)))  # a bad step
    hybrid.n_proposals_ = 5  # the next proposal is due to be a gradient step again
    again = hybrid.propose()
    assert hybrid.proposal_kinds_[-1] != "gradient"
    assert not np.allclose(again, theta)

    first, _ = _hybrid_with_incumbent_runs([g1, other, g2])  # the default
    assert first.hybrid_gradient == "first"
    theta_first = first.propose()
    gz1 = g1[space.free] * space.dtheta_dz(first.incumbent())
    assert (space.to_unit(theta_first) - z_inc) @ gz1 < 0
    assert not np.allclose(theta_first, theta)
    first.observe(theta_first, _result(g1, f=(50.0, 50.0, 0.0, 0.0)))
    first.n_proposals_ = 5
    np.testing.assert_array_equal(first.propose(), theta_first)  # the same step again
    assert first.proposal_kinds_[-1] == "gradient"


def test_hybrid_gradient_option_is_checked_and_resumed():
    """A bad ``hybrid_gradient`` names the option; a checkpoint from before session 17 (no
    ``hybrid_gradient`` key) resumes with the rule it was started with, "first"."""
    s = get_system("lq")
    space, theta0 = s.search_space, s.parameterization.theta0
    with pytest.raises(ValueError, match="hybrid_gradient.*'mean', 'first'"):
        make_learner("hybrid", space, theta0, hybrid_gradient="last")
    hybrid = make_learner("hybrid", space, theta0, seed=0, hybrid_gradient="mean")
    state = hybrid.state_dict()
    assert state["hybrid_gradient"] == "mean"
    again = make_learner("hybrid", space, theta0, seed=0)
    again.load_state_dict(state)  # the checkpoint's rule wins
    assert again.hybrid_gradient == "mean"
    old = make_learner("hybrid", space, theta0, seed=0, hybrid_gradient="mean")
    old.load_state_dict({k: v for k, v in state.items() if k != "hybrid_gradient"})
    assert old.hybrid_gradient == "first"


def test_mpc_rl_keeps_stepping_but_deploys_its_best_verified_iterate():
    """MPC-RL with the pooled judge: with a constant gradient its iterate walks on; the
    episodes' costs (from random starts, whose effect is larger than theta's) fall over the
    first 30 steps and rise again after. The deployed theta is theta0 itself until the evidence
    says otherwise, then one of the iterates run in the good stretch, and it stays there while
    the iterate walks into the bad one."""
    s = get_system("lq")
    space, theta0 = s.search_space, s.parameterization.theta0
    learner = make_learner("mpc-rl", space, theta0, seed=0, lr=0.008, deploy="pooled")
    rng = np.random.default_rng(0)
    g = np.array([0.0, 0.3, -0.2, 0.1, -0.4, 0.05, 0.2, -0.1, 0.3])
    run, deployed = [], []
    for k in range(60):
        theta = learner.propose()
        run.append(theta)
        x0 = rng.uniform(s.x0_lb, s.x0_ub)
        quality = -1.0 * min(k, 30) / 30 + 1.5 * max(k - 30, 0) / 30  # log cost of theta
        f1 = np.exp(quality + 0.5 * (x0 @ x0) + 0.1 * rng.normal())
        learner.observe(theta, EpisodeResult(np.array([f1, 1.0, 0.0, 0.0]), g, True, x0=x0))
        deployed.append(learner.incumbent())
    assert deployed[1] is not None and np.array_equal(deployed[1], theta0)  # theta0 itself
    final = deployed[-1]
    k_final = next(k for k, t in enumerate(run) if np.allclose(t, final, rtol=0, atol=1e-12))
    assert 15 <= k_final <= 45, k_final  # an iterate of the good stretch
    assert not np.allclose(final, learner.propose())  # not the iterate, which walked on


def test_optuna_peer_learner_runs_theta0_first_and_deploys_its_best_trial(monkeypatch, request):
    """The benchmark's Optuna peer (benchmarks/optuna_learners.py, optional): theta0 exactly
    as the first trial, the best trial's theta deployed, an exact resume, and a study that
    accepts the learner once it is registered. The registry is restored afterwards: a later
    test of the same process that runs ``--learner all`` must not run the Optuna peers too."""
    pytest.importorskip("optuna")
    from pathlib import Path

    from mpcmobo.learners import registry

    monkeypatch.syspath_prepend(str(Path(__file__).parents[1] / "benchmarks"))
    saved = [(table, dict(table)) for table in (registry.LEARNER_SPECS, registry.LEARNERS)]

    def restore() -> None:  # in place: other modules imported the dicts by name
        for table, old in saved:
            table.clear()
            table.update(old)

    request.addfinalizer(restore)
    from optuna_learners import OptunaTPE, register

    s = get_system("lq")
    space, theta0 = s.search_space, s.parameterization.theta0
    learner, twin = OptunaTPE(space, theta0, seed=1), None
    costs = []
    for k in range(8):
        theta = learner.propose()
        if k == 0:
            assert np.array_equal(theta, theta0)
        f1 = float(np.sum((space.to_unit(theta) - 0.3) ** 2))
        costs.append((f1, theta))
        learner.observe(theta, _result(np.zeros(len(theta)), f=(f1, 0.0, 0.0, 0.0)))
        if k == 4:
            twin = OptunaTPE(space, theta0, seed=1)
            twin.load_state_dict(learner.state_dict())
        elif k > 4:
            theta_twin = twin.propose()
            assert np.array_equal(theta_twin, theta)
            twin.observe(theta_twin, _result(np.zeros(len(theta)), f=(f1, 0.0, 0.0, 0.0)))
    best = min(costs, key=lambda c: c[0])[1]
    np.testing.assert_array_equal(learner.incumbent(), best)
    register()
    assert load_settings(None, system={"name": "lq"}, learners=["optuna-tpe"]).learners == [
        "optuna-tpe"
    ]


# ----------------------------------------------------------------------- GP learners' box


@pytest.mark.parametrize("name", ["bo", "mobo", "hybrid"])
def test_gp_learners_search_radius_keeps_every_proposal_near_theta0(name):
    """``search_radius = r`` (session 6): the GP learners search the box z0 +- r of the unit
    cube of the declared search space, z0 theta0's point. On lq the defaults' box makes every
    point of a Sobol design worse than theta0 (docs/benchmarks.md, "GP learners on `lq`"); with
    r = 0.1 every proposal (design, acquisition, the hybrid's gradient step) and the deployed
    theta stay within 0.1 of z0, theta0 is the first proposal, and the box spans the full
    2 r in each coordinate that is not clipped at the cube."""
    s = get_system("lq")
    space, theta0 = s.search_space, s.parameterization.theta0
    z0 = space.to_unit(theta0)
    r = 0.1
    # (the trust region, on by default, would search a smaller box inside: off here)
    learner = make_learner(
        name, space, theta0, seed=3, search_radius=r, n_init=3, trust_region="off"
    )
    rng = np.random.default_rng(0)
    Z = []
    for k in range(6):
        theta = learner.propose()
        if k == 0:
            np.testing.assert_allclose(theta, theta0, rtol=1e-12, atol=1e-12)
        Z.append(space.to_unit(theta))
        f = (1.0 + float(np.sum((Z[-1] - 0.45) ** 2)), 1.0 + rng.uniform(), 0.0, 0.0)
        learner.observe(theta, _result(rng.normal(size=space.n_theta), f=f))
        Z.append(space.to_unit(learner.incumbent()))
    Z = np.array(Z)
    assert np.all(np.abs(Z - z0) <= r + 1e-9), np.abs(Z - z0).max()
    assert np.abs(Z - z0).max() > r / 4  # it does search: not stuck at theta0
    np.testing.assert_allclose(
        space.to_unit(learner.space.upper) - space.to_unit(learner.space.lower), 2 * r
    )


def test_search_radius_out_of_range_is_refused():
    s = get_system("lq")
    for bad in (0.0, -0.1, 0.6, float("nan")):
        with pytest.raises(ValueError, match="search_radius"):
            make_learner("bo", s.search_space, s.parameterization.theta0, search_radius=bad)


# ------------------------------------------------- GP learners: the search, noise-free (s7)

GP_BUDGET = 15  # evaluations
GP_SEEDS = (0, 1, 2, 3, 4)
GP_FRACTION = 0.3  # of J_initial - J_LQR
# bo closes the gap at its defaults; mobo at its defaults ended worse than theta0 (1.083 x J*
# after 20 evaluations, seed 0), so mobo and hybrid run with the trust region (session 7); each
# deploys the GP's best point after every fit (deploy = "incumbent": the noise-free f1 needs no evidence rule; with no
# start_id, "auto" would re-run each candidate 6 times since session 11)
GP_OPTIONS = {
    "bo": {"deploy": "incumbent"},
    "mobo": {"trust_region": "auto", "deploy": "incumbent"},
    "hybrid": {"trust_region": "auto", "deploy": "incumbent"},
}


def _search_noise_free(evaluator, learner, budget):
    """``budget`` proposals, each observed with f1 = its J_eval on the evaluation starts
    (noise-free, no exploration; f2 = 1, f3 = f4 = 0); J_eval of the deployed theta after."""
    n_theta = learner.space.n_theta
    for _ in range(budget):
        theta = learner.propose()
        f = np.array([evaluator.J_eval(theta), 1.0, 0.0, 0.0])
        learner.observe(theta, EpisodeResult(f, np.zeros(n_theta), True))
    return evaluator.J_eval(learner.incumbent())


@pytest.fixture(scope="module")
def random_search_J(lq_study):
    """J_eval of a random search's best point per seed of GP_SEEDS (the same for every
    learner)."""
    settings, system, evaluator = lq_study
    space, theta0 = system.search_space, system.parameterization.theta0
    return {
        seed: _search_noise_free(evaluator, RandomSearch(space, theta0, seed=seed), GP_BUDGET)
        for seed in GP_SEEDS
    }


@pytest.mark.parametrize("name", ["bo", "mobo", "hybrid"])
def test_gp_learners_close_the_gap_on_the_noise_free_cost_and_beat_random_search(
    lq_study, J_lqr, random_search_J, name
):
    """bo (defaults), mobo and hybrid (``trust_region = "auto"``, session 7), fed the
    noise-free cost J_eval(theta) of the evaluation starts as f1 for GP_BUDGET evaluations,
    on the seeds GP_SEEDS, judged by the same J_eval against a random search of the box with
    the same budget and seed (which keeps theta0: no point of the declared box it draws is
    better, session 6). bo closes GP_FRACTION of J_initial - J_LQR in median and beats the
    random search in median; mobo and hybrid close it on at least one seed and are not worse
    than the random search in median (measured in session 11: closed fractions -0.11, 0, 0.74,
    0.13, 0 for both; bo 0.35, 1.07, 0.66, 0.73, 0). One seed alone is fragile: mobo's seed 0
    closed 30% on the machine of session 10 and ended 1% above theta0 on that of session 11.
    This tests the search and the incumbent rule without episode noise; the evidence rules
    are tested in test_deploy_*.py."""
    settings, system, evaluator = lq_study
    space, theta0 = system.search_space, system.parameterization.theta0
    J0 = evaluator.J_eval(None)
    J_gp = np.array(
        [
            _search_noise_free(
                evaluator,
                make_learner(name, space, theta0, seed=seed, **GP_OPTIONS[name]),
                GP_BUDGET,
            )
            for seed in GP_SEEDS
        ]
    )
    J_rs = np.array([random_search_J[seed] for seed in GP_SEEDS])
    closed = (J0 - J_gp) / (J0 - J_lqr)
    if name == "bo":
        assert np.median(closed) >= GP_FRACTION, closed
        assert np.median(J_gp) < np.median(J_rs), (J_gp, J_rs)
    else:
        assert closed.max() >= GP_FRACTION, closed
        assert np.median(J_gp) <= np.median(J_rs), (J_gp, J_rs)
