"""`auto`: choose rayleigh-rice, two_scale, kirchhoff or ray from the relief's statistics and the request.

Figures (relief_bsdf.surface.stats; levelled heights, valid points): rms height sigma, rms slope
m, correlation length l (1/e of the radial autocovariance), rms mean curvature kappa from second
differences ((h_xx + h_yy) / 2), radius of curvature R_c = 1 / kappa; n the largest index the
light arrives in, lambda the shortest requested wavelength, k = 2 pi n / lambda.

Wave-optics figures are taken on the relief *band-limited to the propagating band*: components
finer than f_max = (n sin t_i,max + n_max) / lambda scatter into no propagating direction in
those models (first-order grating equation), and on profilometer maps they are mostly noise
(surface.stats.band_limited; the rms removed is in the figures).  Geometric optics is judged on
the relief as traced (raw figures).  The coherent specular share at normal incidence,
|<exp(-i nu h)>|^2 over the map's own heights (any statistics, no Gaussian assumption), with
nu = 2 n1 k0 (R) and |n1 - n2| k0 (T, the smaller and so the more coherent), decides whether a
specular part remains.

Conditions (each "value < limit" or "value >= limit"):
- rayleigh-rice (first-order perturbation): g = (4 pi n sigma / lambda)^2 < 0.1 (Stover,
  *Optical Scattering*, sec. 4: the neglected second order is ~ g), m < 0.15.
- kirchhoff (tangent plane): k R_c >= 5 (Thorsos 1988: k R_c >~ 1, with margin; Ogilvy 1991
  sec. 4.2), k l >= 6, m < 0.5 (no shadowing in the model); and feasible: its sampling limits
  (kirchhoff.check_sampling, check_aliasing).  Where only the pitch limits the directions the
  map can resolve, it runs band-limited (option band_limited = True): the map carries no
  information beyond its band, and the reason says what share of the propagating band it covers.
- two_scale (methods.two_scale; figures on its split, surface.bands: the lowest cut with the fine
  scale's g_F <= 0.05): the fine scale as rayleigh-rice, g_F < 0.1 and rms slope < 0.15 (inside
  the propagating band); the large scale as ray: coherent share < 1 %, sigma_L >= lambda / n,
  l_L >= 10 lambda / n, l_L >= 4 pixels, k R_c(L) >= 10; and two scales: l_L >= 5 l_F
  (SCALE_SEPARATION) with the fine scale resolved, l_F >= 2 pixels (FINE_RESOLVED_PX), and a second
  scale in the spectrum: the relief's binned periodogram fitted by two anisotropic von Karman scales
  beats one by QBIC gain > 10 (`methods.scale_count`, the project's one information criterion): a
  relief with one scale is not a candidate at all, whatever it misses.
- ray (geometric optics): coherent share < 1 %, sigma >= lambda / n, l >= 10 lambda / n,
  l >= 4 pixels, and k R_c >= 10 on the raw map (facets large on the wavelength scale: an
  exponential-autocorrelation relief has wavelength-sized facets whatever its l).

Ranking: each method's miss is the sum over its conditions of how many decades the condition
is missed (0 when it holds; infinite when not feasible).  Valid methods come first in the
order rayleigh-rice, two_scale, kirchhoff, ray (ray before kirchhoff when both are valid and
m >= 0.35: shadowing and inter-reflections only ray tracing includes); then the rest by miss.
two_scale comes before kirchhoff: for a lobe plus a haze both may hold, the composite costs one
ray tracing and a PSD where the tangent plane needs q_z nodes growing with sigma_L, and it adds
the large scale's shadowing and inter-reflections; it agrees with kirchhoff where both apply
(tests/backend/methods/test_two_scale.py).  Where it runs, it uses the very cut its reason states
(option f_cut_per_um).  Ray is
never chosen while a coherent part remains (share > 1 %) and a wave method is within one decade
of valid.  When the chosen method misses its conditions a RuntimeWarning says so.

Output: one line (`Choice.summary`: the method and the figures that decided) written once to
stderr (unless the option quiet is set) or, when no method is valid, once as a RuntimeWarning;
the full ranking with every condition in `metadata["auto_reason"]` (and the debug log
"relief_bsdf.auto").  Options (methods.options.AutoOptions): quiet, plus any option of the
candidates, forwarded to the chosen method when it knows it; an unknown or misspelled option is
a RequestError naming it.
"""
from __future__ import annotations

