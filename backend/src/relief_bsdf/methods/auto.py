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
ray) and a warning says so.  The full reason (every condition with its figure) is returned in
`metadata["auto_reason"]` and logged (logger "relief_bsdf.auto", debug); one short line
(`Choice.summary`: the method and the figures that decided) is written once to stderr, unless
the option quiet is set, or once as a RuntimeWarning when no method is valid.

Options (methods.options.AutoOptions): quiet, plus any option of the candidates
(rayleigh-rice, kirchhoff, ray), forwarded to the chosen method when it knows it.

When the request asks for directions beyond the pitch's band (kirchhoff's sampling limit)
while the relief's own scattering lies well inside it (3 rms slopes, doubled for reflection,
fits in the band), kirchhoff is run with the option band_limited = True and the reason says so.
"""
from __future__ import annotations

import dataclasses
import logging
import sys
import warnings
from dataclasses import dataclass

import numpy as np

from relief_bsdf.errors import RequestError
from relief_bsdf.methods.options import AutoOptions, KirchhoffOptions
from relief_bsdf.surface.stats import relief_stats

log = logging.getLogger("relief_bsdf.auto")


@dataclass
class Choice:
    method: str
    reason: str                   # every condition with its figure (table metadata auto_reason)
    valid: dict                   # method -> (bool, why)
    options: dict                 # extra request options for the chosen method
    figures: dict                 # the numbers behind the choice
    summary: str = ""             # one short line: the method and what decided it (printed once)


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


def _figures(relief, material, request) -> dict:
    """The relief's and request's numbers every validity condition is stated in (module doc)."""
    st = relief_stats(relief)
    sigma, m, ell = st.rms_height_m, st.rms_slope, st.correlation_length_m
    kappa = rms_curvature(relief)
    rc = 1.0 / kappa if kappa > 0 else np.inf
    lam = min(request.wavelengths_nm) * 1e-9
    n = max(float(np.real(v)) for wl in request.wavelengths_nm for fr in request.incident_from
            for v in material.n_pair(wl, fr)[:1])
    lam_n = lam / n
    return {"rms_height_m": sigma, "rms_slope": m, "correlation_length_m": ell, "radius_of_curvature_m": rc,
            "rayleigh_parameter": (4 * np.pi * sigma / lam_n) ** 2, "wavelength_nm": lam * 1e9, "n_incident_max": n,
            "k_rc": 2 * np.pi * rc / lam_n, "k_l": 2 * np.pi * ell / lam_n,
            "pitch_m": max(relief.dx_m, relief.dy_m)}


def _rayleigh_rice_validity(fig) -> tuple[bool, str]:
    g, m = fig["rayleigh_parameter"], fig["rms_slope"]
    return g < 0.1 and m < 0.15, (f"Rayleigh parameter (4 pi n sigma / lambda)^2 = {g:.3g} "
                                  f"({'<' if g < 0.1 else '>='} 0.1), rms slope {m:.3g} "
                                  f"({'<' if m < 0.15 else '>='} 0.15)")


def _kirchhoff_feasibility(relief, material, request, fig, k_opts: KirchhoffOptions) -> tuple[bool, str, dict]:
    """Kirchhoff's sampling limits for this request: (feasible, why, extra options such as band_limited)."""
    from relief_bsdf.methods import kirchhoff
    from relief_bsdf.methods.rayleigh_rice import prepared_heights
    from relief_bsdf.methods.wave_filter import smoothing_width_dcos
    n, lam, m = fig["n_incident_max"], fig["wavelength_nm"] * 1e-9, fig["rms_slope"]
    extra, why = {}, ""
    width = None
    try:
        width = smoothing_width_dcos(kirchhoff.speckle_dcos(relief, material, request), request.theta_s_edges_deg,
                                     k_opts.smoothing_dcos)
        kirchhoff.check_sampling(relief, material, request, width, k_opts.band_limited)
    except RequestError as e:
        band_only = "resolves |n1 sin t_i" in e.message
        reach = min(1.0, 6 * m) * n + n * np.sin(np.radians(max(request.theta_i_deg)))
        if not (band_only and reach <= lam / (2 * fig["pitch_m"])):
            return False, f"; not feasible: {e.message}", {}
        try:
            kirchhoff.check_sampling(relief, material, request, width, True)
        except RequestError as e2:
            return False, f"; not feasible: {e2.message}", {}
        extra["band_limited"] = True
        why = "; run band-limited (the relief scatters within the pitch's band, 3 rms slopes)"
    try:
        h, w = prepared_heights(relief)
        kirchhoff.check_aliasing(h, w, 2 * n * 2 * np.pi / lam)
    except RequestError as e:
        return False, why + f"; not feasible: {e.message}", {}
    return True, why, extra


def _kirchhoff_validity(relief, material, request, fig, k_opts) -> tuple[bool, bool, str, dict]:
    """(valid, feasible, why, extra options) of the tangent-plane model for this relief and request."""
    m = fig["rms_slope"]
    ok = fig["k_rc"] >= 5 and fig["k_l"] >= 6 and m < 0.5
    why = (f"k R_c = {fig['k_rc']:.3g} ({'>=' if fig['k_rc'] >= 5 else '<'} 5), k l = {fig['k_l']:.3g} "
           f"({'>=' if fig['k_l'] >= 6 else '<'} 6), rms slope {m:.3g} ({'<' if m < 0.5 else '>='} 0.5)")
    feasible, why_f, extra = _kirchhoff_feasibility(relief, material, request, fig, k_opts)
    return ok and feasible, feasible, why + why_f, extra


