"""The diagnosis's wave-optics rough face (photon_plate.KirchhoffFace): coherent fraction, the
geometric-optics limit, partial-coherence width, energy bookkeeping, reproducibility."""
import numpy as np
import pytest

from relief_bsdf.core.optics import fresnel_power
from relief_bsdf.validation.photon import KirchhoffFace, direction

WL_NM = 550.0
K0 = 2 * np.pi / (WL_NM * 1e-9)


def _beam(theta_deg, n, inside=False):
    d = -direction(theta_deg, 0.0)
    if inside:
        d[2] = -d[2]
    return (np.tile(d, (n, 1)), np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), np.tile([0.0, 1.0, 0.0], (n, 1)),
            np.full(n, inside))


def _specular(theta_deg, n1, n2):
    """x component of the specular propagation direction (the beam travels towards -x)."""
    return -n1 * np.sin(np.radians(theta_deg)) / n2


@pytest.mark.parametrize("theta, inside", [(0.0, False), (50.0, False), (70.0, False), (20.0, True)])
def test_coherent_fraction_is_the_debye_waller_value_per_side(theta, inside):
    # near normal incidence transmission keeps more coherence than reflection (phase (n - 1) vs 2);
    # at grazing incidence (70 deg) reflection becomes the more coherent one (cos theta_i -> 0)
    sigma = 0.1e-6
    face = KirchhoffFace(sigma, 2.0e-6, WL_NM)
    n = 200_000
    d, S, e, ins = _beam(theta, n, inside)
    out, _, _, ins_new, alive = face.interact(d, S, e, ins, 1.5, np.random.default_rng(1))
    n1, n2 = (1.5, 1.0) if inside else (1.0, 1.5)
    c1 = np.cos(np.radians(theta))
    c2 = np.sqrt(1 - (n1 / n2 * np.sin(np.radians(theta))) ** 2)
    refl = ins_new == inside
    for side, g in ((refl, (2 * K0 * n1 * sigma * c1) ** 2), (~refl, (K0 * sigma * (n1 * c1 - n2 * c2)) ** 2)):
        sx = _specular(theta, n1, n1 if side is refl else n2)
        spec = side & (np.abs(out[:, 0] - sx) < 1e-12) & (np.abs(out[:, 1]) < 1e-12)
        frac = spec.sum() / side.sum()
        assert frac == pytest.approx(np.exp(-g), abs=4 * np.sqrt(np.exp(-g) * (1 - np.exp(-g)) / side.sum()) + 1e-3)
    # the Fresnel split of the mean plane is kept (unpolarised light)
    Rs, Rp, _, _ = fresnel_power(c1, n1, n2)
    assert refl.mean() == pytest.approx(0.5 * (Rs + Rp), abs=4 * np.sqrt(0.25 / n))
    assert alive.all()


def test_rough_limit_is_the_geometric_slope_lobe():
    # g >> 1: the transverse wave-vector change in reflection at normal incidence is 2 k0 times the
    # slope, per axis variance 2 sigma^2 / T^2 for a Gaussian correlation: angle spread 2 m_axis
    sigma, T = 1.0e-6, 20e-6
    face = KirchhoffFace(sigma, T, WL_NM)
    d, S, e, ins = _beam(0.0, 100_000)
    out, _, _, ins_new, alive = face.interact(d, S, e, ins, 1.5, np.random.default_rng(2))
    r = ~ins_new & alive
    m_axis = np.sqrt(2) * sigma / T
    assert np.std(out[r, 0]) == pytest.approx(2 * m_axis, rel=0.03)
    assert np.std(out[r, 1]) == pytest.approx(2 * m_axis, rel=0.03)


def test_smooth_relief_diffuse_part_is_wider_than_the_ray_lobe():
    # g << 1: the incoherent part is mostly the one-"order" term: q variance 2 E[m | m >= 1] / T^2 per
    # axis, E[m | m >= 1] = g / (1 - exp(-g)); far wider than the geometric lobe 2 sqrt(2) sigma / T
    sigma, T = 0.02e-6, 2e-6
    face = KirchhoffFace(sigma, T, WL_NM)
    d, S, e, ins = _beam(0.0, 400_000)
    out, _, _, ins_new, alive = face.interact(d, S, e, ins, 1.5, np.random.default_rng(3))
    diffuse = ~ins_new & (np.abs(out[:, 0]) + np.abs(out[:, 1]) > 0)
    g = (2 * K0 * sigma) ** 2
    assert np.std(out[diffuse, 0]) == pytest.approx(np.sqrt(2 * g / -np.expm1(-g)) / T / K0, rel=0.02)
    assert np.std(out[diffuse, 0]) > 2 * (2 * np.sqrt(2) * sigma / T)      # 1 / sqrt(g) = 2.2 times


def test_partial_coherence_blurs_the_first_event_by_lambda_over_2pi_lc():
    lc = 2e-6
    face = KirchhoffFace(0.0, 1e-6, WL_NM, coherence_length_m=lc)        # flat: only the source's blur
    d, S, e, ins = _beam(0.0, 100_000)
    out, _, _, ins_new, alive = face.interact(d, S, e, ins, 1.5, np.random.default_rng(4))
    t = ins_new                                                           # transmitted into the glass
    assert np.std(out[t, 0]) * 1.5 == pytest.approx(WL_NM * 1e-9 / (2 * np.pi * lc), rel=0.03)
    # light arriving from inside is not blurred again
    d, S, e, ins = _beam(10.0, 20_000, inside=True)
    out, *_ = face.interact(d, S, e, ins, 1.5, np.random.default_rng(5))
    assert np.all(np.abs(out[:, 1]) < 1e-12)


def test_every_photon_leaves_on_its_side_and_runs_are_seeded():
    face = KirchhoffFace(0.3e-6, 1.0e-6, WL_NM)
    d, S, e, ins = _beam(70.0, 50_000)
    a = face.interact(d.copy(), S.copy(), e.copy(), ins.copy(), 1.5, np.random.default_rng(6))
    b = face.interact(d.copy(), S.copy(), e.copy(), ins.copy(), 1.5, np.random.default_rng(6))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    out, Sn, en, ins_new, alive = a
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-12)
    assert np.all(np.where(ins_new, out[:, 2] < 0, out[:, 2] > 0)[alive])
    assert np.abs(np.einsum("ij,ij->i", en, out)).max() < 1e-12
    assert 0.9 < alive.mean() <= 1.0
