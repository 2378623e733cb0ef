"""Uncertain control-affine systems, declared once by their true parametric dynamics.

* :mod:`~drlyap.systems.model` -- :class:`UncertainSystem` (the system: its true model, design model, boxes,
  equilibrium and coordinates) and :class:`SystemDefaults` (its typed training and proof defaults);
* :mod:`~drlyap.systems.library` -- the built-in systems (:func:`pendulum`, :func:`mountain_car`, :func:`cartpole`,
  :func:`quadrotor2d`);
* :mod:`~drlyap.systems.registry` -- systems by name or spec (:func:`get_system`, :func:`resolve_system`,
  :func:`register_system`) and the record of where a run's system came from.
"""

from drlyap.specs import SPEC_FORMS
from drlyap.systems.library import cartpole, mountain_car, pendulum, quadrotor2d
from drlyap.systems.model import Dynamics, Perturbation, SystemDefaults, UncertainSystem, XiSampler
from drlyap.systems.registry import (
    IDENTITY_KEYS,
    default_source,
    get_system,
    identity_mismatch,
    register_system,
    resolve_system,
    system_names,
    system_source,
)

__all__ = [
    "IDENTITY_KEYS", "SPEC_FORMS", "Dynamics", "Perturbation", "SystemDefaults", "UncertainSystem", "XiSampler",
    "cartpole", "default_source", "get_system", "identity_mismatch", "mountain_car", "pendulum", "quadrotor2d",
    "register_system", "resolve_system", "system_names", "system_source",
]
