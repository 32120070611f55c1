"""Every order of the plate's loop meets an anisotropic relief by azimuth sector (PlateSolver inside_sectors,
`_sector_loop`, `_sector_exits`).

The inside table traced at incidence azimuth p scatters the light arriving at the relief from inside at
propagation azimuths nearest p (mod 180); the loop X = S + K D X is then no longer circulant and is
solved by GMRES with the circulant system as preconditioner.  Checked against a closed form (Lambertian
sector tables of different albedos: the trapped light stays uniform in azimuth, so each round trip sees
the azimuth-weighted albedo) and for energy on a ray-traced anisotropic relief.
"""
import warnings

import numpy as np
import pytest

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.fresnel import fresnel_power
from relief_bsdf.core.index import ConstantIndex
from relief_bsdf.methods.request import Request
from plate_setups import plate_setup  # tests/backend/plate/plate_setups.py
from relief_bsdf.plate.solver import PlateSolver

N_GLASS = 1.5
SECTORS = (30.0, 60.0, 90.0, 120.0, 150.0)


def _lambert(frm, aR, aT, th, phi_i=(0.0,)):
    """Constant (Lambertian) cells, albedos aR / aT (one per incidence azimuth phi_i)."""
    r = Request(theta_i_deg=tuple(th))
    aR, aT = np.broadcast_to(aR, (len(phi_i),)), np.broadcast_to(aT, (len(phi_i),))
    v = np.zeros((1, len(th), len(phi_i), 2, r.theta_s_deg.size, r.phi_s_deg.size))
    v[:, :, :, 0] = aR[None, None, :, None, None] / np.pi
    v[:, :, :, 1] = aT[None, None, :, None, None] / np.pi
    return BsdfTable(r.wavelengths_nm, r.theta_i_deg, np.asarray(phi_i, float), r.theta_s_edges_deg,
                     r.phi_s_edges_deg, v, incident_from=frm)


def _sector_weights(A: int) -> np.ndarray:
    """Fraction of the engine's A azimuth cells (centres every 360/A deg) whose nearest traced azimuth (mod 180)
    is each of 0, 30, ..., 150 deg; a cell half-way between two goes to the first (the engine's rule)."""
    delta = np.arange(A) * 360.0 / A
    ps = np.array((0.0,) + SECTORS)
    d = np.abs(np.mod(delta[:, None] - ps[None, :] + 90.0, 180.0) - 90.0)
    return np.bincount(np.argmin(d, axis=1), minlength=ps.size) / A


def _closed_form(m, aR_o: float, aT_o: float, R_k: np.ndarray) -> tuple[float, float, float]:
    """(R, T, r_bar) of Lambertian sectors (albedos R_k, T_k = 1 - R_k, each meeting its share of the engine's
    azimuth cells) under a Lambertian outside face (aR_o, aT_o), the flat face's hemispherical Fresnel r_bar."""
    mu = np.linspace(0, 1, 200001)[1:]
    Rs, Rp, _, _ = fresnel_power(mu, N_GLASS, 1.0)
    r_bar = np.trapz(0.5 * (Rs + Rp) * 2 * mu, mu)
    w = _sector_weights(m.azimuth_cells)
    R_eff, T_eff = float(w @ R_k), float(w @ (1 - R_k))
    return (aR_o + aT_o * r_bar * T_eff / (1 - r_bar * R_eff), aT_o * (1 - r_bar) / (1 - r_bar * R_eff), r_bar)


AR_O, AT_O = 0.1, 0.9                                   # the outside face's Lambertian albedos
TH_IN = np.arange(0, 90, 5.0)                           # the inside tables' incidences
R_K = np.array([0.2, 0.35, 0.5, 0.8, 0.65, 0.45])      # the sectors' R albedos at 0, 30, ..., 150 deg


def _matches_closed_form(inside: BsdfTable, sectors: BsdfTable) -> tuple:
    """Solve the plate of the Lambertian outside face, `inside` and `sectors` at theta_i 0 and 30 and check R and
    T against `_closed_form` of the sectors' albedos R_K; (model, outside table, r_bar, T) for more checks."""
    o = _lambert("outside", AR_O, AT_O, [0.0, 30.0])
    m = plate_setup(thickness_m=2e-3, index=ConstantIndex(N_GLASS))
    want_R, want_T, r_bar = _closed_form(m, AR_O, AT_O, R_K)
    for ti in (0.0, 30.0):
        h = PlateSolver(m, inside, o, inside_sectors=sectors).solve(550.0, [ti])[0].hemispherical()
        assert h["R"] == pytest.approx(want_R, rel=2e-3)
        assert h["T"] == pytest.approx(want_T, rel=2e-3)
    return m, o, r_bar, want_T


def test_lambertian_sectors_of_different_albedo_follow_the_azimuth_weighted_closed_form():
    """Outside table Lambertian (R_o, T_o); inside tables Lambertian with albedos R_k, T_k (R_k + T_k = 1) that
    depend on the incidence azimuth.  Light leaving a Lambertian face into the glass is uniform in azimuth, so
    after the flat face (hemispherical Fresnel average r_bar) a fraction w_k of it meets sector k:
    R_eff = sum w_k R_k, T_eff = sum w_k T_k, and the geometric series of round trips gives
    R = R_o + T_o r_bar T_eff / (1 - r_bar R_eff), T = T_o (1 - r_bar) / (1 - r_bar R_eff)."""
    i = _lambert("inside", R_K[0], 1 - R_K[0], TH_IN)
    sec = _lambert("inside", R_K[1:], 1 - R_K[1:], TH_IN, phi_i=SECTORS)
    m, o, r_bar, want_T = _matches_closed_form(i, sec)
    # the 0-deg table alone (the circulant loop) is another plate: the sectors are what make the difference
    h0 = PlateSolver(m, i, o).solve(550.0, [0.0])[0].hemispherical()
    g0 = r_bar * R_K[0]
    assert h0["T"] == pytest.approx(AT_O * (1 - r_bar) / (1 - g0), rel=2e-3)
    assert abs(h0["T"] - want_T) > 20 * 2e-3 * want_T


