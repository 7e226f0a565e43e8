"""What a GP learner has seen: one row per episode, as plain arrays.

Each row holds the episode's theta as a point ``z`` of the unit cube of the search space, its
modelled objectives (f1..f4 or f1 alone; NaN rows are kept and never fitted), its CDPG
gradient, the index of its start in the study's cycle (-1 under random starts), its start
cost (theta0's mean stage cost from its initial state on the MPC's own model; NaN where not
computed), its plain mean stage cost and its replay (initial state and exploration: what a
twin predicts the cost from), what kind of proposal it was (``"design"``, ``"search"``,
``"verify"``, ``"baseline"``, ``"gradient"``, ``"seed"``; ``"simulated"``: a candidate the
exploration budget refused, its episode simulated on the identified model; ``"bounded"``: the
model switch's stand-in for a plant episode of the twin's theta that the budget kept off the
plant, its simulated cost times the model's spread) and its group (MPC-RL's verification
block; -1: none). Every learner that judges deployments keeps its episodes here, and the judge
(:mod:`mpcmobo.learners.judge`) reads them. Appending is the only change; the queries answer
what the deployment policies ask: the rows of a theta, the starts it was run from, how many
episodes it has, all of them of plant episodes and their bounded stand-ins (a simulated row
is the GP's, never evidence).
"""

from __future__ import annotations

import numpy as np

from mpcmobo.learners.episode import Replay, replays_from_state, replays_state

__all__ = ["BOUNDED", "SIMULATED", "Evidence", "theta_key"]

SIMULATED = "simulated"  # the kind of a row simulated on the identified model
# the kind of a pessimistic stand-in for a plant episode the exploration budget refused: the
# episode simulated on the identified model, its costs times the model's spread
BOUNDED = "bounded"


def theta_key(z: np.ndarray) -> bytes:
    """The identity of a unit-cube theta, up to its round trip through theta (1e-9)."""
    return np.round(np.asarray(z, float), 9).tobytes()


def _keys(Z: np.ndarray) -> np.ndarray:
    """:func:`theta_key` of each row of ``Z`` (n, d), as an array of n raw byte strings (NumPy
    voids: trailing zero bytes kept), to compare with ``np.void(theta_key(z))``."""
    rounded = np.ascontiguousarray(np.round(np.asarray(Z, float), 9))
    return rounded.view(np.dtype((np.void, 8 * rounded.shape[1]))).reshape(-1)


class Evidence:
    """The episodes a learner has observed (see the module docstring)."""

    def __init__(self, dim: int, n_theta: int, n_outputs: int) -> None:
        self.Z = np.zeros((0, dim))
        self.Y = np.zeros((0, n_outputs))
        self.grads = np.zeros((0, n_theta))
        self.starts = np.zeros(0, dtype=int)
        self.start_costs = np.zeros(0)
        self.costs = np.zeros(0)  # the plain mean stage cost (J's measure)
        self.replays: list[Replay | None] = []  # what a twin replays (None: unknown)
        self.kinds: list[str] = []
        self.groups = np.zeros(0, dtype=int)

    def __len__(self) -> int:
        return int(self.Z.shape[0])

    def append(
        self,
        z: np.ndarray,
        y: np.ndarray,
        grad: np.ndarray,
        start: int,
        start_cost: float,
        kind: str,
        cost: float = float("nan"),
        replay: Replay | None = None,
        group: int = -1,
    ) -> None:
        """One more episode (a non-finite gradient entry is stored as 0); ``cost`` and
        ``replay`` its plain mean stage cost and what a twin replays, where known; ``group``
        its verification block (-1: none)."""
        g = np.asarray(grad, dtype=float)
        self.Z = np.vstack([self.Z, np.asarray(z, float)])
        self.Y = np.vstack([self.Y, np.asarray(y, float)])
        self.grads = np.vstack([self.grads, np.where(np.isfinite(g), g, 0.0)])
        self.starts = np.append(self.starts, int(start))
        self.start_costs = np.append(self.start_costs, float(start_cost))
        self.costs = np.append(self.costs, float(cost))
        self.replays.append(replay)
        self.kinds.append(str(kind))
        self.groups = np.append(self.groups, int(group))

    # ------------------------------------------------------------------ queries
    def finite(self) -> np.ndarray:
        """Mask of the rows whose modelled objectives are all finite."""
        return np.all(np.isfinite(self.Y), axis=1)

    def plant(self) -> np.ndarray:
        """Mask of the rows of plant episodes and their ``"bounded"`` stand-ins (not
        ``"simulated"``)."""
        return np.array([k != SIMULATED for k in self.kinds], dtype=bool)

    def rows_of(self, z: np.ndarray) -> np.ndarray:
        """The finite rows of plant episodes run with the unit-cube theta ``z``."""
        rows = np.flatnonzero(self.finite() & self.plant())
        return rows[_keys(self.Z[rows]) == np.void(theta_key(z))]

    def group(self, g: int) -> np.ndarray:
        """The rows of group ``g``, finite or not, in order."""
        return np.flatnonzero(self.groups == g)

    def runs(self, z: np.ndarray) -> int:
        """Finite episodes run with ``z``."""
        return len(self.rows_of(z))

    def starts_of(self, z: np.ndarray) -> set[int]:
        """The cycled starts ``z`` has finite episodes from."""
        return set(self.starts[self.rows_of(z)].tolist())

    def failed(self) -> set[bytes]:
        """The thetas (their :func:`theta_key`) with an episode whose cost is not finite: the
        plant diverged or the episode broke."""
        return {theta_key(z) for z in self.Z[~np.isfinite(self.Y[:, 0])]}

    def ran(self, z: np.ndarray) -> bool:
        """Whether ``z`` was run before the last episode."""
        key = theta_key(z)
        return any(theta_key(zz) == key for zz in self.Z[:-1])

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """The arrays, as copies."""
        return {
            "Z": self.Z.copy(),
            "Y": self.Y.copy(),
            "grads": self.grads.copy(),
            "starts": self.starts.copy(),
            "start_costs": self.start_costs.copy(),
            "costs": self.costs.copy(),
            "replays": replays_state(self.replays),
            "kinds": list(self.kinds),
            "groups": self.groups.copy(),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`."""
        self.Z = np.array(state["Z"], float).reshape(-1, self.Z.shape[1])
        self.Y = np.array(state["Y"], float).reshape(-1, self.Y.shape[1])
        self.grads = np.array(state["grads"], float).reshape(-1, self.grads.shape[1])
        self.starts = np.array(state["starts"], dtype=int)
        self.start_costs = np.array(state["start_costs"], float)
        self.kinds = list(state["kinds"])
        self.costs = np.array(state["costs"], float)
        self.replays = replays_from_state(state["replays"])
        self.groups = np.array(state["groups"], dtype=int)
        n = len(self.Z)
        lengths = (len(self.Y), len(self.grads), len(self.starts), len(self.kinds), len(self.costs))
        if any(k != n for k in (*lengths, len(self.replays), len(self.groups))):
            raise ValueError("the learner's evidence arrays have different lengths")
