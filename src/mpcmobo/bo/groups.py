"""Per-group offsets of a cost (start effects), fitted jointly with the GP's hyperparameters.

When episodes cycle through a fixed set of initial states, the start explains much of an
episode's cost. For one output the model is

``t_i = h(x_i) + b_{g_i} + eps_i``,  ``h ~ GP(c, k_SE-ARD)``,  ``b_s ~ N(0, tau^2)``,
``eps_i ~ N(0, sigma_n^2)``,

with ``g_i`` the group (start index) of row ``i`` (-1: no group, ``b = 0``). The offsets enter
as a mean function ``c + b_g`` whose parameters are maximised together with the kernel and
noise hyperparameters (type-II maximum a posteriori: BoTorch's priors on the kernel, the
Gaussian prior above on ``b``), on standardised targets. :class:`GPSurrogate` subtracts the
fitted offsets and models ``h`` alone, the cost of an average start.
"""

from __future__ import annotations

import gpytorch
import numpy as np
import torch
from botorch.fit import fit_gpytorch_mll
from botorch.models import SingleTaskGP
from botorch.models.transforms.outcome import Standardize
from botorch.models.utils.gpytorch_modules import get_covar_module_with_dim_scaled_prior
from gpytorch.means import Mean
from gpytorch.mlls import ExactMarginalLogLikelihood
from gpytorch.priors import NormalPrior

__all__ = [
    "DTYPE",
    "MAX_CHOLESKY",
    "GroupOffsetMean",
    "fit_group_offsets",
]

DTYPE = torch.float64
# Exact Cholesky up to this many training points (gpytorch switches to CG above 800 by default).
MAX_CHOLESKY = 5000


class GroupOffsetMean(Mean):
    """``m(x) = c + b[g]`` where ``g = x[..., -1]`` is an integer group label (-1: none)."""

    def __init__(self, num_groups: int, prior_std: float) -> None:
        super().__init__()
        self.register_parameter("constant", torch.nn.Parameter(torch.zeros((), dtype=DTYPE)))
        self.register_parameter("offsets", torch.nn.Parameter(torch.zeros(num_groups, dtype=DTYPE)))
        self.register_prior("offsets_prior", NormalPrior(0.0, float(prior_std)), "offsets")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The prior mean ``c + b[g]`` at ``x`` (last column: the group label, -1 for none)."""
        g = x[..., -1].round().long()
        padded = torch.cat([self.offsets, torch.zeros(1, dtype=self.offsets.dtype)])
        return self.constant + padded[torch.where(g < 0, len(self.offsets), g)]


def _offset_gp(
    X: np.ndarray, t: np.ndarray, label: np.ndarray, num_groups: int, prior_std: float
) -> SingleTaskGP:
    """The model of the module docstring: a ``SingleTaskGP`` on ``(x, label)`` with BoTorch's
    SE-ARD kernel on ``x`` only, the mean ``c + b[label]`` and standardised targets."""
    d = X.shape[1]
    tX = torch.as_tensor(np.column_stack([X, label]), dtype=DTYPE)
    tY = torch.as_tensor(t[:, None], dtype=DTYPE)
    covar = get_covar_module_with_dim_scaled_prior(ard_num_dims=d, active_dims=list(range(d)))
    return SingleTaskGP(
        tX,
        tY,
        covar_module=covar,
        mean_module=GroupOffsetMean(num_groups, prior_std),
        outcome_transform=Standardize(m=1),
    ).to(DTYPE)


def fit_group_offsets(
    X: np.ndarray,
    t: np.ndarray,
    groups: np.ndarray,
    *,
    prior_std: float = 1.0,
    maxiter: int = 200,
    seed: int = 0,
) -> dict[int, float]:
    """MAP offsets ``b`` (in the units of ``t``) of the groups present in ``groups``, centred
    over the groups, for one output ``t`` (n,) at inputs ``X`` (n, d) in the unit cube.

    ``prior_std`` is ``tau`` in standardised units of ``t`` (1: a start may shift the cost by
    about the whole spread of the data).
    """
    X = np.asarray(X, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    groups = np.asarray(groups, dtype=int).reshape(-1)
    ids = np.unique(groups[groups >= 0])
    if ids.size == 0:
        return {}
    label = np.where(groups >= 0, np.searchsorted(ids, groups), -1).astype(np.float64)
    model = _offset_gp(X, t, label, len(ids), prior_std)
    mll = ExactMarginalLogLikelihood(model.likelihood, model)
    with torch.random.fork_rng(), gpytorch.settings.max_cholesky_size(MAX_CHOLESKY):
        torch.manual_seed(seed)
        fit_gpytorch_mll(mll, optimizer_kwargs={"options": {"maxiter": maxiter}})
    b = model.mean_module.offsets.detach().numpy().copy()
    b *= float(model.outcome_transform.stdvs.reshape(-1)[0])  # type: ignore[union-attr,operator]  # back to the units of t; Standardize
    b -= b.mean()
    return {int(g): float(b[k]) for k, g in enumerate(ids)}
