"""Bayesian optimisation on the unit cube: GP surrogates, (Log)EI, (Log)EHVI, Pareto tools.

Inputs ``X`` (n, d) lie in [0,1]^d; outcomes ``Y`` (n, m) are costs to be MINIMISED (BoTorch
maximises: the surrogate negates internally). NaN/inf rows are dropped before fitting.
"""

from mpcmobo.bo.acquisition import (
    AcqfSearch,
    EHVIOptions,
    posterior_front,
    propose_ehvi,
    propose_ei,
)
from mpcmobo.bo.pareto import (
    finite_rows,
    hypervolume,
    pareto_mask,
    reference_point,
)
from mpcmobo.bo.surrogate import GPSurrogate, fit_gp

__all__ = [
    "AcqfSearch",
    "EHVIOptions",
    "GPSurrogate",
    "finite_rows",
    "fit_gp",
    "hypervolume",
    "pareto_mask",
    "posterior_front",
    "propose_ehvi",
    "propose_ei",
    "reference_point",
]
