"""The slope inversion (infer.slopes): its map and Jacobian, and its geometry against the forward model.

The forward check is not circular: a relief of known rms slope (surface.synth, Gaussian) is put on
the plate and simulated by the project's one forward model (ray-traced relief, plate loop, detector);
the inversion, written independently from Snell's law at the facet and at the flat back face, must
recover the relief's rms slope from the simulated lobe.
"""
from __future__ import annotations

import numpy as np
import pytest

from relief_bsdf.infer.slopes import exit_cosines, invert_cosines, jacobian, single_pass_transmittance, slope_density


def test_map_is_snell_twice_and_inverts():
    n = 1.5
    # a facet tilted by a about x: Snell at the facet, then at the flat back face, by hand
    a = np.radians(12.0)
    s = np.array([np.tan(a), 0.0])
    t_in = np.arcsin(np.sin(a) / n)                  # refraction angle from the facet normal
    dev_glass = a - t_in                             # the ray in the glass, tilted from -z towards +x
    u_hand = n * np.sin(dev_glass)                   # Snell at z: sin(exit) = n sin(glass angle)
    u, ok = exit_cosines(s, n)
    assert ok and u[0] == pytest.approx(u_hand, rel=1e-12) and u[1] == pytest.approx(0.0, abs=1e-15)
    # small slopes: u = (n - 1) s; Jacobian (n - 1) I
    np.testing.assert_allclose(jacobian(np.zeros(2), n), (n - 1) * np.eye(2), atol=1e-8)
    rng = np.random.default_rng(1)
    S = rng.normal(0.0, 0.3, (500, 2))
    U, ok = exit_cosines(S, n, 3.0, 30.0)
    back, ok2 = invert_cosines(U[ok], n, 3.0, 30.0)
    np.testing.assert_allclose(back[ok2], S[ok][ok2], atol=1e-9)
    assert ok2.mean() > 0.99
    # Jacobian against a finite difference of larger step (consistency of the central difference)
    J = jacobian(S[:5], n)
    h = 1e-4
    for b in range(2):
        e = np.zeros(2)
        e[b] = h
        fd = (exit_cosines(S[:5] + e, n)[0] - exit_cosines(S[:5] - e, n)[0]) / (2 * h)
        np.testing.assert_allclose(J[:, :, b], fd, atol=1e-6)
    # transmittance at normal incidence through a flat facet: (1 - R)^2, R = ((n-1)/(n+1))^2
    R = ((n - 1) / (n + 1)) ** 2
    assert float(single_pass_transmittance(np.zeros(2), n)) == pytest.approx((1 - R) ** 2, rel=1e-12)


@pytest.mark.slow
def test_inversion_recovers_the_rms_slope_of_a_simulated_plate(tmp_path):
    from types import SimpleNamespace

    from relief_bsdf.core.index import ConstantIndex
    from relief_bsdf.fit.optimise import Forward
    from relief_bsdf.plate import Rows, TableGrid, experiment_from_sample
    from relief_bsdf.surface.stats import rms_slope
    from relief_bsdf.surface.synth import random_relief

    n = 1.5
    relief = random_relief(128, 2e-6, rms_height_m=1.0e-6, corr_length_m=10e-6, seed=3)   # rms slope ~ 0.2
    truth = rms_slope(relief)
    sample = SimpleNamespace(path="test", plate=SimpleNamespace(thickness_mm=1.0, index=ConstantIndex(n),
                                                                rough_face="front", absorption_per_mm=None),
                             instrument=SimpleNamespace(detector_half_angle_deg=0.5, polarization="unpolarized"))
    th, ph = np.meshgrid(np.arange(0.0, 41.0, 1.0), np.arange(0.0, 360.0, 5.0), indexing="ij")
    k = th.size
    rows = Rows(wavelength_nm=np.full(k, 633.0), theta_i_deg=np.zeros(k), phi_i_deg=np.zeros(k),
                side=np.full(k, "T"), theta_s_deg=th.ravel(), phi_s_deg=ph.ravel())
    exp = experiment_from_sample(sample, relief, samples=100_000, seed=0)
    sim = Forward(relief, exp, rows, grid=TableGrid()).simulate(1.0, 0.0)
    got = SimpleNamespace(side=rows.side, theta_i_deg=rows.theta_i_deg, phi_i_deg=rows.phi_i_deg,
                          theta_s_deg=rows.theta_s_deg, phi_s_deg=rows.phi_s_deg, bsdf_sr=sim)
    d = slope_density(got, n)
    m = d.moments()
    assert m["rms_slope"] == pytest.approx(truth, rel=0.03), (m, truth)
    assert abs(m["mean_sx"]) < 0.01 and abs(m["mean_sy"]) < 0.01
