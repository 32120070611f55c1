"""Thin phase-screen rough face (wave optics): Fresnel split, energy, Debye-Waller coherent part,
partial-coherence broadening, geometric-optics limit, grating-equation sign, reproducibility."""
import numpy as np
import pytest
from scipy.special import ndtri

from relief_bsdf.core.fresnel import fresnel_amplitudes
from relief_bsdf.validation.phase_screen import PhaseScreenFace, ScreenSampling
from relief_bsdf.validation.photon import NormalsFace, PlatePhysics, direction, run_photons

WL_NM = 550.0
K0 = 2 * np.pi / (WL_NM * 1e-3)     # 1/um


def _beam(theta_deg, n, inside=False, stokes=(1.0, 0.0, 0.0, 0.0)):
    """n photons travelling towards the face: from outside (down) or from inside (up)."""
    d = -direction(theta_deg, 0.0)
    if inside:
        d[2] = -d[2]
    d = np.tile(d, (n, 1))
    e = np.tile([0.0, 1.0, 0.0], (n, 1))
    S = np.tile(np.asarray(stokes, float), (n, 1))
    return d, S, e, np.full(n, inside)


def _gaussian_marginal(h):
    """Same ranks, exactly Gaussian height histogram (normal quantiles), same rms."""
    r = np.argsort(np.argsort(h.ravel()))
    q = ndtri((r + 0.5) / r.size)
    return (q * h.std() / q.std()).reshape(h.shape)


def test_flat_relief_gives_the_fresnel_split_and_only_specular_directions():
    face = PhaseScreenFace(np.zeros((32, 32)), 0.5e-6, 0.5e-6, WL_NM)
    n = 40000
    for theta, inside, pol in ((40.0, False, 1.0), (40.0, False, -1.0), (25.0, True, 1.0), (25.0, True, -1.0)):
        d, S, e, ins = _beam(theta, n, inside, (1.0, pol, 0.0, 0.0))
        n1, n2 = (1.5, 1.0) if inside else (1.0, 1.5)
        dn, Sn, en, ins_new, alive = face.interact(d, S, e, ins, 1.5, np.random.default_rng(3))
        assert alive.all()
        refl = ins_new == inside
        rs, rp, _, _ = fresnel_amplitudes(np.cos(np.radians(theta)), n1, n2)
        R = abs(rs) ** 2 if pol > 0 else abs(rp) ** 2
        assert refl.mean() == pytest.approx(R, abs=4 * np.sqrt(R * (1 - R) / n) + 1e-9)
        spec_r = d[0] * np.array([1, 1, -1])
        st = np.sqrt(1 - (n1 / n2 * np.sin(np.radians(theta))) ** 2)
        spec_t = np.array([n1 / n2 * d[0, 0], 0.0, np.sign(d[0, 2]) * st])
        assert np.allclose(dn[refl], spec_r, atol=1e-12)
        assert np.allclose(dn[~refl], spec_t, atol=1e-12)
        assert np.allclose(np.einsum("ij,ij->i", en, dn), 0.0, atol=1e-12)   # s-axis stays transverse


def test_every_photon_is_accounted_for_and_leaves_on_its_side(gaussian_relief):
    h = gaussian_relief(64, 0.5e-6, 0.2e-6, 2.0e-6, 5).heights_m
    face = PhaseScreenFace(h, 0.5e-6, 0.5e-6, WL_NM)
    n = 30000
    # from inside close to the critical angle (41.8 deg): many transmitted orders are evanescent
    d, S, e, ins = _beam(38.0, n, inside=True)
    dn, Sn, en, ins_new, alive = face.interact(d, S, e, ins, 1.5, np.random.default_rng(1))
    R = np.mean(alive & (ins_new == ins))
    T = np.mean(alive & (ins_new != ins))
    lost = np.mean(~alive)
    assert R + T + lost == pytest.approx(1.0, abs=1e-12)
    assert lost < 0.01 and T > 0.2
    assert np.allclose(np.linalg.norm(dn, axis=1), 1.0)
    assert np.all(dn[ins_new & alive, 2] < 0) and np.all(dn[~ins_new & alive, 2] > 0)
    assert np.allclose(Sn[:, 0], 1.0)
    ex = run_photons(face, PlatePhysics(), 30.0, 0.0, (1, 0, 0, 0), 20000, np.random.default_rng(2))
    assert len(ex.d) + ex.lost == 20000
    assert ex.lost < 100


# (70 deg T: the grazing case, moved here from the removed KirchhoffFace's tests.  Not 70 deg R: there
# much of the diffuse part is evanescent and the screen renormalises the propagating orders, so the
# coherent share of the reflected photons exceeds exp(-sigma_phi^2) by design, see phase_screen.py)
@pytest.mark.parametrize("theta,inside,side", [(60.0, False, "R"), (0.0, False, "T"), (20.0, True, "T"),
                                               (70.0, False, "T")])
