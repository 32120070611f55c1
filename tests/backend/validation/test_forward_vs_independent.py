"""The forward model (plate.simulate over ray-traced boundary tables) against an INDEPENDENT photon
Monte Carlo through the same real relief.

The recording is made by `validation.record.trace_recording`: the validation's own photon engine
with the relief triangulated and ray traced by `conceal.HeightFieldFace` (Embree), its own
transport loop and detector; nothing of plate/ or methods/.  The forward model is the
deterministic engine with `ReliefFace(method="ray")` on the same relief.  z = (forward -
recording) / sigma, sigma = the recording's Monte-Carlo sigma (one-photon floor).

First the generator itself is checked (a wrong truth would blame the forward model): two seeds
must agree to their own noise (rms z ~ 1, so its sigma is right and nothing drifts with the
seed), and doubling the inter-reflection depth must change nothing.  Then the forward model is
held to the issue's target, rms z <= 1.2 over all rows, R and T.  The full table (cases, grids,
photons, cost) is benchmarks/bench_forward_accuracy.py.
"""
import numpy as np
import pytest

from relief_bsdf.validation.photon import PlatePhysics
from relief_bsdf.validation.record import Goniophotometer, instrument_noise, trace_recording

PHYS = PlatePhysics(thickness_mm=2.0, n_glass=1.5)
HALF_ANGLE = 2.0


def _rows(theta_i, theta_s):
    from relief_bsdf.plate import in_plane_rows
    return in_plane_rows(550.0, list(theta_i), list(theta_s))


def _relief(n=64, corr_um=6.0, slope=0.24, seed=5):
    from relief_bsdf.surface.synth import random_relief
    return random_relief(n, 1e-6, slope * corr_um * 1e-6 / 2, corr_um * 1e-6, "gaussian", seed=seed)


def _rms_z(a, b, sigma):
    return float(np.sqrt(np.mean(((np.asarray(a) - b) / sigma) ** 2)))


def test_generator_agrees_with_itself_to_its_own_noise():
    """Two seeds of the independent generator: differences are noise (rms z ~ 1), with its stated sigma."""
    relief = _relief()
    rows = _rows((0.0, 45.0), np.arange(1.0, 89.0, 4.0))
    a, sa, info = trace_recording(relief, rows, PHYS, HALF_ANGLE, 60_000, seed=1)
    b, sb, _ = trace_recording(relief, rows, PHYS, HALF_ANGLE, 60_000, seed=2)
    lobe = a > 0.05 * a.max()
    z_lobe = _rms_z(a[lobe], b[lobe], np.hypot(sa, sb)[lobe])
    assert 0.6 < z_lobe < 1.4, z_lobe
    assert _rms_z(a, b, np.hypot(sa, sb)) < 1.4
    assert max(info["lost_fraction"].values()) < 1e-3         # photons are not silently dropped


def test_generator_is_converged_in_interreflection_depth():
    """max_hits 20 (default) vs 60 on a steep relief (rms slope 0.6): same recording within the noise."""
    relief = _relief(slope=0.6)
    rows = _rows((30.0,), np.arange(1.0, 89.0, 4.0))
    a, sa, _ = trace_recording(relief, rows, PHYS, HALF_ANGLE, 60_000, seed=3, max_hits=20)
    b, sb, _ = trace_recording(relief, rows, PHYS, HALF_ANGLE, 60_000, seed=4, max_hits=60)
    assert _rms_z(a, b, np.hypot(sa, sb)) < 1.4


def test_instrument_noise_has_the_stated_sigma():
    clean = np.linspace(0.1, 20.0, 4000)
    noisy, sigma = instrument_noise(clean, np.zeros_like(clean), Goniophotometer(1500.0, 0.015, 1e-3),
                                    np.random.default_rng(0))
    z = (noisy - clean) / sigma
    assert abs(np.std(z) - 1.0) < 0.05 and abs(np.mean(z)) < 0.06
    rel = sigma / clean
    assert 0.015 < rel[-1] < 0.03                                 # 1-3 % in the lobe


def _forward(relief, rows, grid, samples):
    from relief_bsdf.core.index import ConstantIndex
    from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate, ReliefFace, simulate
    ex = Experiment(Plate(PHYS.thickness_mm * 1e-3, ConstantIndex(PHYS.n_glass),
                          ReliefFace(relief, method="ray", samples=samples, seed=0), FlatFace()),
                    Instrument(detector_half_angle_deg=HALF_ANGLE))
    return simulate(ex, rows, grid=grid).values_per_sr


@pytest.fixture(scope="module")
def recorded():
    relief = _relief(n=128, corr_um=8.0, slope=0.24, seed=7)
    rows = _rows((0.0, 45.0), np.arange(1.0, 89.0, 2.0))
    val, sig, _ = trace_recording(relief, rows, PHYS, HALF_ANGLE, 1_000_000, seed=1)
    return relief, rows, val, sig


