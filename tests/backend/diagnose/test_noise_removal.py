"""Relief smoothing as removal of the map's own measurement noise (diagnose.noise_removal), beside the
paper's Gaussian filter, one effect whose form the information criterion chooses.

Oracles: a synthetic relief of known slopes plus white noise of a known share (the file's rms slope / the
truth's = 1.5, the independent engine's definition of relief smoothing), and a stand-in forward model whose
rows are a closed-form function of the relief's rms slope."""
import numpy as np
import pytest

from relief_bsdf.diagnose.effects import get_effect
from relief_bsdf.diagnose.effects._base import NOISE_FORM, ReliefContext, apply_all
from relief_bsdf.diagnose.fitting import fit_effect
from relief_bsdf.diagnose.noise_removal import remove_noise
from relief_bsdf.fit.residual import chi2
from relief_bsdf.surface.operations import scale_and_filter
from relief_bsdf.surface.stats import noise_floor, rms_height_and_slope
from relief_bsdf.surface.synth import DotPattern, lgp_dots, random_relief

from diagnosis_rows import in_plane_rows  # noqa: E402


def _noisy(rel, ratio=1.5, seed=0):
    m_true = rms_height_and_slope(rel)[1]
    e = np.random.default_rng(seed).standard_normal(rel.heights_m.shape)
    m_e = rms_height_and_slope(rel.with_heights(e, "unit noise"))[1]
    k = np.sqrt(ratio**2 - 1.0) * m_true / m_e          # slopes add in quadrature: file / truth = ratio
    return rel.with_heights(rel.heights_m + k * e, "truth + white noise")


@pytest.mark.parametrize("kind", ["gaussian", "dots"])
def test_the_wiener_filter_at_the_maps_floor_restores_the_true_relief(kind):
    truth = (random_relief(192, 1.9e-6, 1.7e-6, 19e-6, seed=1) if kind == "gaussian"
             else lgp_dots(192, 1.1e-6, DotPattern(40e-6, 13e-6, 5e-6), seed=5))
    f = _noisy(truth)
    d = remove_noise(f)
    m_true, m_file, m_d = (rms_height_and_slope(r)[1] for r in (truth, f, d))
    assert m_file == pytest.approx(1.5 * m_true, rel=0.01)
    assert abs(m_d / m_true - 1.0) < 0.12                  # the noise's slope removed (file: 50 % over)
    err_file = np.std(f.heights_m - truth.heights_m)
    assert np.std(d.heights_m - truth.heights_m) < 0.55 * err_file
    assert d.periodic == f.periodic and d.shape == f.shape
    # a noise-free relief: the floor estimate is the relief's own outer spectrum (an upper estimate, far below
    # the noisy map's), and what the filter takes there is a small part of the heights and of the slopes
    clean = remove_noise(truth)
    assert np.std(clean.heights_m - truth.heights_m) < 0.01 * np.std(truth.heights_m)
    assert rms_height_and_slope(clean)[1] == pytest.approx(m_true, rel=0.05)
    assert noise_floor(f).psd_m4 > 30 * noise_floor(truth).psd_m4


class SlopeForward:
    """Rows that follow the front relief's distribution of facet slopes (geometric optics: the lobe follows
    the density of facet normals): the share of facets whose slope angle falls in each 2-deg bin, per row
    at theta_s; the relief the effects make by `apply_all` on a stand-in experiment; the recording is
    made from `truth_relief`."""

    def __init__(self, measured, truth_relief, seed=2):
        self.rows = in_plane_rows((0.0, 30.0), step_deg=2.0)
        self.context = ReliefContext(relief=measured, method="stand-in", face=lambda r, m, **o: r,
                                     scale_and_filter=scale_and_filter, wavelengths_nm=(550.0,),
                                     detector_half_angle_deg=1.0)
        clean = self._rows(truth_relief)
        sigma = 0.02 * clean + 1e-4
        self.rows.sigma_sr = sigma
        self.rows.bsdf_sr = clean + sigma * np.random.default_rng(seed).standard_normal(clean.size)
        self.evaluations = 0

    def _rows(self, rel):
        h = rel.heights_m
        gx = (np.roll(h, -1, 1) - h) / rel.dx_m
        gy = (np.roll(h, -1, 0) - h) / rel.dy_m
        ang = np.degrees(np.arctan(np.hypot(gx, gy))).ravel()
        th = np.asarray(self.rows.theta_s_deg, float)
        return np.array([np.mean(np.abs(ang - t) < 1.0) for t in th]) + 1e-3

    def evaluate_set(self, effects, values):
        self.evaluations += 1

        class Exp:
            def __init__(self, r):
                self.front = r

            def with_plate(self, front):
                return Exp(front)
        exp = apply_all(Exp(self.context.relief), self.context, effects, values)
        v = self._rows(exp.front)
        return chi2(self.rows, v, 0 * v), v, 0 * v


def test_the_form_with_the_lower_chi2_is_kept():
    truth = random_relief(128, 1.9e-6, 1.7e-6, 19e-6, seed=1)
    eff = get_effect("relief_smoothing")
    # the map is the truth plus white noise: the noise form wins by more than the margin
    noisy = SlopeForward(_noisy(truth), truth)
    fit = fit_effect(noisy, eff)
    assert fit["parameters"][NOISE_FORM] == 1.0 and len(fit["forms"]) == 2
    chi = {f[NOISE_FORM]: f["chi2"] for f in fit["forms"]}
    assert chi[1.0] < chi[0.0] - 10
    # the map is the truth, the real surface its Gaussian blur: the Gaussian form wins at about its width
    blurred = SlopeForward(truth, truth.gaussian_filtered(1.5e-6))
    fit_g = fit_effect(blurred, eff)
    assert fit_g["parameters"][NOISE_FORM] == 0.0
    assert fit_g["parameters"]["filter_sigma_um"] == pytest.approx(1.5, rel=0.15)
