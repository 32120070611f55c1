"""The float32 Fresnel kernels beside the reference versions give the same numbers (core/fresnel.py)."""
import numpy as np
import pytest

from relief_bsdf.core.fresnel import (cos_transmitted, fresnel_power, fresnel_reflectance, fresnel_unpolarized,
                                      interface_coefficients_f32, mueller_interface, reflectance_unpolarized_f32)

F32 = np.float32
COS = np.linspace(0.0, 1.0, 401)[1:]          # grazing excluded: 0/0 there by definition


def _coefficients(M):
    """(a, b, c, d) of the interface form [[a,b,0,0],[b,a,0,0],[0,0,c,d],[0,0,-d,c]]."""
    return M[..., 0, 0], M[..., 0, 1], M[..., 2, 2], M[..., 2, 3]


@pytest.mark.parametrize("n1, n2", [(1.0, 1.5), (1.5, 1.0), (1.0, 2.4), (1.33, 1.0)])
def test_interface_coefficients_f32_equal_reference_mueller(n1, n2):
    (aR, bR, cR, dR), (aT, bT, cT, dT) = interface_coefficients_f32(COS.astype(F32), F32(n1), F32(n2))
    assert aR.dtype == np.float32 and cT.dtype == np.float32
    ref_R = _coefficients(mueller_interface(COS, n1, n2, "R"))
    ref_T = _coefficients(np.nan_to_num(mueller_interface(COS, n1, n2, "T")))
    for fast, ref in zip((aR, bR, cR, dR), ref_R):
        np.testing.assert_allclose(fast, ref, atol=2e-6)
    for fast, ref in zip((aT, bT, cT, dT), ref_T):
        np.testing.assert_allclose(fast, ref, atol=2e-6)
    if n1 > n2:                                 # past the critical angle all power is reflected, with a phase
        tir = COS < np.sqrt(1 - (n2 / n1) ** 2) - 1e-3
        assert tir.any()
        np.testing.assert_allclose(aR[tir], 1.0)
        np.testing.assert_allclose(aT[tir], 0.0)
        np.testing.assert_allclose(cR[tir] ** 2 + dR[tir] ** 2, 1.0, atol=1e-5)
        assert np.abs(dR[tir]).max() > 0.1


def test_interface_coefficients_complex_index_uses_reference():
    n2 = 0.2 + 3.0j                              # a metal
    (aR, bR, cR, dR), (aT, bT, cT, dT) = interface_coefficients_f32(COS.astype(F32), 1.0, n2)
    for fast, ref in zip((aR, bR, cR, dR), _coefficients(mueller_interface(COS, 1.0, n2, "R"))):
        np.testing.assert_allclose(fast, ref, atol=2e-6)
    np.testing.assert_allclose(aT, 1.0 - aR, atol=1e-6)          # power entering (absorbed in) the metal
    assert not cT.any() and not dT.any()


@pytest.mark.parametrize("n1, n2", [(1.0, 1.5), (1.5, 1.0), (1.0, 1.8)])
def test_reflectance_unpolarized_f32_equals_reference(n1, n2):
    ct = np.real(cos_transmitted(COS, n1, n2))
    below = np.imag(cos_transmitted(COS, n1, n2)) == 0            # the kernel's domain: below TIR
    fast = reflectance_unpolarized_f32(COS.astype(F32)[below], F32(n1), F32(n2), ct.astype(F32)[below])
    assert fast.dtype == np.float32
    np.testing.assert_allclose(fast, fresnel_unpolarized(COS[below], n1, n2), atol=1e-6)


@pytest.mark.parametrize("n1, n2", [(1.0, 1.5), (1.5, 1.0), (1.0, 0.2 + 3j)])
def test_fresnel_reflectance_equals_fresnel_power(n1, n2):
    Rs, Rp, _, _ = fresnel_power(COS, n1, n2)
    np.testing.assert_allclose(fresnel_reflectance(COS, n1, n2, "s"), Rs, atol=1e-12)
    np.testing.assert_allclose(fresnel_reflectance(COS, n1, n2, "p"), Rp, atol=1e-12)
    np.testing.assert_allclose(fresnel_reflectance(COS, n1, n2), 0.5 * (Rs + Rp), atol=1e-12)
