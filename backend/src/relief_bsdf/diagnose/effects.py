"""Candidate effects: each a small physical model plugged into the plate forward model.

The forward model (`PlateForward`) is the photon plate of `photon_plate.py` with the rough
face as the *measured facet-normal distribution* of the relief (`NormalsFace`), Stokes
vectors tracked through every interface, run for an s- and a p-polarised source with fixed
seeds (common random numbers: the same photons for every parameter value, so the misfit
varies smoothly with continuous parameters).  Its baseline is the plate exactly as
sample.toml states it: relief as measured (plane-levelled), index, thickness, known
absorption (0 when not known), flat back face, source polarisation, nominal detector cone.

Effects, each with its parameters, bounds and physics (the name is the formats.md name):

- bulk_absorption (absorption_per_mm): Beer-Lambert, every detected photon's weight times
  exp(-a L) with L its total path in the glass (exact reweighting of the recorded paths).
- volume_scattering (scatter_per_mm, hg_g): free paths ~ Exp(mu_s) and Henyey-Greenstein
  phase function in the bulk (photons re-traced).
- back_face_roughness (back_alpha): Beckmann microfacet back face (Walter et al. 2007) with
  roughness alpha (re-traced).
- sample_tilt (tilt_deg): the sample frame rotated about y (in the plane of incidence):
  incidence and exit directions transformed (re-traced).
- instrument_blur (blur_deg): beam divergence and detector aperture as a Gaussian angular
  convolution (1-sigma per axis) of the detector cone (re-detected from recorded exits).
- polarization (polarization_q): source Stokes (1, q, 0, 0), q = +1 s, -1 p; by linearity
  I = ((1 + q) I_s + (1 - q) I_p) / 2 from the two recorded source runs.
- stray_light (background_per_sr): additive background in every row.
- relief_scale (height_scale): heights times s, facet normals re-derived (re-traced).
- relief_smoothing (filter_sigma_um): Gaussian low-pass of the relief (Relief.gaussian_filtered),
  facet normals re-derived (re-traced).
- dispersion (cauchy_B_nm2): n(l) = n_stated(l) + B (1/l^2 - 1/l_ref^2), l_ref the middle
  recorded wavelength (re-traced per wavelength); only for spectral recordings.

- interreflection (interreflection_weight w): the single-scatter facet-normal front face is
  replaced by exact ray tracing through the triangulated relief (`conceal.HeightFieldFace`,
  Embree; paper sec. 2.3): shadowing, masking and multiple bounces on the relief.  Both
  rough-face runs are linear in the photons, so the simulation is the convex mixture
  (1 - w) I_normals + w I_heightfield (exact for the two pure models, w = 1 the ray-traced
  relief; intermediate w is a relaxation, e.g. for a relief only partly resolved by the
  profilometer).  Matters on steep reliefs (rms slope >~ 0.3) at grazing angles.
  Validity: geometric optics; the height map is tiled periodically (3 x 3) for the tracer.
- diffraction (coherent_scale s): wave optics at the rough face instead of ray optics: every
  front-face event follows the scalar Kirchhoff (Beckmann) model of a Gaussian-correlated
  surface (`photon_plate.KirchhoffFace`; Beckmann & Spizzichino 1963, ch. 5): with probability
  s exp(-g) the photon stays coherent (specular direction of the mean plane), g the event's
  phase variance (Debye-Waller exponent: (2 k n1 sigma cos theta_1)^2 in reflection,
  (k sigma (n1 cos theta_1 - n2 cos theta_2))^2 in transmission); otherwise it takes the
  incoherent Beckmann series (m ~ Poisson(g) given m >= 1 phase "orders", a transverse wave-vector
  change of variance 2 m / T^2 per axis), which is wider than the ray lobe when g is small and
  tends to it for g >> 1 (T from the measured rms height and slope).  Because it acts on every
  event, light crossing the face twice (in, reflected by the back face, out) keeps a coherent
  part ~ C_T^2 in the reflected rows.  s = 1 is the Kirchhoff value; s = 0 is the ray-optics
  baseline.  Valid for Gaussian-like statistics, slopes << 1, lateral scales >~ lambda.
- partial_coherence (coherence_length_um l_c): the same Kirchhoff face (s = 1) lit by a
  partially coherent source (Gaussian Schell model; van Cittert-Zernike): the whole field
  leaving the first (illuminated) event, coherent and diffuse, is convolved with a Gaussian
  of angular 1-sigma width lambda / (2 pi l_c) (paper: "BSDF ... filtered over an angular
  spread about lambda / l"), done per photon as a transverse wave-vector kick N(0, 1 / l_c^2)
  per axis.  Later events keep the beam's coherence (approximation).  l_c = 0 is the neutral
  (ray-optics) value; large l_c approaches `diffraction` with s = 1, so l_c is fitted only up to
  lambda / (pi h) (h the detector half-angle): a blur below h / 2 is not resolved by the
  instrument and the case is `diffraction`.

Validity: geometric optics, as photon_plate.py, except for the two wave-optics candidates
above (scalar Kirchhoff per event, Stokes vectors carried through).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from relief_bsdf.parallel.tasks import task_rng
from relief_bsdf.validation.photon import KirchhoffFace, NormalsFace, PlatePhysics, detect, run_photons
from relief_bsdf.io.recording import Recording

TRANSPORT_KEYS = ("scatter_per_mm", "hg_g", "back_alpha", "tilt_deg", "height_scale", "filter_sigma_um",
                  "cauchy_B_nm2", "coherent_scale", "coherence_length_um")
POST_KEYS = ("absorption_per_mm", "blur_deg", "polarization_q", "background_per_sr", "interreflection_weight")
SOURCE_Q = {"unpolarized": 0.0, "s": 1.0, "p": -1.0}


@dataclass(frozen=True)
class Effect:
    """A candidate: its parameters as (name, lower bound, upper bound, neutral value)."""

    name: str
    params: tuple
    description: str
    spectral_only: bool = False


EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect("bulk_absorption", (("absorption_per_mm", 0.0, 3.0, 0.0),),
           "light is absorbed in the glass (Beer-Lambert), more on longer paths"),
    Effect("volume_scattering", (("scatter_per_mm", 0.0, 3.0, 0.0), ("hg_g", 0.0, 0.95, 0.7)),
           "the glass bulk scatters light (Henyey-Greenstein volume scattering)"),
    Effect("back_face_roughness", (("back_alpha", 0.0, 0.5, 0.0),),
           "the back face is not optically flat (Beckmann microfacet surface)"),
    Effect("sample_tilt", (("tilt_deg", -8.0, 8.0, 0.0),),
           "the sample was mounted tilted in the plane of incidence"),
    Effect("instrument_blur", (("blur_deg", 0.0, 8.0, 0.0),),
           "beam divergence / detector aperture wider than stated (angular blur)"),
    Effect("polarization", (("polarization_q", -1.0, 1.0, 0.0),),
           "the source is polarised (q = +1 s, -1 p) unlike stated"),
    Effect("stray_light", (("background_per_sr", 0.0, 2.0, 0.0),),
           "stray light adds a constant background to every reading"),
    Effect("relief_scale", (("height_scale", 0.3, 2.5, 1.0),),
           "the relief's heights are off by a factor (instrument calibration)"),
    Effect("relief_smoothing", (("filter_sigma_um", 0.0, 8.0, 0.0),),
           "the real surface is smoother than measured (measurement noise / tip artefacts)"),
    Effect("interreflection", (("interreflection_weight", 0.0, 1.0, 0.0),),
           "light bounces more than once on the relief and is shadowed by it (ray-traced real relief)"),
    Effect("diffraction", (("coherent_scale", 0.0, 3.0, 0.0),),
           "the relief scatters as a wave (Kirchhoff): part of the light stays coherent and specular"),
    Effect("partial_coherence", (("coherence_length_um", 0.0, 30.0, 0.0),),
           "wave scattering lit by a partially coherent source: the specular peak is broadened"),
    Effect("dispersion", (("cauchy_B_nm2", -40000.0, 80000.0, 0.0),),
           "the glass index depends on wavelength (Cauchy B) unlike stated", spectral_only=True),
)}


@dataclass
class PlateForward:
    """Forward model of the recording for given effect parameters (see module docstring)."""

    heights_m: np.ndarray
    dx_m: float
    dy_m: float
    periodic: bool
    rows: Recording                  # geometry, bsdf_sr, sigma_sr (finite: Recording.with_sigma_fallback())
    thickness_mm: float
    index: object                    # IndexModel of the glass (stated)
    half_angle_deg: float
    source_q: float = 0.0
    known_absorption_per_mm: float = 0.0
    photons: int = 100_000
    seed: int = 0
    _cache_key: dict = field(default_factory=dict, repr=False)
    _cache: dict = field(default_factory=dict, repr=False)
    evaluations: int = field(default=0, repr=False)

    def _heights(self, p: dict) -> np.ndarray:
        h = self.heights_m
        if p.get("filter_sigma_um", 0.0) > 0:
            from scipy import ndimage
            s = p["filter_sigma_um"] * 1e-6
            mode = "wrap" if self.periodic else "reflect"
            h = ndimage.gaussian_filter(np.nan_to_num(h, nan=float(np.nanmean(h))), (s / self.dy_m, s / self.dx_m),
                                        mode=mode)
        return h * p.get("height_scale", 1.0)

    def _faces(self, p: dict, kind: str = "normals"):
        """The front face: measured facet normals, the Kirchhoff wave face, or the ray-traced height field."""
        h = self._heights(p)
        if kind == "kirchhoff":
            s = float(p.get("coherent_scale", 0.0)) or 1.0          # partial coherence: the Kirchhoff value
            return KirchhoffFace.from_heights(h, self.dx_m, self.dy_m, coherent_scale=s,
                                              coherence_length_m=float(p.get("coherence_length_um", 0.0)) * 1e-6)
        if kind == "heightfield":
            from relief_bsdf.validation.conceal import HeightFieldFace
            return HeightFieldFace(np.nan_to_num(h, nan=float(np.nanmean(h))), self.dx_m, self.dy_m)
        return NormalsFace.from_heights(h, self.dx_m, self.dy_m, self.periodic)

    def _n_glass(self, wl: float, p: dict) -> float:
        lref = float(np.median(np.unique(self.rows.wavelength_nm)))
        return float(np.real(self.index.n(wl))) + p.get("cauchy_B_nm2", 0.0) * (1 / wl**2 - 1 / lref**2)

    def _transport(self, p: dict, kind: str = "normals") -> dict:
        key = tuple(round(float(p.get(k, EFFECT_NEUTRAL[k])), 10) for k in TRANSPORT_KEYS)
        if key == self._cache_key.get(kind):
            return self._cache[kind]
        face = self._faces(p, kind)
        rows = self.rows
        wls = np.unique(rows.wavelength_nm)
        recs = {}
        salt = {"normals": (), "heightfield": (2,), "kirchhoff": (3,)}[kind]
        for iw, wl in enumerate(wls):
            if kind == "kirchhoff":
                face.wavelength_nm = float(wl)
            n = self._n_glass(wl, p)
            phys = PlatePhysics(thickness_mm=self.thickness_mm, n_glass=n, scatter_per_mm=p.get("scatter_per_mm", 0.0),
                                hg_g=p.get("hg_g", 0.0), back_alpha=p.get("back_alpha", 0.0),
                                tilt_deg=p.get("tilt_deg", 0.0))
            for (ti, pi) in sorted(set(zip(rows.theta_i_deg[rows.wavelength_nm == wl],
                                           rows.phi_i_deg[rows.wavelength_nm == wl]))):
                idx = np.nonzero((rows.wavelength_nm == wl) & (rows.theta_i_deg == ti) & (rows.phi_i_deg == pi))[0]
                ex = []
                for src, st in enumerate(((1.0, 1.0, 0.0, 0.0), (1.0, -1.0, 0.0, 0.0))):
                    rng = task_rng(self.seed, int(round(wl * 10)), int(round(ti * 100)), int(round(pi * 100)), src,
                                   *salt)
                    ex.append(run_photons(face, phys, ti, pi, st, self.photons // 2, rng))
                recs[(wl, ti, pi)] = (idx, ex)
        self._cache_key[kind], self._cache[kind] = key, recs
        return recs

    def simulate(self, params: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(values, Monte-Carlo sigma) per row for the given effect parameters."""
        p = dict(params or {})
        self.evaluations += 1
        wave = float(p.get("coherent_scale", 0.0)) > 0 or float(p.get("coherence_length_um", 0.0)) > 0
        recs = self._transport(p, "kirchhoff" if wave else "normals")
        a = self.known_absorption_per_mm + p.get("absorption_per_mm", 0.0)
        q = float(np.clip(p.get("polarization_q", self.source_q), -1, 1))
        blur = p.get("blur_deg", 0.0)
        val, var = self._detect_all(recs, a, q, blur)
        w_ir = float(np.clip(p.get("interreflection_weight", 0.0), 0.0, 1.0))
        if w_ir > 0:
            v2, var2 = self._detect_all(self._transport(p, "heightfield"), a, q, blur)
            val, var = (1 - w_ir) * val + w_ir * v2, (1 - w_ir) ** 2 * var + w_ir**2 * var2
        val += p.get("background_per_sr", 0.0)
        return val, np.sqrt(var)

    def _detect_all(self, recs: dict, a: float, q: float, blur) -> tuple[np.ndarray, np.ndarray]:
        """Detected values and MC variances per row of one set of photon runs; `blur` a scalar
        or a per-row array (deg)."""
        rows = self.rows
        val = np.zeros(len(rows))
        var = np.zeros(len(rows))
        blur_rows = np.broadcast_to(np.asarray(blur, float), (len(rows),))
        for (_wl, _ti, _pi), (idx, ex) in recs.items():
            # rows of one incidence share a blur unless it depends on the wavelength (same here)
            for b in np.unique(blur_rows[idx]):
                sub = idx[blur_rows[idx] == b]
                parts = []
                for e in ex:
                    w = e.w * np.exp(-a * e.path_mm) if a > 0 else e.w
                    parts.append(detect(e, rows.side[sub], rows.theta_s_deg[sub], rows.phi_s_deg[sub],
                                        self.half_angle_deg, weights=w, blur_sigma_deg=float(b)))
                (vs, ss), (vp, sp) = parts
                val[sub] = 0.5 * ((1 + q) * vs + (1 - q) * vp)
                var[sub] = 0.25 * ((1 + q) ** 2 * ss**2 + (1 - q) ** 2 * sp**2)
        return val, var


