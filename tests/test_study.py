"""The study runner: records, checkpoints, resume after an interruption, summary."""

from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
import tomllib

import numpy as np
import pandas as pd
import pytest

from mpcmobo.experiment import storage
from mpcmobo.experiment.rundir import RUNNING_FILE, RunDirectory
from mpcmobo.experiment.settings import SettingsError, load_settings
from mpcmobo.experiment.study import StudyError, run_study

TEXT = {"capture_output": True, "text": True}
WALL = ["mpc_time_s", "learner_time_s", "eval_time_s"]


def small(**kw):
    base = dict(
        system={"name": "lq"},
        learners=["mpc-rl"],
        episodes=7,
        steps=10,
        seeds=[0, 1],
        evaluation={"n_starts": 2, "eval_every": 3},
        records={"trajectory_every": 3},
        workers=1,
    )
    base.update(kw)
    return load_settings(None, **base)


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("study") / "full"
    events = []
    summary = run_study(small(), out, progress=events.append)
    return out, summary, events


def test_records_layout_and_eval_policy(full_run):
    out, summary, events = full_run
    for name in ("config.toml", "reference.pkl", "episodes.parquet", "trajectories.parquet"):
        assert (out / name).exists()
    assert (out / "jobs" / "mpc-rl-s1" / "checkpoint.pkl").exists()
    df = storage.read_episodes(out)
    assert len(df) == 14
    for col in (
        "theta",
        "f1",
        "f4",
        "J_tilde",
        "mean_abs_A",
        "violation",
        "solver_failures",
        "mpc_time_s",
        "learner_time_s",
        "incumbent",
        "J_eval_incumbent",
    ):
        assert col in df.columns
    s0 = df[df.seed == 0].set_index("episode")
    evaluated = sorted(s0.index[np.isfinite(s0["J_eval_incumbent"])])
    # evaluated at 0, at the last episode, and where the deployed theta differs from the last
    # evaluated one with at least eval_every = 3 episodes since (MPC-RL deploys its best
    # verified iterate, so it need not change every episode)
    expected, last = [0], 0
    inc = [np.asarray(v, float) for v in s0["incumbent"]]
    for ep in range(1, 7):
        if ep == 6 or (not np.array_equal(inc[ep], inc[last]) and ep - last >= 3):
            expected.append(ep)
            last = ep
    assert evaluated == expected
    assert [e for e in events if e["kind"] == "episode"][-1]["episode"] == 7
    tr = storage.read_trajectories(out)
    assert set(tr.phase) == {"initial", "perfect", "learning", "final"}
    assert set(tr[tr.phase == "learning"].episode) == {0, 3, 6}
    assert len(tr[(tr.phase == "final") & (tr.seed == 0)]) == 2 * 11  # n_starts x (steps + 1)
    assert {"x_p", "x_v", "u_f"} <= set(tr.columns)
    assert summary["complete"] is True


def test_checkpoints_are_plain_dicts_that_round_trip(full_run):
    """A checkpoint on disk is a plain dict (no class of the package inside, so that its rows
    stay readable by later versions) of this version's schema; its typed form gives it back
    unchanged."""
    from mpcmobo.experiment.records import Checkpoint

    out, _, _ = full_run
    d = storage.load_checkpoint(out, "mpc-rl", 0)
    assert type(d) is dict and all(type(r) is dict for r in d["rows"])
    assert d["schema"] == storage.CHECKPOINT_SCHEMA == 3 and "version" not in d
    assert storage.checkpoint_schema(d) == 3
    ckpt = Checkpoint.from_dict(d)
    assert ckpt.schema == 3
    again = dict(ckpt.to_dict(), schema=d["schema"], learner="mpc-rl", seed=0)
    assert list(again) == list(d) and list(again["rows"][0]) == list(d["rows"][0])
    np.testing.assert_equal(again, d)  # nested: arrays, lists, NaN equal to NaN


