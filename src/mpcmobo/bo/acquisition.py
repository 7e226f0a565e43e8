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

import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import gpytorch
import moocore
import numpy as np
import torch
from botorch.acquisition.acquisition import AcquisitionFunction
from botorch.acquisition.analytic import LogExpectedImprovement
from botorch.acquisition.multi_objective import logei as _logei
from botorch.acquisition.multi_objective.logei import qLogExpectedHypervolumeImprovement
from botorch.optim import optimize_acqf
from botorch.sampling.normal import SobolQMCNormalSampler
from botorch.utils.multi_objective.box_decompositions.non_dominated import (
    FastNondominatedPartitioning,
)
from botorch.utils.safe_math import logmeanexp, logsumexp
from torch import Tensor

from mpcmobo.bo.groups import DTYPE, MAX_CHOLESKY
from mpcmobo.bo.pareto import pareto_mask
from mpcmobo.bo.surrogate import GPSurrogate

__all__ = ["AcqfSearch", "EHVIOptions", "posterior_front", "propose_ehvi", "propose_ei"]

# BoTorch compiles its fused qLogEHVI kernel on first use, under a lock file that torch waits
# for without end; a build killed (kill -9) leaves the lock behind. A build takes 20-30 s
# (minutes on a loaded machine): a lock older than this, with no process building in its
# directory, is a dead build's.
STALE_BUILD_LOCK = 120.0


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
    """The log EHVI acquisition of :func:`propose_ehvi` (eq. EHVI): ``mc_samples`` quasi-MC
    Sobol base samples; at most ``max_baseline`` observed points define the current front
    (:func:`posterior_front`)."""

    mc_samples: int = 64
    max_baseline: int = 32


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
    (``docs/benchmarks.md``, proposal time). Anything else falls back to BoTorch's code.
    """

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


def building_in(directory: Path) -> bool:
    """Whether a live process works in ``directory`` (its current directory: torch runs the
    build's ninja, and ninja its compilers, there). Read from ``/proc``; False where there is
    none to read (the lock's age alone then decides)."""
    target = os.path.realpath(directory)
    try:
        entries = os.listdir("/proc")
    except OSError:  # pragma: no cover - not Linux
        return False
    for pid in entries:
        if not pid.isdigit():
            continue
        try:
            if os.path.realpath(f"/proc/{pid}/cwd") == target:
                return True
        except OSError:  # a process that ended, or another user's
            continue
    return False


def clear_dead_build_lock(lock: Path, stale: float = STALE_BUILD_LOCK, poll: float = 1.0) -> bool:
    """Wait while another process builds under ``lock``; remove the lock once it is ``stale``
    seconds old and no process works in its directory (:func:`building_in`: a killed build's,
    which torch would wait for forever), with a warning. Returns whether it removed one."""
    while True:
        try:
            age = time.time() - lock.stat().st_mtime
        except FileNotFoundError:
            return False
        if age >= stale and building_in(lock.parent):  # a slow build, on a loaded machine
            time.sleep(poll)
            continue
        if age >= stale:
            lock.unlink(missing_ok=True)
            warnings.warn(
                f"removed {lock}, the lock of a build of BoTorch's fused EHVI kernel started "
                f"{age:.0f} s ago and never finished (a killed process); building it again",
                RuntimeWarning,
                stacklevel=2,
            )
            return True
        time.sleep(min(poll, stale - age))


_build_lock_checked = False


def _fused_kernel_lock() -> None:
    """Once per process, before BoTorch first loads its fused kernel: clear a dead build's
    lock (:func:`clear_dead_build_lock`)."""
    global _build_lock_checked
    if _build_lock_checked or _logei._load_attempted:
        return
    _build_lock_checked = True
    try:
        from torch.utils.cpp_extension import _get_build_directory

        lock = Path(_get_build_directory("logei_fused_ext", verbose=False)) / "lock"
    except Exception:  # noqa: BLE001 - no build directory: nothing to clear  # pragma: no cover
        return
    clear_dead_build_lock(lock)


def _logehvi(
    surrogate: GPSurrogate,
    Xf: np.ndarray,
    base: np.ndarray,
    tref: torch.Tensor,
    sampler: SobolQMCNormalSampler,
) -> qLogExpectedHypervolumeImprovement:
    """qLogEHVI with the posterior-mean front at ``Xf[base]`` as ``P`` (one box
    decomposition of the region it dominates)."""
    m = surrogate.num_outputs
    if base.size:
        mt = surrogate.posterior_mean_model_space(Xf[base])
        front = torch.as_tensor(mt.reshape(-1, m), dtype=DTYPE)
    else:  # no posterior mean beats the reference point yet: the whole box is improvement
        front = torch.empty((0, m), dtype=DTYPE)
    part = FastNondominatedPartitioning(ref_point=tref, Y=front)
    _fused_kernel_lock()
    return _SingleLogEHVI(  # eq. EHVI (log, MC)
        surrogate.fast_model,  # same posterior, faster
        ref_point=tref,
        partitioning=part,  # type: ignore[arg-type]  # botorch takes any box decomposition
        sampler=sampler,
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
    :func:`~mpcmobo.bo.pareto.reference_point`), computed in log form by quasi-MC with
    ``options.mc_samples`` Sobol base samples. ``P`` is the posterior-mean Pareto front at the
    observed points, pruned by :func:`posterior_front`, with one box decomposition of the
    region it dominates (``FastNondominatedPartitioning``).

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
    acq = _logehvi(surrogate, Xf, base, tref, sampler)
    return _optimize(acq, Xf.shape[1], seed, search, box)
