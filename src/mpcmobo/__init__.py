"""mpcmobo: tune a model predictive controller with MPC-based RL, BO and multi-objective BO.

The subpackages follow the paper's pipeline (``systems -> mpc -> rl -> bo -> learners ->
experiment``); ``mpcmobo.__version__`` is the installed distribution's version.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__: str = version("mpcmobo")
except PackageNotFoundError:  # pragma: no cover - a source tree that was never installed
    __version__ = "0+unknown"
"""The installed distribution's version (``importlib.metadata``); ``mpcmobo --version``."""

__all__ = ["__version__"]
