"""plate.simulate: the one entry point (engines, source polarisation q, what physics it reports)."""
import numpy as np
import pytest

from relief_bsdf.core.index import ConstantIndex
from relief_bsdf.errors import InputError
from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate, in_plane_rows, simulate


def test_source_q_is_linear_between_s_and_p():
    rows = in_plane_rows(550.0, [60.0], [60.0], sides=("R", "T"), phi_s_deg=(180.0,))
    ex = Experiment(Plate(2e-3, ConstantIndex(1.5), FlatFace(), FlatFace()))
    v = {q: simulate(ex.with_instrument(polarization_q=q), rows).values_per_sr for q in (1.0, -1.0, 0.4)}
    np.testing.assert_allclose(v[0.4], 0.7 * v[1.0] + 0.3 * v[-1.0], rtol=1e-12)
    assert v[1.0][0] > 2 * v[-1.0][0]                      # s reflects more than p at 60 deg


def test_simulate_says_which_physics_it_used_and_rejects_unknown_engines():
    rows = in_plane_rows(550.0, [0.0], [0.0], sides=("R",), phi_s_deg=(0.0,))
    ex = Experiment(Plate(2e-3, ConstantIndex(1.5), FlatFace(), FlatFace()), Instrument(blur_deg=0.2))
    sim = simulate(ex, rows)
    assert sim.info["engine"] == "deterministic"
    assert sim.info["physics"]["front"]["face"] == "flat" and sim.info["physics"]["instrument"]["blur_deg"] == 0.2
    mc = simulate(ex, rows, engine="photon", photons=20_000)
    assert mc.info["engine"] == "photon" and mc.sigma_per_sr[0] > 0
    assert mc.values_per_sr[0] == pytest.approx(sim.values_per_sr[0], rel=0.1)
    with pytest.raises(InputError):
        simulate(ex, rows, engine="magic")
