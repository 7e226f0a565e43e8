"""A study's directory and its rules: starting a run, resuming it, extending its budget.

:func:`open_run` is the one owner of these rules (the CLI and :func:`run_study` both go through
it): a new run needs an empty directory and saves every setting to ``config.toml``; a resumed run
uses the saved settings, of which only ``workers``, ``backend`` and a larger ``episodes`` budget
may change. :class:`RunDirectory` reads and writes the typed records of the directory (layout in
:mod:`mpcmobo.experiment.storage`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mpcmobo.experiment import storage
from mpcmobo.experiment.records import Checkpoint, Reference
from mpcmobo.experiment.settings import Settings, load_settings, settings_to_toml

# what a resumed run may take from the settings it is given (the rest is the saved run's)
RESUME_CHANGES = ("workers", "backend", "episodes")


class StudyError(RuntimeError):
    """A study cannot run as asked (e.g. the output directory already holds another run)."""


class RunDirectory:
    """The directory of one study: its settings, reference and job checkpoints."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.config = self.path / "config.toml"
        self.reference_path = self.path / "reference.pkl"

    def holds_run(self) -> bool:
        return self.config.exists()

    def saved_settings(self, **overrides) -> Settings:
        """The run's saved settings (with ``overrides``, see :func:`load_settings`)."""
        if not self.holds_run():
            raise StudyError(f"nothing to resume: {self.config} does not exist")
        return load_settings(self.config, **overrides)

    # ------------------------------------------------------------------ opening
    def create(self, settings: Settings) -> Settings:
        """Start a new run here: the directory must be empty; every setting is saved."""
        if self.path.exists() and any(self.path.iterdir()):
            raise StudyError(
                f"{self.path} is not empty; choose a new --out directory or continue it with "
                "--resume"
            )
        resolved = settings.resolved()
        storage.atomic_write_text(self.config, settings_to_toml(resolved))
        return resolved

    def reopen(self, settings: Settings | None) -> Settings:
        """The saved settings, with the changes a resumed run may take from ``settings``; a
        larger budget is saved (the settings of the run from now on), a smaller one refused."""
        saved = self.saved_settings()
        if settings is None:
            return saved
        if settings.episodes < saved.episodes:
            raise StudyError(
                f"episodes: the run in {self.path} has a budget of {saved.episodes}; a resumed "
                f"run can be extended, not shortened (got {settings.episodes})"
            )
        changed = saved.model_copy(update={k: getattr(settings, k) for k in RESUME_CHANGES})
        if settings.episodes > saved.episodes:
            storage.atomic_write_text(self.config, settings_to_toml(changed))
        return changed

    # ------------------------------------------------------------------ records
    def reference(self) -> Reference | None:
        """The study-level reference, if it was computed."""
        if not self.reference_path.exists():
            return None
        return Reference.from_dict(storage.read_pickle(self.reference_path))

    def save_reference(self, reference: Reference) -> None:
        storage.write_pickle(self.reference_path, reference.to_dict())

    def checkpoint(self, learner: str, seed: int) -> Checkpoint | None:
        """The job's last checkpoint (None if it has not finished an episode)."""
        d = storage.load_checkpoint(self.path, learner, seed)
        return None if d is None else Checkpoint.from_dict(d)

    def save_checkpoint(self, ckpt: Checkpoint) -> None:
        storage.save_checkpoint(self.path, ckpt.learner, ckpt.seed, ckpt.to_dict())

    def incumbents(self, settings: Settings) -> list[tuple[str, int, int, np.ndarray]]:
        """(learner, seed, episodes done, incumbent after the last one) of every job of
        ``settings`` that has run an episode."""
        out = []
        for learner in settings.learners:
            for seed in settings.seeds:
                ckpt = self.checkpoint(learner, seed)
                if ckpt is not None and ckpt.rows:
                    out.append((learner, seed, len(ckpt.rows), ckpt.incumbent))
        return out


def open_run(
    out: str | Path, settings: Settings | None, resume: bool
) -> tuple[RunDirectory, Settings]:
    """The run directory ``out`` and the settings of the run in it: a new run (``settings``
    required, the directory empty) or, with ``resume``, the saved run (see
    :meth:`RunDirectory.reopen`)."""
    run_dir = RunDirectory(out)
    run_dir.path.mkdir(parents=True, exist_ok=True)
    if resume:
        return run_dir, run_dir.reopen(settings)
    if settings is None:
        raise StudyError("settings are required for a new study")
    return run_dir, run_dir.create(settings)