def test_coherent_order_of_a_gaussian_relief_is_the_debye_waller_fraction(theta, inside, side, gaussian_relief):
    s_um = 0.08
    h = _gaussian_marginal(gaussian_relief(128, 0.5e-6, s_um * 1e-6, 2.5e-6, 9).heights_m)
    face = PhaseScreenFace(h, 0.5e-6, 0.5e-6, WL_NM, sampling=ScreenSampling(upsample=1))
    n = 120000
    d, S, e, ins = _beam(theta, n, inside)
    dn, _, _, ins_new, alive = face.interact(d.copy(), S, e, ins, 1.5, np.random.default_rng(4))
    n1, n2 = (1.5, 1.0) if inside else (1.0, 1.5)
    c1 = np.cos(np.radians(theta))
    c2 = np.sqrt(1 - (n1 / n2) ** 2 * (1 - c1**2))
    if side == "R":
        sel = alive & (ins_new == ins)
        spec = d[0] * np.array([1, 1, -1])
        sig_phi = 2 * K0 * n1 * c1 * s_um
    else:
        sel = alive & (ins_new != ins)
        spec = np.array([n1 / n2 * d[0, 0], 0.0, np.sign(d[0, 2]) * c2])
        sig_phi = K0 * abs(n1 * c1 - n2 * c2) * s_um
    coh = np.all(np.abs(dn[sel] - spec) < 1e-9, axis=1)
    C = np.exp(-sig_phi**2)
    m = sel.sum()
    assert 0.1 < C < 0.95
    assert coh.mean() == pytest.approx(C, abs=4.5 * np.sqrt(C * (1 - C) / m))


def test_partial_coherence_broadens_the_specular_order_to_lambda_over_2pi_lc():
    """Flat face, Gaussian Schell source: transverse direction 1-sigma = lambda / (2 pi l_c) per axis.
    Tolerance 10 %: the field's coherence is exp(-s^2 (1 - exp(-r^2/2L^2))) (width bias ~ 1/(4 s^2) =
    1.6 % for s = 4), each realisation holds ~ (128 um / 8 um)^2 = 256 independent psi cells (its gradient
    variance scatters ~ 9 %, / sqrt(16) realisations ~ 2 % on the width), Welch/Hann resolution
    (1 / 64 um) is < 0.4 % of the width in quadrature, photon noise 0.5 %."""
    l_c_um = 2.0
    face = PhaseScreenFace(np.zeros((256, 256)), 0.5e-6, 0.5e-6, WL_NM, coherence_length_um=l_c_um)
    n = 40000
    d, S, e, ins = _beam(0.0, n)
    dn, _, _, ins_new, alive = face.interact(d, S, e, ins, 1.5, np.random.default_rng(6))
    width = WL_NM * 1e-3 / (2 * np.pi * l_c_um)
    R = alive & ~ins_new
    T = alive & ins_new
    for sel, n_out in ((R, 1.0), (T, 1.5)):
        q = dn[sel, :2] * n_out                         # transverse wave vector / k0
        assert q.std(axis=0) == pytest.approx([width, width], rel=0.10)
        assert np.mean(np.all(np.abs(q) < 1e-9, axis=1)) < 0.01   # no sharp specular order left
    # inner events stay coherent (only the source's beam is partially coherent)
    d, S, e, ins = _beam(0.0, 5000, inside=True)
    dn, *_ = face.interact(d, S, e, ins, 1.5, np.random.default_rng(7))
    assert np.allclose(dn[:, :2], 0.0, atol=1e-12)


def test_rough_screen_lobe_approaches_the_geometric_slope_lobe(gaussian_relief):
    """Kirchhoff -> geometric optics: phase rms >> 1 rad (here 18 rad in R, 4.6 rad in T), the far field
    follows the slope distribution.  Compared with the facet-normal photon face (ray optics) on the same
    relief (rms slope 0.1 per axis): median and 90th percentile of the transverse kick within 6 % (the
    screen's small-slope linearisation, e.g. 2 s vs sin(2 atan s) in R, differs from exact facet optics by
    ~ s^2 <= 2.5 % at the 90th percentile; photon noise ~ 1 % on 6000 reflected photons).  A smooth relief
    (phase rms < 1) is far from it: checked too."""
    h = gaussian_relief(512, 0.3e-6, 0.8e-6, 16e-6, 3).heights_m
    n = 150000
    geo = NormalsFace.from_heights(h, 0.3e-6, 0.3e-6)
    d, S, e, ins = _beam(0.0, n)
    dg, _, _, ig, _ = geo.interact(d.copy(), S.copy(), e.copy(), ins.copy(), 1.5, np.random.default_rng(8))
    wave = PhaseScreenFace(h, 0.3e-6, 0.3e-6, WL_NM, sampling=ScreenSampling(upsample=1))
    dw, _, _, iw, aw = wave.interact(d.copy(), S.copy(), e.copy(), ins.copy(), 1.5, np.random.default_rng(9))
    for side in (False, True):
        g = np.linalg.norm(dg[ig == side, :2], axis=1)
        w = np.linalg.norm(dw[(iw == side) & aw, :2], axis=1)
        assert np.percentile(w, 50) == pytest.approx(np.percentile(g, 50), rel=0.06)
        assert np.percentile(w, 90) == pytest.approx(np.percentile(g, 90), rel=0.06)
    smooth = PhaseScreenFace(h * 0.03, 0.3e-6, 0.3e-6, WL_NM, sampling=ScreenSampling(upsample=1))
    ds, _, _, is_, _ = smooth.interact(d.copy(), S.copy(), e.copy(), ins.copy(), 1.5, np.random.default_rng(9))
    g = np.linalg.norm(dg[ig, :2], axis=1) * 0.03
    w = np.linalg.norm(ds[is_, :2], axis=1)
    assert np.percentile(w, 50) < 0.3 * np.percentile(g, 50)   # mostly the coherent order, not a slope lobe


