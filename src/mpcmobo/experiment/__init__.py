"""Settings, evaluation protocol, learning loop, study runner and storage of results."""

from mpcmobo.experiment.evaluation import Evaluator
from mpcmobo.experiment.loop import LearningRun
from mpcmobo.experiment.settings import Settings, SettingsError, load_settings, validate_settings
from mpcmobo.experiment.study import StudyError, run_study

__all__ = [
    "Evaluator",
    "LearningRun",
    "Settings",
    "SettingsError",
    "StudyError",
    "load_settings",
    "run_study",
    "validate_settings",
]