import dataclasses
import logging
import sys
import warnings
from dataclasses import dataclass

import numpy as np

from relief_bsdf.errors import RequestError
from relief_bsdf.criteria import BIC_MARGIN
from relief_bsdf.methods.options import AutoOptions, KirchhoffOptions, TwoScaleOptions
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


def _coherent_fraction(relief, nu_per_m: float) -> float:
    """|<exp(-i nu h)>|^2 over the valid levelled heights: the coherent (specular) share of the
    tangent-plane field at wave-vector transfer nu, for any height statistics (no Gaussian
    Debye-Waller assumption)."""
    from relief_bsdf.surface.stats import levelled
    lv = levelled(relief)
    z = lv.heights_m[lv.valid]
    return float(abs(np.mean(np.exp(-1j * nu_per_m * z))) ** 2) if z.size else 1.0


def _figures(relief, material, request, ts_opts: TwoScaleOptions | None = None) -> dict:
    """The relief's and request's numbers every validity condition is stated in (module doc).

    Wave-optics figures (rayleigh-rice, kirchhoff) are taken on the relief band-limited to the
    spatial frequencies that scatter into propagating directions (surface.stats.band_limited):
    finer components (profilometer noise, tip artefacts) scatter nowhere in those models.
    Geometric optics sees the relief as traced (raw figures).
    """
    from relief_bsdf.surface.stats import band_limited, propagating_f_max
    lam = min(request.wavelengths_nm) * 1e-9
    pairs = [material.n_pair(wl, fr) for wl in request.wavelengths_nm for fr in request.incident_from]
    n = max(float(np.real(p[0])) for p in pairs)
    n_any = max(float(np.real(v)) for p in pairs for v in p if np.imag(v) == 0)
    ti_max = max(request.theta_i_deg)
    f_max = propagating_f_max(lam * 1e9, n, n_any, ti_max)
    nyquist = 0.5 / max(relief.dx_m, relief.dy_m)
    bl = band_limited(relief, f_max) if f_max < nyquist else None
    wave_rel = bl.relief if bl is not None else relief
    st_raw = relief_stats(relief)
    st = relief_stats(wave_rel) if bl is not None else st_raw
    kappa = rms_curvature(wave_rel)
    rc = 1.0 / kappa if kappa > 0 else np.inf
    kappa_raw = rms_curvature(relief) if bl is not None else kappa
    rc_raw = 1.0 / kappa_raw if kappa_raw > 0 else np.inf
    lam_n = lam / n
    k0 = 2 * np.pi / lam
    # coherent share at normal incidence, the least coherent case of each side: R 2 n1 k0, T |n1 - n2| k0
    coh = {}
    for (n1, n2), fr in zip(pairs, [fr for _ in request.wavelengths_nm for fr in request.incident_from]):
        coh[f"coherent_R_{fr}"] = _coherent_fraction(relief, 2 * np.real(n1) * k0)
        if np.imag(n2) == 0:
            coh[f"coherent_T_{fr}"] = _coherent_fraction(relief, abs(np.real(n1) - np.real(n2)) * k0)
    from relief_bsdf.methods import two_scale
    ts = {f"ts_{k}": v for k, v in two_scale.figures(relief, material, request, ts_opts or TwoScaleOptions()).items()}
    ts["pitch_m"] = max(relief.dx_m, relief.dy_m)
    ts.update(_spectrum_test(relief, ts) if _split_separates(ts) else {"ts_spectrum_qbic_gain": float("nan"),
                                                                         "ts_spectrum_two_scales": 0.0})
    ts.pop("pitch_m")
    return {**ts, "rms_height_m": st.rms_height_m, "rms_slope": st.rms_slope, "correlation_length_m": st.correlation_length_m,
            "radius_of_curvature_m": rc, "rayleigh_parameter": (4 * np.pi * st.rms_height_m / lam_n) ** 2,
            "wavelength_nm": lam * 1e9, "n_incident_max": n, "k_rc": 2 * np.pi * rc / lam_n,
            "k_l": 2 * np.pi * st.correlation_length_m / lam_n, "pitch_m": max(relief.dx_m, relief.dy_m),
            "raw_rms_height_m": st_raw.rms_height_m, "raw_rms_slope": st_raw.rms_slope,
            "raw_correlation_length_m": st_raw.correlation_length_m, "raw_k_rc": 2 * np.pi * rc_raw / lam_n,
            "band_f_max_per_m": f_max, "band_removed_rms_m": bl.removed_rms_m if bl is not None else 0.0,
            "coherent_max": max(coh.values()), **coh}


