"""Plants, models, costs and constraints; the CSTR of the paper."""

from mpcmobo.systems.base import System, rk4_step
from mpcmobo.systems.cstr import make_cstr
from mpcmobo.systems.lq import make_lq
from mpcmobo.systems.parameterization import MPCSpec, Parameterization
from mpcmobo.systems.registry import available_systems, get_system, register_system
from mpcmobo.systems.space import SearchSpace

register_system("cstr", make_cstr)
register_system("lq", make_lq)

__all__ = [
    "MPCSpec",
    "Parameterization",
    "SearchSpace",
    "System",
    "available_systems",
    "get_system",
    "make_cstr",
    "make_lq",
    "register_system",
    "rk4_step",
]
