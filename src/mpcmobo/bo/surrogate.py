"""Gaussian-process surrogates of the costs (eq. GP, post, mean_var).

One GP per output (eq. GP), ``J_j(theta) ~ GP(mu_j, k_j)``: the squared-exponential kernel of
the paper with one length scale per input (ARD), BoTorch's default ``SingleTaskGP`` priors, a
constant mean and a Gaussian likelihood with inferred noise. The ``m`` GPs are one batched
``SingleTaskGP`` (independent outputs, same inputs), fitted and evaluated in one call.

* Inputs ``X`` lie in the unit cube of the search space. Outcomes ``Y`` are costs to be
  minimised; the model is trained on ``t = -g(y)`` (BoTorch maximises), ``g`` the identity or,
  for outputs flagged in ``log_outcomes``, a shifted log (:mod:`mpcmobo.bo.transforms`),
  then standardised. Rows with NaN or inf are never fitted. Everything is float64.
* Hyperparameters: a full type-II maximum-likelihood fit (``fit_gpytorch_mll``) starts from
  the previous hyperparameters and runs while ``n < min_refit_n`` and then once every
  ``max(refit_every, ceil(refit_fraction n))`` fits; in between the GP is conditioned on all
  data with the last hyperparameters. Above ``fit_subsample`` points the full fit maximises
  the likelihood of a seeded subset.
* Start effects: with cycled starts, ``fit(X, Y, groups)`` fits for the outputs flagged in
  ``group_outputs`` the additive model ``t_i = h(x_i) + b_{g_i} + eps_i``, one offset per
  start with the prior ``b_s ~ N(0, tau^2)``: jointly with the hyperparameters at a full fit
  (:mod:`mpcmobo.bo.groups`), else as their random-effects (GLS) posterior mean
  ``(H^T A H + I / tau^2) b = H^T A (t - mean(t))``, ``A = (s^2 (K + sigma_n^2 I))^-1``.
  The offsets are centred, and the GP models the cost of an average start, so candidates run
  from different starts are compared fairly.
* Posterior: :meth:`GPSurrogate.predict` gives the latent posterior in cost units;
  :meth:`GPSurrogate.cost_samples` joint or marginal posterior samples of the costs.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator, Sequence
from typing import Any

import gpytorch
import numpy as np
import torch
from botorch.exceptions.warnings import InputDataWarning
from botorch.fit import fit_gpytorch_mll
from botorch.models import SingleTaskGP
from botorch.models.transforms.outcome import Standardize
from gpytorch.mlls import ExactMarginalLogLikelihood

from mpcmobo.bo.fastpost import ExactIndependentGP
from mpcmobo.bo.groups import DTYPE, MAX_CHOLESKY, fit_group_offsets
from mpcmobo.bo.pareto import finite_rows
from mpcmobo.bo.transforms import cost_transform

__all__ = ["GPSurrogate", "fit_gp"]

# points per block of a posterior evaluation (posterior_model_space): large enough for fast
# matrix products, small enough that the (m, block, n) temporaries stay in cache
ROW_BLOCK = 256
# the InputDataWarning BoTorch gives for an output that Standardize leaves constant
NOT_STANDARDIZED = r"Data \(outcome observations\) is not standardized"


def _as_2d(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    return a[:, None] if a.ndim == 1 else a


def _row_blocks(X: np.ndarray) -> Iterator[torch.Tensor]:
    """The rows of ``X`` as tensors (b, 1, d) of at most :data:`ROW_BLOCK` points each (one
    empty block for no rows), for the posterior evaluations."""
    X = _as_2d(X)
    for i in range(0, max(1, len(X)), ROW_BLOCK):
        yield torch.as_tensor(X[i : i + ROW_BLOCK], dtype=DTYPE).unsqueeze(-2)


def _flags(name: str, flags: Sequence[bool] | None, m: int) -> list[bool]:
    """One bool per output (None: all False)."""
    out = [False] * m if flags is None else [bool(b) for b in flags]
    if len(out) != m:
        raise ValueError(f"{name} must have one flag per output")
    return out


def _hyper_tensors(model: SingleTaskGP) -> dict[str, torch.Tensor]:
    """The hyperparameters of ``model`` (standardised units; not the outcome transform)."""
    return {
        k: v.detach().clone()
        for k, v in model.state_dict().items()
        if not k.startswith("outcome_transform")
    }


def _gls_offsets(
    K: np.ndarray, noise: float, H: np.ndarray, t: np.ndarray, t_adj: np.ndarray, prior_std: float
) -> np.ndarray:
    """Random-effects (GLS) posterior mean of one output's group offsets (module docstring,
    "Start effects"): ``(H^T A H + I / tau^2) b = H^T A (t - mean(t))``, ``A = (s^2 (K +
    sigma_n^2 I))^-1`` with ``s^2`` the variance of the adjusted targets ``t_adj``."""
    s2 = max(float(np.var(t_adj)), 1e-12)
    L = np.linalg.cholesky(s2 * (K + noise * np.eye(len(t))))
    AH = np.linalg.solve(L.T, np.linalg.solve(L, H))  # A H
    tau2 = prior_std**2 * max(float(np.var(t)), 1e-12)
    lhs = H.T @ AH + np.eye(H.shape[1]) / tau2
    return np.linalg.solve(lhs, AH.T @ (t - t.mean()))


class GPSurrogate:
    """Independent GPs on ``num_outputs`` costs, minimisation units outside, maximisation inside.

    Parameters
    ----------
    num_outputs: number of cost columns ``m`` of ``Y``.
    refit_every: a full marginal-likelihood fit every ``refit_every`` calls to :meth:`fit`
        (1 = always), or less often with ``refit_fraction``. In between, hyperparameters are
        reused.
    log_outcomes: per output, whether to model ``log(y + c)`` (:mod:`mpcmobo.bo.transforms`).
    min_refit_n: while the number of finite observations is below this, always refit.
    fit_maxiter: L-BFGS-B iteration cap of a full fit.
    fit_subsample: a full fit maximises the marginal likelihood of a seeded random subset of
        at most this many points (None: all points); the GP is then conditioned on all.
    group_outputs: per output, whether ``fit(..., groups=...)`` estimates an offset per group
        (see "Start effects" in the module docstring). None: no output.
    group_prior_std: prior standard deviation ``tau`` of a group offset, in units of the
        output's standard deviation.
    refit_fraction: with ``n`` finite observations, a full fit is due after
        ``max(refit_every, ceil(refit_fraction n))`` calls (0: every ``refit_every`` calls).

    Fitted state (set by :meth:`fit`): ``model``, ``train_X``, ``train_Y``, ``group_offsets``,
    ``last_fit_was_full`` and the fitted ``transform``.
    """

    def __init__(
        self,
        num_outputs: int,
        refit_every: int = 10,
        log_outcomes: Sequence[bool] | None = None,
        *,
        min_refit_n: int = 20,
        fit_maxiter: int = 200,
        fit_subsample: int | None = 300,
        group_outputs: Sequence[bool] | None = None,
        group_prior_std: float = 1.0,
        refit_fraction: float = 0.1,
    ) -> None:
        if num_outputs < 1:
            raise ValueError("num_outputs must be >= 1")
        if refit_every < 1:
            raise ValueError("refit_every must be >= 1")
        if not 0 <= refit_fraction <= 1:
            raise ValueError("refit_fraction must be in [0, 1]")
        self.num_outputs = int(num_outputs)
        self.refit_every = int(refit_every)
        self.refit_fraction = float(refit_fraction)
        self.log_outcomes = _flags("log_outcomes", log_outcomes, self.num_outputs)
        self.group_outputs = _flags("group_outputs", group_outputs, self.num_outputs)
        if not group_prior_std > 0:
            raise ValueError("group_prior_std must be > 0")
        self.group_prior_std = float(group_prior_std)
        self.min_refit_n = int(min_refit_n)
        self.fit_maxiter = int(fit_maxiter)
        self.fit_subsample = None if fit_subsample is None else int(fit_subsample)
        self._reset_fit()
        self._hyper: dict[str, np.ndarray] | None = None
        self._calls_since_refit = 0
        self._n_fits = 0

    def _reset_fit(self) -> None:
        """No fitted model; the transform and the group offsets start from scratch."""
        self.transform = cost_transform(self.log_outcomes)
        self.group_offsets: dict[int, np.ndarray] = {}  # group -> (m,) offsets in model space
        self.model: SingleTaskGP | None = None
        self._fast: ExactIndependentGP | None = None
        self.train_X: np.ndarray | None = None  # finite rows used in the last fit
        self.train_Y: np.ndarray | None = None
        self.last_fit_was_full = False

    # ------------------------------------------------------------------ transforms
    @property
    def offsets(self) -> np.ndarray:
        """The shifts ``c`` of the log outputs in the last fit (0 elsewhere)."""
        return self.transform.steps[0].offsets_

    def to_model_space(self, Y: np.ndarray) -> np.ndarray:
        """Map costs ``Y`` (n, m) to the model's maximisation targets ``t = -g(y)``.

        Log outputs are clamped at ``y + c >= 1e-300`` (only matters for points below the
        training data, e.g. a reference point).
        """
        return self.transform.forward(_as_2d(Y))

    def to_cost_space(self, mt: np.ndarray, st: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The back transform of :meth:`predict`: a model-space posterior ``(mt, st)`` (from
        :meth:`posterior_model_space`) as mean and std of the costs."""
        return self.transform.untransform(mt, st)

    # ------------------------------------------------------------------ fitting
    def _refit_due(self, n: int) -> bool:
        period = max(self.refit_every, int(np.ceil(self.refit_fraction * n)))
        return self._hyper is None or n < self.min_refit_n or self._calls_since_refit >= period - 1

    def _new_gp(self, tX: torch.Tensor, tY: torch.Tensor) -> SingleTaskGP:
        """BoTorch's default ``SingleTaskGP`` with standardised outcomes. An output constant
        over the data (f3 is 0 until the value function changes between episodes) stays at
        zero after ``Standardize``, and is modelled as that constant: BoTorch's warning that
        it is not standardised is silenced for it (it filled the run's log)."""
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", NOT_STANDARDIZED, InputDataWarning)
            model = SingleTaskGP(tX, tY, outcome_transform=Standardize(m=self.num_outputs))
        return model.to(DTYPE)

    def _make_model(self, tX: torch.Tensor, tY: torch.Tensor) -> SingleTaskGP:
        """A GP on ``(tX, tY)`` with the current hyperparameters (BoTorch's initial ones if
        there are none yet)."""
        model = self._new_gp(tX, tY)
        if self._hyper is not None:
            hyper = {k: torch.as_tensor(v) for k, v in self._hyper.items()}
            model.load_state_dict(hyper, strict=False)
        return model

    def start_offsets(self, groups: np.ndarray) -> np.ndarray:
        """(n, m) model-space offsets of each row's group (0 for group -1 and for unflagged
        outputs)."""
        cols = np.asarray(self.group_outputs, dtype=float)
        zero = np.zeros(self.num_outputs)
        return np.array([self.group_offsets.get(int(g), zero) for g in groups]) * cols

    def _fit_group_offsets(
        self, X: np.ndarray, T: np.ndarray, groups: np.ndarray, seed: int
    ) -> dict[int, np.ndarray]:
        ids = np.unique(groups[groups >= 0])
        b = {int(g): np.zeros(self.num_outputs) for g in ids}
        # as for the hyperparameters: a seeded subset; the GLS step of the next fits then
        # refines the offsets with all the data
        rows = self._subsample(len(X))
        rows = np.arange(len(X)) if rows is None else rows
        for j in np.flatnonzero(self.group_outputs):
            bj = fit_group_offsets(
                X[rows], T[rows, j], groups[rows], prior_std=self.group_prior_std, seed=seed
            )
            for g, v in bj.items():
                b[g][j] = v
        return b

    def _estimate_group_offsets(
        self, X: np.ndarray, T: np.ndarray, groups: np.ndarray
    ) -> dict[int, np.ndarray]:
        """Random-effects estimate of the group offsets with the current hyperparameters
        (module docstring, "Start effects"), from the previous offsets' adjusted targets."""
        ids = np.unique(groups[groups >= 0])
        H = (groups[:, None] == ids[None, :]).astype(float)  # (n, G)
        T_adj = T - self.start_offsets(groups)  # scale of the GP's (adjusted) targets
        model = self._make_model(
            torch.as_tensor(X, dtype=DTYPE), torch.as_tensor(T_adj, dtype=DTYPE)
        )
        m = self.num_outputs
        n = len(X)
        with torch.no_grad():
            K = model.covar_module(model.train_inputs[0]).to_dense().reshape(m, n, n).numpy()
            noise = model.likelihood.noise.reshape(m, -1)[:, 0].numpy()
        b = np.zeros((len(ids), m))
        for j in np.flatnonzero(self.group_outputs):
            b[:, j] = _gls_offsets(K[j], noise[j], H, T[:, j], T_adj[:, j], self.group_prior_std)
        b -= b.mean(axis=0)  # centred: h is the cost of an average start
        return {int(g): b[k].copy() for k, g in enumerate(ids)}

    def _offsets_for_fit(
        self, X: np.ndarray, T: np.ndarray, groups: np.ndarray | None, full: bool
    ) -> dict[int, np.ndarray]:
        """The group offsets of this fit: none without groups; with the hyperparameters at a
        full fit (:mod:`mpcmobo.bo.groups`); else their posterior mean under the current
        hyperparameters."""
        if groups is None:
            return {}
        if full:
            return self._fit_group_offsets(X, T, groups, seed=1234 + len(X))
        return self._estimate_group_offsets(X, T, groups)

    def _finite_data(
        self, X: np.ndarray, Y: np.ndarray, groups: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The finite rows of ``(X, Y)`` and their groups (None: no group information for a
        flagged output)."""
        X, Y = _as_2d(X), _as_2d(Y)
        if Y.shape[1] != self.num_outputs:
            raise ValueError(f"Y has {Y.shape[1]} columns, expected {self.num_outputs}")
        if X.shape[0] != Y.shape[0]:
            raise ValueError("X and Y must have the same number of rows")
        if groups is not None and np.shape(groups) != (X.shape[0],):
            raise ValueError("groups must have one entry per row of X")
        ok = finite_rows(Y) & finite_rows(X)
        if not ok.any():
            raise ValueError("no finite observations to fit")
        g = None
        if groups is not None and any(self.group_outputs):
            g = np.asarray(groups, dtype=int)[ok]
            g = g if np.any(g >= 0) else None
        return X[ok], Y[ok], g

    def fit(self, X: np.ndarray, Y: np.ndarray, groups: np.ndarray | None = None) -> GPSurrogate:
        """Fit (or condition) the GPs on the finite rows of ``(X, Y)``; returns ``self``.

        ``groups`` (n,) integers, optional: the group (start index) of each row, -1 for none;
        offsets per group are then estimated for the outputs flagged in ``group_outputs``.
        """
        Xf, Yf, gf = self._finite_data(X, Y, groups)
        self.train_X, self.train_Y = Xf.copy(), Yf.copy()
        T = self.transform.fit(Yf).forward(Yf)
        n = Xf.shape[0]
        full = self._refit_due(n)
        self.group_offsets = self._offsets_for_fit(Xf, T, gf, full)
        tX = torch.as_tensor(Xf, dtype=DTYPE)
        tY = torch.as_tensor(T if gf is None else T - self.start_offsets(gf), dtype=DTYPE)
        # eq. GP: one independent GP per output (batched), SE-ARD kernel, Gaussian noise
        model = self._make_model(tX, tY)
        if full:
            self._ml_fit(model, tX, tY, n)
            self._calls_since_refit = 0
        else:
            self._calls_since_refit += 1
        model.eval()
        self.last_fit_was_full = full
        self._hyper = {k: v.numpy().copy() for k, v in _hyper_tensors(model).items()}
        self._n_fits += 1
        self.model = model
        self._fast = None
        return self

    def restore(
        self, X: np.ndarray, Y: np.ndarray, groups: np.ndarray | None, state: dict[str, Any]
    ) -> GPSurrogate:
        """The model of the last :meth:`fit` on ``(X, Y, groups)``, rebuilt from the
        :meth:`state_dict` saved after it, without fitting: the same hyperparameters, group
        offsets and data give the same posterior (what a loaded tuner answers with at once)."""
        self.load_state_dict(state)
        Xf, Yf, gf = self._finite_data(X, Y, groups)
        self.train_X, self.train_Y = Xf.copy(), Yf.copy()
        T = self.transform.fit(Yf).forward(Yf)
        tX = torch.as_tensor(Xf, dtype=DTYPE)
        tY = torch.as_tensor(T if gf is None else T - self.start_offsets(gf), dtype=DTYPE)
        self.model = self._make_model(tX, tY)
        self.model.eval()
        self.last_fit_was_full = bool(state["last_fit_was_full"])
        return self

    def _subsample(self, n: int) -> np.ndarray | None:
        """The seeded subset of ``fit_subsample`` rows a full fit uses, or None for all."""
        if self.fit_subsample is None or n <= self.fit_subsample:
            return None
        return np.sort(np.random.default_rng(n).choice(n, self.fit_subsample, replace=False))

    def _ml_fit(self, model: SingleTaskGP, tX: torch.Tensor, tY: torch.Tensor, n: int) -> None:
        """Type-II maximum likelihood of ``model``'s hyperparameters, in place."""
        target = model
        sub = self._subsample(n)
        if sub is not None:
            # type-II ML on a seeded random subset (cost O(k^3) instead of O(n^3)), then
            # the hyperparameters are copied into the GP on all n points
            target = self._new_gp(tX[sub], tY[sub])
            target.load_state_dict(_hyper_tensors(model), strict=False)
        mll = ExactMarginalLogLikelihood(target.likelihood, target)
        # fit_gpytorch_mll may resample hyperparameters from their priors after a failed
        # attempt: seed that so a fit is a deterministic function of (data, state).
        with torch.random.fork_rng(), gpytorch.settings.max_cholesky_size(MAX_CHOLESKY):
            torch.manual_seed(1234 + n)
            fit_gpytorch_mll(mll, optimizer_kwargs={"options": {"maxiter": self.fit_maxiter}})
        if target is not model:
            model.load_state_dict(_hyper_tensors(target), strict=False)

    @property
    def fast_model(self) -> ExactIndependentGP:
        """:class:`~mpcmobo.bo.fastpost.ExactIndependentGP` with ``.model``'s exact posterior
        (cached per fit): used for predictions and acquisition evaluation."""
        if self.model is None:
            raise RuntimeError("fit() first")
        if self._fast is None:
            self._fast = ExactIndependentGP.from_singletask(self.model)
        return self._fast

    def is_fitted_on(self, X: np.ndarray, Y: np.ndarray) -> bool:
        """True if the last fit used exactly the finite rows of ``(X, Y)``."""
        if self.model is None or self.train_X is None:
            return False
        X, Y = _as_2d(X), _as_2d(Y)
        ok = finite_rows(Y) & finite_rows(X)
        return np.array_equal(X[ok], self.train_X) and np.array_equal(Y[ok], self.train_Y)  # type: ignore[arg-type]  # set with train_X

    # ------------------------------------------------------------------ prediction
    def posterior_model_space(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Latent posterior mean and std (n, m) of the maximisation targets ``t = -g(y)``
        (eq. mean_var, after undoing the standardisation).

        Evaluated in blocks of :data:`ROW_BLOCK` points: the same numbers as one block (every
        point's posterior is computed on its own row), with temporaries that stay in cache
        (at 3,300 points and n = 590, 1.4x faster than one block)."""
        if self.model is None:
            raise RuntimeError("fit() first")
        means, stds = [], []
        for tX in _row_blocks(X):
            with torch.no_grad():
                post = self.fast_model.posterior(tX)  # eq. post / mean_var
                means.append(post.mean.squeeze(-2).numpy().copy())
                var = post.variance.squeeze(-2).clamp_min(0.0).numpy().copy()
            stds.append(np.sqrt(var))
        if len(means) == 1:
            return means[0], stds[0]
        return np.concatenate(means), np.concatenate(stds)

    def posterior_mean_model_space(self, X: np.ndarray) -> np.ndarray:
        """The mean (n, m) of :meth:`posterior_model_space` alone (the same numbers, bit for
        bit), without the cost of the standard deviations; in blocks as there."""
        if self.model is None:
            raise RuntimeError("fit() first")
        out = []
        for tX in _row_blocks(X):
            with torch.no_grad():
                out.append(self.fast_model.posterior_mean(tX).squeeze(-2).numpy().copy())
        return out[0] if len(out) == 1 else np.concatenate(out)

    def cost_samples(
        self, Z: np.ndarray, *, n_samples: int, seed: int, joint: bool = False
    ) -> np.ndarray:
        """Posterior samples (S, n, m) of the latent costs at the points ``Z`` (n, d), in cost
        units, seeded (a forked torch random state). ``joint=False``: each point sampled on its
        own (the marginals); ``joint=True``: all n points on one joint posterior (common
        random numbers for comparing a few points)."""
        X = torch.as_tensor(np.atleast_2d(np.asarray(Z, dtype=np.float64)), dtype=DTYPE)
        X = X.unsqueeze(0) if joint else X.unsqueeze(-2)  # (1, n, d) or (n, 1, d)
        offsets = self.offsets
        with (
            torch.no_grad(),
            torch.random.fork_rng(),
            gpytorch.settings.max_cholesky_size(MAX_CHOLESKY),
        ):
            torch.manual_seed(int(seed))
            s = self.fast_model.posterior(X).rsample(torch.Size([int(n_samples)]))
            cols = []
            for j in range(s.shape[-1]):
                t = s[..., j]
                cols.append(torch.exp(-t) - float(offsets[j]) if self.log_outcomes[j] else -t)
            out = torch.stack(cols, dim=-1)  # S x b x q x m
        out = out[:, 0] if joint else out.reshape(int(n_samples), -1, out.shape[-1])
        return out.numpy().astype(np.float64)

    def predict(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Posterior mean and std (n, m) of the costs in the original minimisation units.

        Log outputs: mean and std of the back-transformed (log-normal) value
        (:mod:`mpcmobo.bo.transforms`).
        """
        return self.to_cost_space(*self.posterior_model_space(X))

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """Plain-python/numpy, picklable state: settings, counters, hyperparameters.

        Restoring it and calling ``fit`` on the same data rebuilds exactly the same model;
        taken after a fit, :meth:`restore` rebuilds that fit's model without fitting.
        """
        return {
            "version": 1,
            "num_outputs": self.num_outputs,
            "refit_every": self.refit_every,
            "refit_fraction": self.refit_fraction,
            "log_outcomes": list(self.log_outcomes),
            "min_refit_n": self.min_refit_n,
            "fit_maxiter": self.fit_maxiter,
            "fit_subsample": self.fit_subsample,
            "calls_since_refit": self._calls_since_refit,
            "n_fits": self._n_fits,
            "hyper": None if self._hyper is None else {k: v.copy() for k, v in self._hyper.items()},
            "group_outputs": list(self.group_outputs),
            "group_prior_std": self.group_prior_std,
            "group_offsets": {int(g): v.copy() for g, v in self.group_offsets.items()},
            "last_fit_was_full": self.last_fit_was_full,
        }

    def load_state_dict(self, d: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (no fitted model: the next :meth:`fit` rebuilds it)."""
        self.num_outputs = int(d["num_outputs"])
        self.refit_every = int(d["refit_every"])
        self.refit_fraction = float(d["refit_fraction"])
        self.log_outcomes = [bool(b) for b in d["log_outcomes"]]
        self.min_refit_n = int(d["min_refit_n"])
        self.fit_maxiter = int(d["fit_maxiter"])
        fs = d["fit_subsample"]
        self.fit_subsample = None if fs is None else int(fs)
        self._calls_since_refit = int(d["calls_since_refit"])
        self._n_fits = int(d["n_fits"])
        h = d["hyper"]
        self._hyper = None if h is None else {k: np.array(v) for k, v in h.items()}
        self.group_outputs = [bool(b) for b in d["group_outputs"]]
        self.group_prior_std = float(d["group_prior_std"])
        self._reset_fit()
        self.group_offsets = {int(g): np.array(v) for g, v in d["group_offsets"].items()}


def fit_gp(
    X: np.ndarray,
    Y: np.ndarray,
    state: dict[str, Any] | None = None,
    **kwargs: Any,
) -> GPSurrogate:
    """Functional form: a :class:`GPSurrogate` (restored from ``state`` if given) fitted on
    ``(X, Y)``. ``kwargs`` go to the constructor when ``state`` is None."""
    Y2 = _as_2d(Y)
    sur = GPSurrogate(Y2.shape[1], **kwargs)
    if state is not None:
        sur.load_state_dict(state)
    return sur.fit(X, Y2)
