"""MPC-RL-MOBO and the hybrid: one GP per objective f1..f4 and expected hypervolume
improvement (eq. EHVI), and the hybrid's CDPG steps among the EHVI's proposals.

f1 and f2 are modelled in log, f3 and f4 as they are. The hypervolume's reference point is
fixed once, from the initial design (its worst value per objective plus ``ref_margin`` times
its range, :func:`mpcmobo.bo.reference_point`). The EHVI search is halved from
``reduce_effort_after`` episodes on (:func:`search_effort`). The hybrid makes every
``gradient_every``-th proposal a normalised CDPG step (eq. theta) from the deployed theta along
the gradient of its nearest episode, uniting BO's global search with the gradient's local
refinement (the remark of section 4 of the paper).
"""

from __future__ import annotations

from dataclasses import replace
from typing import ClassVar

import numpy as np

from mpcmobo.bo import AcqfSearch, EHVIOptions, propose_ehvi, reference_point
from mpcmobo.learners.base import Starts
from mpcmobo.learners.gp import GPLearner
from mpcmobo.learners.options import BOOptions, HybridOptions, MOBOOptions
from mpcmobo.systems.space import SearchSpace

__all__ = ["HybridLearner", "MOBOLearner", "search_effort"]


def search_effort(
    n: int, options: EHVIOptions, search: AcqfSearch, reduce_after: int
) -> tuple[EHVIOptions, AcqfSearch]:
    """The EHVI options and search after ``n`` episodes: as given, and from ``reduce_after``
    on with half the quasi-MC samples, restarts and raw samples (at least one each, and at
    least as many raw samples as restarts)."""
    if n < reduce_after:
        return options, search
    r = max(1, search.num_restarts // 2)
    return (
        replace(options, mc_samples=max(1, options.mc_samples // 2)),
        replace(search, num_restarts=r, raw_samples=max(r, search.raw_samples // 2)),
    )


class MOBOLearner(GPLearner):
    """MPC-RL-MOBO: one GP per objective f1..f4 and log expected hypervolume improvement."""

    name = "mobo"
    outputs = (0, 1, 2, 3)
    log_outputs = (True, True, False, False)
    options_class: ClassVar[type[BOOptions]] = MOBOOptions
    options: MOBOOptions

    def __init__(
        self,
        space: SearchSpace,
        theta0: np.ndarray,
        seed: int = 0,
        options: MOBOOptions | None = None,
        *,
        starts: Starts | None = None,
    ) -> None:
        super().__init__(space, theta0, seed, options, starts=starts)
        self.ehvi = EHVIOptions(mc_samples=self.options.search.mc_samples)
        self.ref_point_: np.ndarray | None = None

    def _before_fit(self) -> None:
        """The reference point, once the initial design is in."""
        ev = self.evidence_
        if self.ref_point_ is None and len(ev) - self.n_seeded_ >= self.options.n_init:
            ok = ev.finite()
            if np.any(ok):
                self.ref_point_ = reference_point(
                    self._model_Y()[ok], margin=self.options.ref_margin
                )

    def _acquire(self, seed: int) -> np.ndarray:
        ref = self.ref_point_
        if ref is None:
            ref = reference_point(
                self._model_Y()[self.evidence_.finite()], margin=self.options.ref_margin
            )
        options, search = search_effort(
            len(self.evidence_), self.ehvi, self.search, self.options.search.reduce_effort_after
        )
        return propose_ehvi(
            self.surrogate,
            self.evidence_.Z,
            self._model_Y(),
            ref,
            seed=seed,
            options=options,
            search=search,
            box=self._trust_box(),
        )

    def state_dict(self) -> dict:
        """The base state plus the reference point."""
        d = super().state_dict()
        d["ref_point"] = None if self.ref_point_ is None else self.ref_point_.copy()
        return d

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict`."""
        self._check_name(state)
        self.ref_point_ = None if state["ref_point"] is None else np.array(state["ref_point"])
        super().load_state_dict(state)


class HybridLearner(MOBOLearner):
    """MOBO with every ``gradient_every``-th proposal a CDPG step from the deployed theta."""

    name = "hybrid"
    options_class: ClassVar[type[BOOptions]] = HybridOptions
    options: HybridOptions

    def __init__(
        self,
        space: SearchSpace,
        theta0: np.ndarray,
        seed: int = 0,
        options: HybridOptions | None = None,
        *,
        starts: Starts | None = None,
    ) -> None:
        super().__init__(space, theta0, seed, options, starts=starts)
        self.n_proposals_ = 0

    def propose(self) -> np.ndarray:
        """The EHVI's proposal or, every ``gradient_every``-th time once the GP is fitted and
        no candidate waits for verification, a CDPG step."""
        self.n_proposals_ += 1
        due = (
            len(self.evidence_) - self.n_seeded_ >= self.options.n_init
            and self.fitted_
            and self.n_proposals_ % self.options.gradient_every == 0
        )
        if self.verify_z_ is None and due:
            z = self._gradient_step()
            if z is not None:
                return self._proposed("gradient", z)
        return super().propose()

    def _gradient_step(self) -> np.ndarray | None:
        """A normalised CDPG step (eq. theta) from the deployed theta in unit coordinates,
        along the gradient of its nearest episode, clipped to the trust region; None without a
        usable gradient."""
        ev = self.evidence_
        row = int(np.argmin(np.linalg.norm(ev.Z - self.deployed_z_, axis=1)))
        G = ev.grads[[row]]
        G = G[np.any(G != 0, axis=1)]  # a non-finite gradient is stored as 0
        if not len(G):
            return None
        theta = self.theta_of(self.deployed_z_)
        gz = G.mean(axis=0)[self.space.free] * self.space.dtheta_dz(theta)
        norm = np.max(np.abs(gz))
        if not np.isfinite(norm) or norm == 0:
            return None
        lo, hi = self._trust_box() or (0.0, 1.0)
        return np.clip(self.deployed_z_ - self.options.gradient_step * gz / norm, lo, hi)

    def state_dict(self) -> dict:
        """The base state plus the number of proposals."""
        d = super().state_dict()
        d["n_proposals"] = self.n_proposals_
        return d

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict`."""
        self._check_name(state)
        self.n_proposals_ = int(state["n_proposals"])
        super().load_state_dict(state)
