"""The azimuth probe (plate.faces.azimuth_dependent): a relief isotropic in its rms slopes whose arrangement
still makes it scatter trapped light by azimuth (light-guide dots) gets the inside sector tables."""
import warnings

import numpy as np
import pytest

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.methods.request import Request
from relief_bsdf.plate import ReliefFace, TableGrid
from relief_bsdf.plate.faces import anisotropic_face, azimuth_dependent, azimuth_probe_l1, inside_sectors
from relief_bsdf.surface.synth import DotPattern, lgp_dots, random_relief


def _probe_table(first: np.ndarray, second: np.ndarray, sigma: float = 0.0) -> BsdfTable:
    r = Request(theta_i_deg=(85.0,))
    v = np.stack([first, second])[None, None, :, None]                    # (1, 1, 2, 1, S, P): R side only
    v = np.concatenate([v, np.zeros_like(v)], axis=3)
    return BsdfTable(r.wavelengths_nm, r.theta_i_deg, [0.0, 45.0], r.theta_s_edges_deg, r.phi_s_edges_deg, v,
                     incident_from="inside", sigma_per_sr=np.full_like(v, sigma))


def test_the_statistic_is_zero_for_a_turned_copy_and_the_l1_difference_otherwise():
    r = Request(theta_i_deg=(85.0,))
    S, P = r.theta_s_deg.size, r.phi_s_deg.size
    rng = np.random.default_rng(4)
    f0 = rng.uniform(0.5, 1.5, (S, P))
    turned = np.roll(f0, 9, axis=1)                     # an isotropic relief: the 45-deg table is the 0-deg one turned
    assert azimuth_probe_l1(_probe_table(f0, turned)) == pytest.approx(0.0, abs=1e-12)
    # a relief that sends 30 % more into every bin at one azimuth: L1 = 0.3 / 1.15
    assert azimuth_probe_l1(_probe_table(f0, 1.3 * turned)) == pytest.approx(0.3 / 1.15, rel=1e-9)
    # differences the cells' sigma explains are not counted
    assert azimuth_probe_l1(_probe_table(f0, 1.3 * turned, sigma=1.0)) < 0.3 / 1.15 - 0.05


def test_light_guide_dots_are_probed_azimuth_dependent_and_a_gaussian_relief_is_not():
    mat, grid = Material(ConstantIndex(1.49)), TableGrid()
    um = 1e-6
    dots = lgp_dots(256, 1 * um, DotPattern(24 * um, 8 * um, 2.0 * um, micro_rms_m=0.3 * um, micro_corr_m=5 * um),
                    seed=5)
    gauss = random_relief(256, 1 * um, 1.2 * um, 10 * um, "gaussian", seed=5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        d_face, g_face = ReliefFace(dots, "ray", 40_000, 5), ReliefFace(gauss, "ray", 40_000, 5)
        assert not anisotropic_face(d_face) and not anisotropic_face(g_face)      # isotropic rms slopes, both
        assert azimuth_dependent(d_face, mat, grid, [550.0])
        assert not azimuth_dependent(g_face, mat, grid, [550.0])
        t = inside_sectors(d_face, mat, grid, [550.0], [0.0])
    assert t is not None and t.incident_from == "inside"
