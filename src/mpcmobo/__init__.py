"""mpcmobo: tune a model predictive controller with MPC-based RL, BO and multi-objective BO.

The subpackages follow the pipeline (``systems -> mpc -> identify -> rl -> bo -> learners ->
experiment``); ``mpcmobo.__version__`` is the installed distribution's version and
``mpcmobo.Tuner`` the ask-and-tell tuner of a real plant (:mod:`mpcmobo.experiment.tuner`,
imported when first used). Importing the package registers the paper's CSTR plant with
gymnasium as ``mpcmobo/CSTR-v0`` (and the test bed ``mpcmobo/LQ-v0``), lazily: the entry points
are strings, nothing heavy is imported here.
"""

from importlib.metadata import PackageNotFoundError, version
from typing import Any

import gymnasium as _gymnasium

try:
    __version__: str = version("mpcmobo")
except PackageNotFoundError:  # pragma: no cover - a source tree that was never installed
    __version__ = "0+unknown"
"""The installed distribution's version (``importlib.metadata``); ``mpcmobo --version``."""

__all__ = ["Tuner", "__version__"]


def __getattr__(name: str) -> Any:
    """``mpcmobo.Tuner``, imported on first use (it pulls in CasADi, torch and BoTorch)."""
    if name == "Tuner":
        from mpcmobo.experiment.tuner import Tuner

        return Tuner
    raise AttributeError(f"module 'mpcmobo' has no attribute {name!r}")


def __dir__() -> list[str]:
    """The module's names, ``Tuner`` with them (it is imported on first use)."""
    return sorted({*globals(), *__all__})


for _id, _name, _steps in (("mpcmobo/CSTR-v0", "cstr", 60), ("mpcmobo/LQ-v0", "lq", 30)):
    if _id not in _gymnasium.registry:
        _gymnasium.register(
            id=_id,
            entry_point="mpcmobo.systems.plant:SystemPlant",
            kwargs={"system": _name},
            max_episode_steps=_steps,
        )