def test_blazed_grating_sends_light_where_its_facets_do():
    """Sign of the grating equation: a sawtooth rising towards +x (slope s = 0.05) reflects a normal beam
    to -x by ~2 s and refracts it into the glass to +x by (n - 1) s / n (facet optics).  Period 22 um at
    550 nm: the ramp's phase is exactly 2 pi (T) and 8 pi (R) per period (blazed), so the light goes into
    the single orders +1 (T) and -4 (R), exactly the facet directions."""
    s, period_um, pitch_um = 0.05, 22.0, 0.125
    x = np.arange(704) * pitch_um                     # 4 periods
    prof = s * (np.mod(x, period_um) - period_um / 2)
    h = np.tile(prof, (8, 1)) * 1e-6
    face = PhaseScreenFace(h, pitch_um * 1e-6, pitch_um * 1e-6, WL_NM, sampling=ScreenSampling(upsample=1))
    d, S, e, ins = _beam(0.0, 40000)
    dn, _, _, ins_new, alive = face.interact(d, S, e, ins, 1.5, np.random.default_rng(10))
    mr = dn[alive & ~ins_new, 0].mean()
    mt = dn[alive & ins_new, 0].mean()
    assert mr == pytest.approx(-2 * s, rel=0.05)
    assert mt == pytest.approx(0.5 * s / 1.5, rel=0.05)


def test_seeded_runs_are_reproducible(gaussian_relief):
    h = gaussian_relief(64, 0.5e-6, 0.15e-6, 2.5e-6, 2).heights_m
    face = PhaseScreenFace(h, 0.5e-6, 0.5e-6, WL_NM, coherence_length_um=1.0)
    a = run_photons(face, PlatePhysics(), 30.0, 0.0, (1, 0, 0, 0), 6000, np.random.default_rng(11))
    face2 = PhaseScreenFace(h, 0.5e-6, 0.5e-6, WL_NM, coherence_length_um=1.0)
    b = run_photons(face2, PlatePhysics(), 30.0, 0.0, (1, 0, 0, 0), 6000, np.random.default_rng(11))
    c = run_photons(face2, PlatePhysics(), 30.0, 0.0, (1, 0, 0, 0), 6000, np.random.default_rng(12))
    assert np.array_equal(a.d, b.d) and a.lost == b.lost
    assert not np.array_equal(a.d[:100], c.d[:100])


def test_smooth_relief_diffuse_part_is_wider_than_the_ray_lobe(gaussian_relief):
    """Phase rms << 1 (g = (2 k0 s)^2 = 0.21 in reflection at normal incidence): the diffuse part is
    set by the correlation length, not the slopes.  Beckmann series of a Gaussian-correlated
    surface (exp(-r^2/L^2)): per-axis kick std sqrt(2 E[m | m >= 1]) / (k0 L), E[m | m >= 1] =
    g / (1 - exp(-g)), i.e. ~ lambda / (sqrt(2) pi L) for the first order; 1 / sqrt(g) = 2.2 times the
    geometric lobe 2 sqrt(2) s / L.  The screen gets it from the real relief's FFT (tile 50 L: its
    realised spectrum scatters by a few %, hence 6 %).  (Moved here from the removed KirchhoffFace.)"""
    s_um, L_um = 0.02, 2.5
    h = gaussian_relief(256, 0.5e-6, s_um * 1e-6, L_um * 1e-6, 3).heights_m
    face = PhaseScreenFace(h, 0.5e-6, 0.5e-6, WL_NM, sampling=ScreenSampling(upsample=1))
    d, S, e, ins = _beam(0.0, 300_000)
    out, _, _, ins_new, alive = face.interact(d, S, e, ins, 1.5, np.random.default_rng(3))
    diffuse = alive & ~ins_new & (np.abs(out[:, 0]) + np.abs(out[:, 1]) > 0)
    g = (2 * K0 * s_um) ** 2
    expected = np.sqrt(2 * g / -np.expm1(-g)) / (K0 * L_um)
    for axis in (0, 1):
        assert np.std(out[diffuse, axis]) == pytest.approx(expected, rel=0.06)
    assert np.std(out[diffuse, 0]) > 2 * (2 * np.sqrt(2) * s_um / L_um)
