"""Bayesian-optimisation learners: BO on f1 (EI) and MPC-RL-MOBO on f1..f4 (EHVI).

Both search the unit cube of the declared search space (log coordinates for the weights), start
from theta0 (the imperfect MPC) plus a small seeded Sobol design, never fit a NaN objective, and
save and restore their whole state exactly.

Two choices help them work from single noisy episodes (each one a setting, measured in
``docs/benchmarks.md``):

* start effects: with cycled starts (``EpisodeResult.start_id >= 0``) the GP of each
  log-modelled cost carries one offset per start (``start_effects``, see
  :mod:`mpcmobo.bo.groups`), so candidates run on different starts are compared fairly;
* a risk-averse incumbent: the lowest ``m + kappa s`` of the modelled f1 (``incumbent_kappa``;
  0 gives the plain lowest predicted f1).

Three more options are off by default because they made things worse on the CSTR (measured in
``docs/benchmarks.md``): ``noise_floor`` (a lower bound on the GPs' noise variance),
``confirm_runs = 2`` (a new best point is re-run on the next start before it becomes the
incumbent) and ``replicate_every = k`` (every k-th proposal re-runs the incumbent until it has
``max_replicates`` episodes).
"""

from __future__ import annotations

import numpy as np
from scipy.stats import qmc

from mpcmobo.bo import GPSurrogate, pareto_mask, propose_ehvi, propose_ei, reference_point
from mpcmobo.learners.base import EpisodeResult, Learner
from mpcmobo.systems.space import SearchSpace

OBJECTIVES = ("f1", "f2", "f3", "f4")