def test_config_toml_holds_every_learner_option_default(full_run, tmp_path):
    """``config.toml`` of a run holds every option of its learners with its default (nothing
    was given), and the given ones where they were: a later version with other defaults
    resumes the run with the options it was started with."""
    from mpcmobo.learners.registry import learner_options

    out, _, _ = full_run
    saved = tomllib.loads((out / "config.toml").read_text())
    assert saved["learner_options"] == {"mpc-rl": learner_options("mpc-rl")}
    assert saved["learner_options"]["mpc-rl"]["deploy"]["max_runs"] == 12
    options = {
        "mobo": {"n_init": 3, "search": {"num_restarts": 2, "raw_samples": 32, "maxiter": 20}},
        "bo": {"deploy": "incumbent", "trust_region": False},
    }
    s = small(learners=["mpc-rl", "mobo"], learner_options=options, episodes=1, seeds=[0])
    run_study(s, tmp_path / "run", max_episodes_this_call=0)
    saved = tomllib.loads((tmp_path / "run" / "config.toml").read_text())["learner_options"]
    assert set(saved) == {"mpc-rl", "mobo", "bo"}  # the run's learners and the given tables
    mobo = learner_options("mobo")
    mobo["n_init"] = 3
    mobo["search"].update(num_restarts=2, raw_samples=32, maxiter=20)
    assert saved["mobo"] == mobo and saved["mobo"]["search"]["mc_samples"] == 64
    bo = learner_options("bo")
    bo.update(deploy={"rule": "incumbent"}, trust_region=False)
    assert saved["bo"] == bo
    assert saved["mpc-rl"] == learner_options("mpc-rl")
    # the saved file is what a resumed run reads: the same options
    again = load_settings(tmp_path / "run" / "config.toml")
    assert again.learner_options == saved


def test_summary_matches_records(full_run):
    out, summary, _ = full_run
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk["learners"].keys() == summary["learners"].keys()
    df = storage.read_episodes(out)
    J_star = on_disk["J_star"]
    s = on_disk["learners"]["mpc-rl"]
    finals, worst, regressions = [], [], 0
    for seed in (0, 1):
        sub = df[df.seed == seed].sort_values("episode")
        last = sub.iloc[-1]
        assert math.isfinite(last.J_eval_incumbent)
        per = s["per_seed"][str(seed)]
        assert per["J_final"] == pytest.approx(last.J_eval_incumbent, rel=0, abs=0)
        assert per["theta_final"] == pytest.approx(list(last.incumbent))
        ok = sub[sub.J_eval_incumbent - J_star <= 0.02 * abs(J_star)]
        assert per["episodes_to_2pct"] == (int(ok.episode.min()) if len(ok) else None)
        J = sub.J_eval_incumbent[np.isfinite(sub.J_eval_incumbent)]
        assert per["J_worst"] == J.max()
        assert per["regressions"] == int((J > on_disk["J_initial"]).sum())
        assert per["violation_mean"] == pytest.approx(sub.violation.mean())
        finals.append(last.J_eval_incumbent)
        worst.append(per["J_worst"])
        regressions += per["regressions"]
    assert s["J_final"] == pytest.approx(float(np.median(finals)))
    assert s["J_final_worst"] == max(finals) and s["J_worst"] == max(worst)
    assert s["regressions"] == regressions
    assert s["J_star"] == J_star and s["J_initial"] == on_disk["J_initial"]
    assert s["theta_names"][0] == "theta_c" and len(s["theta_names"]) == len(s["theta_final"])
    best = int(np.argmin(finals))  # the learner's theta_final: the best seed's deployed theta
    assert s["theta_final_seed"] == best
    assert s["theta_final"] == s["per_seed"][str(best)]["theta_final"]
    assert s["wall_time_s"] > 0
    assert on_disk["settings"]["episodes"] == 7 and on_disk["system"] == "lq"
    # J_initial is J_eval(theta0): the mean stage cost of the "initial" evaluation episodes
    assert J_star < on_disk["J_initial"]


def test_interrupted_then_resumed_equals_uninterrupted(full_run, tmp_path):
    out_full, _, _ = full_run
    out = tmp_path / "resumed"
    part = run_study(small(), out, max_episodes_this_call=2)
    assert part["complete"] is False
    assert len(storage.read_episodes(out)) == 4
    # simulate a kill while writing: a stray temporary file next to the checkpoint
    ck = storage.checkpoint_path(out, "mpc-rl", 0)
    (ck.parent / ".checkpoint.pkl.abc.tmp").write_bytes(b"partial")
    run_study(None, out, resume=True, max_episodes_this_call=3)
    done = run_study(None, out, resume=True)
    assert done["complete"] is True
    a = storage.read_episodes(out_full).drop(columns=WALL)
    b = storage.read_episodes(out).drop(columns=WALL)
    pd.testing.assert_frame_equal(a, b)
    ta, tb = storage.read_trajectories(out_full), storage.read_trajectories(out)
    pd.testing.assert_frame_equal(ta, tb)
    # resuming a finished study changes nothing
    run_study(None, out, resume=True)
    pd.testing.assert_frame_equal(a, storage.read_episodes(out).drop(columns=WALL))


