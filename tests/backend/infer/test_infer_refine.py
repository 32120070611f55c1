"""infer.families (slope-density families fitted to an inverted density) and infer.refine (the fit's
Gauss-Newton, covariance and information criterion on a candidate's plate)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from relief_bsdf.infer.families import FAMILIES, NONPARAMETRIC, candidates, fit_family
from relief_bsdf.infer.slopes import SlopeDensity


def _density(marginal_pdf, half: float = 0.6, bins: int = 241) -> SlopeDensity:
    e = np.linspace(-half, half, bins + 1)
    c = 0.5 * (e[1:] + e[:-1])
    m = marginal_pdf(c)
    d = np.outer(m, m)
    return SlopeDensity(e, e.copy(), d / (d.sum() * (e[1] - e[0]) ** 2))


def test_top_hat_half_widths_recovered():
    e = np.linspace(-0.6, 0.6, 242)
    c = 0.5 * (e[1:] + e[:-1])
    mx, my = (np.abs(c) <= 0.2).astype(float), (np.abs(c) <= 0.3).astype(float)
    d = np.outer(mx, my)
    dens = SlopeDensity(e, e.copy(), d / (d.sum() * (e[1] - e[0]) ** 2))
    c = fit_family("top-hat", dens)
    assert c.k == 2
    assert c.parameters["half_width_x"] == pytest.approx(0.2, abs=0.006)   # one bin is 0.005
    assert c.parameters["half_width_y"] == pytest.approx(0.3, abs=0.006)
    assert c.density.density.sum() * c.density.cell_area == pytest.approx(1.0)


def test_gaussian_and_dots_recovered():
    g = fit_family("gaussian", _density(lambda s: np.exp(-0.5 * (s / 0.12) ** 2)))
    assert g.parameters["sigma"] == pytest.approx(0.12, rel=0.02)
    # dots: a flat share 0.4 per axis (a spike in the bin at zero) beside Gaussian flanks of 0.15
    e = np.linspace(-0.6, 0.6, 242)
    c = 0.5 * (e[1:] + e[:-1])
    w = np.diff(e)[0]
    m = 0.6 * np.exp(-0.5 * (c / 0.15) ** 2) / (0.15 * np.sqrt(2 * np.pi))
    m[np.argmin(np.abs(c))] += 0.4 / w
    d = np.outer(m, m)
    dots = fit_family("dots", SlopeDensity(e, e.copy(), d / (d.sum() * w * w)))
    assert dots.parameters["flat_share_per_axis"] == pytest.approx(0.4, abs=0.02)
    assert dots.parameters["sigma"] == pytest.approx(0.15, rel=0.05)
    # the Gaussian family does not fit the dots: its CDF misses the spike
    gd = fit_family("gaussian", SlopeDensity(e, e.copy(), d / (d.sum() * w * w)))
    assert abs(gd.parameters["sigma"] - 0.15) > 0.02


def test_candidates_cover_every_family():
    cs = candidates(_density(lambda s: np.exp(-0.5 * (s / 0.1) ** 2)))
    assert [c.name for c in cs] == [NONPARAMETRIC, *FAMILIES]
    assert cs[0].k > max(c.k for c in cs[1:])


def test_choose_takes_the_complex_candidate_only_past_the_margin():
    from relief_bsdf.criteria import BIC_MARGIN
    from relief_bsdf.infer.refine import choose
    n = 1000
    ln = np.log(n)
    simple = {"name": "a", "k": 2, "chi2": 1000.0}
    # 3 more parameters cost 3 ln n; a chi^2 gain just under / over that plus the margin
    under = {"name": "b", "k": 5, "chi2": 1000.0 - 3 * ln - BIC_MARGIN + 1.0}
    best, steps = choose([simple, under], n)
    assert best == 0 and not steps[0]["taken"]
    over = {"name": "b", "k": 5, "chi2": 1000.0 - 3 * ln - BIC_MARGIN - 1.0}
    best, steps = choose([dict(simple), over], n)
    assert best == 1 and steps[0]["taken"]


def test_polish_recovers_scale_and_index_of_a_known_lobe_with_intervals():
    """A lobe model the test owns (width (n - 1) s w, level 4n/(n+1)^2 per face, both faces): the refinement's
    Gauss-Newton and covariance recover the truth from noisy readings within 3 sigma, and the 68 % intervals
    match the scatter of repeated noise draws (within a factor 1.6: a few draws)."""
    from relief_bsdf.infer.refine import Objective, polish_and_intervals
    u = np.linspace(0.0, 0.2, 300)

    def model(s, n):
        t = (4 * n / (n + 1) ** 2) ** 2
        return 30.0 * t * np.exp(-0.5 * (u / ((n - 1) * s * 0.2)) ** 2)

    def forward_at(n):
        return SimpleNamespace(simulate=lambda s, f: model(s, n))

    truth = (1.1, 1.58)
    sigma = 0.05 * model(*truth) + 0.05
    rng = np.random.default_rng(3)
    got, sds = [], []
    for _ in range(6):
        y = model(*truth) + sigma * rng.standard_normal(u.size)
        meas = SimpleNamespace(bsdf_sr=np.clip(y, 1e-9, None), sigma_sr=sigma, wavelength_nm=np.full(u.size, 633.0),
                               theta_i_deg=np.zeros(u.size), phi_i_deg=np.zeros(u.size), side=np.full(u.size, "T"),
                               phi_s_deg=np.zeros(u.size), theta_s_deg=np.degrees(np.arcsin(u)))
        obj = Objective(forward_at, None, np.arange(u.size), meas, 1.5, True)
        ref = polish_and_intervals(obj, np.array([1.0, 1.5]))
        assert np.all(np.abs(ref.s_n - truth) < 3 * ref.sd), (ref.s_n, ref.sd)
        got.append(ref.s_n)
        sds.append(ref.sd)
    scatter = np.std(got, axis=0, ddof=1)
    ratio = np.mean(sds, axis=0) / scatter
    assert np.all((ratio > 1 / 1.6) & (ratio < 1.6 * 1.6)), ratio   # HAC may widen, never shrink far