EFFECT_NEUTRAL = {"scatter_per_mm": 0.0, "hg_g": 0.0, "back_alpha": 0.0, "tilt_deg": 0.0, "height_scale": 1.0,
                  "filter_sigma_um": 0.0, "cauchy_B_nm2": 0.0, "absorption_per_mm": 0.0, "blur_deg": 0.0,
                  "polarization_q": 0.0, "background_per_sr": 0.0,
                  "interreflection_weight": 0.0, "coherent_scale": 0.0, "coherence_length_um": 0.0}


def chi2(rows: Recording, model: np.ndarray, model_sigma: np.ndarray) -> float:
    """Noise-weighted misfit, s^2 = sigma_recording^2 + sigma_model^2.

    Rows with a measured value > 0 contribute ((y - m) / s)^2.  recording.csv holds no
    negative BSDF values, so a reading at exactly 0 is a reading clipped at zero (a
    censored Gaussian, Tobit likelihood): it contributes -2 ln(2 Phi(-m / s)), the
    log-probability of reading <= 0, shifted so that m = 0 costs nothing (as z^2 would).
    Without this, clipped noise reads as a positive background.
    """
    s = np.sqrt(rows.sigma_sr**2 + model_sigma**2)
    y = rows.bsdf_sr
    cens = y <= 0
    z2 = ((y - model) / s) ** 2
    if cens.any():
        from scipy.special import log_ndtr
        z2[cens] = np.maximum(-2.0 * (log_ndtr(-model[cens] / s[cens]) + np.log(2.0)), 0.0)
    return float(np.sum(z2))