def _miss(value: float, limit: float, kind: str) -> float:
    """How far a condition `value kind limit` is missed, in decades (0 when it holds)."""
    if not (np.isfinite(value) and value > 0):
        return 0.0 if (kind == "<" and value <= 0) else np.inf
    r = np.log10(value / limit)
    return max(0.0, r if kind == "<" else -r)


def _conditions(fig) -> dict:
    """method -> [(label, value, limit, kind)] (module doc)."""
    lam_n = fig["wavelength_nm"] * 1e-9 / fig["n_incident_max"]
    return {
        "rayleigh-rice": [("Rayleigh parameter g (band-limited)", fig["rayleigh_parameter"], 0.1, "<"),
                          ("rms slope (band-limited)", fig["rms_slope"], 0.15, "<")],
        "kirchhoff": [("k R_c", fig["k_rc"], 5.0, ">="), ("k l", fig["k_l"], 6.0, ">="),
                      ("rms slope (band-limited)", fig["rms_slope"], 0.5, "<")],
        "two_scale": [("fine-scale Rayleigh parameter g_F", fig["ts_fine_rayleigh"], 0.1, "<"),
                      ("fine-scale rms slope", fig["ts_fine_rms_slope"], 0.15, "<"),
                      ("scale separation l_L / l_F", fig["ts_large_correlation_length_m"]
                       / max(fig["ts_fine_correlation_length_m"], 1e-300), SCALE_SEPARATION, ">="),
                      ("second scale in the spectrum: QBIC gain over one scale (scale_count)",
                       fig.get("ts_spectrum_qbic_gain", float("nan")), BIC_MARGIN, ">="),
                      ("large-scale coherent specular share", fig["ts_large_coherent"], 0.01, "<"),
                      ("large-scale sigma / (lambda/n)", fig["ts_large_rms_m"] / lam_n, 1.0, ">="),
                      ("large-scale l / (lambda/n)", fig["ts_large_correlation_length_m"] / lam_n, 10.0, ">="),
                      ("large-scale l / pitch", fig["ts_large_correlation_length_m"] / fig["pitch_m"], 4.0, ">="),
                      ("large-scale k R_c", fig["ts_large_k_rc"], 10.0, ">=")],
        "ray": [("coherent specular share at normal incidence", fig["coherent_max"], 0.01, "<"),
                ("sigma / (lambda/n)", fig["raw_rms_height_m"] / lam_n, 1.0, ">="),
                ("l / (lambda/n)", fig["raw_correlation_length_m"] / lam_n, 10.0, ">="),
                ("l / pitch", fig["raw_correlation_length_m"] / fig["pitch_m"], 4.0, ">="),
                ("k R_c (facets large on the wavelength scale)", fig["raw_k_rc"], 10.0, ">=")],
    }


def _describe(conds) -> str:
    return ", ".join(f"{lab} = {v:.3g} ({'ok' if _miss(v, lim, k) == 0 else 'missed'}: {k} {lim:g})"
                     for lab, v, lim, k in conds)


