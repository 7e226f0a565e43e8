"""A :class:`~mpcmobo.systems.System` built in Python, recorded so that a tuner loads it again.

``Tuner(system_object, ...)`` saves the system as ``DIR/system.pkl`` (:func:`save_system`) and
registers it under its name; :func:`restore_system` registers it again when the tuner is loaded
(in any process). A system pickles with its CasADi functions; its Python functions (the
dynamics, the path constraints) are pickled by reference, so they must be importable: defined
at the top level of a module, not in a script run as ``__main__``, a function's body or a
lambda. :func:`recorded_system` refuses the others, saying how to make the system loadable.
Where their module was found is recorded too (``DIR/system-modules.json``: the directory on the
Python path of each), so that ``mpcmobo ask`` run from elsewhere, without that directory on its
path, imports it from there.
"""

from __future__ import annotations

import importlib.util
import json
import pickle
import sys
from pathlib import Path

from mpcmobo.experiment import storage
from mpcmobo.experiment.plantlog import TunerError
from mpcmobo.systems.base import System
from mpcmobo.systems.registry import (
    BUILTIN_SYSTEMS,
    add_to_path,
    is_registered,
    register_system,
)

SYSTEM_FILE = "system.pkl"
MODULES_FILE = "system-modules.json"


def _factory(system: System) -> object:
    """A factory without arguments that returns ``system`` (the registry applies the MPC
    settings to it)."""

    def make_system() -> System:
        return system

    return make_system


def recorded_system(system: System) -> System:
    """``system``, registered under its name in this process, if it can be loaded again from
    its pickle; else a :class:`TunerError` saying how to make it loadable."""
    how = (
        "give its factory instead, a function that returns it: Tuner('path/to/file.py:"
        "make_system', ...) (as --system), or register_system(name, make_system) in every "
        "process that loads the tuner"
    )
    if system.name in BUILTIN_SYSTEMS:
        raise TunerError(
            f"the System is named {system.name!r}, a built-in system's name: give it a name of "
            "its own (System(name=...))"
        )
    for label in ("dynamics", "path_constraints"):
        fn = getattr(system, label)
        if fn is None:
            continue
        module = getattr(fn, "__module__", None)
        qualname = getattr(fn, "__qualname__", "")
        if module in (None, "__main__") or "<" in qualname:
            where = "a script run as __main__" if module == "__main__" else "a function or lambda"
            raise TunerError(
                f"the System {system.name!r} cannot be recorded for Tuner.load: its {label} "
                f"({qualname or fn!r}) is defined in {where}, which another process cannot "
                f"import; define it at the top level of a module, or {how}"
            )
    try:
        pickle.dumps(system)
    except Exception as err:  # noqa: BLE001 - any object pickle cannot take
        raise TunerError(
            f"the System {system.name!r} cannot be recorded for Tuner.load "
            f"({type(err).__name__}: {err}); {how}"
        ) from None
    register_system(system.name, _factory(system), overwrite=True)  # type: ignore[arg-type]
    return system


def module_roots(system: System) -> dict[str, str]:
    """The directory on the Python path that each module of the system's functions was
    imported from (its name: the directory), where the module has a file."""
    roots = {}
    for label in ("dynamics", "path_constraints"):
        name = getattr(getattr(system, label), "__module__", None)
        file = getattr(sys.modules.get(name or ""), "__file__", None)
        if name is None or file is None:
            continue
        path = Path(file).resolve()
        depth = name.count(".") + (path.name == "__init__.py")
        roots[name] = str(path.parents[depth])
    return roots


def save_system(directory: str | Path, system: System) -> None:
    """``system`` (from :func:`recorded_system`) saved in the tuner's ``directory``, with
    where its functions' modules are (:func:`module_roots`)."""
    storage.write_pickle(Path(directory) / SYSTEM_FILE, system)
    text = json.dumps(module_roots(system), indent=1) + "\n"
    storage.atomic_write_text(Path(directory) / MODULES_FILE, text)


def _find_modules(directory: Path) -> None:
    """The recorded directories of the system's modules put on the Python path (at its end)
    where this process cannot import those modules otherwise."""
    try:
        roots = json.loads((directory / MODULES_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return
    for name, root in roots.items() if isinstance(roots, dict) else ():
        if importlib.util.find_spec(name.split(".")[0]) is None:
            add_to_path(root)


def restore_system(directory: str | Path) -> None:
    """Register the System a tuner in ``directory`` was given as an object (if it was, and
    its name is not registered in this process yet)."""
    path = Path(directory) / SYSTEM_FILE
    if not path.exists():
        return
    _find_modules(Path(directory))
    try:
        system = storage.read_pickle(path)
    except Exception as err:  # noqa: BLE001 - e.g. its module cannot be imported here
        raise TunerError(
            f"{path}: the tuner's System cannot be loaded ({type(err).__name__}: {err}); its "
            f"functions' module must be importable: where it was when the tuner was made "
            f"({Path(directory) / MODULES_FILE} says where), or on the Python path "
            "(PYTHONPATH)"
        ) from None
    if not isinstance(system, System):
        raise TunerError(f"{path} does not hold a System")
    if not is_registered(system.name):
        register_system(system.name, _factory(system))  # type: ignore[arg-type]
