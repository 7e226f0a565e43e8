"""The system and the plant that a study's settings describe.

:func:`build_system` builds the system of the settings with their MPC-spec overrides (for a
learner's job, with the model parameters it identifies in theta); :func:`build_plant` makes the
plant the closed loop runs. A system or plant that cannot be built is a
:class:`~mpcmobo.experiment.sections.SettingsError` naming the key.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from mpcmobo.experiment.sections import SettingsError
from mpcmobo.systems import System, SystemDefinitionError, SystemSpecError, get_system, make_plant

if TYPE_CHECKING:
    from mpcmobo.experiment.settings import Settings


def build_system(settings: Settings, learner: str | None = None) -> System:
    """The system of the settings, with its MPC-spec overrides applied; for ``learner``'s job
    with the parameters it identifies in theta (:func:`identified_parameters`). A system that
    cannot be found, imported or built is a :class:`SettingsError` (one line, naming the key)."""
    key = "system.factory" if settings.system.factory is not None else "system.name"
    try:
        system = get_system(settings.system.spec, **settings.system.spec_overrides())
        _known_parameters(settings.system.learn_model, system, "system.learn_model")
        names = identified_parameters(settings, system, learner)
        if not names:
            return system
        return get_system(
            settings.system.spec, **settings.system.spec_overrides(), identify=tuple(names)
        )
    except (SystemSpecError, SystemDefinitionError) as err:
        raise SettingsError(f"{key}: {err}") from None
    except ValueError as err:  # an MPC setting the system refuses (or a key named above)
        raise err if isinstance(err, SettingsError) else SettingsError(f"system: {err}") from None


def _known_parameters(names: Sequence[str], system: System, key: str) -> None:
    """A :class:`SettingsError` at ``key`` if ``names`` has a parameter the system lacks."""
    known = list(system.param_names)
    if unknown := [n for n in names if n not in known]:
        raise SettingsError(f"{key}: unknown model parameter(s) {unknown}; the system has {known}")


def identified_parameters(
    settings: Settings, system: System, learner: str | None
) -> tuple[str, ...]:
    """The model parameters ``learner``'s job identifies: ``[system] identify`` (``true``: the
    system's identifiable ones, ``param_names``), and those for the ``identify`` learner; none
    without a learner (the study's reference)."""
    ident = settings.system.identify
    if learner is None:
        return ()
    if isinstance(ident, list) and ident:
        _known_parameters(ident, system, "system.identify")
        return tuple(ident)
    if ident is True or learner == "identify":
        return tuple(system.identifiable or ())
    return ()


def needs_plant(settings: Settings) -> bool:
    """Whether a study builds its plant (:func:`build_plant`): a plant of the settings, or the
    system's own with noise; else the closed loop runs the system's equations itself."""
    return settings.system.plant is not None or settings.system.noisy


def build_plant(settings: Settings, system: System) -> Any:
    """The plant of the settings (``system.plant``, default the system's equations with the
    settings' noise), checked against the system's sizes; a problem is a
    :class:`SettingsError`."""
    try:
        return make_plant(
            settings.system.plant,
            system,
            process_noise=settings.system.process_noise,
            measurement_noise=settings.system.measurement_noise,
        )
    except (SystemSpecError, SystemDefinitionError) as err:
        key = "system.plant" if settings.system.plant is not None else "system"
        raise SettingsError(f"{key}: {err}") from None
