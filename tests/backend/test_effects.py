"""Physics of the photon plate and of each candidate effect (small, fast Monte-Carlo runs)."""
import numpy as np
import pytest

from relief_bsdf.diagnose.effects import EFFECTS, PlateForward, fit_effect
from relief_bsdf.io.recording import Recording
from relief_bsdf.core.optics import ConstantIndex, fresnel_power
from relief_bsdf.validation.photon import NormalsFace, PlatePhysics, _hg_cos, beckmann_normals, detect, run_photons

FLAT = NormalsFace(np.array([[0.0, 0.0, 1.0]]))
N = 20000



def _rows(tis):
    """In-plane rows at 550 nm (theta_s every 10 deg, phi_s 0 and 180, R and T), sigma 0.01."""
    g = [(550.0, ti, sd, t, ps) for ti in tis for sd in ("R", "T") for ps in (0.0, 180.0)
         for t in np.arange(0.0, 90.0, 10.0)]
    W, TI, SD, TS, PS = (np.array(c) for c in zip(*g))
    n = len(W)
    return Recording(W.astype(float), TI.astype(float), np.zeros(n), SD, TS.astype(float), PS.astype(float),
                     np.zeros(n), np.full(n, 0.01))

def _plate_RT(theta_deg, n, t_mm, a_per_mm, pol):
    """Incoherent flat plate (Stokes channel s or p): multiple reflections summed exactly."""
    ci = np.cos(np.radians(theta_deg))
    Rs, Rp, _, _ = fresnel_power(ci, 1.0, n)
    R = float(Rs if pol == "s" else Rp)
    ct = np.sqrt(1 - (np.sin(np.radians(theta_deg)) / n) ** 2)
    att = np.exp(-a_per_mm * t_mm / ct)
    T = (1 - R) ** 2 * att / (1 - R**2 * att**2)
    Rt = R + (1 - R) ** 2 * R * att**2 / (1 - R**2 * att**2)
    return Rt, T


def _fractions(ex):
    up = ex.d[:, 2] > 0
    return ex.w[up].sum() / ex.n_launched, ex.w[~up].sum() / ex.n_launched


@pytest.mark.parametrize("pol,stokes", [("s", (1, 1, 0, 0)), ("p", (1, -1, 0, 0))])
@pytest.mark.parametrize("theta", [0.0, 56.31, 70.0])
def test_flat_plate_matches_incoherent_fresnel_series(pol, stokes, theta):
    ex = run_photons(FLAT, PlatePhysics(thickness_mm=2.0, n_glass=1.5, absorption_per_mm=0.2), theta, 0.0,
                     stokes, N, np.random.default_rng(1))
    R, T = _fractions(ex)
    Rt, Tt = _plate_RT(theta, 1.5, 2.0, 0.2, pol)
    tol = 4 * np.sqrt(Rt * (1 - Rt) / N) + 1e-4
    assert R == pytest.approx(Rt, abs=tol)
    assert T == pytest.approx(Tt, abs=4 * np.sqrt(Tt * (1 - Tt) / N) + 1e-4)


def test_brewster_angle_p_source_reflects_almost_nothing():
    ex_p = run_photons(FLAT, PlatePhysics(), np.degrees(np.arctan(1.5)), 0.0, (1, -1, 0, 0), N, np.random.default_rng(2))
    ex_s = run_photons(FLAT, PlatePhysics(), np.degrees(np.arctan(1.5)), 0.0, (1, 1, 0, 0), N, np.random.default_rng(2))
    assert _fractions(ex_p)[0] < 2e-3
    assert _fractions(ex_s)[0] > 0.2


