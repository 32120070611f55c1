"""The faces of the plate, one module per face behind one interface (`Face`, `plate.faces.base`): each knows
its boundary tables (deterministic engine), how it scatters one photon (photon engine) and what physics
it stands for.

- `flat.FlatFace`: Fresnel (Born & Wolf 1.5.20-21, Mueller matrices of core.fresnel);
- `relief.ReliefFace(relief, method, samples, seed, options)`: tables by `methods.reconstruct` of the
  relief (`derive`); photons traced through the triangulated relief (methods.ray.ReliefTracer) when the
  method is geometric ray tracing ("ray"), otherwise drawn from the face's own tables;
- `table.TableFace(inside, outside)`: given tables; photons drawn from them;
- `microfacet.MicrofacetFace(alpha)`: a Beckmann rough face (Walter et al. 2007): tables from the
  microfacet method at that alpha; photons by sampling Beckmann normals (core.microfacet) with one
  Fresnel event on the sampled facet, Smith masking G1 of both directions as the weight.

Beside them: `derive` (a relief face's tables, kept by the memory owner), `sectors` (how a relief meets
the light inside the plate by azimuth: anisotropy, inside sector tables, the azimuth probe), `photons`
(Fresnel events and table sampling the faces share).
"""
from relief_bsdf.plate.faces.base import Face, FaceEvent, PhotonContext, beam_in_table, material_key, relief_digest
from relief_bsdf.plate.faces.derive import (THREADED_METHODS, TRACED_METHODS, face_request, same_indices)
from relief_bsdf.plate.faces.flat import FlatFace
from relief_bsdf.plate.faces.microfacet import MicrofacetFace
from relief_bsdf.plate.faces.photons import TableSampler, fresnel_event, projected_solid_angle_cells
from relief_bsdf.plate.faces.relief import ReliefFace, half_turned_outside
from relief_bsdf.plate.faces.sectors import (ANISOTROPY_WARN, ISOTROPY_WARNING, PROBE_AZIMUTH_DEG, PROBE_L1,
                                             PROBE_THETA_DEG, SECTOR_AZIMUTHS_DEG, SECTOR_RAY_TABLES, SECTORS_KEY,
                                             TILE_SECTOR_AZIMUTHS_DEG, TILE_SECTOR_RAY_TABLES, anisotropic_face,
                                             azimuth_dependent, azimuth_probe_l1, inside_face, inside_sectors,
                                             isotropy_warning, sector_plan, slope_anisotropy)
from relief_bsdf.plate.faces.table import TableFace

__all__ = ["Face", "FaceEvent", "PhotonContext", "beam_in_table", "material_key", "relief_digest", "THREADED_METHODS",
           "TRACED_METHODS", "face_request", "same_indices", "FlatFace", "MicrofacetFace", "TableSampler",
           "fresnel_event", "projected_solid_angle_cells", "ReliefFace", "half_turned_outside", "ANISOTROPY_WARN",
           "ISOTROPY_WARNING", "PROBE_AZIMUTH_DEG", "PROBE_L1", "PROBE_THETA_DEG", "SECTOR_AZIMUTHS_DEG",
           "SECTOR_RAY_TABLES", "SECTORS_KEY", "TILE_SECTOR_AZIMUTHS_DEG", "TILE_SECTOR_RAY_TABLES", "anisotropic_face",
           "azimuth_dependent", "azimuth_probe_l1", "inside_face", "inside_sectors", "isotropy_warning", "sector_plan",
           "slope_anisotropy", "TableFace"]