def _kirchhoff_feasibility(relief, material, request, fig, k_opts: KirchhoffOptions) -> tuple[bool, str, dict]:
    """Kirchhoff's sampling limits for this request: (feasible, why, extra options such as band_limited).

    Where the pitch cannot resolve every requested direction the map carries no information beyond
    its band anyway: kirchhoff is run band-limited (band_limited = True) and the reason says what
    share of the requested band the map covers."""
    from relief_bsdf.methods import kirchhoff
    from relief_bsdf.methods.rayleigh_rice import prepared_heights
    from relief_bsdf.methods.wave_filter import smoothing_width_dcos
    n, lam = fig["n_incident_max"], fig["wavelength_nm"] * 1e-9
    extra, why = {}, ""
    width = smoothing_width_dcos(kirchhoff.speckle_dcos(relief, material, request), request.theta_s_edges_deg,
                                 k_opts.smoothing_dcos)
    try:
        kirchhoff.check_sampling(relief, material, request, width, k_opts.band_limited)
    except RequestError as e:
        if "resolves |n1 sin t_i" not in e.message:
            return False, f"not feasible: {e.message}", {}
        try:
            kirchhoff.check_sampling(relief, material, request, width, True)
        except RequestError as e2:
            return False, f"not feasible: {e2.message}", {}
        extra["band_limited"] = True
        share = (0.5 / fig["pitch_m"]) / fig["band_f_max_per_m"]
        why = f"band-limited (the pitch resolves {share:.0%} of the propagating band)"
    try:
        # the heights kirchhoff will diffract: band-limited as it does (option band_limit_heights)
        rel_k = kirchhoff._band_limit(relief, material, request, width)[0] if k_opts.band_limit_heights else relief
        h, w = prepared_heights(rel_k)
        n_all = max(float(np.real(v)) for wl in request.wavelengths_nm for fr in request.incident_from
                    for v in material.n_pair(wl, fr))          # kirchhoff's own bound on nu_z
        kirchhoff.check_aliasing(h, w, 2 * n_all * 2 * np.pi / lam)
    except RequestError as e:
        return False, f"not feasible: {e.message}", {}
    return True, why, extra


SCALE_SEPARATION = 5.0        # l_L / l_F at least this: the relief has two scales (two_scale is a candidate)
FINE_RESOLVED_PX = 2.0        # l_F at least this many pixels: the fine scale is resolved by the map


def _split_separates(fig) -> bool:
    """The band split's two lengths: l_L >= SCALE_SEPARATION l_F and the fine one resolved (l_F >=
    FINE_RESOLVED_PX pixels).  A 'fine scale' correlated over less than two samples is the sampling's
    own floor (the kinks between facets of the triangulated map, the instrument's noise band), not a
    surface scale whose haze the map describes."""
    resolved = fig["ts_fine_correlation_length_m"] >= FINE_RESOLVED_PX * fig["pitch_m"]
    return resolved and fig["ts_large_correlation_length_m"] >= SCALE_SEPARATION * fig["ts_fine_correlation_length_m"]


def _spectrum_test(relief, fig) -> dict:
    """The one-scale / two-scale test of the relief's own spectrum (`methods.scale_count`), started from the
    band split's lengths: {ts_spectrum_qbic_gain, ts_spectrum_two_scales (1.0 / 0.0)}."""
    from relief_bsdf.methods.scale_count import scale_test
    t = scale_test(relief, (fig["ts_large_correlation_length_m"], fig["ts_fine_correlation_length_m"]))
    log.debug("auto: %s", t.statement())
    return {"ts_spectrum_qbic_gain": t.qbic_gain, "ts_spectrum_two_scales": float(t.two_scales)}


def _two_scales(fig) -> bool:
    """Whether the relief is rough at one scale and smooth at another: the band split separates two
    lengths (`_split_separates`) AND the relief's spectrum holds a second scale: a two-scale spectrum
    beats the one-scale spectrum of the same relief by the project's information criterion
    (`methods.scale_count`: QBIC gain > 10 on the binned periodogram, each scale anisotropic, a white
    noise floor in both).  The split finds a cut in any spectrum, so the tail of ONE scale (an
    anisotropic Gaussian's, say) is a 'fine scale' to it; the spectrum test says whether the surface
    has one."""
    return _split_separates(fig) and fig.get("ts_spectrum_two_scales", 0.0) > 0.5


