"""The source's beam divergence (Instrument.beam_divergence_deg): a spread of the incidence, not of the reading.

Checks: the photon engine draws each photon's incidence with the stated divergence per axis; a flat
plate's specular beams are read, by both engines, as the aperture-blurred cone of the exact law
(a flat face maps an incidence deviation one to one onto the exit); on a rough relief off normal
incidence the deterministic engine's quadrature of incidences agrees with the validation's own
independent photon Monte Carlo (`validation.photon`, the beam drawn per photon), and a blur of
the reading of the same width does not (slow).
"""
import numpy as np
import pytest

from relief_bsdf.core.index import ConstantIndex
from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate, Rows, simulate
from relief_bsdf.plate.detector import response
from relief_bsdf.plate.deterministic import table_incidences
from relief_bsdf.plate.photon import beam_directions
from relief_bsdf.plate.uncertainty import FORWARD_LEVEL_SD

from lobe_deviation import bright_deviation  # tests/backend/plate/lobe_deviation.py


def test_photon_beam_directions_deviate_by_the_stated_gaussian_per_axis():
    k = np.array([-np.sin(np.radians(55.0)), 0.0, -np.cos(np.radians(55.0))])
    d = beam_directions(k, 2.0, 200_000, np.random.default_rng(1))
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    e_in = np.cross(np.array([0.0, 1.0, 0.0]), k)          # in the plane of incidence, normal to k
    e_out = np.array([0.0, 1.0, 0.0])
    for e in (e_in / np.linalg.norm(e_in), e_out):
        a = np.degrees(np.arcsin(d @ e))
        assert abs(a.mean()) < 0.02 and np.std(a) == pytest.approx(2.0, rel=0.01)
    assert np.array_equal(beam_directions(k, 0.0, 3, np.random.default_rng(1)), np.tile(k, (3, 1)))


def test_the_tables_are_asked_for_at_the_incidences_of_the_beam_quadrature():
    ex = Experiment(Plate(2e-3, ConstantIndex(1.5), FlatFace(), FlatFace()),
                    Instrument(detector_half_angle_deg=2.0, beam_divergence_deg=2.0, tilt_deg=1.0))
    rows = Rows(np.full(2, 550.0), np.array([0.0, 40.0]), np.zeros(2), ["R", "T"], np.array([10.0, 40.0]),
                np.array([0.0, 180.0]))
    _, ti = table_incidences(ex, rows)
    _, plain = table_incidences(ex.with_instrument(beam_divergence_deg=0.0), rows)
    assert set(np.round(plain, 6)) <= set(np.round(ti, 6))       # the nominal ones (delta beams) are kept
    assert ti.size >= 2 + 24 and ti.min() >= 0.0
    c = plain[np.argmin(np.abs(plain - 40.0))]                    # 40 deg as the tilted sample sees it
    near = ti[np.abs(ti - c) < 8]
    assert near.min() < c - 2.0 and near.max() > c + 2.0           # the quadrature spreads to both sides


def test_a_ray_traced_relief_holds_the_beam_in_its_outside_table_and_other_faces_use_the_quadrature():
    """plate.deterministic.front_traces_beam: a relief face traced by rays draws each ray's incidence from
    the beam (one outside table per nominal incidence, its request says so); a flat face or a wave
    method's relief is solved at the quadrature's incidences; the collimated tables are other tables."""
    from relief_bsdf.plate import ReliefFace, TableGrid
    from relief_bsdf.plate.deterministic import front_tables, front_traces_beam
    from relief_bsdf.plate.faces import beam_in_table
    from relief_bsdf.surface.synth import random_relief
    relief = random_relief(96, 1e-6, 0.3e-6, 4e-6, seed=2)
    rows = Rows(np.full(2, 550.0), np.array([0.0, 30.0]), np.zeros(2), ["R", "T"], np.array([10.0, 30.0]),
                np.array([0.0, 180.0]))
    ins = Instrument(detector_half_angle_deg=2.0, beam_divergence_deg=1.5)
    grid = TableGrid()
    ray_ex = Experiment(Plate(2e-3, ConstantIndex(1.5), ReliefFace(relief, "ray", 2000, 1), FlatFace()), ins)
    wave_ex = Experiment(Plate(2e-3, ConstantIndex(1.5), ReliefFace(relief, "kirchhoff", 2000, 1), FlatFace()), ins)
    flat_ex = Experiment(Plate(2e-3, ConstantIndex(1.5), FlatFace(), FlatFace()), ins)
    assert front_traces_beam(ray_ex, rows, grid)
    assert not front_traces_beam(wave_ex, rows, grid) and not front_traces_beam(flat_ex, rows, grid)
    assert not front_traces_beam(ray_ex.with_instrument(beam_divergence_deg=0.0), rows, grid)
    wl, ti = table_incidences(ray_ex, rows, True)
    assert np.allclose(ti, [0.0, 30.0])
    assert table_incidences(ray_ex, rows)[1].size > 2
    out, _ = front_tables(ray_ex, grid, wl, ti, True)
    sharp, _ = front_tables(ray_ex, grid, wl, ti, False)
    assert beam_in_table(out) == 1.5 and beam_in_table(sharp) == 0.0
    assert not np.array_equal(out.values_per_sr, sharp.values_per_sr)