def test_tilt_rotates_the_specular_reflection_by_twice_the_tilt():
    ex = run_photons(FLAT, PlatePhysics(tilt_deg=3.0), 30.0, 0.0, (1, 0, 0, 0), 2000, np.random.default_rng(3))
    up = ex.d[ex.d[:, 2] > 0]
    th = np.degrees(np.arccos(up[:, 2]))
    assert np.allclose(th, 30.0 + 6.0, atol=1e-6) or np.allclose(th, 30.0 - 6.0, atol=1e-6)
    # transmission through a tilted parallel plate stays undeviated
    dn = ex.d[ex.d[:, 2] < 0]
    assert np.allclose(np.degrees(np.arccos(-dn[:, 2])), 30.0, atol=1e-6)


def test_henyey_greenstein_sampler_mean_cosine_is_g():
    u = np.random.default_rng(4).random(200000)
    for g in (0.0, 0.5, 0.9):
        assert np.mean(_hg_cos(g, u)) == pytest.approx(g, abs=5e-3)


def test_volume_scattering_removes_the_direct_beam_as_exp_minus_mu_t():
    mu, t = 0.3, 2.0
    ex = run_photons(FLAT, PlatePhysics(thickness_mm=t, scatter_per_mm=mu, hg_g=0.5), 0.0, 0.0, (1, 0, 0, 0), N,
                     np.random.default_rng(5))
    direct = np.sum(ex.d[:, 2] < -1 + 1e-9) / N
    T0 = _plate_RT(0.0, 1.5, t, 0.0, "s")[1]
    # first-pass direct transmission dominates T0; multiple passes add (R^2 e^{-2 mu t}) corrections
    expect = (1 - 0.04) ** 2 * np.exp(-mu * t)
    assert direct == pytest.approx(expect, abs=0.02)
    assert direct < T0


def test_rough_back_face_spreads_transmission_with_roughness():
    spread = []
    for alpha in (0.05, 0.15):
        ex = run_photons(FLAT, PlatePhysics(back_alpha=alpha), 0.0, 0.0, (1, 0, 0, 0), 5000, np.random.default_rng(6))
        dn = ex.d[ex.d[:, 2] < 0]
        spread.append(np.sqrt(np.mean(np.arccos(-dn[:, 2]) ** 2)))
    assert spread[1] > 2.0 * spread[0]
    # Beckmann normals: mean square slope = alpha^2
    m = beckmann_normals(0.2, 100000, np.random.default_rng(0))
    assert np.mean((m[:, 0] ** 2 + m[:, 1] ** 2) / m[:, 2] ** 2) == pytest.approx(0.04, rel=0.03)


def _small_forward(photons=20000, periodic=True):
    from relief_bsdf.validation.conceal import gaussian_relief
    h = gaussian_relief(48, 1e-6, 0.3e-6, 4e-6, 5)
    return PlateForward(h, 1e-6, 1e-6, periodic, _rows((0.0, 40.0)), 2.0, ConstantIndex(1.5), 3.0, photons=photons,
                        seed=1)


def test_absorption_reweighting_equals_beer_lambert_in_the_run():
    fwd = _small_forward()
    v, _ = fwd.simulate({"absorption_per_mm": 0.3})
    v0, _ = fwd.simulate({})
    T = fwd.rows.side == "T"
    # normal-ish transmission loses at least exp(-a t) and the ratio is the same for every angle family
    ratio = v[T & (v0 > 1)] / v0[T & (v0 > 1)]
    assert np.all(ratio < np.exp(-0.3 * 2.0) * 1.001)
    assert np.all(ratio > np.exp(-0.3 * 2.0 / 0.6))


def test_each_effect_moves_the_simulation_and_is_neutral_at_its_neutral_value():
    fwd = _small_forward()
    v0, _ = fwd.simulate({})
    for name, eff in EFFECTS.items():
        if eff.spectral_only:
            continue
        pars_neutral = {p: neutral for p, lo, hi, neutral in eff.params}
        if name == "volume_scattering":
            pars_neutral["scatter_per_mm"] = 0.0
        vn, _ = fwd.simulate(pars_neutral)
        assert np.allclose(vn, v0), name
        pars = {p: (neutral + 0.3 * (hi - neutral) if hi > neutral else lo) for p, lo, hi, neutral in eff.params}
        v1, _ = fwd.simulate(pars)
        assert np.max(np.abs(v1 - v0) / (np.abs(v0) + 0.05)) > 0.05, name


