"""How the plate treats a boundary model's energy defect: as a defect of the model, not as absorption.

The tangent-plane (Kirchhoff) and first-order perturbation (Rayleigh-Rice) models do not conserve
energy exactly: without shadowing and multiple scattering their R + T departs from 1, most at
grazing incidence and past the critical angle (methods.wave_filter.energy_defect stores the signed
defect 1 - R - T as `lost` and in metadata["energy_defect"]).  A lossless dielectric boundary
conserves energy (R + T = 1: Stokes relations / flux conservation across the interface), so a plate
that let the defect vanish (or appear) would read it as bulk absorption (or gain).  The plate
therefore closes the balance of such a table: per incidence the DIFFUSE part (cells, their sigma and
Mueller matrices) is scaled so that diffuse + coherent = 1, keeping the coherent specular parts (the
exact |<exp(i q h)>|^2 Fresnel term of the model) and the lobes' shapes.  The factors applied are
recorded in metadata["energy_closure"], and the face says so in its physics description.

Regime: a factor near 1 (within a few %) is a small correction of the model; far from 1 (grazing
incidence on a rough face) the model is outside its validity and a RuntimeWarning says so.
Only tables that report an energy defect of a lossless boundary are closed (an absorbing face's
`lost` is real absorption; ray tables' `lost` are paths stopped by the bounce limit).
"""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable

WARN_FACTOR = 0.2        # |factor - 1| beyond which the model is reported outside its validity


def closed(table: BsdfTable) -> BsdfTable:
    """`table` with diffuse + coherent = 1 per incidence when it reports a lossless model defect (module doc)."""
    info = table.metadata.get("energy_defect")
    if not info or info.get("meaning") == "absorption":
        return table
    h = table.hemispherical()
    diffuse = h["diffuse_R"] + h["diffuse_T"]
    coherent = h["specular_R"] + h["specular_T"]
    f = np.divide(1.0 - coherent, diffuse, out=np.ones_like(diffuse), where=diffuse > 0)
    f = np.clip(f, 0.0, None)
    scale = f[..., None, None, None]                                     # (W, I, P, 2, S, A)
    kw = {"values_per_sr": (table.values_per_sr * scale).astype(table.values_per_sr.dtype, copy=False),
          "lost": np.zeros_like(table.lost),
          "metadata": {**table.metadata, "energy_closure": {
              "rule": "diffuse cells scaled per incidence so that diffuse + coherent = 1 (lossless boundary)",
              "factor_min": float(f.min()), "factor_max": float(f.max())}}}
    if table.sigma_per_sr is not None:
        kw["sigma_per_sr"] = (table.sigma_per_sr * scale).astype(table.sigma_per_sr.dtype, copy=False)
    if table.mueller_per_sr is not None:
        kw["mueller_per_sr"] = (table.mueller_per_sr * scale[..., None, None]).astype(table.mueller_per_sr.dtype,
                                                                                    copy=False)
    k = int(np.argmax(np.abs(f - 1.0)))
    if abs(float(f.flat[k]) - 1.0) > WARN_FACTOR:
        w, i, p = np.unravel_index(k, f.shape)
        warnings.warn(f"{table.method} ({table.incident_from}): its diffuse part had to be scaled by "
                      f"{float(f.flat[k]):.3g} at {table.wavelength_nm[w]:g} nm, theta_i {table.theta_i_deg[i]:g} deg "
                      "to conserve energy: the model is outside its validity there (plate.energy)", RuntimeWarning,
                      stacklevel=3)
    return dataclasses.replace(table, **kw)