def test_both_engines_read_a_flat_plates_specular_beams_through_the_divergence():
    """A flat face maps a deviation of the incidence one to one onto the specular exit, so the reading
    is response(psi; h, sqrt(b^2 + s^2)) P / (Omega cos theta_s) (plate.detector): the exact law for the
    deterministic engine; the photon engine, which draws each photon's incidence, agrees within its noise."""
    h, s = 1.0, 0.7
    ex = Experiment(Plate(2e-3, ConstantIndex(1.5), FlatFace(), FlatFace()),
                    Instrument(detector_half_angle_deg=h, beam_divergence_deg=s))
    offs = np.array([0.0, 0.5, 1.0, 1.5, 2.2])
    ts = 30.0 + offs
    n = ts.size
    rows = Rows(np.full(2 * n, 550.0), np.full(2 * n, 30.0), np.zeros(2 * n), ["R"] * n + ["T"] * n,
                np.concatenate([ts, ts]), np.full(2 * n, 180.0))
    det = simulate(ex, rows).values_per_sr
    shape = (response(np.radians(offs), h, s) / response(0.0, h, s) * np.cos(np.radians(30.0))
             / np.cos(np.radians(ts)))
    for k in (slice(0, n), slice(n, 2 * n)):
        assert det[k][0] > 1.0
        np.testing.assert_allclose(det[k] / det[k][0], shape, rtol=1e-6)
    mc = simulate(ex, rows, engine="photon", photons=200_000, seed=4)
    z = (mc.values_per_sr - det) / (mc.sigma_per_sr + 1e-3 * det.max())
    assert np.all(np.abs(z) < 4.0), z
    sharp = simulate(ex.with_instrument(beam_divergence_deg=0.0), rows).values_per_sr
    assert det[0] < 0.8 * sharp[0]                                 # the divergence is seen


def _lobe_rows(theta_i: float) -> Rows:
    ts = np.arange(25.0, 90.0, 5.0)
    n = ts.size
    return Rows(np.full(2 * n, 550.0), np.full(2 * n, theta_i), np.zeros(2 * n), ["R"] * n + ["T"] * n,
                np.concatenate([ts, ts]), np.full(2 * n, 180.0))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [21])
