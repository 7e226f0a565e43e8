"""Plants, models, costs and constraints; the CSTR of the paper; finding a user's system."""

from mpcmobo.systems.base import System, SystemDefinitionError, rk4_step
from mpcmobo.systems.cstr import make_cstr, make_cstr_structural
from mpcmobo.systems.lq import make_lq
from mpcmobo.systems.parameterization import MPCSpec, Parameterization
from mpcmobo.systems.registry import (
    SystemSpecError,
    available_systems,
    describe_systems,
    get_system,
    make_plant,
    register_system,
)
from mpcmobo.systems.space import SearchSpace

register_system("cstr", make_cstr)
register_system("cstr-structural", make_cstr_structural)
register_system("lq", make_lq)

__all__ = [
    "MPCSpec",
    "Parameterization",
    "SearchSpace",
    "System",
    "SystemDefinitionError",
    "SystemSpecError",
    "available_systems",
    "describe_systems",
    "get_system",
    "make_plant",
    "make_cstr",
    "make_cstr_structural",
    "make_lq",
    "register_system",
    "rk4_step",
]
