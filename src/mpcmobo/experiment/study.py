"""A study: learners x seeds learning runs, evaluated and recorded, resumable after a crash.

``run_study(settings, out_dir)`` opens the run directory (:func:`open_run`: ``config.toml``
holds every setting), computes the study-level :class:`Reference` (J*, J_eval(theta0) and their
evaluation episodes) once, then runs one :class:`Job` per (learner, seed), in parallel worker
processes. After every episode a job rewrites its checkpoint atomically; ``resume=True``
continues each job from its checkpoint with the saved settings, and since an episode depends
only on that state, the records equal those of an uninterrupted run (wall-time columns aside).
Resumed with a larger ``episodes``, a run is extended to that budget, and its records equal those
of a run started with it. When a job evaluates its incumbent and what it stores is the
:class:`EvaluationSchedule` (in :mod:`mpcmobo.experiment.job`).

Its parts: the reference (:mod:`~mpcmobo.experiment.reference`), the records and summary
(:mod:`~mpcmobo.experiment.summary`) and where the jobs run (:mod:`~mpcmobo.experiment.workers`).
"""

from __future__ import annotations

from pathlib import Path

from mpcmobo.experiment import interrupts
from mpcmobo.experiment.build import build_plant, build_system
from mpcmobo.experiment.job import Progress, explores, make_study_learner, progress_event
from mpcmobo.experiment.logs import run_log
from mpcmobo.experiment.records import Reference
from mpcmobo.experiment.reference import check_run_system, compute_reference
from mpcmobo.experiment.rundir import ReferenceFailed, RunDirectory, StudyError, open_run
from mpcmobo.experiment.sections import SettingsError
from mpcmobo.experiment.settings import Settings
from mpcmobo.experiment.summary import write_records
from mpcmobo.experiment.workers import check_backend, run_jobs
from mpcmobo.learners.registry import LEARNER_SPECS
from mpcmobo.mpc.codegen import require_compiler
from mpcmobo.systems.base import SystemDefinitionError
from mpcmobo.systems.plant import check_reset

# relative cost per episode of a learner's job, to start the slowest jobs first
JOB_COST = {name: spec.job_cost for name, spec in LEARNER_SPECS.items()}


def check_learners(settings: Settings) -> None:
    """The system can be built, its plant made and matched to it, and every learner accepts
    its options (else a SettingsError naming them), before anything is written."""
    system = build_system(settings)
    plant = build_plant(settings, system)
    try:
        check_reset(plant, system, settings.system.measurement_noise)
    except SystemDefinitionError as err:
        raise SettingsError(f"system.plant: {err}") from None
    finally:
        plant.close()
    try:
        if settings.mpc.codegen is True:
            require_compiler()
    except RuntimeError as err:
        raise SettingsError(f"mpc.codegen: {err}") from None
    for name in settings.learners:
        job_system = build_system(settings, name)
        try:
            theta0 = job_system.parameterization.theta0
            make_study_learner(settings, job_system, name, theta0, seed=0)
        except (TypeError, ValueError) as err:
            raise SettingsError(f"learner_options.{name}: {err}") from None


# ---------------------------------------------------------------------- the study
def run_study(
    settings: Settings | None,
    out_dir: str | Path,
    resume: bool = False,
    progress: Progress | None = None,
    max_episodes_this_call: int | None = None,
) -> dict:
    """Run the study (or continue it with ``resume=True``); return the summary dict.

    ``max_episodes_this_call`` stops every job after that many episodes of this call (used to
    simulate an interruption); the summary then has ``complete: false``.

    SIGINT and SIGTERM stop the study (in the main thread): the jobs stop at the end of their
    current MPC step, the workers are stopped, the records are rebuilt from the checkpoints
    and :class:`~mpcmobo.experiment.interrupts.Interrupted` (a ``KeyboardInterrupt``) is
    raised. Library warnings go to ``DIR/run.log`` (:mod:`mpcmobo.experiment.logs`).
    """
    with interrupts.catching():
        if settings is not None and not resume:
            check_learners(settings)  # a bad learner option fails before anything is written
            check_backend(settings)  # so does a Ray backend without ray or its cluster
        if resume and RunDirectory(out_dir).is_tuner():
            raise StudyError(
                f"{out_dir} holds a tuner (ask and tell): its trials run on the plant, not in "
                f"mpcmobo run. Go on with `mpcmobo ask {out_dir}`; `mpcmobo ask {out_dir} "
                "--episodes N` extends its budget"
            )
        if resume:
            check_run_system(RunDirectory(out_dir))
        existed = Path(out_dir).exists()
        run_dir, settings = open_run(out_dir, settings, resume)
        try:
            with run_log(run_dir.path, "study"), run_dir.running():
                return _run_study(run_dir, settings, resume, progress, max_episodes_this_call)
        except ReferenceFailed:
            if not resume:  # nothing was recorded: the directory is as it was
                run_dir.remove_new(existed)
            raise


def _run_study(
    run_dir: RunDirectory,
    settings: Settings,
    resume: bool,
    progress: Progress | None,
    max_episodes_this_call: int | None,
) -> dict:
    if resume:
        check_learners(settings)
    emit = progress or (lambda event: None)
    jobs = [(n, s) for n in settings.learners for s in settings.seeds]
    emit(
        {"kind": "start", "jobs": jobs, "episodes": settings.episodes, "out_dir": str(run_dir.path)}
    )
    reference = _reference(run_dir, settings, emit)
    args = dict(
        settings_dict=settings.to_dict(),
        out_dir=str(run_dir.path),
        J_initial=reference.J_initial,
        max_episodes=max_episodes_this_call,
    )
    try:
        run_jobs(_pending(run_dir, settings, jobs, emit), args, settings, run_dir, emit)
    finally:
        with interrupts.deferred():  # the records of what is checkpointed, written whole
            summary = write_records(run_dir.path, settings, reference)
    emit({"kind": "done", "summary": summary})
    return summary  # type: ignore[return-value]  # a dict: the reference exists


def _reference(run_dir: RunDirectory, settings: Settings, emit: Progress) -> Reference:
    """The study's reference: computed once, then read from the run directory."""
    reference = run_dir.reference()
    if reference is None:
        emit({"kind": "reference", "status": "running"})
        reference = compute_reference(settings)
        # a signal that landed in a solve of a library's own (swallowed there, the solve
        # failed) stops the run here, before a reference that may hold that failure is kept
        interrupts.check()
        run_dir.save_reference(reference)
    emit(
        {
            "kind": "reference",
            "status": "done",
            "J_star": reference.J_star,
            "J_initial": reference.J_initial,
        }
    )
    return reference


def _pending(
    run_dir: RunDirectory, settings: Settings, jobs: list[tuple[str, int]], emit: Progress
) -> list[tuple[str, int]]:
    """The jobs with episodes left (unfinished or extended), longest first: with fewer workers
    than jobs, the slowest job does not start last. Reports the progress of the others."""
    pending = []
    for n, s in jobs:
        ckpt = run_dir.checkpoint(n, s)
        if ckpt is not None:
            emit(progress_event(n, s, ckpt.rows, settings.episodes, explores(ckpt.state)))
        if ckpt is None or len(ckpt.rows) < settings.episodes:
            pending.append((n, s))
    pending.sort(key=lambda job: -JOB_COST.get(job[0], LEARNER_SPECS[job[0]].job_cost))
    return pending