def test_a_running_study_names_its_process_until_it_ends(tmp_path):
    """``running.json`` names the study's process while it runs (what the dashboard reads),
    and is gone when it ends, by its end or by an interruption."""
    out = tmp_path / "run"
    seen = []
    run_study(
        small(episodes=2, seeds=[0]),
        out,
        progress=lambda event: seen.append(RunDirectory(out).study_alive()),
    )
    assert len(seen) > 2 and all(v is True for v in seen)
    assert not (out / RUNNING_FILE).exists() and RunDirectory(out).study_alive() is False

    def stop(event):
        if event["kind"] == "start":
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_study(None, out, resume=True, progress=stop)
    assert not (out / RUNNING_FILE).exists()
    # a second process on a running study is refused; a killed study's file is replaced
    (out / RUNNING_FILE).write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname()}))
    with pytest.raises(StudyError, match="is being run by another process"):
        run_study(None, out, resume=True)
    assert (out / RUNNING_FILE).exists()
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], **TEXT)
    (out / RUNNING_FILE).write_text(json.dumps({"pid": int(gone.stdout), "host": "h"}))
    with pytest.raises(StudyError, match="another host's"):  # another host: cannot tell
        run_study(None, out, resume=True)
    (out / RUNNING_FILE).write_text(
        json.dumps({"pid": int(gone.stdout), "host": socket.gethostname()})
    )
    assert run_study(None, out, resume=True)["complete"] is True
    assert not (out / RUNNING_FILE).exists()


def test_extended_budget_equals_a_run_with_that_budget(full_run, tmp_path):
    out_full, _, _ = full_run
    out = tmp_path / "extended"
    run_study(small(episodes=5), out)
    short = storage.read_episodes(out)
    # the old last episode (4) had the final evaluation and trajectories of a 5-episode run
    assert np.isfinite(short[short.episode == 4].J_eval_incumbent).all()
    with pytest.raises(StudyError, match="extended, not shortened"):
        run_study(small(episodes=3), out, resume=True)
    done = run_study(small(episodes=7), out, resume=True)
    assert done["complete"] is True
    assert load_settings(out / "config.toml").episodes == 7
    a = storage.read_episodes(out_full).drop(columns=WALL)
    b = storage.read_episodes(out).drop(columns=WALL)
    pd.testing.assert_frame_equal(a, b)
    pd.testing.assert_frame_equal(
        storage.read_trajectories(out_full), storage.read_trajectories(out)
    )


def test_parallel_workers_match_serial(full_run, tmp_path):
    out_full, _, _ = full_run
    out = tmp_path / "par"
    run_study(small(workers=2), out)
    a = storage.read_episodes(out_full).drop(columns=WALL)
    b = storage.read_episodes(out).drop(columns=WALL)
    pd.testing.assert_frame_equal(a, b)


def test_refuses_to_overwrite_and_checks_learners(full_run, tmp_path, monkeypatch):
    out_full, _, _ = full_run
    with pytest.raises(StudyError, match="holds a run"):
        run_study(small(), out_full)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(StudyError, match="is not empty; choose a new or empty directory$"):
        run_study(small(), tmp_path / "other")
    with pytest.raises(StudyError, match="nothing to resume"):
        run_study(None, tmp_path / "empty", resume=True)
    with pytest.raises(SettingsError, match=r"learner_options\.mpc-rl\.optimizer\.lr: "):
        run_study(small(learner_options={"mpc-rl": {"optimizer": {"lr": -1.0}}}), tmp_path / "bad")
    assert not (tmp_path / "bad").exists()  # nothing written: the fixed settings can use it
    # the Ray backend without ray installed (hidden here, installed or not): a settings error
    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(SettingsError, match=r"backend: 'ray' needs the optional dependency ray"):
        run_study(small(backend="ray", workers=2), tmp_path / "ray")
    assert not (tmp_path / "ray").exists()


def test_orphaned_worker_stops_after_its_checkpoint(tmp_path):
    """A worker whose study process is gone (parent pid changed) stops after one episode's
    checkpoint; resuming then completes the job as usual."""
    from mpcmobo.experiment.job import run_job

    s = small(seeds=[0])
    out = tmp_path / "orphan"
    run_study(s, out, max_episodes_this_call=0)  # the study directory, config and J*
    res = run_job(s.to_dict(), str(out), "mpc-rl", 0, parent_pid=-12345)
    assert res == {"learner": "mpc-rl", "seed": 0, "episodes": 1, "done": False}
    done = run_study(None, out, resume=True)
    assert done["complete"] is True
    assert len(storage.read_episodes(out)) == 7