def _ray_validity(fig) -> tuple[bool, str]:
    sigma, ell, pitch = fig["rms_height_m"], fig["correlation_length_m"], fig["pitch_m"]
    lam_n = fig["wavelength_nm"] * 1e-9 / fig["n_incident_max"]
    ok = sigma >= lam_n and ell >= 10 * lam_n and ell >= 4 * pitch
    return ok, (f"sigma / (lambda/n) = {sigma / lam_n:.3g} ({'>=' if sigma >= lam_n else '<'} 1), "
                f"l / (lambda/n) = {ell / lam_n:.3g} ({'>=' if ell >= 10 * lam_n else '<'} 10), "
                f"l / pitch = {ell / pitch:.3g} ({'>=' if ell >= 4 * pitch else '<'} 4)")


def _summary(method: str, fig: dict, k_opts: dict, warning: bool) -> str:
    """One short line: the method and the figures that decided."""
    g, m = fig["rayleigh_parameter"], fig["rms_slope"]
    if warning:
        return (f"no method is valid (g = {g:.3g}, k R_c = {fig['k_rc']:.3g}, k l = {fig['k_l']:.3g}, "
                f"slope {m:.3g}); using {method} as the least bad (details: table metadata auto_reason)")
    if method == "rayleigh-rice":
        return f"optically smooth: g = {g:.3g} < 0.1, rms slope {m:.3g} < 0.15"
    if method == "kirchhoff":
        return (f"g = {g:.3g} >= 0.1 but locally flat: k R_c = {fig['k_rc']:.3g}, k l = {fig['k_l']:.3g}, "
                f"slope {m:.3g}" + ("; band-limited" if k_opts.get("band_limited") else ""))
    lam_n = fig["wavelength_nm"] * 1e-9 / fig["n_incident_max"]
    return (f"rough: sigma = {fig['rms_height_m'] / lam_n:.3g} lambda/n, l = "
            f"{fig['correlation_length_m'] / lam_n:.3g} lambda/n, slope {m:.3g}")


def choose(relief, material, request) -> Choice:
    """Decide the method (module doc); no reconstruction is run."""
    opts = AutoOptions.from_request(request)
    k_opts = KirchhoffOptions.from_mapping(opts.for_method(KirchhoffOptions), "auto")
    fig = _figures(relief, material, request)
    ok_rr, why_rr = _rayleigh_rice_validity(fig)
    ok_k, feasible_k, why_k, extra_k = _kirchhoff_validity(relief, material, request, fig, k_opts)
    ok_ray, why_ray = _ray_validity(fig)
    valid = {"rayleigh-rice": (ok_rr, why_rr), "kirchhoff": (ok_k, why_k), "ray": (ok_ray, why_ray)}
    m = fig["rms_slope"]
    if ok_rr:
        method, reason = "rayleigh-rice", "small roughness: " + why_rr
    elif ok_k and not (ok_ray and m >= 0.35):
        method = "kirchhoff"
        reason = "smooth on the wavelength scale but not small: " + why_k + "; Rayleigh-Rice invalid: " + why_rr
    elif ok_ray:
        method = "ray"
        reason = "rough on the wavelength scale: " + why_ray + \
                 ("; steep slopes favour ray tracing (shadowing, inter-reflections)" if ok_k else
                  "; Kirchhoff invalid: " + why_k)
    else:
        method = "kirchhoff" if feasible_k else "ray"
        reason = ("WARNING: no method is valid for this relief and wavelength; using " + method + " as the least bad. "
                  + "; ".join(f"{k}: {v[1]}" for k, v in valid.items()))
    extra = extra_k if method == "kirchhoff" else {}
    fig.pop("pitch_m")
    return Choice(method, reason, valid, extra, fig, _summary(method, fig, extra, reason.startswith("WARNING")))


def reconstruct(relief, material, request, progress=None):
    """Tables of the chosen method, with metadata auto_reason / auto_method / auto_figures."""
    from relief_bsdf.methods.registry import entry
    request.validate()
    opts = AutoOptions.from_request(request)
    c = choose(relief, material, request)
    line = f"auto: {c.method}: {c.summary}"
    log.debug("auto: %s: %s", c.method, c.reason)
    if c.reason.startswith("WARNING"):
        # the one line, once (no source line under it: warn_explicit at a location with no text)
        warnings.warn_explicit(line, RuntimeWarning, "relief_bsdf.auto", 0, module="relief_bsdf.methods.auto")
    elif not opts.quiet:
        print(line, file=sys.stderr)
    chosen = entry(c.method)
    req = dataclasses.replace(request, options={**opts.for_method(chosen.options), **c.options})
    tables = chosen.load().reconstruct(relief, material, req, progress=progress)
    for t in tables:
        t.metadata = {**t.metadata, "auto_method": c.method, "auto_reason": c.reason, "auto_summary": c.summary,
                      "auto_figures": {k: float(v) for k, v in c.figures.items()},
                      "auto_valid": {k: bool(v[0]) for k, v in c.valid.items()}}
    return tables
