"""mpcmobo dashboard in headless Chromium: the page of a finished run shows its numbers and
asks nothing of the network; an episode recorded while the page is open appears without a
reload; a damaged Parquet file is reported on the page, and its repair is seen; a tuner's
recommendation and trials are shown."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pandas as pd
import pytest
from dashboard_helpers import chromium, needs_chromium, serving

from mpcmobo.experiment import storage

pytestmark = needs_chromium

ROWS = "rows => rows.slice(1).map(r => [...r.cells].map(c => c.textContent))"


@pytest.fixture(scope="module")
def browser():
    with chromium() as b:
        yield b


@pytest.fixture
def copy(dashboard_run, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(dashboard_run, out)
    return out


def _open(browser, url):
    page = browser.new_page(viewport={"width": 1300, "height": 900})
    requests = []
    page.on("request", lambda r: requests.append(r.url))
    page.goto(url)
    page.wait_for_selector("body[data-ready='1']", timeout=30_000)
    return page, requests


def _jobs(page):
    return page.eval_on_selector_all("#jobs tr", ROWS)


def test_the_page_of_a_finished_run_shows_its_numbers(dashboard_run, browser):
    ep = pd.read_parquet(dashboard_run / "episodes.parquet")
    ref = storage.read_pickle(dashboard_run / "reference.pkl")
    with serving(dashboard_run) as url:
        page, requests = _open(browser, url)
        rows = _jobs(page)
        assert [(r[1], r[2], r[3]) for r in rows] == [
            (lr, s, "3 / 3") for lr in ("identify", "mobo") for s in ("0", "1")
        ]
        for r in rows:  # the cumulative plant cost: the sum of the episodes' mean stage cost
            job = ep[(ep.learner == r[1]) & (ep.seed == int(r[2]))]
            assert float(r[6]) == pytest.approx(job.mean_stage_cost.sum(), rel=1e-3)
            assert float(r[9]) == pytest.approx(ref["J_star"], rel=1e-3)
        page.check("#per-seed")
        perf = page.evaluate(
            "() => { const u = window.charts.perf; "
            "return [u.series.map(s => s.label), u.data, u.levels.map(l => l.y)]; }"
        )
        job = ep[(ep.learner == "mobo") & (ep.seed == 1)].sort_values("episode")
        J = perf[1][perf[0].index("mobo s1: J_eval deployed")]
        assert J == pytest.approx(
            [None if not math.isfinite(v) else v for v in job.J_eval_incumbent]
        )
        assert perf[2] == pytest.approx([ref["J_star"], ref["J_initial"]])
        stepped = page.evaluate(  # J_eval held between evaluations, not sloped: not the cost's path
            "() => { const s = window.charts.perf.series, at = (l) => s.find(x => x.label === l); "
            "return at('mobo s1: J_eval deployed').paths !== at('mobo s1: plant cost').paths; }"
        )
        assert stepped
        whole = "() => window.charts.perf.axes[0]._splits.every(Number.isInteger)"
        assert page.evaluate(whole)  # the episode axis ticks whole episodes only
        # one episode's states against their limits: the stored trajectory's numbers
        key = page.input_value("#trajectory")
        _, learner, seed, phase, episode, start = key.split("|")
        tr = pd.read_parquet(dashboard_run / "trajectories.parquet")
        tr = tr.set_index(["learner", "seed", "phase", "episode", "start"])
        tr = tr.loc[(learner, int(seed), phase, int(episode), int(start))]
        y, bounds = page.evaluate(
            "() => { const u = window.charts['episode-x_p']; "
            "return [u.data[1], u.levels.map(l => l.y)]; }"
        )
        assert y == pytest.approx(tr.sort_values("k").x_p.tolist())
        assert bounds[:2] == [ref["system"]["x_lb"][0], ref["system"]["x_ub"][0]]
        assert page.is_visible("#identified-section") and page.is_visible("#objectives-section")
        assert page.inner_text("#messages") == ""
        assert requests and all(u.startswith(url) for u in requests), requests  # no CDN


def test_the_texts_of_close_levels_do_not_cover_each_other(dashboard_run, browser):
    """J*, theta0's level and a limit a pixel apart: each text is drawn where no other is."""
    made = (
        "() => { const u = chart('close-levels', { x: [0, 1, 2], parent: document.body, "
        "series: [{ label: 'cost', y: [1, 2, 3] }], levels: [{ y: 2, text: 'J*' }, "
        "{ y: 2.005, dash: 'dot', text: 'theta0' }, { y: 1.995, text: 'a limit' }] }); "
        "window.closeLevels = u; }"
    )
    with serving(dashboard_run) as url:
        page, _ = _open(browser, url)
        page.evaluate(made)
        page.wait_for_function("() => (window.closeLevels.levelLabels || []).length === 3")
        boxes = page.evaluate("() => window.closeLevels.levelLabels")
    for i, a in enumerate(boxes):
        for b in boxes[i + 1 :]:
            apart = (
                a["right"] <= b["left"]
                or b["right"] <= a["left"]
                or a["bottom"] <= b["top"]
                or b["bottom"] <= a["top"]
            )
            assert apart, (a, b)


