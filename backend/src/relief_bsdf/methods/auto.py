"""`auto`: choose ray, kirchhoff or rayleigh-rice from the relief's statistics and the request.

Quantities (relief_bsdf.surface.stats.relief_stats, levelled heights): rms height sigma, rms slope
magnitude m, correlation length l (1/e of the radial autocovariance), and the rms mean
curvature kappa from second differences ((h_xx + h_yy) / 2, rms over valid points), radius of
curvature R_c = 1 / kappa.  With n the largest index the light travels in (1 from
outside, n_inside for --from inside) and lambda the shortest requested wavelength:

- Rayleigh-Rice (first-order perturbation) is valid when the Rayleigh parameter at normal
  incidence g = (4 pi n sigma / lambda)^2 < 0.1 (Stover, *Optical Scattering*, sec. 4: the
  first-order result is accurate for g << 1; 0.1 keeps the neglected second order ~5 %) and
  slopes are small, m < 0.15.  Incidence angles only lower g (cos theta), so normal
  incidence is the worst case.
- Kirchhoff (tangent plane) is valid when the surface is locally flat on the wavelength
  scale: k R_c >= 5 with k = 2 pi n / lambda (Thorsos 1988: k R_c >~ 1, with margin;
  Ogilvy 1991 sec. 4.2) and k l >= 6, slopes m < 0.5 (no shadowing in the model);
  and its sampling limits for this request must hold (kirchhoff.check_sampling,
  kirchhoff.check_aliasing).
- Ray (geometric optics) is valid when the relief is rough on the wavelength scale,
  sigma >= lambda / n (g >= (4 pi)^2: no coherent specular left) and its facets are large,
  l >= 10 lambda / n, with slopes resolved by the pitch (l >= 4 pixels).

Preference: rayleigh-rice when valid (cheapest, vector, exact to first order); otherwise
kirchhoff when valid, except that ray is preferred when it is also valid and slopes are
steep (m >= 0.35: shadowing and inter-reflections, which only ray tracing includes);
otherwise ray.  When none is valid the least-bad one is used (kirchhoff if feasible, then
ray) and a warning says so.  The reason is returned in `metadata["auto_reason"]`, written
as one line to stderr (unless options["quiet"]) and logged (logger "relief_bsdf.auto").

When the request asks for directions beyond the pitch's band (kirchhoff's sampling limit)
while the relief's own scattering lies well inside it (3 rms slopes, doubled for reflection,
fits in the band), kirchhoff is run with options["band_limited"] = True and the reason says so.
"""
from __future__ import annotations

import dataclasses
import logging
import sys
import warnings
from dataclasses import dataclass

import numpy as np

from relief_bsdf.errors import RequestError
from relief_bsdf.surface.stats import relief_stats

log = logging.getLogger("relief_bsdf.auto")


@dataclass
class Choice:
    method: str
    reason: str
    valid: dict                   # method -> (bool, why)
    options: dict                 # extra request options for the chosen method
    figures: dict                 # the numbers behind the choice


def rms_curvature(relief) -> float:
    """rms mean curvature (1/m) of the levelled relief from second differences, valid points only."""
    from relief_bsdf.surface.stats import levelled
    lv = levelled(relief)
    h = lv.heights_m
    dx, dy = relief.dx_m, relief.dy_m
    if relief.periodic:
        hxx = (np.roll(h, -1, 1) - 2 * h + np.roll(h, 1, 1)) / dx**2
        hyy = (np.roll(h, -1, 0) - 2 * h + np.roll(h, 1, 0)) / dy**2
        k = 0.5 * (hxx + hyy)
    else:
        hxx = (h[1:-1, 2:] - 2 * h[1:-1, 1:-1] + h[1:-1, :-2]) / dx**2
        hyy = (h[2:, 1:-1] - 2 * h[1:-1, 1:-1] + h[:-2, 1:-1]) / dy**2
        k = 0.5 * (hxx + hyy)
    k = k[np.isfinite(k)]
    return float(np.sqrt(np.mean(k * k))) if k.size else float("nan")


