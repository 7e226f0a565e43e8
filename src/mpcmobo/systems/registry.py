"""Named systems: ``get_system("cstr")`` and ``register_system`` for user-defined ones.

The registry lives in the process. A study's worker processes receive the factory of their
system (``system_factory(name)``, pickled by reference) and register it again, so a system
registered by the user's script is also known to the workers.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from mpcmobo.systems.base import System

_REGISTRY: dict[str, Callable[..., System]] = {}


def register_system(name: str, factory: Callable[..., System], *, overwrite: bool = False) -> None:
    """Make ``get_system(name)`` build a system with ``factory(**options)``."""
    if not isinstance(name, str) or not name:
        raise ValueError("a system name must be a non-empty string")
    if name in _REGISTRY and not overwrite:
        raise ValueError(f"a system named '{name}' is already registered")
    _REGISTRY[name] = factory


def available_systems() -> list[str]:
    """The names of the registered systems, sorted."""
    return sorted(_REGISTRY)


def system_factory(name: str) -> Callable[..., System]:
    """The factory registered as ``name``."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown system '{name}'; available: {', '.join(available_systems())}")
    return _REGISTRY[name]


def get_system(name: str, **options: Any) -> System:
    """Build the registered system ``name`` (options go to its factory)."""
    return system_factory(name)(**options)
