"""Contact models: PF and PFF (baselines, eq. 3-5), NH (eq. 14-20), smoothed NH (IV-C) and NH with the pressure
field's normal force (``nh_pressure_normal``: NH's shear and stick-slip, PF's normal force).

All of them share ``step(geometry: ContactStep, forces, material) -> forces`` (see ``base.ContactModel``).
"""

import dataclasses

from hydrosoft.contact.base import ContactModel, ContactStep, Material
from hydrosoft.contact.nonholonomic import (
    NonHolonomic, NonHolonomicPressureNormal, SmoothedNonHolonomic, inside_fraction,
)
from hydrosoft.contact.pressure_field import PressureField, PressureFieldFrictionless
from hydrosoft.contact.wrenches import wrench

MODELS = {
    "nh": NonHolonomic,
    "snh": SmoothedNonHolonomic,
    "pf": PressureField,
    "pff": PressureFieldFrictionless,
    "nh_pressure_normal": NonHolonomicPressureNormal,
}


def make(name: str, **params) -> ContactModel:
    """Build a contact model by name (one of ``MODELS``) with its parameters.

    Raises ValueError for an unknown name, an unknown parameter (naming the ones the model takes) or a bad value
    (naming the parameter).
    """
    try:
        cls = MODELS[name]
    except KeyError:
        raise ValueError(f"unknown contact model {name!r}; known models: {', '.join(MODELS)}") from None
    known = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(params) - set(known))
    if unknown:
        takes = f"it takes {', '.join(known)}" if known else "it takes none"
        raise ValueError(f"{', '.join(unknown)}: unknown parameter(s) of contact model {name!r}; {takes}")
    return cls(**params)


__all__ = [
    "ContactModel", "ContactStep", "Material", "NonHolonomic", "NonHolonomicPressureNormal", "SmoothedNonHolonomic",
    "PressureField",
    "PressureFieldFrictionless", "inside_fraction", "wrench", "make", "MODELS",
]