def test_ray_backend_matches_serial(full_run, tmp_path):
    """The optional Ray backend (pip install 'mpcmobo[ray]') gives the serial records, with the
    system given as a factory path that the Ray workers import themselves."""
    ray = pytest.importorskip("ray")
    out_full, _, _ = full_run
    out = tmp_path / "ray"
    factory = tmp_path / "my_lq.py"
    factory.write_text("from mpcmobo.systems import make_lq\n\ndef make():\n    return make_lq()\n")
    try:
        run_study(small(workers=2, backend="ray", system={"factory": f"{factory}:make"}), out)
    finally:
        ray.shutdown()
    a = storage.read_episodes(out_full).drop(columns=WALL)
    b = storage.read_episodes(out).drop(columns=WALL)
    pd.testing.assert_frame_equal(a, b)


def test_ray_joins_the_cluster_ray_address_names(tmp_path, monkeypatch):
    """With RAY_ADDRESS set the Ray backend connects to that cluster (whose CPUs decide how
    many jobs run at once) instead of starting one of ``workers`` CPUs."""
    import types

    from mpcmobo.experiment import workers

    calls = []

    def init(**kwargs):
        calls.append(kwargs)
        raise RuntimeError("stop here")

    fake = types.SimpleNamespace(is_initialized=lambda: False, init=init)
    monkeypatch.setitem(sys.modules, "ray", fake)
    monkeypatch.setattr(workers, "check_reachable", lambda address: None)  # no "head" here
    monkeypatch.setenv("RAY_ADDRESS", "ray://head:10001")
    with pytest.raises(RuntimeError, match="stop here"):
        workers._run_ray([], {}, 2, None)  # type: ignore[arg-type]
    monkeypatch.delenv("RAY_ADDRESS")
    with pytest.raises(RuntimeError, match="stop here"):
        workers._run_ray([], {}, 2, None)  # type: ignore[arg-type]
    assert calls[0] == {"address": "ray://head:10001", "ignore_reinit_error": True}
    assert calls[1]["num_cpus"] == 2 and "address" not in calls[1]


def test_a_ray_cluster_takes_the_jobs_with_one_worker_and_must_answer(tmp_path, monkeypatch):
    """With ``backend = "ray"`` and RAY_ADDRESS set, the jobs go to the cluster even with
    ``workers = 1`` (its CPUs decide); an address where nothing answers is refused at once,
    naming it, where Ray would wait for minutes."""
    import socket

    from mpcmobo.experiment import workers
    from mpcmobo.experiment.rundir import RunDirectory, StudyError

    sent = []
    monkeypatch.setattr(workers, "_run_ray", lambda jobs, args, n, watch: sent.append(jobs))
    monkeypatch.setenv("RAY_ADDRESS", "127.0.0.1:1")
    s = small(workers=1, backend="ray")
    run_dir = RunDirectory(tmp_path / "run")
    workers.run_jobs([("mpc-rl", 0)], {}, s, run_dir, lambda event: None)
    assert sent == [[("mpc-rl", 0)]]
    with socket.socket() as free:  # a port nothing listens on
        free.bind(("127.0.0.1", 0))
        port = free.getsockname()[1]
    with pytest.raises(StudyError, match=f"RAY_ADDRESS=127.0.0.1:{port}: no Ray cluster answers"):
        workers.check_reachable(f"127.0.0.1:{port}")
    workers.check_reachable("auto")  # left to Ray
    # a new run refuses the address before it writes anything (J* is not computed for nothing)
    monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{port}")
    monkeypatch.setattr(workers, "_run_ray", lambda *a: pytest.fail("the jobs were started"))
    with pytest.raises(StudyError, match="no Ray cluster answers"):
        run_study(s, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def tiny_lq(**options):
    """A user-defined system: defined at module level, registered only inside the test below
    (a worker process that imports this module does not register it by itself)."""
    from mpcmobo.systems import make_lq

    return make_lq(**options)


@pytest.fixture
def own_registry(monkeypatch):
    """The systems a test registers are gone after it (a copy of the registry)."""
    from mpcmobo.systems import registry

    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))


