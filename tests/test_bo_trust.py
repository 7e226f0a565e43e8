"""The trust region of the GP learners (``trust_region``, :mod:`mpcmobo.bo.trust`, session 7).

Its rule written out by hand (double after a run of successes, halve after a run of failures,
cap, restart at the floor); the learners' proposals inside the box of the current length around
the deployed theta; the box following a success; the state saved and resumed exactly; old
states resuming without it; bad options refused with a message naming the problem.
"""

from __future__ import annotations

import numpy as np
import pytest

from mpcmobo.bo import AcqfSearch, GPSurrogate, propose_ei
from mpcmobo.bo.trust import TrustRegion, TrustState, trust_region_from_option
from mpcmobo.learners import EpisodeResult, make_learner
from mpcmobo.learners.bo import _DefaultAny
from mpcmobo.learners.registry import LearnerOptionError
from mpcmobo.systems import get_system

FAST = {"n_init": 3, "num_restarts": 2, "raw_samples": 32, "maxiter": 20}


def test_length_doubles_halves_caps_and_restarts_as_written():
    tr = TrustRegion(length_init=0.2, length_min=0.05, length_max=0.5, success_tolerance=2,
                     failure_tolerance=3)  # fmt: skip
    s = tr.start()
    assert s == TrustState(0.2, 0, 0)
    s = tr.update(s, True, d=8)
    assert s == TrustState(0.2, 1, 0)
    s = tr.update(s, False, d=8)  # a failure ends the run of successes
    assert s == TrustState(0.2, 0, 1)
    for _ in range(2):
        s = tr.update(s, True, d=8)
    assert s == TrustState(0.4, 0, 0)  # doubled after 2 successes in a row
    for _ in range(2):
        s = tr.update(s, True, d=8)
    assert s.length == 0.5  # capped at length_max
    for length in (0.25, 0.125, 0.0625, 0.2):  # halved after 3 failures; below 0.05: restart
        for _ in range(3):
            s = tr.update(s, False, d=8)
        assert s == TrustState(length, 0, 0)
    # failure_tolerance 0: max(4, d) failures (TuRBO-1)
    assert TrustRegion().failures(3) == 4 and TrustRegion().failures(13) == 13


def test_box_is_centred_and_clipped():
    tr = TrustRegion()
    lo, hi = tr.box(np.array([0.5, 0.05, 1.0]), 0.2)
    np.testing.assert_allclose(lo, [0.4, 0.0, 0.9])
    np.testing.assert_allclose(hi, [0.6, 0.15, 1.0])


def test_option_values_and_errors():
    assert trust_region_from_option("off") is None and trust_region_from_option(None) is None
    assert trust_region_from_option("auto") == TrustRegion()
    assert trust_region_from_option({"length_init": 0.1}) == TrustRegion(length_init=0.1)
    with pytest.raises(ValueError, match="unknown key.*'length'"):
        trust_region_from_option({"length": 0.1})
    with pytest.raises(ValueError, match="length_min <= length_init"):
        trust_region_from_option({"length_init": 3.0})
    with pytest.raises(ValueError, match="success_tolerance must be an integer >= 1"):
        trust_region_from_option({"success_tolerance": 0})
    with pytest.raises(ValueError, match="trust_region must be 'off', 'auto'"):
        trust_region_from_option("on")
    s = get_system("lq")
    with pytest.raises(LearnerOptionError, match="trust_region"):
        make_learner("bo", s.search_space, s.parameterization.theta0, trust_region="yes")


def test_acquisition_stays_in_the_box():
    rng = np.random.default_rng(0)
    X = rng.uniform(size=(12, 3))
    y = ((X - 0.9) ** 2).sum(1)  # the optimum lies outside the box
    lo, hi = np.array([0.1, 0.2, 0.3]), np.array([0.3, 0.4, 0.5])
    z = propose_ei(GPSurrogate(1), X, y, seed=1, search=AcqfSearch(2, 32), box=(lo, hi))
    assert np.all(z >= lo) and np.all(z <= hi)
    free = propose_ei(GPSurrogate(1), X, y, seed=1, search=AcqfSearch(2, 32))
    assert not (np.all(free >= lo) and np.all(free <= hi))  # without the box: elsewhere
    with pytest.raises(ValueError, match="box must satisfy"):
        propose_ei(GPSurrogate(1), X, y, seed=1, box=(hi, lo))


