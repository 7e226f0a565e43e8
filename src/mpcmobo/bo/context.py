"""The initial state as a context of the surrogate (issue 11, items 1-2).

An episode's outcomes depend on theta and on the initial state x0, which the learner observes
but does not choose. With ``context = "x0"`` the GPs model each outcome over ``(z, c)``: ``z``
the unit-cube theta, ``c = (x0 - x0_lb) / (x0_ub - x0_lb)`` the initial state scaled to the
system's initial-state box. What is searched and deployed is the expectation over the
initial-state distribution,

    J(theta) = E_x0[f(theta, x0)]  ~  (1/K) sum_k f(theta, x0_k),

with ``x0_1..x0_K`` a fixed sample drawn from that distribution with its own seed (never the
evaluation starts). BoTorch provides the pieces: :class:`~botorch.models.transforms.input.
AppendFeatures` appends the K contexts to every candidate (a ``q x d`` batch becomes a
``q K x (d + d_c)`` batch on one joint posterior), and a :class:`~botorch.acquisition.
multi_objective.multi_output_risk_measures.MultiOutputExpectation` averages the K samples of
each candidate. The average is taken in cost space: a log-modelled output ``t = -log(y + c)``
averages as ``-log(mean_k exp(-t_k))`` (log-mean-exp), not as the mean of the logs.

Safety (item 2): the per-episode plant violation is one more modelled output; a candidate is
*safe* when the ``safety_confidence`` quantile of its expected violation over the contexts is
at most ``violation_budget``. :func:`violation_constraint` is the same condition as a BoTorch
outcome constraint (negative = feasible) for a constrained (log) EHVI / EI.

Without a context (``contexts`` of zero columns) everything reduces to K = 1 and the plain
surrogate: the safety constraint and the deployment rule then work on theta alone.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import gpytorch
import numpy as np
import torch
from botorch.acquisition.acquisition import AcquisitionFunction
from botorch.acquisition.multi_objective.multi_output_risk_measures import (
    MultiOutputExpectation,
)
from botorch.models.model import Model
from botorch.models.transforms.input import AppendFeatures
from botorch.posteriors import Posterior

from mpcmobo.bo.groups import DTYPE, MAX_CHOLESKY

if TYPE_CHECKING:
    from mpcmobo.bo.acquisition import AcqfSearch
    from mpcmobo.bo.surrogate import GPSurrogate

__all__ = [
    "ContextModel",
    "ContextSpec",
    "ContextExpectation",
    "context_posterior",
    "expected_outcome_means",
    "expected_outcome_samples",
    "violation_constraint",
    "with_contexts",
]

# the context sample's own random stream (SeedSequence entropy), apart from the evaluation
# starts (settings.evaluation.seed) and the learning runs' streams
CONTEXT_STREAM = 11


@dataclass(frozen=True)
class ContextSpec:
    """The context box (the system's initial-state box) and a fixed pool of initial states drawn
    from the initial-state distribution with their own seed.

    ``violation_floor`` is the absolute floor of the default violation budget: 0.1% of the
    summed widths of the finite state bounds (per episode), in the units of
    ``system.constraint_violation``.
    """

    lb: np.ndarray
    ub: np.ndarray
    pool: np.ndarray  # (P, nx) initial states
    violation_floor: float = 0.0
    seed: int = 0

    @classmethod
    def from_system(cls, system: Any, seed: int = 0, pool_size: int = 256) -> ContextSpec:
        """The system's initial-state box and a pool of ``pool_size`` initial states drawn with
        ``seed`` (a stream of its own)."""
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), CONTEXT_STREAM]))
        pool = np.array([system.sample_initial_state(rng) for _ in range(pool_size)])
        span = np.asarray(system.x_ub, float) - np.asarray(system.x_lb, float)
        floor = 1e-3 * float(np.sum(span[np.isfinite(span)]))
        return cls(
            np.asarray(system.x0_lb, float).copy(),
            np.asarray(system.x0_ub, float).copy(),
            pool,
            violation_floor=floor,
            seed=int(seed),
        )

    def __post_init__(self) -> None:
        lb, ub = np.asarray(self.lb, float), np.asarray(self.ub, float)
        if lb.shape != ub.shape or lb.ndim != 1 or not np.all(np.isfinite(lb) & np.isfinite(ub)):
            raise ValueError("ContextSpec: lb and ub must be finite vectors of the same length")
        if np.any(ub < lb):
            raise ValueError("ContextSpec: a lower bound exceeds its upper bound")
        pool = np.asarray(self.pool, float)
        if pool.ndim != 2 or pool.shape[1] != lb.shape[0] or pool.shape[0] < 1:
            raise ValueError("ContextSpec: pool must be (P, nx) initial states, P >= 1")

    @property
    def dim(self) -> int:
        """Number of context coordinates (the state dimension)."""
        return int(np.asarray(self.lb).shape[0])

    def unit(self, x0: np.ndarray) -> np.ndarray:
        """x0 scaled to the initial-state box (a zero-width coordinate maps to 0.5)."""
        lb, ub = np.asarray(self.lb, float), np.asarray(self.ub, float)
        span = ub - lb
        x0 = np.asarray(x0, float)
        safe = np.where(span > 0, span, 1.0)
        return np.where(span > 0, (x0 - lb) / safe, 0.5)

    def sample(self, n: int) -> np.ndarray:
        """The first ``n`` states of the pool, scaled (n, nx): the fixed integration sample."""
        if not 1 <= n <= len(self.pool):
            raise ValueError(f"n_contexts must be in [1, {len(self.pool)}], got {n}")
        return self.unit(np.asarray(self.pool, float)[:n])


class ContextModel(Model):
    """A fitted model on ``(z, c)`` seen as a model on ``z``: its posterior at a ``b x q x d``
    batch is the base model's joint posterior at the ``b x (q K) x (d + d_c)`` batch made by
    :class:`AppendFeatures` (K fixed contexts per candidate). With no context columns it is
    the base model itself (K = 1)."""

    def __init__(self, base: Model, contexts: np.ndarray) -> None:
        super().__init__()
        self.base = base
        C = np.asarray(contexts, dtype=np.float64)
        self.n_w = max(1, C.shape[0]) if C.ndim == 2 and C.shape[1] > 0 else 1
        self.append = (
            AppendFeatures(feature_set=torch.as_tensor(C, dtype=DTYPE))
            if C.ndim == 2 and C.shape[1] > 0
            else None
        )

    @property
    def num_outputs(self) -> int:
        """Number of outputs of the base model."""
        return self.base.num_outputs

    @property
    def batch_shape(self) -> torch.Size:
        """Empty: the model is not batched."""
        return torch.Size([])

    def posterior(  # type: ignore[override]  # posterior_transform goes through **kwargs
        self,
        X: torch.Tensor,
        output_indices: list[int] | None = None,
        observation_noise: bool | torch.Tensor = False,
        **kwargs: Any,
    ) -> Posterior:
        """The base model's joint posterior at ``X`` with the K contexts appended to every
        candidate."""
        if self.append is not None:
            X = self.append.transform(X)
        return self.base.posterior(X, output_indices=output_indices, **kwargs)


class ContextExpectation(MultiOutputExpectation):
    """The expectation over the K contexts of each candidate, in cost space, of the columns
    ``keep`` of model-space samples ``t`` (maximisation convention, ``t = -g(y)``).

    Columns flagged in ``log_flags`` are ``t = -log(y + c)``: their expectation
    ``-log(mean_k (y_k + c)) = -(logsumexp_k(-t_k) - log K)``; the others are averaged as they
    are. The result stays in the model space, so hypervolumes and reference points are those of
    the non-contextual learner.
    """

    def __init__(
        self, n_w: int, log_flags: Sequence[bool], keep: Sequence[int] | None = None
    ) -> None:
        super().__init__(n_w=n_w)
        self.log_flags = [bool(b) for b in log_flags]
        self.keep = list(range(len(self.log_flags))) if keep is None else list(keep)

    def forward(self, samples: torch.Tensor, X: torch.Tensor | None = None) -> torch.Tensor:
        """Expectation over the K contexts of each candidate of the ``keep`` columns of ``samples``
        (class docstring)."""
        s = self._prepare_samples(samples)  # ... x q x n_w x m
        lin = s.mean(dim=-2)
        if any(self.log_flags):
            lme = -(torch.logsumexp(-s, dim=-2) - np.log(self.n_w))
            flags = torch.tensor(self.log_flags, dtype=torch.bool)
            lin = torch.where(flags, lme, lin)
        return lin[..., self.keep]


def _to_cost(t: torch.Tensor, log: bool, offset: float) -> torch.Tensor:
    return torch.exp(-t) - offset if log else -t


def violation_constraint(
    n_w: int, column: int, log: bool, offset: float, budget: float
) -> Callable[[torch.Tensor], torch.Tensor]:
    """A BoTorch outcome constraint (``<= 0`` is feasible) on model-space samples
    ``... x (q K) x m``: the expected violation over the K contexts minus ``budget``."""

    def constraint(samples: torch.Tensor) -> torch.Tensor:
        v = _to_cost(samples[..., column], log, offset)
        v = v.view(*v.shape[:-1], -1, n_w).mean(dim=-1)
        return v - budget

    return constraint


def expected_outcome_samples(
    surrogate: GPSurrogate,
    Z: np.ndarray,
    contexts: np.ndarray,
    *,
    n_samples: int = 128,
    seed: int = 0,
    joint: bool = False,
) -> np.ndarray:
    """Posterior samples (S, n, m) of the expected outcomes over the contexts, in cost units,
    at the unit-cube points ``Z`` (n, d).

    ``joint=False``: each point's K contexts are sampled jointly, the points independently (the
    marginals). ``joint=True``: all n points on one joint posterior (for comparing a few
    points with common random numbers).
    """
    Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
    model = ContextModel(surrogate.fast_model, contexts)
    X = torch.as_tensor(Z, dtype=DTYPE)
    X = X.unsqueeze(0) if joint else X.unsqueeze(-2)  # (1, n, d) or (n, 1, d)
    offsets = surrogate.offsets
    with (
        torch.no_grad(),
        torch.random.fork_rng(),
        gpytorch.settings.max_cholesky_size(MAX_CHOLESKY),
    ):
        torch.manual_seed(int(seed))
        post = model.posterior(X)
        s = post.rsample(torch.Size([int(n_samples)]))  # S x b x (q K) x m
        m = s.shape[-1]
        cols = []
        for j in range(m):
            y = _to_cost(s[..., j], surrogate.log_outcomes[j], float(offsets[j]))
            cols.append(y.view(*y.shape[:-1], -1, model.n_w).mean(dim=-1))
        out = torch.stack(cols, dim=-1)  # S x b x q x m
    out = out.reshape(int(n_samples), -1, m) if not joint else out[:, 0]
    return out.numpy().astype(np.float64)


def context_posterior(
    surrogate: Any, Z: np.ndarray, contexts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The marginal model-space posterior mean and std (n K, m) at every ``(z, c_k)`` (row
    ``i K + k``: the i-th theta with the k-th context), remembered per theta for the life of
    the surrogate's fit (:meth:`~mpcmobo.bo.surrogate.GPSurrogate.fit_memo`).

    After each fit the safe design asks for the same posterior at all observed thetas three
    times (the deployment rule's shortlist, the safe points and the EHVI's current front);
    at 600 observations each evaluation costs about 0.5 s (3,300 points against 590), so
    it is computed once. A theta's rows are the same numbers whichever other thetas are
    evaluated with it (each point's posterior is computed on its own row)."""
    Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
    C = np.asarray(contexts, dtype=np.float64)
    has_c = C.ndim == 2 and C.shape[1] > 0
    K = C.shape[0] if has_c else 1
    memo = getattr(surrogate, "fit_memo", None)
    if memo is None:  # a surrogate without a memo (a test double): evaluate
        return surrogate.posterior_model_space(with_contexts(Z, C) if has_c else Z)
    memo = memo("context_posterior")
    ckey = (C.shape, C.tobytes())
    keys = [(ckey, z.tobytes()) for z in Z]
    new: dict[tuple, int] = {}
    for i, k in enumerate(keys):
        if k not in memo and k not in new:
            new[k] = i
    if new:
        Zn = Z[list(new.values())]
        mt, st = surrogate.posterior_model_space(with_contexts(Zn, C) if has_c else Zn)
        m = mt.shape[1]
        mt, st = mt.reshape(len(Zn), K, m), st.reshape(len(Zn), K, m)
        for j, k in enumerate(new):
            memo[k] = (mt[j], st[j])
    rows = [memo[k] for k in keys]
    mt = np.concatenate([r[0] for r in rows])
    st = np.concatenate([r[1] for r in rows])
    return mt, st


