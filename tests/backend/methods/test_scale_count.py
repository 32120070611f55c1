"""auto's two-scale criterion: a second scale only where the relief's spectrum holds one (methods.scale_count).

Oracles: reliefs whose spectrum is known by construction (surface.synth: FFT-filtered white noise of a
stated autocovariance).  An anisotropic Gaussian relief with rms slopes 0.30 / 0.11 across / along its lay is
ONE scale with two lengths; the sum of two independent Gaussian reliefs of lengths 40 and 7 um is two."""
import math

import numpy as np

from relief_bsdf.methods.scale_count import scale_test
from relief_bsdf.surface.stats import slope_tensor
from relief_bsdf.surface.synth import RandomFieldSpec, random_relief, relief_from_spec


def _aniso(angle_deg: float, seed: int):
    # rms slope ~ s sqrt(2) / L per axis: L_u / L_v = 0.30 / 0.11 gives the issue's slopes' ratio
    return relief_from_spec(RandomFieldSpec(192, 192, 1.2e-6, 1.6e-6, 7.5e-6, anisotropy=0.30 / 0.11,
                                            angle_deg=angle_deg), seed=seed)


def test_an_anisotropic_gaussian_relief_is_one_scale():
    for angle, seed in ((0.0, 3), (30.0, 4)):
        rel = _aniso(angle, seed)
        ev = np.linalg.eigvalsh(slope_tensor(rel))
        assert math.sqrt(ev[1] / ev[0]) > 2.3                     # the relief is as anisotropic as stated
        t = scale_test(rel)
        assert not t.two_scales, t.statement()


def test_two_gaussian_scales_are_two_and_one_is_one():
    big = random_relief(192, 1.5e-6, 3e-6, 40e-6, seed=11)
    fine = random_relief(192, 1.5e-6, 0.6e-6, 7e-6, seed=12)
    t = scale_test(big.with_heights(big.heights_m + fine.heights_m, "two scales"))
    assert t.two_scales, t.statement()
    assert 25e-6 < t.large_length_m < 60e-6 and 4e-6 < t.fine_length_m < 10e-6
    one = scale_test(big)
    assert not one.two_scales and one.qbic_gain < t.qbic_gain / 10, one.statement()
    expo = scale_test(random_relief(192, 2.7e-6, 1.0e-6, 30e-6, kind="exponential", seed=2))
    assert not expo.two_scales, expo.statement()


def test_auto_does_not_choose_two_scale_for_an_anisotropic_relief_and_says_why():
    import warnings

    from relief_bsdf.core.index import ConstantIndex, Material
    from relief_bsdf.methods import auto
    from relief_bsdf.methods.request import Request
    # pitch 0.8 um: the band split separates two lengths (l_L / l_F > 5, l_F resolved), so only the
    # spectrum test stands between this one-scale relief and two_scale
    rel = relief_from_spec(RandomFieldSpec(192, 192, 0.8e-6, 1.6e-6, 7.5e-6, anisotropy=0.30 / 0.11), seed=3)
    req = Request(theta_i_deg=(0.0, 30.0, 60.0), incident_from=("outside", "inside"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        c = auto.choose(rel, Material(inside=ConstantIndex(1.5)), req)
    assert auto._split_separates({**c.figures, "pitch_m": 0.8e-6})
    assert c.figures["ts_spectrum_qbic_gain"] < 10 and c.figures["ts_spectrum_two_scales"] == 0.0
    assert c.method != "two_scale", c.summary
    assert "second scale in the spectrum" in c.valid["two_scale"][1]