def _fit_1d(f, lo: float, hi: float, grid: int, refine: int, neutral: float | None = None) -> tuple[float, float]:
    """Coarse grid (always including the neutral value) then bounded Brent refinement
    between the best grid point's neighbours."""
    xs = np.linspace(lo, hi, grid)
    if neutral is not None:
        xs = np.unique(np.append(xs, neutral))
    ys = [f(x) for x in xs]
    k = int(np.argmin(ys))
    a, b = xs[max(k - 1, 0)], xs[min(k + 1, len(xs) - 1)]
    best_x, best_y = xs[k], ys[k]
    if refine > 0 and b > a:
        r = optimize.minimize_scalar(f, bounds=(a, b), method="bounded",
                                     options={"maxiter": refine, "xatol": (hi - lo) * 1e-3})
        if r.fun < best_y:
            best_x, best_y = float(r.x), float(r.fun)
    return float(best_x), float(best_y)


def fit_effect(model: PlateForward, effect: str, progress=None) -> dict:
    """Fit one effect's parameters by least chi^2; returns name, parameters, chi2, values."""
    eff = EFFECTS[effect]
    base = {"polarization_q": model.source_q}

    def run(pars: dict) -> tuple[float, np.ndarray, np.ndarray]:
        v, s = model.simulate({**base, **pars})
        return chi2(model.rows, v, s), v, s

    post = all(name in POST_KEYS for name, *_ in eff.params)
    grid, refine = (9, 10) if post else (5, 6)
    pars: dict = {}
    if effect == "stray_light":     # linear in the background: weighted mean as a start, then the censored chi2
        v0, s0 = model.simulate(base)
        w = 1.0 / (model.rows.sigma_sr**2 + s0**2)
        b0 = max(0.0, float(np.sum(w * (model.rows.bsdf_sr - v0)) / np.sum(w)))
        r = optimize.minimize_scalar(lambda b: run({"background_per_sr": b})[0], bounds=(0.0, max(3 * b0, 1e-3)),
                                     method="bounded", options={"maxiter": 12})
        pars = {"background_per_sr": float(r.x) if r.fun < run({"background_per_sr": 0.0})[0] else 0.0}
    elif effect == "partial_coherence":  # the lobe width ~ 1 / l_c: fit on a log scale (0.3 um .. hi), plus l_c = 0
        name, lo, hi, neutral = eff.params[0]
        # identifiable only where the instrument resolves the blur: lambda / (2 pi l_c) >= half the detector's
        # half-angle; a longer coherence length looks like a coherent source to it, i.e. `diffraction`
        wl_um = float(np.median(model.rows.wavelength_nm)) * 1e-3
        hi = min(hi, wl_um / (np.pi * np.radians(model.half_angle_deg)))
        f = lambda u: run({name: 10.0**u})[0]  # noqa: E731
        u, cu = _fit_1d(f, np.log10(0.3), np.log10(hi), grid, refine)
        pars = {name: 10.0**u if cu < run({name: neutral})[0] else neutral}
    elif len(eff.params) == 1:
        name, lo, hi, neutral = eff.params[0]
        x, _ = _fit_1d(lambda x: run({name: x})[0], lo, hi, grid, refine, neutral)
        pars = {name: x}
    else:  # volume scattering: coefficient at a typical forward g, then g, then the coefficient again
        (n1, lo1, hi1, _), (n2, lo2, hi2, g0) = eff.params
        x1, _ = _fit_1d(lambda x: run({n1: x, n2: g0})[0], lo1, hi1, 4, 4, 0.0)
        if x1 > 0:
            x2, _ = _fit_1d(lambda x: run({n1: x1, n2: x})[0], lo2, hi2, 4, 3)
            x1, _ = _fit_1d(lambda x: run({n1: x, n2: x2})[0], 0.5 * x1, min(hi1, 1.5 * x1), 3, 2)
        else:
            x2 = g0
        pars = {n1: x1, n2: x2}
    c, v, s = run(pars)
    return {"effect": effect, "parameters": {k: float(v_) for k, v_ in pars.items()}, "chi2": c,
            "k": len(eff.params), "values": v, "model_sigma": s}
