"""The one detector (plate.detector): response = cone (x) Gaussian, read the same by both engines."""
import numpy as np
import pytest

from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate, Rows, TableFace, in_plane_rows, simulate
from relief_bsdf.plate.detector import cone_solid_angle, quadrature_offsets, response


def test_response_is_the_fraction_of_a_gaussian_inside_the_cone():
    h, b = 1.0, 0.5
    rng = np.random.default_rng(0)
    g = np.radians(b) * rng.standard_normal((400_000, 2))
    for psi in (0.0, 0.6, 1.0, 1.5, 2.5):
        mc = np.mean(np.hypot(np.radians(psi) + g[:, 0], g[:, 1]) <= np.radians(h))
        assert response(np.radians(psi), h, b) == pytest.approx(mc, abs=3e-3)
    assert response(np.radians([0.9, 1.1]), h, 0.0).tolist() == [1.0, 0.0]
    # its plane integral is the cone's area (the normalisation both engines use, Omega)
    r = np.linspace(0, np.radians(h + 6 * b), 4001)
    area = np.trapz(response(r, h, b) * 2 * np.pi * r, r)
    assert area == pytest.approx(cone_solid_angle(h), rel=1e-3)


def test_quadrature_of_cone_and_gaussian_reproduces_the_blurred_average():
    # the average of a smooth field over the product quadrature = its integral against response / Omega
    off = quadrature_offsets(1.0, 19, 0.8)
    f = lambda x, y: 1.0 + 300.0 * x + 4e4 * x * x + 2e4 * y * y      # noqa: E731 (smooth test field, rad)
    quad = np.mean(f(off[:, 0], off[:, 1]))
    s = np.radians(0.8)
    h = np.radians(1.0)
    exact = 1.0 + 4e4 * (h * h / 4 + s * s) + 2e4 * (h * h / 4 + s * s)   # second moments of cone + Gaussian
    assert quad == pytest.approx(exact, rel=0.01)


def _rows_around_the_specular(offsets_deg, ti=30.0):
    ts = ti + np.asarray(offsets_deg, float)
    n = ts.size
    return Rows(np.full(n, 550.0), np.full(n, ti), np.zeros(n), ["R"] * n, ts, np.full(n, 180.0))


def test_both_engines_read_a_delta_beam_through_a_blurred_cone():
    ex = Experiment(Plate(2e-3, ConstantIndex(1.5), FlatFace(), FlatFace()),
                    Instrument(detector_half_angle_deg=1.0, blur_deg=0.4))
    offs = np.array([0.0, 0.5, 0.9, 1.2, 1.6])
    rows = _rows_around_the_specular(offs)
    det = simulate(ex, rows).values_per_sr
    mc = simulate(ex, rows, engine="photon", photons=100_000, seed=3)
    assert det[0] > 1.0                                  # the specular beam, not the diffuse floor (0 here)
    # f = response(psi) P / (Omega cos theta_s): the shape over the rows is response x cos ratio
    expect_shape = (response(np.radians(offs), 1.0, 0.4) / response(0.0, 1.0, 0.4)
                    * np.cos(np.radians(30.0)) / np.cos(np.radians(rows.theta_s_deg)))
    np.testing.assert_allclose(det / det[0], expect_shape, rtol=1e-6)
    np.testing.assert_allclose(mc.values_per_sr, det, rtol=0.0, atol=4 * mc.sigma_per_sr.max() + 1e-9)


def test_both_engines_read_a_smooth_lambertian_field_through_a_blurred_cone(lambert_table):
    o = lambert_table("outside", 0.2, 0.8, [0, 30])
    i = lambert_table("inside", 0.5, 0.5, np.arange(0, 90, 5.0))
    ex = Experiment(Plate(2e-3, ConstantIndex(1.5), TableFace(i, o), FlatFace()),
                    Instrument(detector_half_angle_deg=2.0, blur_deg=1.5))
    rows = in_plane_rows(550.0, [30.0], np.arange(5.0, 80.0, 10.0))
    det = simulate(ex, rows).values_per_sr
    sharp = simulate(ex.with_instrument(blur_deg=0.0), rows).values_per_sr
    np.testing.assert_allclose(det, sharp, rtol=0.01)               # a smooth field is not changed by blur
    mc = simulate(ex, rows, engine="photon", photons=200_000, seed=5)
    z = (mc.values_per_sr - det) / mc.sigma_per_sr
    assert np.sqrt(np.mean(z**2)) < 1.6, z


