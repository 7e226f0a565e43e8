"""Finding a system by name: built-ins, registered systems, factory paths and plug-ins.

``get_system(spec)`` builds the system named by ``spec``, one of:

- a registered name: the built-ins ``cstr`` and ``lq``, or a name given to
  :func:`register_system` in this process (a study sends the factory to its worker processes);
- ``"my_pkg.my_module:make_system"``: a function of an importable module;
- ``"path/to/file.py:make_system"``: a function of a Python file (not a package);
- the name of an installed plug-in: an entry point of the group ``mpcmobo.systems``
  (``[project.entry-points."mpcmobo.systems"] my_system = "my_pkg.my_module:make_system"``).

The factory is called without arguments (the MPC settings of a study are then applied with
:meth:`System.with_spec`) and must return a :class:`~mpcmobo.systems.System`. Spawned worker
processes receive the spec string and import the factory themselves. Every failure is a
:class:`SystemSpecError` with a one-line message naming the spec. :func:`make_plant` does the
same for a study's plant (a gymnasium environment).
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import sys
from collections.abc import Callable
from dataclasses import replace
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

from mpcmobo.systems.base import System, SystemDefinitionError

ENTRY_POINT_GROUP = "mpcmobo.systems"
BUILTIN_SYSTEMS = ("cstr", "cstr-structural", "lq")

_REGISTRY: dict[str, Callable[..., System]] = {}


class SystemSpecError(ValueError):
    """A system or plant that cannot be found, imported or built (one-line message)."""


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split())


def register_system(name: str, factory: Callable[..., System], *, overwrite: bool = False) -> None:
    """Make ``get_system(name)`` build a system with ``factory(**options)``."""
    if not isinstance(name, str) or not name:
        raise ValueError("a system name must be a non-empty string")
    if ":" in name:
        raise ValueError(f"a system name may not contain ':' (that is a factory path): {name!r}")
    if name in _REGISTRY and not overwrite:
        raise ValueError(f"a system named '{name}' is already registered")
    _REGISTRY[name] = factory


def is_factory_path(spec: str) -> bool:
    """Whether ``spec`` is ``module:function`` or ``file.py:function`` (not a name)."""
    return isinstance(spec, str) and ":" in spec


def normalise_spec(spec: str) -> str:
    """``file.py:function`` with an absolute path (so that a resumed run or a worker finds it
    from any directory); names and ``module:function`` unchanged. Checks the syntax only."""
    if not is_factory_path(spec):
        return spec
    target, _, attr = spec.rpartition(":")
    if not target or not attr.isidentifier():
        raise SystemSpecError(f"'{spec}' is not 'module:function' or 'path/to/file.py:function'")
    if _is_file(target):
        return f"{Path(target).expanduser().resolve()}:{attr}"
    if not all(part.isidentifier() for part in target.split(".")):
        raise SystemSpecError(
            f"'{spec}': '{target}' is neither a module name nor a path to a .py file"
        )
    return spec


def _is_file(target: str) -> bool:
    return target.endswith(".py") or "/" in target or "\\" in target


def load_object(spec: str, what: str = "system factory") -> Any:
    """The object named by ``module:attr`` or ``file.py:attr``."""
    spec = normalise_spec(spec)
    target, _, attr = spec.rpartition(":")
    if _is_file(target):
        module = _load_file(Path(target), spec, what)
    else:
        try:
            module = importlib.import_module(target)
        except Exception as err:  # noqa: BLE001 - user code: any failure is reported
            raise SystemSpecError(
                f"{what} '{spec}': cannot import module '{target}': {type(err).__name__}: {_one_line(err)}"
            ) from None
    if not hasattr(module, attr):
        raise SystemSpecError(f"{what} '{spec}': '{target}' has no attribute '{attr}'")
    obj = getattr(module, attr)
    if not callable(obj):
        raise SystemSpecError(f"{what} '{spec}': '{attr}' is not callable")
    return obj


def add_to_path(folder: str | Path) -> None:
    """``folder`` (a user's: their system's or plant's modules) on the Python path, at its end,
    so that it shadows no installed package."""
    if str(folder) not in sys.path:
        sys.path.append(str(folder))


def _load_file(path: Path, spec: str, what: str) -> Any:
    """Import a Python file once per process, as a module named after its path. Its folder
    goes on the Python path (:func:`add_to_path`), so that it imports the modules beside it,
    as a script run from there would."""
    if not path.is_file():
        raise SystemSpecError(f"{what} '{spec}': file not found: {path}")
    add_to_path(path.resolve().parent)
    digest = hashlib.sha1(str(path).encode()).hexdigest()[:10]
    name = f"mpcmobo_user_{path.stem if path.stem.isidentifier() else 'file'}_{digest}"
    if name in sys.modules:
        return sys.modules[name]
    module_spec = importlib.util.spec_from_file_location(name, path)
    if module_spec is None or module_spec.loader is None:
        raise SystemSpecError(f"{what} '{spec}': {path} is not a Python file")
    module = importlib.util.module_from_spec(module_spec)
    sys.modules[name] = module
    try:
        module_spec.loader.exec_module(module)
    except BaseException as err:  # noqa: BLE001 - SystemExit of a script, syntax errors, ...
        del sys.modules[name]
        if isinstance(err, KeyboardInterrupt):
            raise
        raise SystemSpecError(
            f"{what} '{spec}': cannot import {path}: {type(err).__name__}: {_one_line(err)}"
        ) from None
    return module


def _plugins() -> dict[str, Any]:
    """The installed plug-ins: entry points of the group ``mpcmobo.systems``, by name."""
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def available_systems() -> list[str]:
    """Registered names and installed plug-ins."""
    return sorted(set(_REGISTRY) | set(_plugins()))


def describe_systems() -> list[tuple[str, str]]:
    """(name, where it comes from) of every system that can be run by name."""
    out = []
    for name in sorted(_REGISTRY):
        out.append((name, "built-in" if name in BUILTIN_SYSTEMS else "registered"))
    for name, ep in sorted(_plugins().items()):
        if name not in _REGISTRY:
            dist = getattr(getattr(ep, "dist", None), "name", None)
            out.append((name, f"plug-in {ep.value}" + (f" ({dist})" if dist else "")))
    return out


def is_registered(spec: str) -> bool:
    """Whether ``spec`` is a name registered in this process (its factory can be pickled)."""
    return spec in _REGISTRY


def system_factory(spec: str) -> Callable[..., System]:
    """The factory named by ``spec`` (see the module docstring)."""
    if not isinstance(spec, str) or not spec:
        raise SystemSpecError(f"a system is named by a non-empty string, got {spec!r}")
    if spec in _REGISTRY:
        return _REGISTRY[spec]
    if is_factory_path(spec):
        return load_object(spec)
    plugins = _plugins()
    if spec in plugins:
        try:
            return plugins[spec].load()
        except Exception as err:  # noqa: BLE001 - a broken plug-in is reported, not raised
            raise SystemSpecError(
                f"plug-in system '{spec}' ({plugins[spec].value}) cannot be loaded: "
                f"{type(err).__name__}: {_one_line(err)}"
            ) from None
    raise SystemSpecError(
        f"unknown system '{spec}'; available: {', '.join(available_systems())}; or give a "
        "factory as 'module:function' or 'path/to/file.py:function'"
    )


def _takes_options(factory: Any, options: dict[str, Any]) -> bool:
    """Whether ``factory`` accepts the keyword arguments ``options`` (``**kwargs`` or each by
    name)."""
    try:
        params = inspect.signature(factory).parameters
    except (TypeError, ValueError):  # a callable without a signature: as registered
        return True
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return True
    return all(k in params for k in options)


def get_system(spec: str, **options: Any) -> System:
    """Build the system named by ``spec`` with the MPC settings ``options`` (``MPCSpec``
    overrides). A registered factory that takes them receives them as keywords; any other
    factory (one without keyword arguments, a factory path, a plug-in) is called without
    arguments and the settings are applied to the ``MPCSpec`` it returns."""
    factory = system_factory(spec)
    registered = spec in _REGISTRY
    takes = registered and _takes_options(factory, options)  # else: overrides applied after
    try:
        system = factory(**options) if takes else factory()
    except SystemDefinitionError as err:
        raise SystemDefinitionError(f"system '{spec}': {err}") from None
    except Exception as err:  # noqa: BLE001 - user code: any failure is reported
        if registered:
            raise
        raise SystemSpecError(
            f"the system factory '{spec}' failed: {type(err).__name__}: {_one_line(err)}"
        ) from None
    if not isinstance(system, System):
        raise SystemSpecError(
            f"the system factory '{spec}' returned {type(system).__name__}, expected a "
            "mpcmobo.systems.System"
        )
    if options and not takes:
        try:
            system = replace(
                system, mpc_spec=system.mpc_spec.with_overrides(system.name, **options)
            )
        except (TypeError, ValueError) as err:
            raise SystemSpecError(f"system '{spec}': {err}") from None
    return system


def make_plant(
    spec: str | None,
    system: System,
    *,
    process_noise: Any = None,
    measurement_noise: Any = None,
) -> Any:
    """The plant of a study: ``spec`` a gymnasium id (``"mpcmobo/CSTR-v0"``) or a factory
    path returning a ``gymnasium.Env``; None: the system's own equations
    (:class:`~mpcmobo.systems.plant.SystemPlant`, with the given noise levels, which only it
    takes). Its spaces must match the model's sizes."""
    import gymnasium

    from mpcmobo.systems.plant import SystemPlant, check_plant

    if spec is None:
        return SystemPlant(system, process_noise=process_noise, measurement_noise=measurement_noise)
    if process_noise is not None or measurement_noise is not None:
        raise SystemSpecError(
            f"plant '{spec}': process_noise and measurement_noise apply to the system's own "
            "plant; a plant of your own adds its own noise"
        )
    if is_factory_path(spec):
        make = load_object(spec, what="plant factory")
        try:
            env = make()
        except Exception as err:  # noqa: BLE001 - user code: any failure is reported
            raise SystemSpecError(
                f"the plant factory '{spec}' failed: {type(err).__name__}: {_one_line(err)}"
            ) from None
    else:
        try:
            env = gymnasium.make(spec)
        except Exception as err:  # noqa: BLE001 - unknown ids, bad entry points
            raise SystemSpecError(
                f"plant '{spec}': {type(err).__name__}: {_one_line(err)}"
            ) from None
    if not isinstance(env, gymnasium.Env):
        raise SystemSpecError(
            f"the plant factory '{spec}' returned {type(env).__name__}, expected a gymnasium.Env"
        )
    check_plant(env, system, label=f"plant '{spec}'")
    return env
