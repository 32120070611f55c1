"""Method `ray`: geometric-optics ray tracing of the real relief with Embree (paper sec. 2.3).

Model and regime of validity
----------------------------
Geometric optics on the measured surface: valid when the relief's lateral features
(correlation length) and heights are much larger than the wavelength, so that each facet
reflects and refracts like a flat interface and diffraction is negligible (Beckmann &
Spizzichino 1963, ch. 2; Ogilvy 1991 sec. 4).  Polarisation is tracked exactly within that
model; interference between rays is ignored.

- Surface (`tracer`): the height map as the one periodic triangulation
  (`surface.mesh.build_tile_mesh`) in an Embree BVH built once per relief; a ray leaving the
  tile sideways re-enters from the opposite side (no boundary losses at grazing incidence).
  Embree's buffers are written by numpy (`embree_buffers`, fallback: embreex's TriangleMesh);
  a fit re-uses the grid: `ReliefTracer.with_heights` (new tracer, topology reused) or
  `update_heights` (in place, BVH refitted).
- Transport (`transport`): ONE bounce loop, generic over what a ray carries - unpolarised
  intensity or K Stokes columns (a Mueller matrix for tables) - with the per-event Fresnel
  update supplied by the carrier (Fresnel: `core.fresnel`, Born & Wolf 1.5.20-21; Stokes frame
  rotation: `core.stokes`).  Reflect or refract by Russian roulette on the reflectance of the
  ray's current state, P_R = (M_R S)_0 / S_0, with S <- M S / P (Veach 1997 sec. 4.2: unbiased,
  every weight stays 1; the uniform numbers are a hash of (chunk, path, interaction): common
  random numbers across height maps); for tables the first interaction is split deterministically into both
  branches (option `first_hit_split`, default True: a flat surface is then exact and the BRDF
  of a dielectric gets all N rays).  Without polarisation the unpolarised Fresnel reflectance
  is used at every bounce (the usual scalar approximation).  Light transmitted into an
  absorbing medium is absorbed and counted as `lost`.
- Exits (`exits`): one record per finished path (direction, weight, state, bounces, Stokes
  columns in the frame s = z x k, p = s x k).
- Tables (`method`): one `parallel.map_tasks` task per (side, wavelength, incidence); exits go
  through the one table builder (`bsdf.builder`: cell averages in projected solid angle,
  1/sr, delta parts along the flat mean plane's ideal directions, `lost`, sigma = Monte-Carlo
  noise and the finite tile's realisation uncertainty from sub-tile batch means, with a warning
  when the tile holds too few correlation areas for the cells).
  For light from inside the table's frame is mirrored (z -> -z) and Mueller matrices become
  D M D, D = diag(1, 1, -1, -1).

Options (request.options): polarized (True), max_bounces (100), first_hit_split (True),
specular_tol_rad (1e-5), fill_holes (None: NaN refused; True or a max gap in px), threads
(in this process; a pool worker uses one), backend (map_tasks backend, default as configured),
tile_uncertainty (True: sigma includes the tile's realisation uncertainty).
`request.samples` rays per (wavelength, incidence, side).  Tables store the unpolarised BSDF
(M00) whatever `request.polarization` says; the Mueller matrices carry the rest.
Speed: benchmarks/bench_ray.py (paths/s and the ratio to Embree alone on the same segments).  The
hottest numpy-side steps (slab distances, facets, the polarised event, exit records and columns, the
table builder's binning) run as optional compiled kernels (`relief_bsdf.kernels`, Cython, built by
`pip install -e backend`) with the numpy code as fallback: the same tables bit for bit; the kernel that
ran is in each table's metadata["ray_kernel"].
"""
from relief_bsdf.bsdf.builder import CellIndex as _CellIndex   # noqa: F401  (kept for tests/benchmarks)
from relief_bsdf.methods.ray.exits import STATE_NAMES, Exits
from relief_bsdf.methods.ray.method import check_request, reconstruct, reconstruct_with
from relief_bsdf.methods.ray.tracer import CHUNK, ReliefTracer, ScatterResult
from relief_bsdf.methods.ray.transport import IntensityCarrier, Media, Rays, StokesCarrier, TraceSettings, trace_chunk

__all__ = ["reconstruct", "reconstruct_with", "check_request", "ReliefTracer", "ScatterResult", "Exits",
           "STATE_NAMES", "CHUNK", "trace_chunk", "Rays", "Media", "TraceSettings", "IntensityCarrier",
           "StokesCarrier"]