def reduced_effort(mc_samples: int, num_restarts: int, raw_samples: int) -> dict[str, int]:
    """Half the quasi-MC samples, restarts and raw samples of an EHVI search (at least 1
    each, and at least as many raw samples as restarts).

    On the CSTR's 600-observation data this makes a proposal 2.9x faster; over the first 50
    episodes of 10 seeds the halved search learned worse than the full one
    (``docs/benchmarks.md``, "EHVI effort"). The mobo learner therefore searches in full
    while data are few and switches after ``reduce_effort_after`` observations.
    """
    r = max(1, num_restarts // 2)
    return {
        "mc_samples": max(1, mc_samples // 2),
        "num_restarts": r,
        "raw_samples": max(r, raw_samples // 2),
    }


def search_effort(
    n: int, *, mc_samples: int, num_restarts: int, raw_samples: int, reduce_effort_after: int | None
) -> dict[str, int]:
    """The EHVI search settings of a proposal after ``n`` observations: ``mc_samples``,
    ``num_restarts`` and ``raw_samples`` as given, halved (:func:`reduced_effort`) from
    ``reduce_effort_after`` observations on (None: never)."""
    effort = {"mc_samples": mc_samples, "num_restarts": num_restarts, "raw_samples": raw_samples}
    if reduce_effort_after is not None and n >= reduce_effort_after:
        return reduced_effort(**effort)
    return effort


class _GPLearner(Learner):
    """Shared machinery: design, data, surrogate fit after each episode, incumbent."""

    outputs: tuple[int, ...] = (0,)

    def __init__(
        self,
        space: SearchSpace,
        theta0: np.ndarray,
        seed: int = 0,
        *,
        n_init: int = 5,
        refit_every: int = 10,
        refit_fraction: float = 0.1,
        log_outcomes: tuple[bool, ...] | None = None,
        num_restarts: int = 4,
        raw_samples: int = 256,
        maxiter: int = 100,
        start_effects: bool = True,
        incumbent_kappa: float = 1.0,
        replicate_every: int = 0,
        max_replicates: int = 3,
        confirm_runs: int = 1,
        noise_floor: float | None = None,
    ) -> None:
        super().__init__(space, theta0, seed)
        if replicate_every < 0 or max_replicates < 1:
            raise ValueError(
                "replicate_every must be >= 0 and max_replicates >= 1, got "
                f"{replicate_every} and {max_replicates}"
            )
        self.replicate_every, self.max_replicates = int(replicate_every), int(max_replicates)
        if confirm_runs < 1:
            raise ValueError(f"confirm_runs must be >= 1, got {confirm_runs}")
        self.confirm_runs = int(confirm_runs)
        self._challenger_z: np.ndarray | None = None
        if not np.isfinite(incumbent_kappa) or incumbent_kappa < 0:
            raise ValueError(f"incumbent_kappa must be a finite number >= 0, got {incumbent_kappa}")
        self.incumbent_kappa = float(incumbent_kappa)
        if n_init < 1:
            raise ValueError(f"n_init must be at least 1, got {n_init}")
        self.n_init = int(n_init)
        self.num_restarts, self.raw_samples, self.maxiter = num_restarts, raw_samples, maxiter
        m = len(self.outputs)
        log = (True,) * m if log_outcomes is None else tuple(log_outcomes)
        if len(log) != m:
            raise ValueError(f"log_outcomes needs {m} entries, got {len(log)}")
        # per-start offsets on the log-modelled costs, used when episodes cycle through fixed
        # starts (EpisodeResult.start_id >= 0); see "Start effects" in mpcmobo.bo.surrogate
        self.start_effects = bool(start_effects)
        self.surrogate = GPSurrogate(
            m,
            refit_every=refit_every,
            refit_fraction=refit_fraction,
            log_outcomes=log,
            group_outputs=log if self.start_effects else None,
            noise_floor=noise_floor,
        )
        # initial design: theta0, then scrambled Sobol points (seeded)
        z0 = space.to_unit(self.theta0)
        sob = qmc.Sobol(d=space.dim, scramble=True, seed=self.seed).random(
            max(1, 2 ** int(np.ceil(np.log2(max(1, n_init)))))
        )
        self.design = np.vstack([z0, sob])[: self.n_init]
        self.Z = np.zeros((0, space.dim))
        self.Y = np.zeros((0, m))
        self.grads = np.zeros((0, space.n_theta))
        self.starts = np.zeros(0, dtype=int)  # start index of each observation (-1: random)
        self._pre_fit_state: dict | None = None
        self._fitted = False
        self._incumbent_z = z0.copy()
        self._pre_fit_incumbent = z0.copy()

    # -------------------------------------------------------------- data
    def _theta(self, z: np.ndarray) -> np.ndarray:
        return self.space.from_unit(z, base=self.theta0)

    def _finite(self) -> np.ndarray:
        return np.all(np.isfinite(self.Y), axis=1)

    def observe(self, theta: np.ndarray, result: EpisodeResult) -> None:
        z = self.space.to_unit(self.space.clip(theta))
        y = np.asarray(result.objectives, dtype=float)[list(self.outputs)]
        self.Z = np.vstack([self.Z, z])
        self.Y = np.vstack([self.Y, y])  # NaN rows stay in the log, never in the fit
        g = np.asarray(result.grad, dtype=float)
        self.grads = np.vstack([self.grads, np.where(np.isfinite(g), g, 0.0)])
        self.starts = np.append(self.starts, int(result.start_id))
        self.n_observed += 1
        self._fit()

    def _fit(self) -> None:
        """Fit the GP(s) on the finite observations; the pre-fit state makes resume exact."""
        self._pre_fit_state = self.surrogate.state_dict()
        self._pre_fit_incumbent = self._incumbent_z.copy()
        if np.count_nonzero(self._finite()) < 2:
            self._fitted = False
            return
        self.surrogate.fit(self.Z, self.Y, groups=self.starts)
        self._fitted = True
        self._update_incumbent()

    def _runs(self, z: np.ndarray) -> int:
        """Number of finite episodes run with exactly ``z``."""
        return int(np.count_nonzero(np.all(self.Z == z, axis=1) & self._finite()))

    def _update_incumbent(self) -> None:
        """Among the observed points whose posterior means are Pareto-optimal (for one
        objective: all observed points), the one with the lowest predicted f1, judged
        risk-aversely by ``m + kappa * s`` with ``m, s`` the posterior mean and standard
        deviation of the modelled f1 (log f1 for a log output; ``kappa = 0``: the lowest
        predicted mean).

        Confirmation (``confirm_runs = r > 1``): a best point with fewer than ``r`` episodes is
        a *challenger*; the next proposal re-runs it (on the next start), and until then the
        incumbent is the best point that has ``r`` episodes, or the current incumbent. One
        lucky episode thus never becomes the deployed controller on its own.
        """
        ok = self._finite()
        Zf = self.Z[ok]
        mt, st = self.surrogate.posterior_model_space(Zf)
        mean, _ = self.surrogate.to_cost_space(mt, st)
        cand = np.flatnonzero(pareto_mask(mean)) if mean.shape[1] > 1 else np.arange(len(Zf))
        score = -mt[:, 0] + self.incumbent_kappa * st[:, 0]  # model space is maximised: -mt
        best = cand[int(np.argmin(score[cand]))]
        self._challenger_z = None
        if self.confirm_runs == 1:
            self._incumbent_z = Zf[best].copy()
            return
        # finite episodes run with each row's point (as _runs, for all rows at once)
        _, inverse, counts = np.unique(Zf, axis=0, return_inverse=True, return_counts=True)
        runs = counts[inverse.reshape(-1)]
        if runs[best] < self.confirm_runs:
            self._challenger_z = Zf[best].copy()
            current = self._incumbent_z
            eligible = np.flatnonzero((runs >= self.confirm_runs) | np.all(Zf == current, axis=1))
            if eligible.size:
                best = eligible[int(np.argmin(score[eligible]))]
            else:
                return  # keep the current incumbent (it has no finite episode yet)
        self._incumbent_z = Zf[best].copy()

    def incumbent(self) -> np.ndarray:
        return self._theta(self._incumbent_z)

    def _next_seed(self) -> int:
        return int(self.rng.integers(2**31 - 1))

    def propose(self) -> np.ndarray:
        n = self.Z.shape[0]
        if n < self.n_init:
            return self._theta(self.design[n])
        if not self._fitted:  # every observation so far failed: keep exploring the design
            return self._theta(self.rng.uniform(size=self.space.dim))
        if self._challenger_z is not None:
            return self._theta(self._challenger_z)
        if self._replicate_due(n):
            return self._theta(self._incumbent_z)
        return self._theta(self._acquire(self._next_seed()))

    def _replicate_due(self, n: int) -> bool:
        """Every ``replicate_every``-th proposal after the design re-runs the incumbent (on the
        next start) while it has fewer than ``max_replicates`` episodes: one lucky episode
        cannot stay the incumbent without confirmation (replication in noisy BO)."""
        k = self.replicate_every
        if k == 0 or (n - self.n_init) % k != k - 1:
            return False
        return self._runs(self._incumbent_z) < self.max_replicates

    def _acquire(self, seed: int) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    # -------------------------------------------------------------- state
    def state_dict(self) -> dict:
        d = super().state_dict()
        d.update(
            {
                "Z": self.Z.copy(),
                "Y": self.Y.copy(),
                "grads": self.grads.copy(),
                "starts": self.starts.copy(),
                "surrogate_pre_fit": self._pre_fit_state,
                "incumbent_z": self._incumbent_z.copy(),
                "incumbent_pre_fit": self._pre_fit_incumbent.copy(),
            }
        )
        return d

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.Z, self.Y = np.array(state["Z"], float), np.array(state["Y"], float)
        self.grads = np.array(state["grads"], float)
        self.starts = np.array(state.get("starts", np.full(len(self.Z), -1)), dtype=int)
        self._incumbent_z = np.array(state["incumbent_z"], float)
        self._pre_fit_incumbent = np.array(
            state.get("incumbent_pre_fit", state["incumbent_z"]), float
        )
        self._challenger_z = None
        self._fitted = False
        if state["surrogate_pre_fit"] is not None:
            # replay the last fit from the state it started from: same model, same counters
            self.surrogate.load_state_dict(state["surrogate_pre_fit"])
            self._incumbent_z = self._pre_fit_incumbent.copy()
            self._fit()


class BOLearner(_GPLearner):
    """Single-objective BO: a GP on f1 (eq. GP, mean_var) and log expected improvement (eq. EI)."""

    name = "bo"
    outputs = (0,)

    def _acquire(self, seed: int) -> np.ndarray:
        return propose_ei(
            self.surrogate,
            self.Z,
            self.Y,
            seed=seed,
            num_restarts=self.num_restarts,
            raw_samples=self.raw_samples,
            maxiter=self.maxiter,
        )


class MOBOLearner(_GPLearner):
    """MPC-RL-MOBO: one GP per objective f1..f4 and expected hypervolume improvement (eq. EHVI).

    The reference point is fixed once, from the initial design (its nadir plus ``ref_margin``
    times its range per objective, :func:`mpcmobo.bo.reference_point`), and never moves.
    ``hybrid_every = k > 0`` makes every k-th proposal a CDPG gradient step from the incumbent
    (the gradient observed in the incumbent's episode), uniting BO's global search with the
    gradient's local refinement (remark of section 4).

    The EHVI search (``mc_samples`` quasi-MC samples, ``num_restarts`` L-BFGS-B restarts from
    the best of ``raw_samples`` random points) is halved once ``reduce_effort_after``
    observations are in (None: never), see :meth:`search_effort`.
    """

    name = "mobo"
    outputs = (0, 1, 2, 3)

    def __init__(
        self,
        space: SearchSpace,
        theta0: np.ndarray,
        seed: int = 0,
        *,
        ref_margin: float = 0.1,
        mc_samples: int = 64,
        max_baseline: int = 32,
        reduce_effort_after: int | None = 100,
        method: str = "logehvi",
        hybrid_every: int = 0,
        hybrid_step: float = 0.05,
        log_outcomes: tuple[bool, ...] | None = (True, True, False, False),
        **options,
    ) -> None:
        super().__init__(space, theta0, seed, log_outcomes=log_outcomes, **options)
        if reduce_effort_after is not None and reduce_effort_after < 0:
            raise ValueError(f"reduce_effort_after must be >= 0 or None, got {reduce_effort_after}")
        self.reduce_effort_after = reduce_effort_after
        if hybrid_every < 0:
            raise ValueError(f"hybrid_every must be >= 0, got {hybrid_every}")
        self.ref_margin, self.mc_samples, self.max_baseline = ref_margin, mc_samples, max_baseline
        self.method = method
        self.hybrid_every, self.hybrid_step = int(hybrid_every), float(hybrid_step)
        self.ref_point: np.ndarray | None = None
        self.n_proposals = 0

    def _fit(self) -> None:
        if self.ref_point is None and self.Z.shape[0] >= self.n_init:
            ok = self._finite()
            if np.any(ok):
                self.ref_point = reference_point(self.Y[ok], margin=self.ref_margin)
        super()._fit()

    def propose(self) -> np.ndarray:
        n = self.Z.shape[0]
        self.n_proposals += 1
        if (
            n >= self.n_init
            and self._fitted
            and self.hybrid_every > 0
            and self.n_proposals % self.hybrid_every == 0
        ):
            step = self._gradient_step()
            if step is not None:
                return step
        return super().propose()

    def _gradient_step(self) -> np.ndarray | None:
        """A normalised CDPG step (eq. theta) from the incumbent, in unit coordinates."""
        dist = np.linalg.norm(self.Z - self._incumbent_z, axis=1)
        i = int(np.argmin(dist))
        g = self.grads[i]
        if not np.any(g):
            return None
        theta = self._theta(self._incumbent_z)
        gz = g[self.space.free] * self.space.dtheta_dz(theta)
        norm = np.max(np.abs(gz))
        if not np.isfinite(norm) or norm == 0:
            return None
        return self._theta(np.clip(self._incumbent_z - self.hybrid_step * gz / norm, 0, 1))

    def search_effort(self, n: int) -> dict[str, int]:
        """The EHVI search settings of this learner's proposal after ``n`` observations
        (:func:`search_effort`)."""
        return search_effort(
            n,
            mc_samples=self.mc_samples,
            num_restarts=self.num_restarts,
            raw_samples=self.raw_samples,
            reduce_effort_after=self.reduce_effort_after,
        )

    def _acquire(self, seed: int) -> np.ndarray:
        ref = self.ref_point
        if ref is None:
            ref = reference_point(self.Y[self._finite()], margin=self.ref_margin)
        return propose_ehvi(
            self.surrogate,
            self.Z,
            self.Y,
            ref,
            seed=seed,
            **self.search_effort(self.Z.shape[0]),
            max_baseline=self.max_baseline,
            method=self.method,
            maxiter=self.maxiter,
        )

    def state_dict(self) -> dict:
        d = super().state_dict()
        d["ref_point"] = None if self.ref_point is None else self.ref_point.copy()
        d["n_proposals"] = self.n_proposals
        return d

    def load_state_dict(self, state: dict) -> None:
        self.ref_point = None if state["ref_point"] is None else np.array(state["ref_point"])
        self.n_proposals = int(state["n_proposals"])
        super().load_state_dict(state)


class HybridLearner(MOBOLearner):
    """MOBO with every ``hybrid_every``-th proposal a CDPG step from the incumbent (default 3)."""

    name = "hybrid"

    def __init__(self, space, theta0, seed=0, *, hybrid_every: int = 3, **options) -> None:
        super().__init__(space, theta0, seed, hybrid_every=hybrid_every, **options)
