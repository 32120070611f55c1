"""`microfacet+dw`: the fast surrogate of the fit, a microfacet lobe plus a Debye-Waller specular part.

Physics.  The diffuse lobe is the Walter et al. 2007 microfacet BSDF (methods.microfacet) of
one Beckmann lobe with alpha = the relief's rms slope magnitude.  The coherent specular part
comes from the rms height sigma by the Kirchhoff / Debye-Waller factor (Beckmann &
Spizzichino 1963, ch. 5; Ogilvy 1991 eq. 4.30):

    reflection    g_R = exp(-(2 k n1 sigma cos theta_i)^2)
    transmission  g_T = exp(-(k sigma (n1 cos theta_i - n2 cos theta_t))^2)   (0 past the critical angle)

(k = 2 pi / lambda, lambda in vacuum); the delta parts are g_R R_F and g_T T_F (Fresnel
Mueller matrices, core.fresnel.mueller_interface) and the diffuse cells are scaled by (1 - g).
Heights then set the specular peak and slopes the lobe width, so a fit of height scale and
smoothing can tell them apart.

Regime: Gaussian height statistics, lateral scales >> wavelength (the geometric lobe), any
sigma (g -> 0 for rough reliefs, -> 1 for smooth ones); no interference structure, no
shadowing beyond the microfacet model's.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.fresnel import mueller_interface
from relief_bsdf.core.index import Material
from relief_bsdf.methods.options import MicrofacetDwOptions
from relief_bsdf.surface.stats import rms_height_and_slope

ALPHA_MIN = 1e-4           # a flat relief still gets a (very narrow) lobe


def relief_sigma_slope(relief) -> tuple[float, float]:
    """(rms height of the levelled relief in m, rms slope magnitude): surface.stats' one definition,
    the same numbers the fit (fit.optimise.relief_rms) and `relief info` use."""
    return rms_height_and_slope(relief)


def coherent_fractions(material: Material, wavelength_nm: float, incident_from: str, theta_i_deg,
                       sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Debye-Waller factors (g_R, g_T) per incidence angle (module doc)."""
    n1, n2 = (float(np.real(x)) for x in material.n_pair(wavelength_nm, incident_from))
    k = 2 * np.pi / (wavelength_nm * 1e-9)
    ci = np.cos(np.radians(theta_i_deg))
    st2 = (n1 / n2) ** 2 * (1 - ci**2)
    ct = np.sqrt(np.clip(1 - st2, 0, 1))
    g_r = np.exp(-(2 * k * n1 * sigma_m * ci) ** 2)
    g_t = np.where(st2 < 1, np.exp(-(k * sigma_m * (n1 * ci - n2 * ct)) ** 2), 0.0)
    return g_r, g_t


def debye_waller(table: BsdfTable, material: Material, sigma_m: float) -> BsdfTable:
    """Split a diffuse (microfacet) table into coherent specular + scaled diffuse (module doc)."""
    W, I = table.wavelength_nm.size, table.theta_i_deg.size
    gR, gT = np.zeros((W, I, 1)), np.zeros((W, I, 1))
    sR, sT = np.zeros((W, I, 1, 4, 4)), np.zeros((W, I, 1, 4, 4))
    for w, wl in enumerate(table.wavelength_nm):
        n1, n2 = (float(np.real(x)) for x in material.n_pair(wl, table.incident_from))
        ci = np.cos(np.radians(table.theta_i_deg))
        gR[w, :, 0], gT[w, :, 0] = coherent_fractions(material, wl, table.incident_from, table.theta_i_deg, sigma_m)
        sR[w, :, 0] = mueller_interface(ci, n1, n2, "R") * gR[w, :, 0, None, None]
        sT[w, :, 0] = mueller_interface(ci, n1, n2, "T") * gT[w, :, 0, None, None]
    v = table.values_per_sr.copy()
    v[:, :, :, 0] *= (1 - gR)[..., None, None]
    v[:, :, :, 1] *= (1 - gT)[..., None, None]
    mu = None
    if table.mueller_per_sr is not None:
        mu = table.mueller_per_sr.copy()
        mu[:, :, :, 0] *= (1 - gR)[..., None, None, None, None]
        mu[:, :, :, 1] *= (1 - gT)[..., None, None, None, None]
    return dataclasses.replace(table, values_per_sr=v, mueller_per_sr=mu, specular_R=sR[..., 0, 0],
                               specular_T=sT[..., 0, 0], specular_mueller_R=sR, specular_mueller_T=sT,
                               sigma_per_sr=None, method=table.method + "+dw",
                               metadata={**table.metadata, "debye_waller_sigma_m": sigma_m})


def reconstruct(relief, material: Material, request, progress=None) -> list[BsdfTable]:
    """microfacet+dw tables, one per side in request.incident_from (module doc)."""
    from relief_bsdf.methods import microfacet
    opts = MicrofacetDwOptions.from_request(request)
    sigma, slope = relief_sigma_slope(relief)
    inner = {"alpha": max(slope, ALPHA_MIN)}
    if opts.polarized:
        inner["polarized"] = True
    tables = microfacet.reconstruct(relief, material, dataclasses.replace(request, options=inner), progress=progress)
    return [debye_waller(t, material, sigma) for t in tables]