def _result(f, rng, n_theta):
    return EpisodeResult(np.asarray(f, float), rng.normal(size=n_theta), True)


@pytest.mark.parametrize("name", ["bo", "mobo", "hybrid"])
def test_every_proposal_lies_in_the_box_around_the_deployed_theta(name):
    """Design inside the first box around theta0; then every proposal (acquisition, the
    hybrid's gradient step) inside the box of the current length around the deployed theta;
    a point that becomes the deployed theta is a success (the box moves to it)."""
    s = get_system("lq")
    space, theta0 = s.search_space, s.parameterization.theta0
    z0 = space.to_unit(theta0)
    tr = {"length_init": 0.1, "success_tolerance": 1, "failure_tolerance": 2}
    # the incumbent rule deploys after every fit (no start_id: random starts, where "auto" has
    # needed 6 episodes a side since session 11), so that the box can move within 10 episodes
    learner = make_learner(name, space, theta0, seed=3, trust_region=tr, deploy="incumbent", **FAST)
    rng = np.random.default_rng(0)
    lengths, successes = [], 0
    for k in range(10):
        center, length = space.to_unit(learner.incumbent()), learner.trust_.length
        theta = learner.propose()
        z = space.to_unit(theta)
        # the design fills the first box around theta0; later proposals the current box
        c, half = (z0, 0.05) if k < 3 else (center, length / 2)
        assert np.all(np.abs(z - c) <= half + 1e-9), (k, np.abs(z - c).max(), half)
        f = (1.0 + float(np.sum((z - 0.6) ** 2)), 1.0 + rng.uniform(), 0.0, 0.0)
        learner.observe(theta, _result(f, rng, space.n_theta))
        lengths.append(learner.trust_.length)
        successes += np.allclose(space.to_unit(learner.incumbent()), z) and k >= 3
    assert len(set(lengths)) > 1  # it did change length
    assert successes > 0  # and moved: the cost falls towards 0.6, away from theta0 (0.5)


@pytest.mark.parametrize("name", ["bo", "hybrid"])
def test_trust_state_resumes_exactly_and_old_states_resume_without_it(name):
    s = get_system("lq")
    space, theta0 = s.search_space, s.parameterization.theta0
    tr = {"length_init": 0.1, "success_tolerance": 1, "failure_tolerance": 2}
    a = make_learner(name, space, theta0, seed=3, trust_region=tr, **FAST)
    rng = np.random.default_rng(1)
    for _ in range(7):
        th = a.propose()
        z = space.to_unit(th)
        a.observe(th, _result((1.0 + float(np.sum((z - 0.6) ** 2)), 1.0, 0, 0), rng, space.n_theta))
    state = a.state_dict()
    assert state["trust_region"] == a.trust_.to_dict()
    b = make_learner(name, space, theta0, seed=99, trust_region=tr, **FAST)
    b.load_state_dict(state)
    assert b.trust_ == a.trust_
    np.testing.assert_array_equal(a.propose(), b.propose())
    # a state written before session 7 (no "trust_region" key) was made without a trust
    # region: a learner whose option is at its default (a marked default, as the option
    # would be if "auto" became the default) resumes without one; an explicit one keeps it
    old_state = {k: v for k, v in state.items() if k not in ("trust_region", "trust_pre_fit")}
    marked = make_learner(name, space, theta0, seed=3, trust_region=_DefaultAny("auto"), **FAST)
    assert marked.trust_region is not None
    marked.load_state_dict(old_state)
    assert marked.trust_region is None and marked.trust_ is None
    explicit = make_learner(name, space, theta0, seed=3, trust_region="auto", **FAST)
    explicit.load_state_dict(old_state)
    assert explicit.trust_region is not None
    # a state written with the trust region off (its key None) resumes without one too
    off_state = make_learner(name, space, theta0, seed=3, trust_region="off", **FAST).state_dict()
    assert off_state["trust_region"] is None
    marked = make_learner(name, space, theta0, seed=3, trust_region=_DefaultAny("auto"), **FAST)
    marked.load_state_dict(off_state)
    assert marked.trust_region is None
