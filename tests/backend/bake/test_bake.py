"""relief_bsdf.bake: lookup rows for renderer closures (no bpy)."""
from __future__ import annotations

import numpy as np
import pytest

from relief_bsdf.bake import ClosureAlbedo, bake_lut, unit_albedo
from relief_bsdf.errors import InputError
from relief_bsdf.core.fresnel import critical_angle_deg, fresnel_unpolarized
from relief_bsdf.core.index import CauchyIndex, ConstantIndex, Material
from relief_bsdf.methods.flat import flat_tables

TH = np.arange(0.0, 90.0, 5.0)


def _flat(material, wavelengths=(550.0,)):
    return list(flat_tables(material, list(wavelengths), TH, TH, np.linspace(0, 90, 10), np.arange(-15.0, 360, 30)))


def test_flat_boundary_rows_are_fresnel_both_sides():
    mat = Material(ConstantIndex(1.5))
    lut = bake_lut(_flat(mat), "flat")
    cols = lut.theta_deg
    F_out = np.interp(cols, TH, fresnel_unpolarized(np.cos(np.radians(TH)), 1.0, 1.5))
    # rows are float32 (the image format): agreement to float32 precision
    np.testing.assert_allclose(lut.lookup("outside", "specular_R", cols)[:, 1], F_out, rtol=1e-6)
    np.testing.assert_allclose(lut.lookup("outside", "specular_T", cols)[:, 1], 1 - F_out, rtol=1e-6)
    # light from inside: total internal reflection past the critical angle (41.8 deg)
    tc = critical_angle_deg(1.5, 1.0)
    past = TH[TH > tc + 1]
    np.testing.assert_allclose(lut.lookup("inside", "specular_R", past)[:, 1], 1.0, atol=1e-12)
    np.testing.assert_allclose(lut.lookup("inside", "specular_T", past)[:, 1], 0.0, atol=1e-12)
    # nothing diffuse, roughness 0
    assert np.all(lut.rows[lut.row_index("outside", "diffuse_R")][:, :3] == 0)
    assert np.all(lut.rows[lut.row_index("inside", "roughness")][:, :2] == 0)
    assert lut.ior == pytest.approx(1.5)


def test_missing_inside_table_uses_smooth_interface():
    mat = Material(ConstantIndex(1.5))
    full = bake_lut(_flat(mat), "a")
    only_out = bake_lut(_flat(mat)[:1], "b")
    assert isinstance(only_out.info["inside"], str) and "smooth" in only_out.info["inside"]
    for row in ("specular_R", "specular_T"):
        np.testing.assert_allclose(only_out.lookup("inside", row, TH)[:, 1], full.lookup("inside", row, TH)[:, 1],
                                   atol=1e-9)


def test_spectral_tables_fill_rgb_at_their_wavelengths():
    mat = Material(CauchyIndex(1.45, 8000.0))          # dispersive: n(465) > n(550) > n(610)
    lut = bake_lut(_flat(mat, (450.0, 550.0, 650.0)), "disp")
    rgb = lut.lookup("outside", "specular_R", 0.0)[:3]
    n = [mat.inside.n(w) for w in (450.0, 550.0, 650.0)]
    R = [((x - 1) / (x + 1)) ** 2 for x in n]
    # channels: 610 nm (R), 550 (G), 465 (B), linear between the tabulated wavelengths
    assert rgb[0] == pytest.approx(R[1] + (R[2] - R[1]) * 0.6, rel=1e-6)
    assert rgb[1] == pytest.approx(R[1], rel=1e-6)
    assert rgb[2] == pytest.approx(R[0] + (R[1] - R[0]) * 0.15, rel=1e-6)
    assert rgb[2] > rgb[1] > rgb[0]
    assert lut.ior == pytest.approx(float(mat.inside.n(550.0)))
    assert lut.ior_rgb[2] > lut.ior_rgb[1] > lut.ior_rgb[0]


def test_weights_divide_by_the_closure_albedo():
    mat = Material(ConstantIndex(1.5))
    tabs = _flat(mat)
    half = ClosureAlbedo(theta_deg=np.array([0.0, 90.0]), roughness=np.array([0.0, 1.0]), ior=np.array([1.0, 3.0]),
                         glossy=np.full((2, 2), 0.5), refraction_front=np.full((2, 2, 2), 0.25),
                         refraction_back=np.full((2, 2, 2), 0.25), source="test")
    a = bake_lut(tabs, "ideal", reflection_closure="glossy")
    b = bake_lut(tabs, "half", albedo=half, reflection_closure="glossy")
    k = a.row_index("outside", "specular_R")
    np.testing.assert_allclose(b.rows[k, :, :3], 2 * a.rows[k, :, :3], rtol=1e-6)
    k = a.row_index("outside", "specular_T")
    np.testing.assert_allclose(b.rows[k, :, :3], 4 * a.rows[k, :, :3], rtol=1e-6)


def test_rough_table_energy_and_roughness():
    from relief_bsdf.methods import reconstruct
    from relief_bsdf.methods.request import Request
    mat = Material(ConstantIndex(1.5))
    req = Request(theta_i_deg=(0.0, 30.0, 60.0), incident_from=("outside",), theta_s_edges_deg=tuple(np.linspace(0, 90, 91)),
                  phi_s_edges_deg=tuple(np.arange(-2.5, 360, 5)), options={"alpha": 0.2, "distribution": "ggx"})
    (t,) = reconstruct(None, mat, req, "microfacet")
    lut = bake_lut([t], "rough", reflection_closure="glossy")
    h = t.hemispherical()
    # ideal closures: the weights are the table's directional integrals at its incidences
    np.testing.assert_allclose(lut.lookup("outside", "diffuse_R", t.theta_i_deg)[:, 1], h["diffuse_R"][0, :, 0], rtol=1e-6)
    np.testing.assert_allclose(lut.lookup("outside", "diffuse_T", t.theta_i_deg)[:, 1], h["diffuse_T"][0, :, 0], rtol=1e-6)
    # the fitted GGX lobe recovers the table's roughness: Cycles roughness = sqrt(alpha)
    r = lut.lookup("outside", "roughness", t.theta_i_deg)
    np.testing.assert_allclose(r[:, 0], np.sqrt(0.2), rtol=0.02)
    np.testing.assert_allclose(r[:, 1], np.sqrt(0.2), rtol=0.02)


def test_texel_centred_coordinates():
    lut = bake_lut(_flat(Material(ConstantIndex(1.5))), "c", n_columns=91)
    c = lut.theta_deg.size
    assert lut.texture_u(0.0) == pytest.approx(0.5 / c) and lut.texture_u(90.0) == pytest.approx(1 - 0.5 / c)
    # column k's centre is at theta_k
    k = np.arange(c)
    np.testing.assert_allclose(lut.texture_u(lut.theta_deg) * c - 0.5, k, atol=1e-9)
    assert lut.texture_v(0) == pytest.approx(0.5 / lut.n_rows)
    assert lut.image_pixels().dtype == np.float32 and lut.image_pixels().size == lut.n_rows * c * 4


def test_bad_input():
    mat = Material(ConstantIndex(1.5))
    with pytest.raises(InputError, match="outside"):
        bake_lut(_flat(mat)[1:], "x")
    with pytest.raises(InputError, match="reflection_closure"):
        bake_lut(_flat(mat), "x", reflection_closure="phong")
    assert np.all(unit_albedo("glossy", np.zeros(3), np.zeros(3), 1.5) == 1)
