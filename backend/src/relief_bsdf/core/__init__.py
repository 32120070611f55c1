"""The physics core: the only copies of the optics every other package uses.

Modules (data flows one way; nothing here imports from outside `core` except `errors`):
    frames      directions w(theta, phi), the sample tilt rot_y, dot / normalize (+ row-wise fast kernels),
                solid angles of cells
    index       refractive index models (constant, Cauchy, Sellmeier) and the Material pair
    fresnel     Snell, Fresnel amplitudes / powers, Mueller matrix of a flat interface, reflect /
                refract, and the float32 kernels of the ray tracer (tested equal to the reference)
    stokes      the Stokes reference frame and its rotation (Chandrasekhar / Born & Wolf), and the
                in-place float32 kernels of the ray tracer's Stokes columns (tested equal)
    microfacet  Beckmann / GGX distributions, Smith Lambda and G1, V-cavity, slope sampling
    bulk        Beer-Lambert absorption, Henyey-Greenstein phase function and its sampling
"""
from relief_bsdf.core.bulk import beer_lambert, hg_phase, sample_hg_cos, scatter_directions, slab_transmittance
from relief_bsdf.core.frames import (
    any_perpendicular, cross_rows, direction, dot, dot_rows, normalize, projected_solid_angle, rot_y, solid_angle, spherical_angles_deg)
from relief_bsdf.core.fresnel import (
    cos_transmitted, critical_angle_deg, fresnel_amplitudes, fresnel_power, fresnel_reflectance, fresnel_unpolarized,
    interface_coefficients_f32, mueller_interface, reflect, reflectance_unpolarized_f32, refract)
from relief_bsdf.core.index import (
    CauchyIndex, ConstantIndex, IndexModel, Material, SellmeierIndex, index_from_dict)
from relief_bsdf.core.microfacet import (
    DISTRIBUTIONS, distribution_D, lobes, normals_from_slopes, sample_normals, sample_slopes, smith_G1,
    smith_lambda, vcavity_G1)
from relief_bsdf.core.stokes import (
    apply_interface_mueller, apply_interface_mueller_columns, rotate_stokes, rotate_stokes_columns, rotation_by_angle,
    s_axis, s_axis_rows, stokes_rotation)

__all__ = [
    "beer_lambert", "slab_transmittance", "hg_phase", "sample_hg_cos", "scatter_directions",
    "direction", "rot_y", "dot", "dot_rows", "cross_rows", "normalize", "any_perpendicular", "spherical_angles_deg",
    "projected_solid_angle", "solid_angle",
    "cos_transmitted", "fresnel_amplitudes", "fresnel_power", "fresnel_reflectance", "fresnel_unpolarized", "critical_angle_deg",
    "reflect", "refract", "mueller_interface", "interface_coefficients_f32", "reflectance_unpolarized_f32",
    "IndexModel", "ConstantIndex", "CauchyIndex", "SellmeierIndex", "index_from_dict", "Material",
    "DISTRIBUTIONS", "lobes", "distribution_D", "smith_lambda", "smith_G1", "vcavity_G1",
    "sample_slopes", "normals_from_slopes", "sample_normals",
    "s_axis", "stokes_rotation", "rotation_by_angle", "rotate_stokes", "apply_interface_mueller",
    "s_axis_rows", "rotate_stokes_columns", "apply_interface_mueller_columns",
]