def test_a_sector_at_0_deg_takes_the_inside_tables_place_in_the_loop():
    """The sector tables of `plate.faces.inside_sectors` include the sector at 0 deg (each table the average
    over its sector's incidence azimuths): its cells then scatter by it, and the 0-deg inside table serves
    no light of the loop.  The closed form of the Lambertian sectors with the sector-0 albedo, whatever
    the inside table's (here 0.95 instead of 0.2)."""
    inside = _lambert("inside", 0.95, 0.05, TH_IN)
    m, o, _, want_T = _matches_closed_form(inside, _lambert("inside", R_K, 1 - R_K, TH_IN, phi_i=(0.0,) + SECTORS))
    # the check can tell: had the 0.95 inside table served the loop, T would be far from the sectors' closed form
    alone = PlateSolver(m, inside, o).solve(550.0, [0.0])[0].hemispherical()
    assert abs(alone["T"] - want_T) > 20 * 2e-3 * want_T


def test_sector_tables_equal_to_the_turned_0_deg_table_give_the_circulant_plate():
    """An isotropic relief's table at incidence azimuth p is its 0-deg table turned by p: with such sector
    tables the sector loop must give the circulant loop's plate (the frames of the two agree)."""
    th_in = np.arange(0, 90, 5.0)
    r = Request(theta_i_deg=tuple(th_in))
    rng = np.random.default_rng(3)
    T, P = r.theta_s_deg.size, r.phi_s_deg.size
    base = rng.uniform(0.5, 1.5, (1, th_in.size, 1, 2, T, P)) * np.cos(np.radians(r.phi_s_deg))[None] ** 2 * 0.05
    step = 360.0 / P
    turned = np.concatenate([np.roll(base, int(round(p / step)), axis=5) for p in SECTORS], axis=2)
    args = (r.wavelengths_nm, r.theta_i_deg)
    edges = (r.theta_s_edges_deg, r.phi_s_edges_deg)
    i = BsdfTable(*args, [0.0], *edges, base, incident_from="inside")
    sec = BsdfTable(*args, np.asarray(SECTORS), *edges, turned, incident_from="inside")
    o = _lambert("outside", 0.1, 0.9, [0.0, 40.0])
    m = plate_setup(thickness_m=2e-3, index=ConstantIndex(N_GLASS))
    a = PlateSolver(m, i, o, inside_sectors=sec).solve(550.0, [0.0, 40.0])
    b = PlateSolver(m, i, o).solve(550.0, [0.0, 40.0])
    for x, y in zip(a, b):
        np.testing.assert_allclose(x.grid_R, y.grid_R, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(x.grid_T, y.grid_T, rtol=1e-9, atol=1e-12)


@pytest.mark.slow   # physics-long: ray-traced sector tables on the default grid
def test_the_sector_loop_keeps_a_lossless_plate_lossless_on_a_ray_traced_anisotropic_relief(monkeypatch):
    """Each sector table conserves the energy of its rays, so sending light through one or another moves it
    between R and T but loses or makes none: R + T with the sectors equals R + T with the 0-deg table alone
    (both carry the same discretisation defect of the tables), while R itself changes."""
    from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate, ReliefFace, Rows, TableGrid
    from relief_bsdf.plate.deterministic import solver_of
    from relief_bsdf.plate.memory import ForwardMemory
    from relief_bsdf.surface.synth import RandomFieldSpec, relief_from_spec
    import relief_bsdf.plate.deterministic as faces   # where the front door calls it
    relief = relief_from_spec(RandomFieldSpec(128, 128, 1e-6, 0.5e-6, 4e-6, anisotropy=2.5, angle_deg=0.0), 33)
    ex = Experiment(Plate(2e-3, ConstantIndex(1.5), ReliefFace(relief, "ray", 4000, 34), FlatFace()),
                    Instrument(detector_half_angle_deg=2.5))
    rows = Rows([550.0] * 2, [0.0, 60.0], [0.0] * 2, ["R", "T"], [10.0, 10.0], [0.0, 0.0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        s = solver_of(ex, rows, TableGrid())
        assert s.inside_sectors is not None
        with_sec = [r.hemispherical() for r in s.solve(550.0, [0.0, 60.0])]
        monkeypatch.setattr(faces, "inside_sectors", lambda *a, **k: None)
        with ForwardMemory(4e9).active():      # an owner of its own: the held solver answers the same request
            plain = [r.hemispherical() for r in solver_of(ex, rows, TableGrid()).solve(550.0, [0.0, 60.0])]
    for a, b in zip(with_sec, plain):
        assert a["R"] + a["T"] == pytest.approx(b["R"] + b["T"], abs=2e-5)
        assert a["R"] + a["T"] == pytest.approx(1.0, abs=0.01)
    assert abs(with_sec[1]["R"] - plain[1]["R"]) > 1e-4
