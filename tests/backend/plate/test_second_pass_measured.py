"""The second pass through a real measured relief, against the validation's independent photon Monte Carlo.

The plate's R beyond the direct reflection is the second pass (through the relief, reflected by the flat
back face, out through the relief from inside) and the light trapped after it.  On the real instrument
map (ST_x3p-2, levelled, cropped, heights x 3, mirrored into a periodic tile: its slopes 2.2x steeper
along x than along y) that light is narrow across the plane of incidence, so the loop's 5-deg azimuth
cells matter: the first transmission's cell averages widened it by a cell's variance once more at the
exit (7 % low at 30 and 60 deg with the cells' averages); entered as point sources weighted by the centre values
(plate.deterministic `_incidence`, plate.detector.centre_values) it reads ~4 % low.  The direct reflection,
read on the direct grid, is checked alike (an opaque plate: the same relief, a bulk that keeps nothing).
The truth is the Monte Carlo's (validation.record.trace_recording: its own Embree tracing of the relief
and its own transport loop and detector), not the engine's.
"""
import numpy as np
import pytest

from relief_bsdf.core.index import ConstantIndex
from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate, ReliefFace, TableGrid, in_plane_rows, simulate
from relief_bsdf.plate.description import Bulk

N_GLASS, THICKNESS_MM, CONE_DEG, OPAQUE_PER_MM = 1.52, 1.1, 2.0, 30.0


def _recordings(relief, rows):
    """(forward, Monte Carlo) R rows of the clear plate and of the opaque one (exp(-33) through the bulk)."""
    from relief_bsdf.validation.photon import PlatePhysics
    from relief_bsdf.validation.record import trace_recording
    out = {}
    for absorb in (0.0, OPAQUE_PER_MM):
        mc, _, _ = trace_recording(relief, rows, PlatePhysics(thickness_mm=THICKNESS_MM, n_glass=N_GLASS,
                                                               absorption_per_mm=absorb), CONE_DEG, 1_000_000, seed=1)
        ex = Experiment(Plate(THICKNESS_MM * 1e-3, ConstantIndex(N_GLASS),
                              ReliefFace(relief, method="ray", samples=400_000, seed=0), FlatFace(),
                              bulk=Bulk(absorption_per_m=absorb * 1e3)),
                        Instrument(detector_half_angle_deg=CONE_DEG))
        with pytest.warns(RuntimeWarning):          # the engine says the tile is anisotropic / small
            out[absorb] = (simulate(ex, rows, grid=TableGrid()).values_per_sr, mc)
    return out


@pytest.mark.slow
def test_the_measured_maps_second_pass_and_direct_reflection_agree_with_the_independent_monte_carlo():
    from relief_bsdf.validation.conceal import measured_tile
    relief = measured_tile(crop_n=160)
    rows = in_plane_rows(550.0, [30.0, 60.0], list(np.arange(1.0, 89.0, 2.0)))
    rec = _recordings(relief, rows)
    (fwd_all, mc_all), (fwd_direct, mc_direct) = rec[0.0], rec[OPAQUE_PER_MM]
    side, ti = np.asarray(rows.side).astype(str), np.asarray(rows.theta_i_deg, float)
    for t in (30.0, 60.0):
        m = (side == "R") & (ti == t)
        direct = m & (mc_direct >= 0.2 * mc_direct[m].max())
        assert fwd_direct[direct].sum() / mc_direct[direct].sum() == pytest.approx(1.0, abs=0.01)
        fwd2, mc2 = fwd_all - fwd_direct, mc_all - mc_direct          # the second pass and what follows it
        lobe = m & (mc2 >= 0.2 * mc2[m].max())
        assert lobe.sum() >= 5
        assert fwd2[lobe].sum() / mc2[lobe].sum() == pytest.approx(1.0, abs=0.05)
