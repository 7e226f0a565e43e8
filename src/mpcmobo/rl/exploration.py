r"""Exploration noise added to the MPC policy during closed-loop episodes.

The applied input is :math:`u_k = \mathrm{clip}(\pi_\theta(x_k) + e_k, u_{lb}, u_{ub})`, with
:math:`e_k \sim \mathcal N(0, \mathrm{diag}(\sigma_e^2))` i.i.d. over the steps of an episode.
The exploration makes the compatible features :math:`\Psi_k = \nabla_\theta\pi_k (u_k - \pi_k)`
non-zero, without which w (eq. lstdq_update) is not identifiable.

The standard deviation of episode e is :math:`\sigma_e = \max(\sigma_0\,d^{e}, \sigma_{min})`
(per input), with decay factor d (``decay=1`` keeps it constant). The clipping is done by the
rollout (``mpcmobo.mpc``), not here.
"""

from __future__ import annotations

import copy

import numpy as np


class GaussianExploration:
    """Gaussian input noise with a per-episode geometric decay of its standard deviation.

    Parameters
    ----------
    std:
        (nu,) standard deviation per input at episode 0 (a scalar is broadcast to one input).
    decay:
        Factor applied per episode, in (0, 1]; 1 keeps the noise constant.
    min_std:
        Floor on the standard deviation (scalar or (nu,)).

    Sampling always draws ``nu`` standard normals from the generator, also when the standard
    deviation is zero, so the random stream (e.g. the initial states drawn from the same
    generator) does not depend on the noise level: candidates compared on common random numbers.
    """

    def __init__(
        self,
        std: np.ndarray | float,
        decay: float = 1.0,
        min_std: np.ndarray | float = 0.0,
        episode: int = 0,
    ) -> None:
        std = np.atleast_1d(np.asarray(std, dtype=float)).reshape(-1)
        if np.any(std < 0) or not np.all(np.isfinite(std)):
            raise ValueError("std must be finite and >= 0")
        if not (0.0 < decay <= 1.0):
            raise ValueError("decay must be in (0, 1]")
        min_std = np.broadcast_to(np.asarray(min_std, dtype=float), std.shape).copy()
        if np.any(min_std < 0) or not np.all(np.isfinite(min_std)):
            raise ValueError("min_std must be finite and >= 0")
        self.std0 = std
        self.decay = float(decay)
        self.min_std = min_std
        self.episode = int(episode)

    @property
    def nu(self) -> int:
        """Number of inputs."""
        return int(self.std0.shape[0])

    def std_at(self, episode: int) -> np.ndarray:
        """(nu,) standard deviation of episode ``episode``: max(std0 * decay**e, min_std)."""
        return np.maximum(self.std0 * self.decay ** max(0, int(episode)), self.min_std)

    @property
    def std(self) -> np.ndarray:
        """(nu,) standard deviation of the current episode."""
        return self.std_at(self.episode)

    def at_episode(self, episode: int) -> GaussianExploration:
        """A copy set to episode ``episode`` (the original is unchanged)."""
        other = copy.deepcopy(self)
        other.episode = int(episode)
        return other

    def sample(self, rng: np.random.Generator, k: int = 0) -> np.ndarray:
        """(nu,) noise e_k for step ``k`` of the current episode; i.i.d. over k, from ``rng``."""
        del k  # the noise is white: the step index does not change the distribution
        return rng.standard_normal(self.nu) * self.std

    def state_dict(self) -> dict:
        """The noise settings and the current episode."""
        return {
            "std": self.std0.tolist(),
            "decay": self.decay,
            "min_std": self.min_std.tolist(),
            "episode": self.episode,
        }

    @classmethod
    def from_state_dict(cls, d: dict) -> GaussianExploration:
        """The exploration from a :meth:`state_dict`."""
        return cls(d["std"], d["decay"], d["min_std"], d["episode"])

    def __repr__(self) -> str:
        return (
            f"GaussianExploration(std={self.std0.tolist()}, decay={self.decay}, "
            f"min_std={self.min_std.tolist()}, episode={self.episode})"
        )