def test_rough_plate_off_normal_the_traced_beam_and_the_quadrature_agree_with_the_independent_monte_carlo(seed):
    """Gaussian relief (rms 0.4 um, correlation 5 um, 1 um pitch: rms slope ~0.11, the diagnosis benchmark's
    kind), n 1.5, 2 mm, theta_i 55 deg, beam divergence 2.5 deg, 2.5-deg cone.  In the bright part of both
    lobes the deterministic engine's beam divergence stays within a few percent of the validation's photon
    Monte Carlo; the same width as a blur of the reading misses it several times more.  (Set on seed 5's
    concealed relief: T within 1-1.5 %, R 2-4.5 %, the reading blur 5-12 %; this tile is a
    fresh one: rms T 1.7 % against 5.3 %, R 3.9 % (its level, 0.96) against 7.2 %; with the Gauss-Laguerre
    rule of plate.detector.beam_offsets, T 0.8 %, R 3.9 %; the beam traced into the outside
    table (the default for a ray-traced relief, plate.deterministic.front_traces_beam): T 1.4 %, R 3.9 %,
    the quadrature beside it 0.8 % and 3.9 %, the reading blur 5.3 % and 7.2 %.)"""
    from relief_bsdf.plate import ReliefFace
    from relief_bsdf.surface.synth import random_relief
    from relief_bsdf.validation.conceal import HeightFieldFace
    from relief_bsdf.validation.photon import PlatePhysics, detect, run_photons
    relief = random_relief(96, 1e-6, 0.4e-6, 5e-6, kind="gaussian", seed=seed)
    rows = _lobe_rows(55.0)
    phys = PlatePhysics(thickness_mm=2.0, n_glass=1.5, beam_sigma_deg=2.5)
    ex_mc = run_photons(HeightFieldFace(relief.heights_m, relief.dx_m, relief.dy_m), phys, 55.0, 0.0,
                        (1.0, 0.0, 0.0, 0.0), 1_500_000, np.random.default_rng(seed))
    mc, mc_sigma = detect(ex_mc, np.asarray(rows.side), rows.theta_s_deg, rows.phi_s_deg, 2.5)
    plate = Plate(2e-3, ConstantIndex(1.5), ReliefFace(relief, "ray", 400_000, seed), FlatFace())
    ex = Experiment(plate, Instrument(detector_half_angle_deg=2.5, beam_divergence_deg=2.5))
    traced = simulate(ex, rows).values_per_sr
    with pytest.MonkeyPatch.context() as m:
        import relief_bsdf.plate.deterministic as det
        m.setattr(det, "front_traces_beam", lambda experiment, rows, grid: False)
        beam = simulate(ex, rows).values_per_sr
    blur = simulate(Experiment(plate, Instrument(detector_half_angle_deg=2.5, blur_deg=2.5)), rows).values_per_sr
    dev = {sd: bright_deviation((traced, beam, blur), mc, mc_sigma, np.asarray(rows.side), sd, 5) for sd in ("R", "T")}
    print(dev)
    assert dev["T"][0] < 0.03 and dev["T"][1] < 0.03 and dev["T"][2] > 2 * max(dev["T"][:2]), dev
    # R: the forward's stated R level accuracy (2 %) is the larger part here; within 3x it, and closer
    # than the reading blur
    assert max(dev["R"][:2]) < 3 * FORWARD_LEVEL_SD["R"] and dev["R"][2] > max(dev["R"][:2]), dev


def test_an_incidence_of_the_beam_is_solved_in_the_nominal_plane_and_its_specular_lands_where_it_belongs():
    """beam_split: a divergent ray's source direction (theta', phi') around the nominal (30, 0) is solved at
    the in-plane incidence theta'' (azimuth 0, or 180 when it crosses the normal) and its field shifted;
    the shift takes the ray's own specular direction (theta', phi' + 180) onto the solved incidence's
    specular direction (theta'', phi'' + 180), for the reflected and the straight-through transmitted ray."""
    from relief_bsdf.plate.readout import _shifted, beam_split
    th = np.array([33.0, 31.0, 2.0, 4.0])
    ph = np.array([10.0, -7.0, 120.0, 250.0])
    nom_t = np.array([30.0, 30.0, 0.0, 0.0])
    t2, p2, shift = beam_split(th, ph, nom_t, np.zeros(4))
    assert np.allclose(np.sin(np.radians(t2)), np.abs(np.sin(np.radians(th)) * np.cos(np.radians(ph))))
    assert np.allclose(p2, [0.0, 0.0, 180.0, 180.0])
    got_t, got_p, ok = _shifted(th, np.mod(ph + 180.0, 360.0), shift)
    assert ok.all()
    np.testing.assert_allclose(got_t, t2, atol=1e-7)
    d = np.mod(got_p - (p2 + 180.0) + 180.0, 360.0) - 180.0
    assert np.all(np.abs(d[t2 > 1e-6]) < 1e-6)
    # in the nominal plane nothing is shifted; far beyond the horizon the shifted field is evanescent
    t3, p3, s3 = beam_split(np.array([35.0]), np.array([0.0]), np.array([30.0]), np.array([0.0]))
    assert t3[0] == pytest.approx(35.0) and np.allclose(s3, 0.0)
    assert not _shifted(np.array([80.0]), np.array([90.0]), np.array([[0.0], [0.2]]))[2][0]