def _rank(fig, feasible_k: bool) -> list:
    """[(method, miss in decades, why)] best first: valid methods in preference order (rayleigh-rice,
    two_scale, kirchhoff, ray - ray ahead of kirchhoff when slopes are steep, m >= 0.35, and it is valid),
    then the others by how far their conditions are missed.  Ray is never ranked while a coherent
    specular part remains (share > 1 % at normal incidence) unless no wave method can run."""
    conds = _conditions(fig)
    miss = {m: sum(_miss(v, lim, k) for _, v, lim, k in c) for m, c in conds.items()}
    if not feasible_k:
        miss["kirchhoff"] = np.inf
    if not _two_scales(fig):                  # one scale: the composite is not a candidate (module doc)
        miss["two_scale"] = np.inf
    order = ["rayleigh-rice", "two_scale", "kirchhoff", "ray"]
    if miss["ray"] == 0 and miss["kirchhoff"] == 0 and fig["rms_slope"] >= 0.35:
        order = ["rayleigh-rice", "two_scale", "ray", "kirchhoff"]
    # a coherent part remains and a wave method is close to valid (within a decade): never ray then
    wave_close = min(miss["rayleigh-rice"], miss["kirchhoff"]) <= 1.0
    coherent = fig["coherent_max"] > 0.01 and wave_close
    key = lambda m: (m == "ray" and coherent, miss[m] > 0, miss[m], order.index(m))  # noqa: E731
    return [(m, miss[m], _describe(conds[m])) for m in sorted(order, key=key)]


def _summary(method: str, miss: float, fig: dict, extra: dict, why_k: str) -> str:
    """One short line: the method and the figures that decided."""
    g, m = fig["rayleigh_parameter"], fig["rms_slope"]
    coh = fig["coherent_max"]
    head = "" if miss == 0 else f"no method fully valid; {method} misses its conditions least ({miss:.2g} decades); "
    if method == "rayleigh-rice":
        return head + f"optically smooth: g = {g:.3g}, rms slope {m:.3g} (band-limited), coherent share {coh:.2f}"
    if method == "kirchhoff":
        return head + (f"locally flat: k R_c = {fig['k_rc']:.3g}, k l = {fig['k_l']:.3g}, slope {m:.3g}, g = {g:.3g}, "
                       f"coherent share {coh:.2f}" + (f"; {why_k}" if extra.get("band_limited") else ""))
    lam_n = fig["wavelength_nm"] * 1e-9 / fig["n_incident_max"]
    if method == "two_scale":
        return head + (f"two scales: large {fig['ts_large_rms_m'] * 1e9:.4g} nm rms, l {fig['ts_large_correlation_length_m'] * 1e6:.3g} "
                       f"um (ray: k R_c {fig['ts_large_k_rc']:.3g}, coherent {fig['ts_large_coherent']:.3f}) + fine "
                       f"{fig['ts_fine_rms_m'] * 1e9:.3g} nm rms, l {fig['ts_fine_correlation_length_m'] * 1e6:.3g} um "
                       f"(rayleigh-rice: g_F {fig['ts_fine_rayleigh']:.3g}), split at {fig['ts_f_cut_per_m'] * 1e-6:.3g} /um")
    return head + (f"rough: sigma = {fig['raw_rms_height_m'] / lam_n:.3g} lambda/n, l = "
                   f"{fig['raw_correlation_length_m'] / lam_n:.3g} lambda/n, coherent share {coh:.3f}")


def choose(relief, material, request) -> Choice:
    """Decide the method (module doc); no reconstruction is run."""
    opts = AutoOptions.from_request(request)
    k_opts = KirchhoffOptions.from_mapping(opts.for_method(KirchhoffOptions), "auto")
    ts_opts = TwoScaleOptions.from_mapping(opts.for_method(TwoScaleOptions), "auto")
    fig = _figures(relief, material, request, ts_opts)
    feasible_k, why_k, extra_k = _kirchhoff_feasibility(relief, material, request, fig, k_opts)
    ranked = _rank(fig, feasible_k)
    method, miss, _ = ranked[0]
    valid = {m: (ms == 0, why) for m, ms, why in ranked}
    if not feasible_k:
        valid["kirchhoff"] = (False, valid["kirchhoff"][1] + "; " + why_k)
    reason = ("; ".join(f"{m} (missed by {ms:.2g} decades): {why}" for m, ms, why in ranked)
              + (f"; kirchhoff {why_k}" if why_k and feasible_k else ""))
    if miss > 0:
        reason = "WARNING: no method is valid for this relief and wavelength; ranked: " + reason
    extra = extra_k if method == "kirchhoff" else {}
    if method == "two_scale":                     # the run uses the very split the reason states
        extra = {"f_cut_per_um": fig["ts_f_cut_per_m"] * 1e-6}
    fig.pop("pitch_m")
    return Choice(method, reason, valid, extra, fig, _summary(method, miss, fig, extra, why_k))


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