def test_user_registered_system_runs_in_worker_processes(tmp_path, own_registry):
    from mpcmobo.systems import register_system

    register_system("tiny-lq", tiny_lq, overwrite=True)
    s = small(system={"name": "tiny-lq"}, episodes=2, workers=2)
    done = run_study(s, tmp_path / "tiny")
    assert done["complete"] is True
    assert len(storage.read_episodes(tmp_path / "tiny")) == 4  # two seeds, two jobs in workers


def test_unsendable_system_factory_is_a_study_error(tmp_path, own_registry):
    from mpcmobo.systems import make_lq, register_system

    register_system("lambda-lq", lambda **o: make_lq(**o), overwrite=True)
    with pytest.raises(StudyError, match="cannot be sent to worker processes"):
        run_study(small(system={"name": "lambda-lq"}, episodes=2, workers=2), tmp_path / "x")


def test_evaluation_schedule_every_eval_every_when_the_incumbent_changes():
    from mpcmobo.experiment.job import EvaluationSchedule

    changing = EvaluationSchedule(episodes=7, eval_every=3, trajectory_every=3)
    assert [e for e in range(7) if changing.step(e, np.array([float(e)]))] == [0, 3, 6]
    fixed = EvaluationSchedule(episodes=7, eval_every=3, trajectory_every=3)
    assert [e for e in range(7) if fixed.step(e, np.zeros(1))] == [0, 6]


def test_summary_counts_the_deployed_thetas_worst_evaluation_and_regressions():
    """Per seed the worst J_eval of the deployed theta over the run (not the
    last), the evaluations above J_eval(theta0) and the mean violation; per learner the worst
    seed's final, the worst deployed J_eval of any seed and the regressions summed."""
    from mpcmobo.experiment.records import Reference
    from mpcmobo.experiment.summary import summarize

    settings = small(episodes=4, seeds=[0, 1])
    ref = Reference(
        J_star=1.0, J_initial=6.0, theta0=np.zeros(2), system={"theta_names": ["a", "b"]}
    )
    nan = math.nan
    J = {0: [6.0, 9.0, nan, 2.0], 1: [6.0, 7.0, 8.0, 5.0]}
    df = pd.DataFrame(
        [
            {
                "learner": "mpc-rl",
                "seed": seed,
                "episode": k,
                "J_eval_incumbent": J[seed][k],
                "violation": float(k + seed),
                "incumbent": np.zeros(2),
            }
            for seed in (0, 1)
            for k in range(4)
        ]
    )
    s = summarize(settings, ref, df, {})["learners"]["mpc-rl"]
    per = s["per_seed"]
    assert (per["0"]["J_final"], per["0"]["J_worst"], per["0"]["regressions"]) == (2.0, 9.0, 1)
    assert (per["1"]["J_final"], per["1"]["J_worst"], per["1"]["regressions"]) == (5.0, 8.0, 2)
    assert per["0"]["violation_mean"] == 1.5 and per["1"]["violation_mean"] == 2.5
    assert (s["J_final"], s["J_final_worst"], s["J_worst"]) == (3.5, 5.0, 9.0)
    assert (s["regressions"], s["seeds_with_regressions"]) == (3, 2)


def test_a_job_that_ends_at_theta0_draws_the_episodes_of_its_j_eval(tmp_path, monkeypatch):
    """Every job's J_eval of theta0 is the reference's; a job that ends at theta0 (identify,
    too few episodes to deploy) stores the reference's episodes of theta0 as its final ones,
    not theta0 solved again (on the CSTR another local minimum from a hot start: 15126
    against 15410), so figures 3 and 4 draw the closed loops that J_final is of."""
    from mpcmobo.experiment.evaluation import Evaluator

    solved_again = []
    original = Evaluator.episodes

    def episodes(self, theta=None, model="imperfect"):
        solved_again.append(model)
        return original(self, theta, model)

    monkeypatch.setattr(Evaluator, "episodes", episodes)
    settings = small(learners=["identify"], seeds=[0], episodes=3)
    summary = run_study(settings, tmp_path / "r")
    tr = pd.read_parquet(tmp_path / "r" / "trajectories.parquet")
    columns = ["start", "k", "x_p", "x_v", "u_f"]
    initial = tr[tr.phase == "initial"][columns].reset_index(drop=True)
    final = tr[tr.phase == "final"][columns].reset_index(drop=True)
    assert len(final) > 0
    pd.testing.assert_frame_equal(initial, final)
    assert solved_again == ["imperfect", "perfect"]  # the reference's, none for the final
    job = summary["learners"]["identify"]
    assert job["J_final"] == pytest.approx(summary["J_initial"])