@pytest.mark.slow
def test_anisotropic_relief_at_normal_incidence_the_divergent_lobe_keeps_the_reliefs_orientation(monkeypatch):
    """Anisotropic Gaussian relief (correlation 10 um along x, 4 um along y: rms slopes ~2.5x apart), n 1.5,
    2 mm, theta_i 0, beam divergence 3 deg, 2.5-deg cone; rows across both principal planes; against the
    validation's photon Monte Carlo through the relief.  Three ways to the divergent beam:

    - traced (the default for a relief traced by rays, plate.deterministic.front_traces_beam): each ray of
      the outside table drawn from the beam, exact for any relief;
    - the quadrature of incidences solved in the nominal plane and shifted (plate.deterministic.beam_split,
      the engine's way for tables of single incidences on an anisotropic relief): first order;
    - the quadrature with each incidence's table turned about the normal (exact only for an isotropic
      relief): the divergent rays come from every azimuth, and the lobe is smeared round.

    R's second pass leaves through the relief's inside tables by azimuth sector (plate.faces.inside_sectors;
    before them R missed this relief's Monte Carlo by 20-30 % with or without a divergence).  Measured
    Rms deviation in the bright part: T traced 1.1 %, shifted 5.0 % (its flank across the
    steep axis 12 % low: the lobe shape of the in-plane incidence, second order), turned 58 %; R 2.8 %,
    3.0 %, 40 % (without the sectors 21.6 %, 21 %, 43 %).  (The measured map of seed-6 case14 missed by
    chi^2 3590 on its 70 rows at normal incidence turned.)"""
    import relief_bsdf.plate.deterministic as det
    from relief_bsdf.plate import ReliefFace
    from relief_bsdf.surface.synth import RandomFieldSpec, relief_from_spec
    from relief_bsdf.validation.conceal import HeightFieldFace
    from relief_bsdf.validation.photon import PlatePhysics, detect, run_photons
    relief = relief_from_spec(RandomFieldSpec(128, 128, 1e-6, 0.5e-6, 4e-6, anisotropy=2.5, angle_deg=0.0), 33)
    ts = np.arange(2.5, 40.0, 2.5)
    n = ts.size
    side = (["R"] * n + ["T"] * n) * 2
    rows = Rows(np.full(4 * n, 550.0), np.zeros(4 * n), np.zeros(4 * n), side, np.tile(ts, 4),
                np.repeat([0.0, 90.0], 2 * n))
    phys = PlatePhysics(thickness_mm=2.0, n_glass=1.5, beam_sigma_deg=3.0)
    ex_mc = run_photons(HeightFieldFace(relief.heights_m, relief.dx_m, relief.dy_m), phys, 0.0, 0.0,
                        (1.0, 0.0, 0.0, 0.0), 1_500_000, np.random.default_rng(33))
    mc, mc_sigma = detect(ex_mc, np.asarray(rows.side), rows.theta_s_deg, rows.phi_s_deg, 2.5)
    plate = Plate(2e-3, ConstantIndex(1.5), ReliefFace(relief, "ray", 400_000, 33), FlatFace())
    ex = Experiment(plate, Instrument(detector_half_angle_deg=2.5, beam_divergence_deg=3.0))
    assert det.relief_anisotropic(ex)
    traced = simulate(ex, rows).values_per_sr
    monkeypatch.setattr(det, "front_traces_beam", lambda experiment, rows, grid: False)
    shifted = simulate(ex, rows).values_per_sr
    monkeypatch.setattr(det, "relief_anisotropic", lambda experiment: False)
    turned = simulate(ex, rows).values_per_sr
    dev = {sd: bright_deviation((traced, shifted, turned), mc, mc_sigma, np.asarray(rows.side), sd, 8)
           for sd in ("R", "T")}
    assert dev["T"][0] < 0.025 and dev["T"][1] < 0.07 and dev["T"][2] > 5 * dev["T"][1], dev
    assert dev["R"][0] < 0.06 and dev["R"][1] < 0.06 and dev["R"][2] > 5 * dev["R"][1], dev