@pytest.mark.slow
def test_forward_on_the_default_grid_reaches_the_independent_recording(recorded):
    """The default TableGrid: the direct reflection and the first transmitted pass read from the
    outside tables' own cells (0.5-1 deg rings with the exit side's Snell pre-images, 1-deg azimuth
    cells around the plane of incidence; on this 128^2 tile the rings are 1 deg: a tile fills at most
    one cell per facet), integrated over the cone; the loop on the 1 x 5 deg engine grid with inside
    incidences every 2.5 deg.  Measured 1.17 (forward seed 0; 1.16-1.20 over forward seeds before the
    in-cell reconstruction: the margin is the forward's own Monte-Carlo noise); the single-grid engine
    (TableGrid(1, 5, 5, direct_theta_step_deg=None)) missed by 2.3."""
    from relief_bsdf.plate import TableGrid
    relief, rows, val, sig = recorded
    assert _rms_z(_forward(relief, rows, TableGrid(), 400_000), val, sig) <= 1.2


@pytest.mark.slow
def test_finer_azimuth_cells_converge_on_the_independent_transmitted_lobe(recorded):
    """Where the single-grid engine missed: the in-plane cut of the oblique transmitted lobe (theta_i 45,
    T, phi_s 180).  Its in-plane integral sum f sin(theta_s) must approach the independent recording as
    the engine grid's azimuth cells shrink (5 -> 2.5 deg, no direct grid), the error falling at least 2x,
    to under 3 %; the default grid (direct grid) is within 1 %."""
    from relief_bsdf.plate import TableGrid
    relief, rows, val, sig = recorded
    m = (rows.side == "T") & (rows.theta_i_deg == 45.0) & (rows.phi_s_deg == 180.0)
    w = np.sin(np.radians(rows.theta_s_deg[m]))

    def err(grid):
        v = _forward(relief, rows, grid, 400_000)
        return abs(float((v[m] * w).sum() / (val[m] * w).sum()) - 1.0)
    single = [err(TableGrid(theta_step_deg=1.0, phi_step_deg=p, direct_theta_step_deg=None)) for p in (5.0, 2.5)]
    assert single[1] < 0.5 * single[0] and single[1] < 0.03, single
    assert err(TableGrid()) < 0.01


@pytest.mark.slow
def test_forward_reaches_the_independent_recording_on_light_guide_dots():
    """Light-guide dots (spherical caps 8 um in radius, 2 um high, on a 24-um hexagonal lattice, with
    micro-roughness; the case of benchmarks/bench_forward_accuracy.py, relief seed 11), n 1.49, 2 mm,
    2-deg cone, theta_i 0 / 30 / 60, 1 M photons per incidence: the lattice scatters the light trapped
    in the glass by its azimuth, which the plate's loop meets through inside tables by azimuth sector,
    each the average over its sector (plate.faces.inside_sectors; docs/decisions/004)."""
    from relief_bsdf.core.index import ConstantIndex
    from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate, ReliefFace, TableGrid, simulate
    from relief_bsdf.surface.synth import DotPattern, lgp_dots
    um = 1e-6
    relief = lgp_dots(256, 1 * um, DotPattern(24 * um, 8 * um, 2.0 * um, micro_rms_m=0.3 * um, micro_corr_m=5 * um),
                      seed=11)
    phys = PlatePhysics(thickness_mm=2.0, n_glass=1.49)
    rows = _rows((0.0, 30.0, 60.0), np.arange(1.0, 89.0, 2.0))
    val, sig, _ = trace_recording(relief, rows, phys, HALF_ANGLE, 1_000_000, seed=1)
    ex = Experiment(Plate(2e-3, ConstantIndex(1.49), ReliefFace(relief, method="ray", samples=400_000, seed=0),
                          FlatFace()), Instrument(detector_half_angle_deg=HALF_ANGLE))
    assert _rms_z(simulate(ex, rows, grid=TableGrid()).values_per_sr, val, sig) <= 1.2


@pytest.mark.slow
def test_forward_reaches_the_independent_recording_on_a_steep_gaussian_tile():
    """The top of the issue's slope range: a Gaussian relief of rms slope 0.35 (10-um correlation, a 256^2
    tile of 1-um pixels: ~650 correlation areas; the case gauss_high of benchmarks/bench_forward_accuracy.py
    at relief seed 11), n 1.6, 3 mm, 2.5-deg cone, theta_i 0 / 30 / 60, 1 M photons per incidence, with the
    loop's one inside table averaged over the incidence azimuths within +-45 deg
    (TableGrid.inside_azimuth_spread_deg=45, the default).  The 45 was chosen on relief seed 12
    (docs/decisions/003); this seed chose nothing.
    What the test holds is the spread table's accuracy on a tile it was not chosen on, against the
    independent photon Monte Carlo."""
    from relief_bsdf.core.index import ConstantIndex
    from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate, ReliefFace, TableGrid, simulate
    from relief_bsdf.surface.synth import random_relief
    relief = random_relief(256, 1e-6, 0.35 * 10e-6 / 2, 10e-6, "gaussian", seed=11)
    phys = PlatePhysics(thickness_mm=3.0, n_glass=1.6)
    rows = _rows((0.0, 30.0, 60.0), np.arange(1.0, 89.0, 2.0))
    val, sig, _ = trace_recording(relief, rows, phys, 2.5, 1_000_000, seed=1)
    ex = Experiment(Plate(3e-3, ConstantIndex(1.6), ReliefFace(relief, method="ray", samples=400_000, seed=0),
                          FlatFace()), Instrument(detector_half_angle_deg=2.5))
    assert _rms_z(simulate(ex, rows, grid=TableGrid(inside_azimuth_spread_deg=45.0)).values_per_sr, val, sig) <= 1.2
