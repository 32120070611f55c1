"""The rough surface: the height map and everything derived from its geometry alone.

    relief      Relief (heights in m on a grid, NaN = not measured, history of what was done) and its
                operations: level, fill_holes, scaled, gaussian_filtered, cropped
    operations  scale_and_filter: the fit's and the diagnosis's relief modification (one definition)
    stats       the ONE slope definition (slopes, facet_slopes, rms_slope, rms_height_and_slope), rms
                height, ACF, PSD, correlation length, facet normals, slope histogram (relief_stats)
    synth       the ONE random-field generator (random_relief / RandomFieldSpec / relief_from_spec /
                random_heights / gaussian_field,
                autocovariance s^2 exp(-r^2/L^2) or s^2 exp(-r/L)) and light-guide dot patterns
    mesh        the ONE triangulation (build_tile_mesh: the periodic mesh the ray tracer intersects)
"""
from relief_bsdf.surface.mesh import TileMesh, build_tile_mesh, periodic_heights
from relief_bsdf.surface.operations import scale_and_filter
from relief_bsdf.surface.relief import Relief
from relief_bsdf.surface.stats import (
    ReliefStats, acf_2d, facet_normals, facet_slopes, levelled, psd_2d, radial_psd, relief_stats, rms_height,
    rms_height_and_slope, rms_slope, rms_slope_xy, slope_histogram, slopes)
from relief_bsdf.surface.synth import (
    DotPattern, RandomFieldSpec, gaussian_field, lgp_dots, random_heights, random_relief, relief_from_spec)

__all__ = ["Relief", "scale_and_filter", "TileMesh", "build_tile_mesh", "periodic_heights",
           "ReliefStats", "relief_stats", "levelled", "slopes", "facet_slopes", "facet_normals", "rms_height",
           "rms_slope", "rms_slope_xy", "rms_height_and_slope", "slope_histogram", "acf_2d", "psd_2d", "radial_psd",
           "RandomFieldSpec", "gaussian_field", "random_heights", "random_relief", "relief_from_spec", "DotPattern",
           "lgp_dots"]
