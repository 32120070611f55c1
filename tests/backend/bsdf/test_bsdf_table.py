"""BsdfTable: integrals, interpolation and HDF5 round trip on analytic tables."""
import numpy as np
import pytest

from relief_bsdf.bsdf.table import BsdfTable, reciprocity_error
from relief_bsdf.core.frames import projected_solid_angle
from relief_bsdf.io.hdf5 import load_tables, save_tables
from relief_bsdf.errors import InputError
from relief_bsdf.methods.request import Request


def lambert_table(albedo_R=0.3, albedo_T=0.6, spec=0.05):
    r = Request(theta_i_deg=(0, 30, 60))
    shape = (1, 3, 1, 2, r.theta_s_deg.size, r.phi_s_deg.size)
    v = np.zeros(shape)
    v[:, :, :, 0] = albedo_R / np.pi
    v[:, :, :, 1] = albedo_T / np.pi
    return BsdfTable(r.wavelengths_nm, r.theta_i_deg, r.phi_i_deg, r.theta_s_edges_deg, r.phi_s_edges_deg,
                     v, specular_R=spec, method="test", material={"inside": {"model": "constant", "n": 1.5}})


def test_projected_solid_angle_of_hemisphere_is_pi():
    r = Request()
    assert projected_solid_angle(r.theta_s_edges_deg, r.phi_s_edges_deg).sum() == pytest.approx(np.pi, rel=1e-12)


def test_lambertian_integrals_are_exact():
    t = lambert_table()
    h = t.hemispherical()
    np.testing.assert_allclose(h["R"], 0.35, rtol=1e-12)
    np.testing.assert_allclose(h["T"], 0.6, rtol=1e-12)
    rows = t.albedo_rows()
    assert len(rows) == 3 and rows[0]["from"] == "outside"
    assert rows[1]["R"] == pytest.approx(0.35)


def test_eval_interpolates_linearly_and_is_periodic():
    r = Request(theta_i_deg=(0, 30, 60))
    ts, ps = r.theta_s_deg, r.phi_s_deg
    shape = (1, 3, 1, 2, ts.size, ps.size)
    # f = theta_s (deg) + 10 theta_i, linear in both -> interpolation exact inside the grid
    v = (ts[None, None, None, None, :, None] + 10 * np.array([0, 30, 60])[None, :, None, None, None, None]
         + 0 * ps) * np.ones(shape)
    t = BsdfTable(r.wavelengths_nm, r.theta_i_deg, r.phi_i_deg, r.theta_s_edges_deg, r.phi_s_edges_deg, v)
    got = t.eval(550, [10.0, 45.0], 0.0, "R", [20.25, 33.7], [359.0, 181.0])
    np.testing.assert_allclose(got, [20.25 + 100, 33.7 + 450], rtol=1e-12)
    # isotropic rotation: phi_i shifts the azimuth
    assert t.eval(550, 30, 90.0, "T", 40.5, 90.0) == pytest.approx(t.eval(550, 30, 0.0, "T", 40.5, 0.0))


def test_hdf5_round_trip(tmp_path):
    t = lambert_table()
    t.metadata = {"seed": 3, "note": "x"}
    p = save_tables(tmp_path / "t.h5", [t])
    (u,) = load_tables(p)
    np.testing.assert_allclose(u.values_per_sr, t.values_per_sr, rtol=1e-7)
    np.testing.assert_array_equal(u.theta_s_edges_deg, t.theta_s_edges_deg)
    assert u.metadata == {"seed": 3, "note": "x"} and u.method == "test"
    np.testing.assert_allclose(u.specular_R, 0.05)


def test_hdf5_bad_files(tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not hdf5 at all")
    with pytest.raises(InputError, match="bad.h5"):
        load_tables(bad)
    with pytest.raises(InputError, match="not found"):
        load_tables(tmp_path / "missing.h5")


def test_reciprocity_of_symmetric_table():
    t = lambert_table()
    assert reciprocity_error(t)["max_rel"] < 1e-12


def test_hdf5_round_trip_with_mueller(tmp_path):
    t = lambert_table()
    m = np.zeros(t.values_per_sr.shape + (4, 4))
    m[..., 0, 0] = t.values_per_sr
    m[..., 1, 1] = 0.5 * t.values_per_sr
    t.mueller_per_sr = m
    t.specular_mueller_R = np.tile(np.eye(4), t.specular_R.shape + (1, 1)) * 0.05
    (u,) = load_tables(save_tables(tmp_path / "m.h5", [t]))
    assert u.is_polarized
    np.testing.assert_allclose(u.mueller_per_sr, m, rtol=1e-6)
    np.testing.assert_allclose(u.specular_mueller_R[0, 0, 0], 0.05 * np.eye(4), rtol=1e-6)
    with pytest.raises(InputError, match="mueller"):
        BsdfTable(t.wavelength_nm, t.theta_i_deg, t.phi_i_deg, t.theta_s_edges_deg, t.phi_s_edges_deg,
                  t.values_per_sr, mueller_per_sr=np.zeros(3))
