"""Which of its own iterates MPC-RL deploys: a pooled, start-adjusted comparison (issue 11,
item 3).

MPC-RL keeps stepping from its iterate; the theta it deploys (its incumbent, what J_eval
measures) changes only when the evidence of its own episodes says that another iterate it has
run is better in expectation over the initial states. One episode is a poor witness (on the CSTR
the log cost of one theta spans a factor of e^3 across starts), so the judge pools:

* **nearby iterates**: the value of iterate j is a kernel-weighted mean over the episodes run
  near it, ``a_j = sum_k w_jk r_k / sum_k w_jk`` with ``w_jk = exp(-|z_k - z_j|^2 / (2 h^2))``,
  ``z`` the unit-cube theta and ``h`` the ``bandwidth`` (a length in the unit cube, so
  scale-free). Successive steps are small, so each iterate borrows the evidence of its
  neighbours on the path.
* **the start**: ``r_k = y_k - phi(c_k)^T beta`` removes the part of the episode's log cost
  ``y_k = log f1_k`` that its initial state explains, ``phi`` the full quadratic features of the
  standardised initial state and ``beta`` the (slightly ridged) estimate of the partially linear
  model ``y = a(z) + phi(c)^T beta + e`` with the kernel smoother for ``a`` (Speckman's:
  regress ``(I - S) y`` on ``(I - S) phi``). Under random
  starts this puts iterates run from easy and from hard starts on the same footing; with
  cycled starts it does the same job as per-start offsets.

The deployed theta changes from ``d`` to the best candidate ``j`` (lowest ``a_j + z_p se_j``,
among iterates with an effective number of episodes of at least ``min_evidence``) only when
``(a_d - a_j) / (sigma |w~_j - w~_d|) >= z_p``, ``w~`` the normalised weights (the exact standard
error of the difference of two weighted means of the same residuals, shared episodes included),
``sigma`` the residual standard deviation and ``z_p`` the standard normal quantile of
``confidence``. It never uses J_eval or the evaluation starts.

Everything is recomputed from the data at each episode (O(n^2) for n episodes), so the judge's
state is its data: resume is exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import norm


def check_confidence(name: str, value: float, unset: str = "") -> float:
    """``value`` as a float if it is a confidence in [0.5, 1) (a probability that a candidate is
    better, or safe), else a ``ValueError`` naming the option ``name``; ``unset`` says what
    else the option accepts (the learners check None and 0 themselves)."""
    if not 0.5 <= float(value) < 1:
        raise ValueError(f"{name} must be in [0.5, 1){unset}, got {value}")
    return float(value)


def quadratic_features(C: np.ndarray) -> np.ndarray:
    """(n, q): the columns of C and their pairwise products (squares included)."""
    C = np.atleast_2d(C)
    n, d = C.shape
    cols = [C[:, i] for i in range(d)]
    cols += [C[:, i] * C[:, j] for i in range(d) for j in range(i, d)]
    return np.column_stack(cols) if cols else np.zeros((n, 0))


@dataclass(frozen=True)
class PooledJudge:
    """Options of the pooled judge (see the module docstring)."""

    confidence: float = 0.95
    bandwidth: float = 0.1
    min_evidence: float = 3.0
    ridge: float = 1.0

    def __post_init__(self) -> None:
        check_confidence("deploy_confidence", self.confidence)
        if not self.bandwidth > 0:
            raise ValueError(f"deploy_bandwidth must be positive, got {self.bandwidth}")
        if not self.min_evidence >= 1:
            raise ValueError(f"min_evidence must be >= 1, got {self.min_evidence}")

    # ----------------------------------------------------------------- the fit
    def weights(self, Z: np.ndarray, at: np.ndarray) -> np.ndarray:
        """(m, n) kernel weights of the n episodes (rows of Z) for the m points ``at``."""
        d2 = ((at[:, None, :] - Z[None, :, :]) ** 2).sum(-1)
        return np.exp(-0.5 * d2 / self.bandwidth**2)

    def fit(self, Z: np.ndarray, X0: np.ndarray, f1: np.ndarray) -> dict:
        """The start adjustment and the residual scale from all episodes: returns ``r`` (the
        start-adjusted log costs), ``sigma`` and ``beta``."""
        y = self.log_costs(f1)
        W = self.weights(Z, Z)
        S = W / W.sum(1, keepdims=True)  # the smoother at the episodes' own thetas
        F = self.context_features(X0)
        beta = np.zeros(F.shape[1])
        if F.shape[1] and len(y) > F.shape[1] + 2:
            # the partially linear model's estimate (Speckman): regress the part of y that the
            # smoother along the iterates does not explain on the same part of the features
            Ft, yt = F - S @ F, y - S @ y
            beta = np.linalg.solve(Ft.T @ Ft + self.ridge * np.eye(F.shape[1]), Ft.T @ yt)
        r = y - F @ beta
        resid = r - S @ r
        dof = max(len(y) - np.trace(S) - F.shape[1], 1.0)
        sigma = float(np.sqrt(resid @ resid / dof)) if len(y) > 1 else np.inf
        return {"r": r, "sigma": sigma, "beta": beta}

    @staticmethod
    def log_costs(f1: np.ndarray) -> np.ndarray:
        """log f1; an episode without a finite cost counts as the worst one seen (a failure is
        evidence against its theta, never for it)."""
        f1 = np.asarray(f1, float)
        ok = np.isfinite(f1) & (f1 > 0)
        y = np.full(f1.shape, np.nan)
        y[ok] = np.log(f1[ok])
        worst = np.max(y[ok]) if ok.any() else 0.0
        return np.where(ok, y, worst)

    @staticmethod
    def context_features(X0: np.ndarray) -> np.ndarray:
        """Quadratic features of the initial states, standardised over the episodes (columns
        without spread are dropped)."""
        X0 = np.atleast_2d(np.asarray(X0, float))
        if X0.shape[1] == 0 or len(X0) < 2:
            return np.zeros((len(X0), 0))
        sd = X0.std(0)
        keep = sd > 0
        C = (X0[:, keep] - X0[:, keep].mean(0)) / sd[keep]
        F = quadratic_features(C)
        F = F - F.mean(0)
        fs = F.std(0)
        return F[:, fs > 0] / fs[fs > 0]

    # ----------------------------------------------------------------- the decision
    def choose(
        self, Z: np.ndarray, X0: np.ndarray, f1: np.ndarray, current: np.ndarray
    ) -> np.ndarray:
        """The deployed unit-cube theta after the episodes (Z, X0, f1): ``current`` unless an
        iterate in Z is better with probability ``confidence`` (see the module docstring)."""
        if len(Z) < 2:
            return current
        fit = self.fit(Z, X0, f1)
        if not np.isfinite(fit["sigma"]) or fit["sigma"] <= 0:
            return current
        cand = np.unique(Z, axis=0)
        W = self.weights(Z, np.vstack([current[None, :], cand]))
        n_eff = W.sum(1) ** 2 / (W**2).sum(1)
        Wn = W / W.sum(1, keepdims=True)
        a = Wn @ fit["r"]
        se = fit["sigma"] * np.sqrt((Wn**2).sum(1))
        zp = float(norm.ppf(self.confidence))
        score = np.where(n_eff[1:] >= self.min_evidence, a[1:] + zp * se[1:], np.inf)
        if not np.isfinite(score).any():
            return current
        j = int(np.argmin(score))
        if np.array_equal(cand[j], current):
            return current
        sd = fit["sigma"] * np.linalg.norm(Wn[1 + j] - Wn[0])
        if sd > 0 and (a[0] - a[1 + j]) / sd >= zp:
            return cand[j].copy()
        return current
