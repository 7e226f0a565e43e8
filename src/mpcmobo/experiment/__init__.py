"""Settings, evaluation protocol, learning loop, study runner and storage of results."""

from mpcmobo.experiment.evaluation import Evaluator
from mpcmobo.experiment.job import EvaluationSchedule, Job
from mpcmobo.experiment.loop import LearningRun
from mpcmobo.experiment.rundir import RunDirectory, open_run
from mpcmobo.experiment.settings import Settings, SettingsError, load_settings, validate_settings
from mpcmobo.experiment.study import StudyError, run_study

__all__ = [
    "EvaluationSchedule",
    "Evaluator",
    "Job",
    "LearningRun",
    "RunDirectory",
    "Settings",
    "SettingsError",
    "StudyError",
    "load_settings",
    "open_run",
    "run_study",
    "validate_settings",
]
