"""Contact models: PF and PFF (baselines, eq. 3-5), NH (eq. 14-20) and smoothed NH (IV-C).

All four share ``step(geometry: ContactStep, forces, material) -> forces`` (see ``base.ContactModel``).
"""

from hydrosoft.contact.base import ContactModel, ContactStep, Material
from hydrosoft.contact.nonholonomic import NonHolonomic, SmoothedNonHolonomic, inside_fraction
from hydrosoft.contact.pressure_field import PressureField, PressureFieldFrictionless
from hydrosoft.contact.wrenches import wrench

MODELS = {
    "nh": NonHolonomic,
    "snh": SmoothedNonHolonomic,
    "pf": PressureField,
    "pff": PressureFieldFrictionless,
}


def make(name: str, **params) -> ContactModel:
    """Build a contact model by name (``nh``, ``snh``, ``pf``, ``pff``); raises ValueError for others."""
    try:
        cls = MODELS[name]
    except KeyError:
        raise ValueError(f"unknown contact model {name!r}; known models: {', '.join(MODELS)}") from None
    return cls(**params)


__all__ = [
    "ContactModel", "ContactStep", "Material", "NonHolonomic", "SmoothedNonHolonomic", "PressureField",
    "PressureFieldFrictionless", "inside_fraction", "wrench", "make", "MODELS",
]