def test_relief_scale_broadens_and_smoothing_narrows_the_transmitted_lobe():
    fwd = _small_forward()
    T0 = (fwd.rows.side == "T") & (fwd.rows.theta_i_deg == 0.0) & (fwd.rows.theta_s_deg == 0.0)
    peak = lambda p: fwd.simulate(p)[0][T0].mean()  # noqa: E731
    p0 = peak({})
    assert peak({"height_scale": 1.5}) < 0.7 * p0
    assert peak({"filter_sigma_um": 2.0}) > 1.3 * p0


def test_fit_recovers_a_background_and_an_absorption():
    fwd = _small_forward()
    truth, _ = fwd.simulate({"absorption_per_mm": 0.25})
    fwd.rows.bsdf_sr = truth
    fwd.rows.sigma_sr = 0.02 * truth + 1e-3
    f = fit_effect(fwd, "bulk_absorption")
    assert f["parameters"]["absorption_per_mm"] == pytest.approx(0.25, abs=0.01)
    truth2, _ = fwd.simulate({"background_per_sr": 0.05})
    fwd.rows.bsdf_sr = truth2
    f = fit_effect(fwd, "stray_light")
    assert f["parameters"]["background_per_sr"] == pytest.approx(0.05, abs=0.005)


def test_detector_blur_keeps_the_integral_and_lowers_a_sharp_peak():
    ex = run_photons(NormalsFace(beckmann_normals(0.05, 20000, np.random.default_rng(1))), PlatePhysics(), 0.0, 0.0,
                     (1, 0, 0, 0), N, np.random.default_rng(7))
    th = np.array([0.0])
    sharp, _ = detect(ex, np.array(["T"]), th, th, 2.0)
    wide, _ = detect(ex, np.array(["T"]), th, th, 2.0, blur_sigma_deg=3.0)
    assert wide[0] < 0.8 * sharp[0]


def test_chi2_treats_zero_readings_as_clipped_and_is_unbiased_for_a_background():
    """A flat zero signal with Gaussian noise clipped at 0 must not look like a background."""
    from relief_bsdf.diagnose.effects import chi2
    rng = np.random.default_rng(8)
    n = 4000
    y = np.maximum(0.002 * rng.normal(size=n), 0.0)
    rows = Recording(*(np.zeros(n),) * 3, np.array(["R"] * n), *(np.zeros(n),) * 2, y, np.full(n, 0.002))
    bs = np.linspace(-0.001, 0.001, 41)
    c = [chi2(rows, np.full(n, b), np.zeros(n)) for b in bs]
    assert abs(bs[int(np.argmin(c))]) <= 1e-4
    # the plain chi2 of the clipped data would be minimised at a clearly positive background
    plain = [np.sum(((y - b) / 0.002) ** 2) for b in bs]
    assert bs[int(np.argmin(plain))] > 5e-4


# ------------------------------------------------------------------ wave-optics and interreflection candidates

def _forward_on(h, photons=20000, tis=(0.0, 40.0, 70.0), dx_m=1e-6):
    return PlateForward(h, dx_m, dx_m, True, _rows(tis), 2.0, ConstantIndex(1.5), 3.0, photons=photons, seed=3)


def _names_it(fwd, truth_params, effect, rivals, noise_rel=0.03):
    """Noisy synthetic recording from `truth_params`; fit `effect` and rivals; select by BIC."""
    from relief_bsdf.diagnose.run import select
    from relief_bsdf.diagnose.effects import chi2
    truth, _ = fwd.simulate(truth_params)
    rng = np.random.default_rng(11)
    sig = noise_rel * np.abs(truth) + 2e-3
    fwd.rows.bsdf_sr = np.maximum(truth + sig * rng.normal(size=truth.size), 0.0)
    fwd.rows.sigma_sr = sig
    v0, s0 = fwd.simulate({})
    fits = [fit_effect(fwd, e) for e in (effect, *rivals)]
    name, cands, _ = select(chi2(fwd.rows, v0, s0), len(fwd.rows), fits)
    return name, fits[0]["parameters"]


