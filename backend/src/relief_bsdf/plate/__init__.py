"""The ONE forward model of the plate: a description (faces, bulk, instrument) and two engines.

    experiment = Experiment(Plate(thickness_m, index, front=ReliefFace(relief), back=FlatFace(),
                                  bulk=Bulk(absorption_per_m, scatter_per_m, hg_g)),
                            Instrument(detector_half_angle_deg, polarization_q, blur_deg, tilt_deg,
                                       background_per_sr, cone_points, beam_divergence_deg))
    sim = simulate(experiment, rows, engine="deterministic" | "photon", photons=..., seed=...)
    sim.values_per_sr, sim.sigma_per_sr, sim.info      # info: the physics used (faces, engine)

- `plate.description`: the data (Experiment, Plate, Bulk, Instrument);
- `plate.faces`: FlatFace, ReliefFace, TableFace, MicrofacetFace (tables + photon interaction);
- `plate.memory`: ForwardMemory, the one owner of everything the engines keep (byte budget);
- `plate.choice`: DEFAULT_METHOD = "auto" and its resolution (the relief's own physics, once);
- `plate.grid`: TableGrid, the tables' axes = the deterministic discretisation;
- `plate.deterministic`: radiative transfer between the faces' tables (adding / azimuthal modes);
- `plate.photon`: photon Monte Carlo of the same description (independent code, checks the first);
- `plate.detector`: the one detector, its aperture blur (cone (x) Gaussian) and the beam
  divergence (each ray's incidence drawn in a ray-traced relief's table, else a quadrature of
  incidences; not a blur of the reading).

Rows are any object with wavelength_nm, theta_i_deg, phi_i_deg, side, theta_s_deg, phi_s_deg
arrays (a Recording, `Rows`, `in_plane_rows(...)`); values follow formats.md's goniophotometer
definition f = P / (P_inc Omega cos theta_s).
"""
from relief_bsdf.plate.description import SOURCE_Q, Bulk, Experiment, Instrument, Plate
from relief_bsdf.plate.faces import FlatFace, MicrofacetFace, PhotonContext, ReliefFace, TableFace, relief_digest
from relief_bsdf.plate.memory import ForwardMemory, current_memory
from relief_bsdf.plate.grid import TableGrid
from relief_bsdf.methods.flat import flat_tables   # the flat face's tables (public here too: add-on, tests)
from relief_bsdf.plate.rows import Rows, check_rows, in_plane_rows
from relief_bsdf.plate.simulate import Simulated, experiment_from_sample, simulate
from relief_bsdf.plate.choice import DEFAULT_METHOD, chosen_lines, resolve_auto

__all__ = ["Experiment", "Plate", "Bulk", "Instrument", "SOURCE_Q", "FlatFace", "ReliefFace", "TableFace",
           "MicrofacetFace", "PhotonContext", "ForwardMemory", "current_memory", "relief_digest", "TableGrid", "Rows", "in_plane_rows",
           "check_rows", "flat_tables", "Simulated", "simulate", "experiment_from_sample",
           "DEFAULT_METHOD", "resolve_auto", "chosen_lines"]