def test_a_new_episode_appears_without_a_reload(copy, browser):
    ep = pd.read_parquet(copy / "episodes.parquet")
    storage.write_parquet(copy / "episodes.parquet", ep[ep.episode < 2])
    with serving(copy) as url:
        page, _ = _open(browser, url)
        assert {r[3] for r in _jobs(page)} == {"2 / 3"}
        page.evaluate("() => { window.stillHere = true; }")
        storage.write_parquet(copy / "episodes.parquet", ep)
        page.wait_for_function(
            "() => [...document.querySelectorAll('#jobs tr')].slice(1)"
            ".every(r => r.cells[3].textContent === '3 / 3')",
            timeout=30_000,  # behaviour, not speed: benchmarks/dashboard_load.py times it
        )
        assert page.evaluate("() => window.stillHere") is True


def test_a_damaged_parquet_is_reported_and_its_repair_seen(copy, browser):
    good = (copy / "episodes.parquet").read_bytes()
    (copy / "episodes.parquet").write_bytes(good[: len(good) // 2])
    with serving(copy) as url:
        page, _ = _open(browser, url)
        text = page.inner_text("#messages")
        assert "episodes.parquet cannot be read" in text, text
        assert page.is_visible("#perf")  # the rest of the page is there
        storage.atomic_write_bytes(copy / "episodes.parquet", good)
        page.wait_for_function(
            "() => document.getElementById('messages').textContent === ''",
            timeout=30_000,  # behaviour, not speed: benchmarks/dashboard_load.py times it
        )
        assert len(_jobs(page)) == 4


def test_a_tuner_shows_its_pending_trial_recommendation_and_trials(copy, browser):
    (copy / "tuner.json").write_text("{}")
    status = {
        "plant_cost": 12.5,
        "excess_cost": 1.25,
        "recommendation": {"action": "stop", "reason": "no candidate pays back its exploration"},
        "quarantined": [7],
        "pending": 3,
        "evidence": {"test": "one-sided t", "confidence": 0.9, "episodes": 6},
        "trials": [
            {"id": 0, "role": "candidate", "plant_cost": 0.5, "verdict": "kept"},
            {"id": 1, "role": "deployed", "plant_cost": 0.25, "verdict": "kept"},
        ],
    }
    (copy / "status.json").write_text(json.dumps(status))
    with serving(copy) as url:
        page, _ = _open(browser, url)
        text = page.inner_text("#tuner")
        for part in ("trial 3", "stop: no candidate pays back", "12.5", "1.25", "7", "one-sided t"):
            assert part in text, text
        assert "test: one-sided t; confidence: 0.9; episodes: 6" in text  # in words, not JSON
        assert "{" not in text, text
        trials = page.eval_on_selector_all("#tuner table tr", ROWS)
        assert trials == [["0", "candidate", "0.5", "kept"], ["1", "deployed", "0.25", "kept"]]
        assert np.isfinite(float(_jobs(page)[0][6]))