def choose(relief, material, request) -> Choice:
    """Decide the method (module doc); no reconstruction is run."""
    from relief_bsdf.methods import kirchhoff
    st = relief_stats(relief)
    sigma, m, ell = st.rms_height_m, st.rms_slope, st.correlation_length_m
    kappa = rms_curvature(relief)
    rc = 1.0 / kappa if kappa > 0 else np.inf
    lam = min(request.wavelengths_nm) * 1e-9
    n = max(float(np.real(v)) for wl in request.wavelengths_nm for fr in request.incident_from
            for v in material.n_pair(wl, fr)[:1])
    lam_n = lam / n
    g = (4 * np.pi * sigma / lam_n) ** 2
    pitch = max(relief.dx_m, relief.dy_m)
    fig = {"rms_height_m": sigma, "rms_slope": m, "correlation_length_m": ell, "radius_of_curvature_m": rc,
           "rayleigh_parameter": g, "wavelength_nm": lam * 1e9, "n_incident_max": n,
           "k_rc": 2 * np.pi * rc / lam_n, "k_l": 2 * np.pi * ell / lam_n}
    valid = {}
    # Rayleigh-Rice
    ok_rr = g < 0.1 and m < 0.15
    valid["rayleigh-rice"] = (ok_rr, f"Rayleigh parameter (4 pi n sigma / lambda)^2 = {g:.3g} "
                                     f"({'<' if g < 0.1 else '>='} 0.1), rms slope {m:.3g} "
                                     f"({'<' if m < 0.15 else '>='} 0.15)")
    # Kirchhoff physics
    ok_k = fig["k_rc"] >= 5 and fig["k_l"] >= 6 and m < 0.5
    why_k = (f"k R_c = {fig['k_rc']:.3g} ({'>=' if fig['k_rc'] >= 5 else '<'} 5), k l = {fig['k_l']:.3g} "
             f"({'>=' if fig['k_l'] >= 6 else '<'} 6), rms slope {m:.3g} ({'<' if m < 0.5 else '>='} 0.5)")
    k_opts = {}
    feasible_k = True
    opts = dict(request.options or {})
    width = None
    try:
        from relief_bsdf.methods.wave_filter import smoothing_width_dcos
        width = smoothing_width_dcos(kirchhoff.speckle_dcos(relief, material, request), request.theta_s_edges_deg, opts)
        kirchhoff.check_sampling(relief, material, request, width, opts)
    except RequestError as e:
        msg = e.message
        band_only = "resolves |n1 sin t_i" in msg
        reach = min(1.0, 6 * m) * n + n * np.sin(np.radians(max(request.theta_i_deg)))
        if band_only and reach <= lam / (2 * pitch):
            try:
                kirchhoff.check_sampling(relief, material, request, width, {**opts, "band_limited": True})
                k_opts["band_limited"] = True
                why_k += "; run band-limited (the relief scatters within the pitch's band, 3 rms slopes)"
            except RequestError as e2:
                feasible_k, why_k = False, why_k + f"; not feasible: {e2.message}"
        else:
            feasible_k, why_k = False, why_k + f"; not feasible: {msg}"
    if feasible_k:
        from relief_bsdf.methods.rayleigh_rice import prepared_heights
        try:
            h, w = prepared_heights(relief)
            kirchhoff.check_aliasing(h, w, 2 * n * 2 * np.pi / lam)
        except RequestError as e:
            feasible_k, why_k = False, why_k + f"; not feasible: {e.message}"
    valid["kirchhoff"] = (ok_k and feasible_k, why_k)
    # ray
    ok_ray = sigma >= lam_n and ell >= 10 * lam_n and ell >= 4 * pitch
    valid["ray"] = (ok_ray, f"sigma / (lambda/n) = {sigma / lam_n:.3g} ({'>=' if sigma >= lam_n else '<'} 1), "
                            f"l / (lambda/n) = {ell / lam_n:.3g} ({'>=' if ell >= 10 * lam_n else '<'} 10), "
                            f"l / pitch = {ell / pitch:.3g} ({'>=' if ell >= 4 * pitch else '<'} 4)")
    if valid["rayleigh-rice"][0]:
        method = "rayleigh-rice"
        reason = "small roughness: " + valid["rayleigh-rice"][1]
    elif valid["kirchhoff"][0] and not (ok_ray and m >= 0.35):
        method = "kirchhoff"
        reason = "smooth on the wavelength scale but not small: " + why_k + "; Rayleigh-Rice invalid: " + \
                 valid["rayleigh-rice"][1]
    elif ok_ray:
        method = "ray"
        reason = "rough on the wavelength scale: " + valid["ray"][1] + \
                 ("; steep slopes favour ray tracing (shadowing, inter-reflections)" if valid["kirchhoff"][0] else
                  "; Kirchhoff invalid: " + why_k)
    else:
        method = "kirchhoff" if feasible_k else "ray"
        reason = ("WARNING: no method is valid for this relief and wavelength; using " + method + " as the least bad. "
                  + "; ".join(f"{k}: {v[1]}" for k, v in valid.items()))
    return Choice(method, reason, valid, k_opts if method == "kirchhoff" else {}, fig)


def reconstruct(relief, material, request, progress=None):
    """Tables of the chosen method, with metadata auto_reason / auto_method / auto_figures."""
    from relief_bsdf.methods import get_method
    request.validate()
    c = choose(relief, material, request)
    quiet = bool((request.options or {}).get("quiet", False))
    line = f"auto: {c.method}: {c.reason}"
    log.info(line)
    if not quiet:
        print(line, file=sys.stderr)
    if c.reason.startswith("WARNING"):
        warnings.warn(line, RuntimeWarning, stacklevel=2)
    req = dataclasses.replace(request, options={**dict(request.options or {}), **c.options})
    tables = get_method(c.method).reconstruct(relief, material, req, progress=progress)
    for t in tables:
        t.metadata = {**t.metadata, "auto_method": c.method, "auto_reason": c.reason,
                      "auto_figures": {k: float(v) for k, v in c.figures.items()},
                      "auto_valid": {k: bool(v[0]) for k, v in c.valid.items()}}
    return tables
