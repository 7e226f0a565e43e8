"""The trust region of the GP learners (``trust_region``, :mod:`mpcmobo.bo.trust`).

Its rule written out by hand (double after a run of successes, halve after a run of failures,
cap, restart at the floor); the learners' proposals inside the box of the current length around
the deployed theta; the box following a success; the state saved and resumed exactly; the
option's table reaching the learner, and bad values refused with a message naming the option.
"""

from __future__ import annotations

import numpy as np
import pytest

from mpcmobo.bo import AcqfSearch, GPSurrogate, propose_ei
from mpcmobo.bo.trust import TrustRegion, TrustState
from mpcmobo.learners import EpisodeResult, make_learner
from mpcmobo.learners.registry import LearnerOptionError
from mpcmobo.systems import get_system

FAST = {"n_init": 3, "search": {"num_restarts": 2, "raw_samples": 32, "maxiter": 20}}
# the EHVI learners with fewer quasi-MC samples: the box, not the acquisition, is tested here
EHVI = {"n_init": 3, "search": {**FAST["search"], "mc_samples": 16}}


def _fast(name):
    return FAST if name == "bo" else EHVI


def test_length_doubles_halves_caps_and_restarts_as_written():
    tr = TrustRegion(
        length_init=0.2, length_min=0.05, length_max=0.5, success_tolerance=2, failure_tolerance=3
    )
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


def test_the_option_reaches_the_learner():
    s = get_system("lq")
    space, theta0 = s.search_space, s.parameterization.theta0
    assert make_learner("bo", space, theta0).trust_region == TrustRegion()  # the default
    assert make_learner("bo", space, theta0, trust_region=True).trust_region == TrustRegion()
    off = make_learner("bo", space, theta0, trust_region=False)
    assert off.trust_region is None and off.trust_ is None
    tr = {"length_init": 0.1, "success_tolerance": 3, "failure_tolerance": 5}
    lr = make_learner("mobo", space, theta0, trust_region=tr)
    assert lr.trust_region == TrustRegion(**tr)
    assert lr.trust_ == TrustState(0.1, 0, 0)


def test_the_trust_regions_own_checks():
    with pytest.raises(ValueError, match="length_min <= length_init"):
        TrustRegion(length_init=3.0)
    with pytest.raises(ValueError, match="success_tolerance must be an integer >= 1"):
        TrustRegion(success_tolerance=0)
    with pytest.raises(ValueError, match="length_min must be a finite number"):
        TrustRegion(length_min=float("nan"))


@pytest.mark.parametrize(
    "value, match",
    [
        ({"length": 0.1}, r"^trust_region\.length: unknown option"),
        ({"length_init": 3.0}, r"^trust_region\.length_init: .*less than or equal to 2"),
        ({"success_tolerance": 0}, r"^trust_region\.success_tolerance: "),
        ({"length_init": 0.01}, r"^trust_region: needs length_min <= length_init <= length_max"),
    ],
)
def test_bad_trust_region_options_name_the_option(value, match):
    """The message's first line names the option by its dotted path, as for every other
    nested table (``deploy.confidence``, ``search.num_restarts``)."""
    s = get_system("lq")
    with pytest.raises(LearnerOptionError, match=match) as err:
        make_learner("bo", s.search_space, s.parameterization.theta0, trust_region=value)
    assert "the options of 'bo'" in str(err.value)


def test_a_bad_trust_region_value_is_refused():
    s = get_system("lq")
    for bad in ("yes", "auto", 0.2):
        with pytest.raises(LearnerOptionError, match="trust_region"):
            make_learner("bo", s.search_space, s.parameterization.theta0, trust_region=bad)


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
    # the incumbent rule deploys after every fit, so that the box can move within 8 episodes
    learner = make_learner(
        name, space, theta0, seed=3, trust_region=tr, deploy="incumbent", **_fast(name)
    )
    rng = np.random.default_rng(0)
    lengths, successes = [], 0
    for k in range(8):
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
def test_trust_state_resumes_exactly(name):
    s = get_system("lq")
    space, theta0 = s.search_space, s.parameterization.theta0
    tr = {"length_init": 0.1, "success_tolerance": 1, "failure_tolerance": 2}
    a = make_learner(
        name, space, theta0, seed=3, trust_region=tr, deploy="incumbent", **_fast(name)
    )
    rng = np.random.default_rng(1)
    for k in range(12):  # past the design, until the state is not the first one
        th = a.propose()
        z = space.to_unit(th)
        a.observe(th, _result((1.0 + float(np.sum((z - 0.6) ** 2)), 1.0, 0, 0), rng, space.n_theta))
        if k >= 4 and a.trust_ != TrustState(0.1, 0, 0):
            break
    assert a.trust_ != TrustState(0.1, 0, 0)  # the resume has something to restore
    state = a.state_dict()
    assert state["trust"] == a.trust_.to_dict()
    b = make_learner(
        name, space, theta0, seed=3, trust_region=tr, deploy="incumbent", **_fast(name)
    )
    b.load_state_dict(state)
    assert b.trust_ == a.trust_
    np.testing.assert_array_equal(a.propose(), b.propose())
    off = make_learner(name, space, theta0, seed=3, trust_region=False, **FAST)
    assert off.state_dict()["trust"] is None
