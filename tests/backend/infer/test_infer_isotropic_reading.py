"""The isotropic reading of an in-plane scan (infer.slopes.isotropic_reading).

The lobes here are the test's own: the single-pass image of a known slope density, made by pushing
slope draws through `exit_cosines` and histogramming them in direction cosines (the BTDF is power per
unit area of the direction-cosine plane), so the inversion is checked against densities the test knows,
not against itself.  An isotropic density's cut inverts to its rms slope; an anisotropic one's cut is
read with the slopes along the plane of scatter on both axes (the assumption's stated failure).
"""
from __future__ import annotations

import numpy as np
import pytest

from relief_bsdf.errors import InputError
from relief_bsdf.infer.slopes import LobeRows, exit_cosines, isotropic_reading, slope_density

N = 1.5


def _lobe_rows(sigma_x: float, sigma_y: float, phis_deg, seed: int = 3) -> LobeRows:
    """T rows at normal incidence, theta_s 0..30 deg every 1 deg at the azimuths phis_deg: the lobe of
    Gaussian slopes (sigma_x, sigma_y), its single-pass image binned in direction cosines (no Fresnel:
    the inversion's weight varies by < 1 % over these slopes, the same on both readings compared)."""
    rng = np.random.default_rng(seed)
    s = np.stack([rng.normal(0, sigma_x, 600_000), rng.normal(0, sigma_y, 600_000)], axis=-1)
    u, ok = exit_cosines(s, N)
    u = u[ok]
    edges = np.linspace(-0.6, 0.6, 241)
    H, _, _ = np.histogram2d(u[:, 0], u[:, 1], bins=[edges, edges])
    H = H / (len(s) * np.diff(edges)[0] ** 2)
    c = 0.5 * (edges[1:] + edges[:-1])
    from scipy.interpolate import RegularGridInterpolator
    from scipy.ndimage import gaussian_filter
    f = RegularGridInterpolator((c, c), gaussian_filter(H, 1.0), bounds_error=False, fill_value=0.0)
    th, ph = np.meshgrid(np.arange(0.0, 31.0), np.asarray(phis_deg, float), indexing="ij")
    th, ph = th.reshape(-1), ph.reshape(-1)
    uu = np.stack([np.sin(np.radians(th)) * np.cos(np.radians(ph)), np.sin(np.radians(th)) * np.sin(np.radians(ph))], -1)
    n = th.size
    return LobeRows(np.full(n, "T"), np.zeros(n), np.zeros(n), th, ph, f(uu))


def test_an_isotropic_lobe_is_recovered_from_its_cut():
    sigma = 0.15
    full = _lobe_rows(sigma, sigma, np.arange(0.0, 360.0, 5.0))
    cut = _lobe_rows(sigma, sigma, [0.0, 180.0])
    lobe, facts = isotropic_reading(cut)
    assert facts["plane_phi_s_deg"] == 0.0 and facts["readings_per_half"] == [30, 30]
    assert facts["half_asymmetry_over_peak"] < 0.05
    m_full = slope_density(full, N).moments()
    m_cut = slope_density(lobe, N).moments()
    for k in ("rms_slope_x", "rms_slope_y"):
        assert m_cut[k] == pytest.approx(m_full[k], rel=0.02), (m_cut, m_full)
        assert m_cut[k] == pytest.approx(sigma, rel=0.03), m_cut      # the bins and the 0.5-bin blur


def test_an_anisotropic_lobe_is_read_along_the_plane_of_scatter():
    """The cut along x of slopes (0.1, 0.25) reads 0.1 on both axes: the y slopes are invisible to it."""
    lobe, _ = isotropic_reading(_lobe_rows(0.10, 0.25, [0.0, 180.0]))
    m = slope_density(lobe, N).moments()
    assert m["rms_slope_x"] == pytest.approx(0.10, rel=0.04) and m["rms_slope_y"] == pytest.approx(0.10, rel=0.04), m


def test_the_cut_is_at_normal_incidence_in_one_plane():
    th = np.repeat(np.arange(0.0, 31.0), 2)
    cut = LobeRows(np.full(th.size, "T"), np.zeros(th.size), np.zeros(th.size), th, np.tile([0.0, 180.0], 31),
                   np.exp(-0.5 * (th / 5.0) ** 2))
    with pytest.raises(InputError, match="normal"):
        isotropic_reading(LobeRows(cut.side, cut.theta_i_deg + 5.0, cut.phi_i_deg, cut.theta_s_deg, cut.phi_s_deg,
                                   cut.bsdf_sr))
    with pytest.raises(InputError, match="one plane"):
        isotropic_reading(LobeRows(cut.side, cut.theta_i_deg, cut.phi_i_deg, cut.theta_s_deg,
                                   np.tile([0.0, 90.0], 31), cut.bsdf_sr))
