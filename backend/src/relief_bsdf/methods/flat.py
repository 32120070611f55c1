"""`flat`: the boundary tables of a perfectly flat interface (the plate's smooth face).

Physics: all power goes into the delta parts, reflected and refracted by the Fresnel equations
(Born & Wolf 1.5.20-21) as Mueller matrices (core.fresnel.mueller_interface, unpolarised
values = M00); the diffuse cells are zero.  Exact for a plane boundary between two
homogeneous media; past the critical angle (light from inside) R = 1, T = 0.  The relief, if
one is given, is ignored.  The flat face of the plate (`plate.FlatFace`) uses these tables (`flat_tables`: both sides).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.fresnel import mueller_interface
from relief_bsdf.core.index import Material
from relief_bsdf.methods.options import FlatOptions
from relief_bsdf.methods.request import DEFAULT_PHI_S_EDGES_DEG, DEFAULT_THETA_S_EDGES_DEG


def flat_table(material: Material, wavelengths_nm, theta_i_deg, phi_i_deg, theta_s_edges_deg, phi_s_edges_deg,
               incident_from: str) -> BsdfTable:
    """One flat-interface table for light from `incident_from` (module doc)."""
    th = np.asarray(theta_i_deg, float)
    ph = np.asarray(phi_i_deg, float)
    te, pe = np.asarray(theta_s_edges_deg, float), np.asarray(phi_s_edges_deg, float)
    W = len(wavelengths_nm)
    sR = np.zeros((W, th.size, ph.size, 4, 4))
    sT = np.zeros((W, th.size, ph.size, 4, 4))
    cos_i = np.cos(np.radians(th))
    for k, wl in enumerate(wavelengths_nm):
        n1, n2 = material.n_pair(wl, incident_from)
        sR[k] = mueller_interface(cos_i, n1, n2, "R")[:, None]
        sT[k] = mueller_interface(cos_i, n1, n2, "T")[:, None]
    vals = np.zeros((W, th.size, ph.size, 2, te.size - 1, pe.size - 1))
    return BsdfTable(np.asarray(wavelengths_nm, float), th, ph, te, pe, vals, incident_from=incident_from,
                     specular_R=sR[..., 0, 0], specular_T=sT[..., 0, 0], specular_mueller_R=sR,
                     specular_mueller_T=sT, method="flat", material=material.describe())


def flat_tables(material: Material, wavelengths_nm: Sequence[float], theta_i_outside_deg: Sequence[float],
                theta_i_inside_deg: Sequence[float], theta_s_edges_deg: Sequence[float] | None = None,
                phi_s_edges_deg: Sequence[float] | None = None) -> tuple[BsdfTable, BsdfTable]:
    """(outside, inside) tables of a perfectly flat boundary at incidence azimuth 0 (`flat_table` for each
    side); default axes: the methods' default scatter grid."""
    te = np.asarray(theta_s_edges_deg if theta_s_edges_deg is not None else DEFAULT_THETA_S_EDGES_DEG, float)
    pe = np.asarray(phi_s_edges_deg if phi_s_edges_deg is not None else DEFAULT_PHI_S_EDGES_DEG, float)
    wl = [float(w) for w in wavelengths_nm]
    return tuple(flat_table(material, wl, th, [0.0], te, pe, side)
                 for side, th in (("outside", theta_i_outside_deg), ("inside", theta_i_inside_deg)))


def reconstruct(relief, material: Material, request, progress=None) -> list[BsdfTable]:
    """Flat-interface tables, one per side in request.incident_from (the relief is not used)."""
    FlatOptions.from_request(request)
    return [flat_table(material, request.wavelengths_nm, request.theta_i_deg, request.phi_i_deg,
                       request.theta_s_edges_deg, request.phi_s_edges_deg, fr) for fr in request.incident_from]
