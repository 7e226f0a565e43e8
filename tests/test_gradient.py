"""The gradient the study uses, at the study's settings.

``tests/test_learners.py`` checks the CDPG direction with a discounted weighting, no warm start
and tol 1e-10; ``tests/test_mpc.py`` the MPC's sensitivities with no warm start and tol 1e-10.
The study runs ``LearningRun`` with the settings' critic (LSTD, V^nu target, uniform weighting)
and the settings' MPC (warm start, tol 1e-8). Here both are checked at those settings against
central finite differences: the MPC's sensitivities at a closed-loop state with an active input
bound and an active slack, and the episode gradient against the objective the learner
descends, f1 (the discounted closed-loop cost from the episode's start).

Measured (lq, 24 episodes on the study's 6 cycled starts, exploration 0.2 = the default 2% of
the input range): cosine with the finite-difference gradient of f1 of 0.83 for
``weighting="discounted"`` and 0.40 for the study's default ``"uniform"`` (0.89 and 0.50
against the undiscounted mean stage cost). The uniform mean of eq. DPG, as the paper prints it,
is a descent direction here but not the gradient: its R component has the wrong sign.
"""

from __future__ import annotations

import numpy as np
import pytest
from cstr_reference import fd_sensitivities

from mpcmobo.experiment.loop import LearningRun
from mpcmobo.experiment.sections import MPCSettings
from mpcmobo.experiment.settings import load_settings
from mpcmobo.learners.base import EpisodeResult, Learner
from mpcmobo.mpc import ParametricMPC, rollout
from mpcmobo.rl import CompatibleCritic
from mpcmobo.systems import get_system


class _Theta0(Learner):
    """Proposes theta0 every episode and keeps what it observes: the study's episode loop
    (``LearningRun``) then computes exactly the gradient a learner would get at theta0."""

    name = "theta0-probe"

    def __init__(self, space, theta0, seed=0):
        super().__init__(space, theta0, seed)
        self.results: list[EpisodeResult] = []

    def propose(self):
        return self.theta0.copy()

    def observe(self, theta, result):
        self.results.append(result)

    def incumbent(self):
        return self.theta0.copy()


def _cosine(a, b):
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


@pytest.fixture(scope="module")
def lq_study_gradients():
    """24 episodes at theta0 of the lq study with the default settings (seed 0, cycled starts),
    the gradient of each (the study's critic, and the discounted weighting refitted on the same
    records), and the finite-difference gradient of f1 over the same starts."""
    settings = load_settings(None, system={"name": "lq"}).resolved()
    system = get_system("lq")
    mpc = ParametricMPC(system, model="imperfect", **settings.mpc.options())
    assert mpc.warm_start and mpc.tau == 1e-6
    probe = _Theta0(system.search_space, mpc.theta0)
    c = settings.critic
    run = LearningRun(
        system,
        probe,
        mpc,
        seed=0,
        steps=settings.steps,
        exploration_std=settings.exploration.std,
        start_mode=settings.start_mode,
        n_cycle_starts=settings.n_cycle_starts,
        critic_ridge=c.ridge,
        critic_method=c.method,
        critic_q_target=c.q_target,
        critic_min_valid_steps=c.min_valid_steps,
        critic_weighting=c.weighting,
        beta=settings.beta,
    )
    assert run.critic.weighting == "uniform" and run.critic.method == "lstd"
    discounted = CompatibleCritic(
        gamma=mpc.gamma, ridge=c.ridge, method=c.method, weighting="discounted"
    )
    g_disc = []
    for _ in range(4 * settings.n_cycle_starts):
        _, record = run.run_episode()
        res = discounted.fit(record)
        assert res.ok
        g_disc.append(res.grad)
    assert all(r.critic_ok for r in probe.results)
    g_study = np.mean([r.grad for r in probe.results], axis=0)

    T, th0 = settings.steps, mpc.theta0
    disc = mpc.gamma ** np.arange(T)

    def f1(theta):  # eq. cl_perf: (1/T) sum_k gamma^k L_k, mean over the cycled starts
        return np.mean(
            [
                disc @ rollout(system, mpc, theta, x0, T, sensitivities=False).L / T
                for x0 in run.cycle_starts
            ]
        )

    fd = np.zeros(mpc.n_theta)
    for i in range(1, mpc.n_theta):  # theta_c (0) changes no policy
        h = 1e-3 * max(1.0, abs(th0[i]))
        tp, tm = th0.copy(), th0.copy()
        tp[i] += h
        tm[i] -= h
        fd[i] = (f1(tp) - f1(tm)) / (2 * h)
    return g_study, np.mean(g_disc, axis=0), fd


def test_study_gradient_is_a_descent_direction_of_f1(lq_study_gradients):
    """The study's own gradient (uniform weighting, warm-started MPC at tol 1e-8) points
    downhill of f1 (measured cosine 0.40; see the module docstring for why not higher)."""
    g_study, _, fd = lq_study_gradients
    assert _cosine(g_study, fd) > 0.25


def test_discounted_gradient_at_study_settings_matches_f1(lq_study_gradients):
    """With the discounted weighting, at the study's MPC and critic settings otherwise, the
    CDPG estimate is the gradient of f1 in direction (measured cosine 0.83)."""
    _, g_disc, fd = lq_study_gradients
    assert _cosine(g_disc, fd) >= 0.7


# ----------------------------------------------------------------------------- sensitivities

# A state of a CSTR learning episode (seed 0, exploration 1.7 on both inputs, theta0) and the
# input applied there; from the next state the imperfect MPC keeps q_c on its lower bound 55,
# q_s inside its bounds, and one of its slacks is active.
X_PREV = np.array([105.68243978564169, 0.26921780921020344, 401.00389133571883])
U_PREV = np.array([83.78867392307545, 60.65369244350106])


def test_sensitivities_with_warm_start_at_study_tolerance(cstr):
    """The sensitivities of a warm-started solve at the study's tolerance (1e-8) match
    central differences of a cold solver at tol 1e-10, at a state with an active input bound
    (q_c) and an active slack."""
    study = ParametricMPC(cstr, model="imperfect", **MPCSettings().options())
    th = study.theta0.copy()
    study.reset()
    assert study.solve(X_PREV, th, sensitivities=False).success
    x = cstr.plant_step(X_PREV, U_PREV)
    sol = study.solve(x, th)  # warm-started from the shifted previous solution
    assert sol.success and sol.slack > 0.1
    assert sol.action[1] == pytest.approx(cstr.u_lb[1], abs=1e-4)  # q_c on its bound
    assert cstr.u_lb[0] + 1 < sol.action[0] < cstr.u_ub[0] - 1  # q_s inside

    ref = ParametricMPC(cstr, model="imperfect", warm_start=False, tol=1e-10)
    dpi, dV = fd_sensitivities(ref, x, th)
    scale_pi = np.abs(dpi).max(axis=0)
    assert scale_pi[0] > 1e-2 and scale_pi[1] < 1e-6  # the bound input barely moves
    assert np.all(np.abs(sol.dpi_dtheta - dpi) <= 1e-4 * scale_pi + 1e-9)
    assert np.all(np.abs(sol.dV_dtheta - dV) <= 1e-4 * np.abs(dV) + 1e-6 * np.abs(dV).max())
