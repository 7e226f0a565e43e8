"""Identification of the MPC's model parameters from the plant's transitions.

:func:`identify` fits the declared model parameters of a system's own model structure
(``System.discrete_step``) to observed transitions ``(x_k, u_k) -> x_{k+1}`` by robust least
squares on the scaled one-step prediction error, within the parameters' bounds, with a prior
toward the nominal model; :class:`Transitions` collects the transitions of episodes.
:func:`~mpcmobo.identify.fit.at_bounds` tells which estimates the bounds held.
"""

from mpcmobo.identify.fit import (
    Identification,
    ModelFit,
    Transitions,
    identify,
    prediction_error,
)

__all__ = ["Identification", "ModelFit", "Transitions", "identify", "prediction_error"]
