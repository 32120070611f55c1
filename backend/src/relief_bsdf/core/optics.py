"""Transitional re-export module: import from core.index / core.fresnel (and core.frames, core.stokes).

The package was split (issue 12): index models and `Material` live in `relief_bsdf.core.index`,
the flat-interface optics (Snell, Fresnel, Mueller) in `relief_bsdf.core.fresnel`.  This module
only re-exports them so that callers keep working during the move; the integrator removes it.
"""
from relief_bsdf.core.fresnel import (  # noqa: F401
    cos_transmitted, critical_angle_deg, fresnel_amplitudes, fresnel_power, fresnel_reflectance, fresnel_unpolarized,
    interface_coefficients_f32, mueller_interface, reflect, reflectance_unpolarized_f32, refract)
from relief_bsdf.core.index import (  # noqa: F401
    CauchyIndex, ConstantIndex, IndexModel, Material, SellmeierIndex, index_from_dict)

__all__ = ["IndexModel", "ConstantIndex", "CauchyIndex", "SellmeierIndex", "index_from_dict", "Material",
           "cos_transmitted", "fresnel_amplitudes", "fresnel_power", "fresnel_reflectance", "fresnel_unpolarized", "critical_angle_deg",
           "reflect", "refract", "mueller_interface", "interface_coefficients_f32", "reflectance_unpolarized_f32"]
