"""Acquisition functions and their optimisation on the unit cube (eq. EI, acq_EI, EHVI).

Both proposers take a :class:`~mpcmobo.bo.surrogate.GPSurrogate` and the data ``(X, Y)`` in
minimisation units. If the surrogate was not fitted on exactly the finite rows of ``(X, Y)``
it is fitted first (``surrogate.fit(X, Y)``), so a caller may either fit then propose, or
just propose. The acquisition works on the surrogate's model, which maximises
``t = -g(y)`` (see ``surrogate``); maximising EI/EHVI of ``t`` is minimising the costs.

Following BoTorch, an acquisition is built from the model plus an options object
(:class:`EHVIOptions`; log EI needs none) and its maximisation is separate, configured by
:class:`AcqfSearch` (``optimize_acqf``: L-BFGS-B restarts from the best raw samples).

Determinism: the result is a function of (data, surrogate state, seed). The torch RNG is
seeded with ``seed`` (in a forked RNG state, the caller's stream is untouched) for the raw
samples of ``optimize_acqf`` and the quasi-MC sampler is ``SobolQMCNormalSampler(seed=seed)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import gpytorch
import moocore
import numpy as np
import torch
from botorch.acquisition.acquisition import AcquisitionFunction
from botorch.acquisition.analytic import LogExpectedImprovement
from botorch.acquisition.multi_objective import logei as _logei
from botorch.acquisition.multi_objective.logei import (
    qLogExpectedHypervolumeImprovement,
    qLogNoisyExpectedHypervolumeImprovement,
)
from botorch.optim import optimize_acqf
from botorch.sampling.normal import SobolQMCNormalSampler
from botorch.utils.multi_objective.box_decompositions.non_dominated import (
    FastNondominatedPartitioning,
    NondominatedPartitioning,
)
from botorch.utils.safe_math import logmeanexp, logsumexp
from torch import Tensor

from mpcmobo.bo.fastpost import ExactIndependentGP
from mpcmobo.bo.groups import DTYPE, MAX_CHOLESKY
from mpcmobo.bo.pareto import pareto_mask
from mpcmobo.bo.surrogate import GPSurrogate

__all__ = ["AcqfSearch", "EHVIOptions", "posterior_front", "propose_ehvi", "propose_ei"]

EHVI_METHODS = ("logehvi", "lognehvi")


@dataclass(frozen=True)
class AcqfSearch:
    """How an acquisition is maximised on the unit cube (BoTorch's ``optimize_acqf``):
    L-BFGS-B from ``num_restarts`` starts, the best of ``raw_samples`` random points, at most
    ``maxiter`` iterations each."""

    num_restarts: int = 4
    raw_samples: int = 256
    maxiter: int = 100


@dataclass(frozen=True)
class EHVIOptions:
    """The (log) EHVI acquisition of :func:`propose_ehvi` (eq. EHVI).

    ``mc_samples``: quasi-MC Sobol base samples. ``max_baseline``: at most this many observed
    points define the current front (:func:`posterior_front`). ``alpha > 0``: approximate box
    decomposition (``NondominatedPartitioning(alpha)``). ``method``: ``"logehvi"`` or
    ``"lognehvi"`` (see :func:`propose_ehvi`). ``direct_samples`` (``"logehvi"`` only): draw
    the quasi-MC samples of a candidate directly from its posterior mean and standard
    deviation (:class:`_SingleLogEHVI`): the same acquisition up to rounding, about 1.6x
    faster to evaluate, but not the same numbers bit for bit, so the search and the records
    change (``docs/benchmarks.md``, "The mobo learner's time per episode").
    """

    mc_samples: int = 64
    max_baseline: int = 32
    alpha: float = 0.0
    method: str = "logehvi"
    direct_samples: bool = False

    def __post_init__(self) -> None:
        if self.method not in EHVI_METHODS:
            raise ValueError(f"unknown method {self.method!r}")


def _prepare(surrogate: GPSurrogate, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Fit if needed; return the finite-row inputs used by the model."""
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    if Y.ndim == 1:
        Y = Y[:, None]
    if not surrogate.is_fitted_on(X, Y):
        surrogate.fit(X, Y)
    return surrogate.train_X  # type: ignore[return-value]  # set by fit


Box = tuple[np.ndarray, np.ndarray]


def _optimize(
    acq: AcquisitionFunction, d: int, seed: int, search: AcqfSearch, box: Box | None = None
) -> np.ndarray:
    """The maximiser (d,) of ``acq`` on [0,1]^d, or on the sub-box ``box = (lower, upper)``
    of it (a trust region, :mod:`mpcmobo.bo.trust`), seeded."""
    if box is None:
        bounds = torch.stack([torch.zeros(d, dtype=DTYPE), torch.ones(d, dtype=DTYPE)])
    else:
        lo, hi = (np.asarray(b, dtype=np.float64).reshape(d) for b in box)
        if not (np.all(0 <= lo) and np.all(lo <= hi) and np.all(hi <= 1)):
            raise ValueError(f"box must satisfy 0 <= lower <= upper <= 1, got {lo}, {hi}")
        bounds = torch.as_tensor(np.stack([lo, hi]), dtype=DTYPE)
    with torch.random.fork_rng(), gpytorch.settings.max_cholesky_size(MAX_CHOLESKY):
        torch.manual_seed(seed)
        cand, _ = optimize_acqf(
            acq,
            bounds=bounds,
            q=1,
            num_restarts=search.num_restarts,
            raw_samples=search.raw_samples,
            options={
                "maxiter": search.maxiter,
                "seed": seed,
                "batch_limit": search.num_restarts,
                "init_batch_limit": 128,
            },
        )
    z = cand.detach().numpy().reshape(d).astype(np.float64)
    return np.clip(z, bounds[0].numpy(), bounds[1].numpy())


def propose_ei(
    surrogate: GPSurrogate,
    X: np.ndarray,
    y: np.ndarray,
    *,
    seed: int,
    search: AcqfSearch = AcqfSearch(),
    box: Box | None = None,
) -> np.ndarray:
    """Next point (d,) in [0,1]^d (in ``box`` when given) maximising log expected improvement
    of one cost.

    eq. EI / acq_EI, written for the maximised target ``t = -g(y)`` with ``Z = (mu - t*)/sigma``:
    ``EI = sigma (Z Phi(Z) + phi(Z))``, optimised as ``log EI`` (BoTorch's
    ``LogExpectedImprovement``, numerically stable where EI underflows). Noisy setting: the
    incumbent ``t*`` is the best posterior mean at the observed points, not the best noisy
    observation.
    """
    Xf = _prepare(surrogate, X, y)
    if surrogate.num_outputs != 1:
        raise ValueError("propose_ei needs a single-output surrogate")
    mt, _ = surrogate.posterior_model_space(Xf)
    best_f = float(mt[:, 0].max())  # incumbent: best posterior mean (noisy EI)
    model = surrogate.fast_model  # same posterior, faster
    acq = LogExpectedImprovement(model, best_f=best_f)  # eq. acq_EI (log form)
    return _optimize(acq, Xf.shape[1], seed, search, box)


def posterior_front(
    surrogate: GPSurrogate, Xf: np.ndarray, ref_t: np.ndarray, max_baseline: int
) -> np.ndarray:
    """Indices into ``Xf`` of the pruned baseline: the points whose posterior mean is
    non-dominated (maximisation of ``t``) and better than the reference point in every
    objective, at most ``max_baseline`` of them.

    If more remain, the point with the smallest exclusive hypervolume contribution (of the
    posterior means, w.r.t. ``ref_t``) is removed, repeatedly, until ``max_baseline`` are
    left: the kept set is the one that best preserves the front's hypervolume.
    """
    mt = surrogate.posterior_mean_model_space(Xf)
    C = -mt  # minimisation view of the posterior means
    r = -np.asarray(ref_t, dtype=np.float64)
    idx = np.flatnonzero(pareto_mask(C) & np.all(C < r, axis=1))
    # duplicates of one mean add nothing: keep the first of each
    _, first = np.unique(C[idx], axis=0, return_index=True)
    idx = idx[np.sort(first)]
    while idx.size > max_baseline:
        contrib = moocore.hv_contributions(C[idx], ref=r)
        excess = idx.size - max_baseline
        # drop several of the smallest at once when far above the cap (contributions change
        # little for points far apart), one at a time near the cap
        k = max(1, excess // 4)
        drop = np.argsort(contrib, kind="stable")[:k]
        idx = np.delete(idx, drop)
    return idx


class _SingleLogEHVI(qLogExpectedHypervolumeImprovement):
    """BoTorch's ``qLogExpectedHypervolumeImprovement`` with a shorter path for ``q = 1``.

    For one candidate (``q = 1``, no constraints, BoTorch's fused C++ kernel loaded) the
    inclusion-exclusion of ``_compute_log_qehvi`` has one term: the smooth log-sums over
    subsets of one, ``logplusexp(-inf, a)`` and ``logdiffexp(-inf, a)`` all return ``a``
    exactly and pass its gradient on multiplied by exactly 1. This class skips them and
    computes ``logmeanexp(logsumexp(log_areas))`` of the same fused log areas: the same values
    and gradients, bit for bit (``tests/test_ehvi_value.py``), 2.7-3.6x faster
    (``docs/benchmarks.md``, "The mobo learner's time per episode"). Anything else falls back
    to BoTorch's general code.
    """

    direct_samples: bool = False  # set by _logehvi (EHVIOptions.direct_samples)

    def forward(self, X: Tensor) -> Tensor:
        """BoTorch's forward; with ``direct_samples`` and one point per batch, the quasi-MC
        samples ``mean + std * z`` straight from the posterior mean and standard deviation
        (:meth:`~mpcmobo.bo.fastpost.ExactIndependentGP.mean_std_single`) with the sampler's
        own base samples ``z``."""
        model = self.model
        if (
            not self.direct_samples
            or X.dim() < 3
            or X.shape[-2] != 1
            or self.X_pending is not None
            or not isinstance(model, ExactIndependentGP)
        ):
            return super().forward(X)
        if self.sampler.base_samples is None:  # BoTorch draws them from a first posterior
            self.sampler(model.posterior(X.detach()))
        mean, std = model.mean_std_single(X)  # (b, 1, m)
        samples = mean + std * self.sampler.base_samples  # (mc, b, 1, m)
        return self._compute_log_qehvi(samples=samples, X=X)

    def _compute_log_qehvi(self, samples: Tensor, X: Tensor | None = None) -> Tensor:
        # torch types a Module attribute as Tensor; BoTorch set it to an MCMultiOutputObjective
        obj = self.objective(samples, X=X)  # type: ignore[operator]  # mc x batch x q x m
        if (
            obj.shape[-2] != 1
            or self.constraints is not None
            or not self.fat
            or obj.device.type != "cpu"
            or self.cell_lower_bounds.ndim != 2
        ):
            return super()._compute_log_qehvi(samples, X=X)
        if _logei._C is None:  # pragma: no cover - BoTorch without its C++ extension
            return super()._compute_log_qehvi(samples, X=X)
        # (mc, batch, 1 subset, 1 point, m) -> log areas (mc, batch, cells, 1 subset)
        log_areas = _logei._FusedLogAreas.apply(
            obj.unsqueeze(-2),
            self.cell_lower_bounds,
            self.cell_upper_bounds,
            self.tau_relu,
            self.tau_max,
        )
        return logmeanexp(logsumexp(log_areas[..., 0], dim=-1), dim=0)


def _logehvi(
    surrogate: GPSurrogate,
    Xf: np.ndarray,
    base: np.ndarray,
    tref: torch.Tensor,
    sampler: SobolQMCNormalSampler,
    alpha: float,
    direct_samples: bool = False,
) -> qLogExpectedHypervolumeImprovement:
    """qLogEHVI with the posterior-mean front at ``Xf[base]`` as ``P`` (one box
    decomposition of the region it dominates)."""
    m = surrogate.num_outputs
    if base.size:
        mt = surrogate.posterior_mean_model_space(Xf[base])
        front = torch.as_tensor(mt.reshape(-1, m), dtype=DTYPE)
    else:  # no posterior mean beats the reference point yet: the whole box is improvement
        front = torch.empty((0, m), dtype=DTYPE)
    if alpha > 0:
        part = NondominatedPartitioning(ref_point=tref, Y=front, alpha=alpha)
    else:
        part = FastNondominatedPartitioning(ref_point=tref, Y=front)  # type: ignore[assignment]  # botorch takes any box decomposition
    acq = _SingleLogEHVI(  # eq. EHVI (log, MC)
        surrogate.fast_model,  # same posterior, faster
        ref_point=tref,
        partitioning=part,
        sampler=sampler,
    )
    acq.direct_samples = direct_samples
    return acq


def _lognehvi(
    surrogate: GPSurrogate,
    Xf: np.ndarray,
    base: np.ndarray,
    tref: torch.Tensor,
    sampler: SobolQMCNormalSampler,
    alpha: float,
    seed: int,
) -> qLogNoisyExpectedHypervolumeImprovement:
    """qLogNEHVI with the baseline points ``Xf[base]`` (the front integrated over the joint
    posterior there)."""
    # nothing better than ref yet: fall back to the best point per objective
    if base.size == 0:
        mt, _ = surrogate.posterior_model_space(Xf)
        base = np.unique(np.argmax(mt, axis=0))
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        return qLogNoisyExpectedHypervolumeImprovement(  # eq. EHVI (log, noisy, MC)
            surrogate.model,  # type: ignore[arg-type]  # fitted by _prepare
            ref_point=tref,
            X_baseline=torch.as_tensor(Xf[base], dtype=DTYPE),
            sampler=sampler,
            prune_baseline=False,
            alpha=alpha,
            cache_root=True,
        )


def propose_ehvi(
    surrogate: GPSurrogate,
    X: np.ndarray,
    Y: np.ndarray,
    ref_point: np.ndarray,
    *,
    seed: int,
    options: EHVIOptions = EHVIOptions(),
    search: AcqfSearch = AcqfSearch(),
    box: Box | None = None,
) -> np.ndarray:
    """Next point (d,) in [0,1]^d maximising (log) expected hypervolume improvement (eq. EHVI).

    ``alpha_EHVI(theta) = E[ V(P u {f(theta)}) - V(P) ]`` with ``P`` the current front and
    ``V`` the hypervolume w.r.t. ``ref_point`` (minimisation units, mapped to the model's
    maximisation space with the surrogate's outcome transform; fix it once per run, see
    :func:`~mpcmobo.bo.pareto.reference_point`). Computed in log form by quasi-MC with
    ``options.mc_samples`` Sobol base samples.

    ``options.method``:
      * ``"logehvi"`` (default, fast): ``P`` = the posterior-mean Pareto front at the observed
        points (pruned by :func:`posterior_front`), one box decomposition of the region it
        dominates (``FastNondominatedPartitioning``, or the approximate
        ``NondominatedPartitioning(alpha)`` when ``alpha > 0``), then
        ``qLogExpectedHypervolumeImprovement``.
      * ``"lognehvi"``: ``qLogNoisyExpectedHypervolumeImprovement`` with the same pruned
        baseline points ``X_baseline`` (the front is then integrated over the joint posterior
        at the baseline, one decomposition per MC sample: slower, accounts for noise).

    ``search`` bounds the maximisation (:class:`AcqfSearch`); ``box = (lower, upper)``
    restricts it to a sub-box of the cube (a trust region, :mod:`mpcmobo.bo.trust`).
    """
    Xf = _prepare(surrogate, X, Y)
    ref = np.asarray(ref_point, dtype=np.float64).reshape(-1)
    if ref.shape[0] != surrogate.num_outputs or not np.all(np.isfinite(ref)):
        raise ValueError("ref_point must be a finite vector with one entry per output")
    ref_t = surrogate.to_model_space(ref[None, :])[0]
    base = posterior_front(surrogate, Xf, ref_t, options.max_baseline)
    tref = torch.as_tensor(ref_t, dtype=DTYPE)
    sampler = SobolQMCNormalSampler(sample_shape=torch.Size([options.mc_samples]), seed=seed)
    alpha = float(options.alpha)
    if options.method == "logehvi":
        acq = _logehvi(surrogate, Xf, base, tref, sampler, alpha, options.direct_samples)
    else:
        acq = _lognehvi(surrogate, Xf, base, tref, sampler, alpha, seed)
    return _optimize(acq, Xf.shape[1], seed, search, box)