def test_diffraction_restores_the_specular_beam_of_a_smooth_relief_and_is_named():
    from relief_bsdf.validation.conceal import gaussian_relief
    # sigma = lambda / 11 (mostly coherent), slopes ~ 0.12 rad: a geometric lobe wider than the detector
    h = gaussian_relief(48, 0.2e-6, 0.05e-6, 0.6e-6, 4)
    fwd = _forward_on(h, tis=(0.0, 40.0), dx_m=0.2e-6)
    spec = (fwd.rows.side == "R") & (fwd.rows.theta_s_deg == fwd.rows.theta_i_deg) & (fwd.rows.phi_s_deg == 180.0)
    spec |= (fwd.rows.side == "R") & (fwd.rows.theta_i_deg == 0) & (fwd.rows.theta_s_deg == 0)
    v0, _ = fwd.simulate({})
    v1, _ = fwd.simulate({"coherent_scale": 1.0})
    # the coherent part concentrates the specular reflection into the detector cone
    assert np.all(v1[spec] > 1.2 * v0[spec])
    name, pars = _names_it(fwd, {"coherent_scale": 1.0}, "diffraction", ("instrument_blur", "relief_smoothing"))
    assert name == "diffraction"
    assert pars["coherent_scale"] == pytest.approx(1.0, abs=0.15)


def test_partial_coherence_broadens_the_coherent_lobe_and_is_named():
    from relief_bsdf.validation.conceal import gaussian_relief
    h = gaussian_relief(48, 0.2e-6, 0.05e-6, 0.6e-6, 4)
    fwd = _forward_on(h, tis=(0.0, 40.0), dx_m=0.2e-6)
    r = fwd.rows
    spec = (r.side == "T") & (r.theta_i_deg == 0) & (r.theta_s_deg == 0)
    near = (r.side == "T") & (r.theta_i_deg == 0) & (r.theta_s_deg == 10)
    long_, _ = fwd.simulate({"coherence_length_um": 30.0})
    short, _ = fwd.simulate({"coherence_length_um": 0.8})
    # a shorter coherence length moves coherent light from the regular beam to its neighbourhood
    assert np.all(short[spec] < 0.8 * long_[spec])
    assert np.all(short[near] > long_[near])
    name, pars = _names_it(fwd, {"coherence_length_um": 1.5}, "partial_coherence",
                           ("diffraction", "instrument_blur"))
    assert name == "partial_coherence"
    assert pars["coherence_length_um"] == pytest.approx(1.5, rel=0.3)


def test_interreflection_matters_on_a_steep_relief_and_is_named():
    from relief_bsdf.validation.conceal import gaussian_relief
    h = gaussian_relief(48, 1e-6, 2e-6, 2e-6, 6)    # rms slope ~ 1.3: shadowing and multiple bounces
    fwd = _forward_on(h, tis=(0.0, 70.0))
    v0, s0 = fwd.simulate({})
    v1, s1 = fwd.simulate({"interreflection_weight": 1.0})
    z = (v1 - v0) / np.sqrt(s0**2 + s1**2 + 1e-6)
    assert np.sum(z**2) > 4 * len(z)      # far beyond Monte-Carlo noise
    # at grazing incidence the real relief shadows and traps light the single-scatter model reflects
    g = (fwd.rows.side == "R") & (fwd.rows.theta_i_deg == 70.0)
    assert v1[g].sum() < 0.6 * v0[g].sum()
    name, pars = _names_it(fwd, {"interreflection_weight": 1.0}, "interreflection", ("relief_scale", "instrument_blur"))
    assert name == "interreflection"
    assert pars["interreflection_weight"] > 0.8