def test_the_sub_points_share_each_cell_and_lie_in_it():
    """The sub-points' quantities, made for the indices asked: their solid angles add up to each cell's,
    every unit vector lies in its own cell, and the cell and sub-ring of an index agree."""
    from relief_bsdf.plate.detector import _sub_points
    theta_edges = np.concatenate([np.arange(0.0, 20.0, 0.5), np.arange(20.0, 90.1, 2.0)])
    delta_edges = -37.5 + np.concatenate([np.arange(0.0, 30.0, 1.0), np.arange(30.0, 360.1, 5.0)])
    pts = _sub_points(theta_edges, delta_edges, 3)
    idx = np.arange(pts.size)
    ring, az = pts.ring(idx), pts.az(idx)
    S, P = theta_edges.size - 1, delta_edges.size - 1
    cell_sr = np.bincount(ring * P + az, weights=pts.weight_sr(idx), minlength=S * P).reshape(S, P)
    ct = np.cos(np.radians(theta_edges))
    np.testing.assert_allclose(cell_sr, (ct[:-1] - ct[1:])[:, None] * np.radians(np.diff(delta_edges))[None, :],
                               rtol=1e-12)
    v = pts.vec(idx)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, rtol=1e-12)
    th = np.degrees(np.arccos(v[:, 2]))
    assert np.all((th > theta_edges[ring]) & (th < theta_edges[ring + 1]))
    ph = delta_edges[0] + np.mod(np.degrees(np.arctan2(v[:, 1], v[:, 0])) - delta_edges[0], 360.0)
    assert np.all((ph > delta_edges[az] - 1e-9) & (ph < delta_edges[az + 1] + 1e-9))
    assert np.array_equal(pts.cos_theta(idx), pts.cos_sub[pts.sub_ring(idx)])
    assert np.array_equal(pts.ring_of_sub[pts.sub_ring(idx)], ring)


@pytest.mark.parametrize("delta0_deg", [0.0, -180.0, -37.5])
def test_the_cone_members_ring_by_ring_are_a_ball_query_of_the_sub_points(delta0_deg):
    """`_cone_members` (sub-ring by sub-ring, spherical law of cosines) finds exactly the sub-points a
    KD-tree's ball query of their unit vectors finds, in the same order: rows at the pole, at grazing
    angles, across the azimuth turn's end, and caps wider than whole rings."""
    from scipy.spatial import cKDTree
    from relief_bsdf.plate.detector import _cone_members, _sub_points, unit
    theta_edges = np.concatenate([np.arange(0.0, 20.0, 0.5), np.arange(20.0, 90.1, 2.0)])
    delta_edges = delta0_deg + np.concatenate([np.arange(0.0, 30.0, 1.0), np.arange(30.0, 360.1, 5.0)])
    pts = _sub_points(theta_edges, delta_edges, 3)
    tree = cKDTree(pts.vec(np.arange(pts.size)))
    rng = np.random.default_rng(4)
    ts = np.concatenate([[0.0, 0.3, 89.5, 45.0, 10.0], rng.uniform(0, 90, 30)])
    ds = np.concatenate([[0.0, 123.0, delta0_deg + 359.7, delta0_deg + 0.2, delta0_deg - 1.0],
                         rng.uniform(-360, 720, 30)])
    for reach_deg in (0.7, 2.5, 12.0):
        reach = np.radians(reach_deg)
        row, col = _cone_members(pts, np.radians(ts), np.radians(ds), reach)
        hits = tree.query_ball_point(unit(ts, ds), 2 * np.sin(reach / 2), return_sorted=True)
        assert all(np.array_equal(col[row == i], np.asarray(h, int)) for i, h in enumerate(hits)), reach_deg
        assert np.all(np.diff(row) >= 0) and row.size == sum(len(h) for h in hits) > 0
