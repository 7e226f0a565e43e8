"""Batched closed loops: the same records as the sequential ones, a failed loop on its own."""

import numpy as np
import pytest

from mpcmobo.experiment.evaluation import Evaluator
from mpcmobo.experiment.loop import model_costs
from mpcmobo.learners import Learner
from mpcmobo.mpc import ParametricMPC, PlantDiverged, model_plant, rollout, rollouts
from mpcmobo.rl.objectives import mean_stage_cost
from mpcmobo.systems import get_system
from mpcmobo.systems.plant import SystemPlant

FIELDS = ("x", "u", "pi", "V", "L", "violation", "slack", "success", "theta")


def _starts(system, n, seed=0):
    rng = np.random.default_rng(seed)
    return np.array([system.sample_initial_state(rng) for _ in range(n)])


def _assert_same(a, b):
    """Two records equal bit for bit (the solve times aside)."""
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.status == b.status


@pytest.fixture(scope="module")
def lq():
    return get_system("lq")


@pytest.fixture(scope="module")
def lq_mpc(lq):
    return ParametricMPC(lq, model="imperfect")


@pytest.mark.parametrize("replayed", [False, True])
def test_batch_equals_sequential_lq(lq, lq_mpc, replayed):
    steps, starts = 12, _starts(lq, 5)
    noise = np.random.default_rng(3).normal(0, 0.3, (steps, lq.nu)) if replayed else None
    theta = lq_mpc.theta0 * 1.1
    params = lq_mpc.model_params
    batch = rollouts(lq, lq_mpc, theta, starts, steps, plant_params=params, noise=noise)
    plant = model_plant(lq, lq_mpc)
    for x0, rec in zip(starts, batch):
        seq = rollout(lq, lq_mpc, theta, x0, steps, sensitivities=False, plant=plant, noise=noise)
        _assert_same(seq, rec)
    statuses = {s for rec in batch for s in rec.status}
    assert "Newton_Succeeded" in statuses  # the batched Newton path ran
    (one,) = rollouts(lq, lq_mpc, theta, starts[:1], steps, plant_params=params, noise=noise)
    _assert_same(batch[0], one)  # a batch of one


def test_batch_equals_sequential_cstr(cstr, cstr_mpc):
    steps, starts = 8, _starts(cstr, 4, seed=5)
    theta = cstr_mpc.theta0
    batch = rollouts(cstr, cstr_mpc, theta, starts, steps)  # the true plant
    for x0, rec in zip(starts, batch):
        _assert_same(rollout(cstr, cstr_mpc, theta, x0, steps, sensitivities=False), rec)
    statuses = [s for rec in batch for s in rec.status]
    assert statuses.count("Newton_Succeeded") > len(starts) * steps // 2


def test_failed_loop_among_many(lq, lq_mpc):
    """A start whose plant runs away fails alone with the sequential loop's error; the
    others' records and costs are the sequential ones."""
    steps = 6
    starts = _starts(lq, 4, seed=1)
    starts[2] = lq.x_ref + 500 * np.asarray(lq.x_scale, float)  # runs away at once
    batch = rollouts(lq, lq_mpc, None, starts, steps)
    with pytest.raises(PlantDiverged) as seq_err:
        rollout(lq, lq_mpc, None, starts[2], steps, sensitivities=False)
    assert isinstance(batch[2], PlantDiverged)
    assert str(batch[2]) == str(seq_err.value)
    assert (batch[2].step, batch[2].violation) == (seq_err.value.step, seq_err.value.violation)
    for i in (0, 1, 3):
        _assert_same(rollout(lq, lq_mpc, None, starts[i], steps, sensitivities=False), batch[i])
    costs = model_costs(lq, lq_mpc, lq_mpc.theta0, starts, steps, SystemPlant(lq))
    assert np.isnan(costs[2]) and np.all(np.isfinite(np.delete(costs, 2)))
    np.testing.assert_array_equal(
        np.delete(costs, 2), [mean_stage_cost(batch[i]) for i in (0, 1, 3)]
    )


def test_failed_solve_among_many(lq, lq_mpc, monkeypatch):
    """A loop whose own solve raises fails alone (NaN cost); bad input is still an error."""
    steps, starts = 5, _starts(lq, 3, seed=2)
    solve = lq_mpc.solve
    bad = starts[1].copy()

    def failing(x, theta=None, sensitivities=True, **kwargs):
        if np.array_equal(x, bad):
            raise RuntimeError("broken solve")
        return solve(x, theta, sensitivities, **kwargs)

    monkeypatch.setattr(lq_mpc, "solve", failing)
    costs = model_costs(lq, lq_mpc, lq_mpc.theta0, starts, steps, SystemPlant(lq))
    assert np.isnan(costs[1]) and np.all(np.isfinite(costs[[0, 2]]))
    monkeypatch.undo()
    with pytest.raises(ValueError, match="noise must be"):
        rollouts(lq, lq_mpc, None, starts, steps, noise=np.zeros((steps + 1, lq.nu)))


def test_evaluator_batches_the_same_episodes(lq):
    ev = Evaluator(lq, n_starts=3, steps=7)
    mpc = ev.mpc()
    for x0, rec in zip(ev.starts, ev.episodes(None)):
        _assert_same(rollout(lq, mpc, None, x0, 7, sensitivities=False), rec)


def test_start_costs_run_together(lq, lq_mpc, monkeypatch):
    """The loop's start costs of many starts: one batch for those not cached, the costs of
    the sequential closed loops."""
    import mpcmobo.experiment.loop as loop

    class Bare(Learner):
        name = "bare"

        def __init__(self):
            super().__init__(lq.search_space, lq.parameterization.theta0)

        def propose(self):
            return lq.parameterization.theta0.copy()

        def observe(self, theta, result):
            pass

        def incumbent(self):
            return lq.parameterization.theta0.copy()

    run = loop.LearningRun(lq, Bare(), lq_mpc, seed=0, steps=6)
    batches = []
    monkeypatch.setattr(loop, "rollouts", lambda *a, **k: batches.append(a[3]) or rollouts(*a, **k))
    theta, params = lq_mpc.theta0 * 0.9, lq_mpc.model_params * 1.05
    starts = _starts(lq, 4, seed=7)
    first = run.start_cost(starts[0], theta, params)  # one start: alone, then cached
    costs = run.start_costs(starts, theta, params)
    assert len(batches) == 1 and len(batches[0]) == 3  # the three not cached, together
    plant = model_plant(lq, lq_mpc, params)
    ref = [
        mean_stage_cost(rollout(lq, lq_mpc, theta, x0, 6, sensitivities=False, plant=plant))
        for x0 in starts
    ]
    np.testing.assert_array_equal(costs, ref)
    assert costs[0] == first
    np.testing.assert_array_equal(run.start_costs(starts, theta, params), costs)
    assert len(batches) == 1  # all cached
