"""Settings, evaluation protocol, learning loop, study runner and storage of results.

The names below are imported when first used (PEP 562): ``import mpcmobo.experiment.rundir``
(what ``mpcmobo status`` reads) does not import the learners, torch or BoTorch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from mpcmobo.lazy import lazy_names

if TYPE_CHECKING:
    from mpcmobo.experiment.evaluation import Evaluator
    from mpcmobo.experiment.job import EvaluationSchedule, Job
    from mpcmobo.experiment.loop import LearningRun
    from mpcmobo.experiment.rundir import RunDirectory, open_run
    from mpcmobo.experiment.settings import (
        Settings,
        SettingsError,
        load_settings,
        validate_settings,
    )
    from mpcmobo.experiment.study import StudyError, run_study

_WHERE = {
    "Evaluator": "evaluation",
    "EvaluationSchedule": "job",
    "Job": "job",
    "LearningRun": "loop",
    "RunDirectory": "rundir",
    "open_run": "rundir",
    "Settings": "settings",
    "SettingsError": "settings",
    "load_settings": "settings",
    "validate_settings": "settings",
    "StudyError": "study",
    "run_study": "study",
}

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


__getattr__, __dir__ = lazy_names(__name__, _WHERE, __all__)
