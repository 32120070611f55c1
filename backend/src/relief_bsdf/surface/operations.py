"""Pipeline operations on a relief that the fit and the diagnosis vary: the ONE definition.

`scale_and_filter(relief, height_scale, filter_sigma_m)` is paper sec. 3 step 6, the global
relief modification the fit optimises and the diagnosis's relief_scale / relief_smoothing
effects apply:

    z'(x, y) = s * (G_sigma * z)(x, y)

with G_sigma a Gaussian of standard deviation sigma (metres, both axes).  Scaling multiplies
heights and slopes by s (raises diffuse scattering); smoothing lowers slopes faster than
heights (sigma_slope / sigma_height falls), so the two parameters act differently on the
plate.  Filtering is NaN-aware (normalised convolution, `Relief.gaussian_filtered`):
invalid points neither contribute nor get filled, so a measured map with holes keeps them
(filling holes with the mean, as an older copy did, biases their neighbours toward the mean
height).  Periodic tiles wrap around, non-periodic maps are mirrored at the border
(scipy 'reflect').  Both operations are linear, so their order does not matter.
"""
from __future__ import annotations

from relief_bsdf.surface.relief import Relief


def scale_and_filter(relief: Relief, height_scale: float, filter_sigma_m: float) -> Relief:
    """Relief with heights times `height_scale`, then Gaussian-filtered with sigma `filter_sigma_m` (m).

    Each step is recorded in the relief's history.  A zero sigma leaves the heights unfiltered;
    a negative one or a negative scale is an InputError.
    """
    return relief.scaled(float(height_scale)).gaussian_filtered(float(filter_sigma_m))
