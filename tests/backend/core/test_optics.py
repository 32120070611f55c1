"""Flat-interface optics against closed forms (Born & Wolf sec. 1.5)."""
import numpy as np
import pytest

from relief_bsdf.errors import InputError
from relief_bsdf.core.fresnel import (critical_angle_deg, fresnel_power, fresnel_unpolarized, mueller_interface, reflect,
                                      refract)
from relief_bsdf.core.index import CauchyIndex, ConstantIndex, Material, SellmeierIndex


def test_normal_incidence_reflectance():
    for n in (1.33, 1.5, 2.4):
        R = fresnel_unpolarized(1.0, 1.0, n)
        assert R == pytest.approx(((n - 1) / (n + 1)) ** 2, rel=1e-12)
        # the same from inside
        assert fresnel_unpolarized(1.0, n, 1.0) == pytest.approx(R, rel=1e-12)


def test_brewster_angle_kills_p():
    n = 1.5
    cb = np.cos(np.arctan(n))
    Rs, Rp, Ts, Tp = fresnel_power(cb, 1.0, n)
    assert Rp == pytest.approx(0.0, abs=1e-14)
    assert Rs > 0.1


def test_total_internal_reflection():
    n = 1.5
    tc = critical_angle_deg(n, 1.0)
    assert tc == pytest.approx(np.degrees(np.arcsin(1 / n)))
    c = np.cos(np.radians(np.array([tc + 0.5, 60.0, 89.0])))
    Rs, Rp, Ts, Tp = fresnel_power(c, n, 1.0)
    np.testing.assert_allclose(Rs, 1.0, atol=1e-12)
    np.testing.assert_allclose(Rp, 1.0, atol=1e-12)
    np.testing.assert_allclose(Ts, 0.0, atol=1e-12)


def test_mueller_energy_conservation_and_stokes_relations():
    c = np.cos(np.radians(np.linspace(0, 89, 30)))
    for n1, n2 in ((1.0, 1.5), (1.5, 1.0)):
        MR = mueller_interface(c, n1, n2, "R")
        MT = mueller_interface(c, n1, n2, "T")
        np.testing.assert_allclose(MR[:, 0, 0] + MT[:, 0, 0], 1.0, atol=1e-12)
        # s and p separately conserve energy too
        Rs = MR[:, 0, 0] + MR[:, 0, 1]
        Ts = MT[:, 0, 0] + MT[:, 0, 1]
        np.testing.assert_allclose(Rs + Ts, 1.0, atol=1e-12)
        # pure (non-depolarising) Jones matrix: M00^2 = M01^2 + M22^2 + M23^2
        for M in (MR, MT):
            np.testing.assert_allclose(M[:, 0, 0] ** 2, M[:, 0, 1] ** 2 + M[:, 2, 2] ** 2 + M[:, 2, 3] ** 2,
                                       atol=1e-12)


def test_metal_reflectance_is_high_and_absorbing():
    # aluminium at 550 nm: n ~ 0.96 + 6.69i, R(normal) = ((n-1)^2 + k^2)/((n+1)^2 + k^2)
    n, k = 0.96, 6.69
    R = fresnel_unpolarized(1.0, 1.0, complex(n, k))
    assert R == pytest.approx(((n - 1) ** 2 + k**2) / ((n + 1) ** 2 + k**2), rel=1e-12)


def test_reflect_refract_snell():
    rng = np.random.default_rng(0)
    w = rng.normal(size=(1000, 3))
    w[:, 2] = np.abs(w[:, 2])
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    nrm = np.broadcast_to([0.0, 0.0, 1.0], w.shape)
    r = reflect(w, nrm)
    np.testing.assert_allclose(r[:, 2], w[:, 2])
    np.testing.assert_allclose(r[:, :2], -w[:, :2])
    eta = 1 / 1.5
    t, ok = refract(w, nrm, eta)
    assert ok.all()
    sin_i = np.linalg.norm(w[:, :2], axis=1)
    sin_t = np.linalg.norm(t[:, :2], axis=1)
    np.testing.assert_allclose(sin_t, eta * sin_i, rtol=1e-12)
    assert np.all(t[:, 2] < 0)
    np.testing.assert_allclose(np.linalg.norm(t, axis=1), 1.0)
    _, ok_in = refract(w, nrm, 1.5)
    np.testing.assert_array_equal(ok_in, 1.5 * sin_i < 1)


def test_index_models_and_range():
    c = CauchyIndex(1.4580, 3540.0)
    assert c.n(589.3) == pytest.approx(1.4580 + 3540 / 589.3**2)
    with pytest.raises(InputError, match="outside the index model"):
        c.check_range([200.0])
    bk7 = SellmeierIndex()
    assert bk7.n(587.56) == pytest.approx(1.5168, abs=2e-4)
    with pytest.raises(InputError):
        ConstantIndex(-1.0)
    m = Material(inside=ConstantIndex(1.5))
    assert m.n_pair(550, "inside") == (1.5, 1.0)
    assert Material.from_dict(m.describe()) == m


def test_check_incidence_refuses_light_from_inside_a_metal():
    from relief_bsdf.errors import RequestError

    metal = Material(inside=ConstantIndex(0.96, 6.69))
    metal.check_incidence([550.0], ("outside",))             # reflection off a metal is fine
    with pytest.raises(RequestError, match="kirchhoff: light cannot arrive from inside an absorbing"):
        metal.check_incidence([550.0], ("outside", "inside"), "kirchhoff")
    Material(inside=ConstantIndex(1.5)).check_incidence([450.0, 650.0], ("outside", "inside"))