def with_contexts(Z: np.ndarray, C: np.ndarray) -> np.ndarray:
    """The rows ``(z_i, c_k)`` (n K, d + d_c), row ``i K + k``."""
    K = C.shape[0]
    return np.hstack([np.repeat(Z, K, axis=0), np.tile(C, (len(Z), 1))])


def expected_outcome_means(
    surrogate: Any, Z: np.ndarray, contexts: np.ndarray, *, quantile: float | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """The cheap first pass of the deployment and safety rules (issue 11, item 2): from the
    marginal posterior at each ``(z, c_k)`` only (no joint sampling), the expected outcomes
    over the contexts in cost units, ``(1/K) sum_k E[y(z, c_k)]`` (n, m), and with
    ``quantile = q`` an upper bound ``(1/K) sum_k Q_q[y(z, c_k)]`` (n, m) of the ``q``
    quantile of that expectation.

    The bound is conservative: a quantile of a sum of comonotone terms is the sum of their
    quantiles, and the contexts' errors are positively correlated at most; so a point whose
    bound is within a budget is safe by the sampled test too. Cost: one marginal posterior
    of ``n K`` points, about the price of 1 of the 128 joint samples per point it replaces.
    """
    Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
    C = np.asarray(contexts, dtype=np.float64)
    K = C.shape[0] if C.ndim == 2 and C.shape[1] > 0 else 1
    mt, st = context_posterior(surrogate, Z, C)
    mean, _ = surrogate.to_cost_space(mt, st)
    n, m = len(Z), mean.shape[1]
    E = mean.reshape(n, K, m).mean(axis=1)
    if quantile is None:
        return E, None
    from scipy.stats import norm

    tq = mt - float(norm.ppf(quantile)) * st  # lower model-space quantile = upper cost quantile
    offsets = np.asarray(surrogate.offsets, float)
    U = np.empty_like(tq)
    for j in range(m):
        U[:, j] = np.exp(-tq[:, j]) - offsets[j] if surrogate.log_outcomes[j] else -tq[:, j]
    return E, U.reshape(n, K, m).mean(axis=1)


# ---------------------------------------------------------------------- acquisition
def _front_indices(C: np.ndarray, r: np.ndarray, max_baseline: int) -> np.ndarray:
    """Non-dominated rows of ``C`` (minimised) better than ``r`` everywhere, pruned to at most
    ``max_baseline`` by smallest hypervolume contribution (as :func:`posterior_front`)."""
    import moocore

    from mpcmobo.bo.pareto import pareto_mask

    idx = np.flatnonzero(pareto_mask(C) & np.all(C < r, axis=1))
    _, first = np.unique(C[idx], axis=0, return_index=True)
    idx = idx[np.sort(first)]
    while idx.size > max_baseline:
        contrib = moocore.hv_contributions(C[idx], ref=r)
        k = max(1, (idx.size - max_baseline) // 4)
        idx = np.delete(idx, np.argsort(contrib, kind="stable")[:k])
    return idx


def _model_space_means(surrogate: GPSurrogate, E: np.ndarray) -> np.ndarray:
    """Expected costs (n, m) mapped to the model space ``t = -g(y)``."""
    return surrogate.to_model_space(E)


def propose_context(
    surrogate: GPSurrogate,
    Xf: np.ndarray,
    contexts: np.ndarray,
    *,
    n_objectives: int,
    ref_point: np.ndarray | None,
    seed: int,
    mc_samples: int = 64,
    max_baseline: int = 32,
    budget: float | None = None,
    search: AcqfSearch | None = None,
    safe_points: np.ndarray | None = None,
    box: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Next unit-cube theta (d,) (in ``box = (lower, upper)`` when given) maximising the (constrained) log EHVI (``n_objectives > 1``)
    or log EI (one objective) of the expected outcomes over ``contexts``.

    ``surrogate`` is fitted on ``(z, c)`` rows ``Xf``; its outputs are the objectives, plus the
    violation as the last column when ``budget`` is given (then the acquisition is weighted
    by the probability that the expected violation stays within the budget, BoTorch's
    ``constraints=``). The incumbent front / best value is the posterior mean of the expected
    outcomes at the observed thetas (those in ``safe_points`` when given).
    """
    from botorch.acquisition.logei import qLogExpectedImprovement
    from botorch.acquisition.multi_objective.logei import qLogExpectedHypervolumeImprovement
    from botorch.sampling.normal import SobolQMCNormalSampler
    from botorch.utils.multi_objective.box_decompositions.non_dominated import (
        FastNondominatedPartitioning,
    )

    from mpcmobo.bo.acquisition import AcqfSearch, _optimize

    search = AcqfSearch() if search is None else search
    dc = 0 if contexts.ndim < 2 else contexts.shape[1]
    d = Xf.shape[1] - dc
    model = ContextModel(surrogate.fast_model, contexts)
    m_all = surrogate.num_outputs
    keep = list(range(n_objectives))
    log_flags = list(surrogate.log_outcomes)
    objective = ContextExpectation(model.n_w, log_flags, keep=keep)
    constraints = None
    if budget is not None:
        j = m_all - 1
        constraints = [
            violation_constraint(
                model.n_w, j, log_flags[j], float(surrogate.offsets[j]), float(budget)
            )
        ]
    Zobs = np.unique(Xf[:, :d], axis=0) if safe_points is None else np.atleast_2d(safe_points)
    E, _ = expected_outcome_means(surrogate, Zobs, contexts)
    T = _model_space_means(surrogate, E)[:, keep]  # (n, m_obj), maximised
    sampler = SobolQMCNormalSampler(sample_shape=torch.Size([mc_samples]), seed=seed)
    if n_objectives > 1:
        ref_t = surrogate.to_model_space(
            np.concatenate([np.asarray(ref_point, float), np.zeros(m_all - n_objectives)])[None, :]
        )[0][keep]
        base = _front_indices(-T, -ref_t, max_baseline)
        front = torch.as_tensor(T[base].reshape(-1, n_objectives), dtype=DTYPE)
        tref = torch.as_tensor(ref_t, dtype=DTYPE)
        part = FastNondominatedPartitioning(ref_point=tref, Y=front)
        acq: AcquisitionFunction = qLogExpectedHypervolumeImprovement(
            model,
            ref_point=tref,
            partitioning=part,  # type: ignore[arg-type]  # botorch takes any box decomposition
            sampler=sampler,
            objective=objective,
            constraints=constraints,
        )
    else:
        from botorch.acquisition.objective import GenericMCObjective

        best_f = float(T[:, 0].max())
        acq = qLogExpectedImprovement(
            model,
            best_f=best_f,
            sampler=sampler,
            objective=GenericMCObjective(lambda s, X=None: objective(s, X)[..., 0]),  # type: ignore[misc]
            constraints=constraints,
        )
    return _optimize(acq, d, seed, search, box)
