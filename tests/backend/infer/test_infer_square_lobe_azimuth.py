"""A square lobe does not turn with the azimuth a normal-incidence beam is named by.

At normal incidence the incidence azimuth only names the plane the source's polarisation is referred
to: the plate's transmitted lobe, in the sample's own frame, cannot depend on it.  A relief whose lobe
is a square (random crossed lenslets with uniform slopes, what `relief infer` makes of an engineered
top-hat) has equal rms slopes along x and y, so no anisotropy test flags it; read from its phi_i = 0
outside table turned by phi_i, its lobe at (0 deg, phi_i 45) came out turned by 45 deg: half-maximum
edges along the axes at 0.134 instead of 0.097 (n 1.5, slopes <= 0.2 per axis, 256^2 tile, 100k rays).
The plate reads such rows from the relief traced from their own azimuth
(`plate.deterministic.turned_tables`).
"""
from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.slow
def test_a_square_lobe_at_normal_incidence_does_not_turn_with_the_azimuth_label():
    from relief_bsdf.core.index import ConstantIndex
    from relief_bsdf.infer.lobe import lobe_figures
    from relief_bsdf.infer.slopes import SlopeDensity
    from relief_bsdf.infer.synth import lenslet_relief, plan_for
    from relief_bsdf.io.recording import Recording
    from relief_bsdf.plate import Bulk, Experiment, FlatFace, Instrument, Plate, ReliefFace, TableGrid, simulate
    from relief_bsdf.plate.faces import slope_anisotropy

    e = np.linspace(-0.3, 0.3, 61)
    c = 0.5 * (e[1:] + e[:-1])
    m = (np.abs(c) <= 0.2).astype(float)
    d = np.outer(m, m)
    relief, _ = lenslet_relief(SlopeDensity(e, e.copy(), d / (d.sum() * (e[1] - e[0]) ** 2)), plan_for(633.0, 256, seed=0))
    assert slope_anisotropy(relief)[0] < 1.01          # equal rms slopes: not flagged as anisotropic
    plate = Plate(thickness_m=2e-3, index=ConstantIndex(1.5),
                  front=ReliefFace(relief, method="ray", samples=100_000, seed=0), back=FlatFace(),
                  bulk=Bulk(absorption_per_m=0.0))
    exp = Experiment(plate, Instrument(detector_half_angle_deg=0.5, polarization_q=0.0))
    T, P = np.meshgrid(np.arange(0.0, 16.0, 1.0), np.arange(0.0, 360.0, 1.0), indexing="ij")
    edges = {}
    for phi_i in (0.0, 45.0):
        n = T.size
        rows = Recording(wavelength_nm=np.full(n, 633.0), theta_i_deg=np.zeros(n), phi_i_deg=np.full(n, phi_i),
                         side=np.full(n, "T"), theta_s_deg=T.ravel(), phi_s_deg=P.ravel(),
                         bsdf_sr=np.ones(n), sigma_sr=np.full(n, np.nan))
        edges[phi_i] = np.asarray(lobe_figures(rows, simulate(exp, rows, grid=TableGrid()).values_per_sr)["edges_u"])
    assert np.max(np.abs(edges[45.0] - edges[0.0])) <= 0.005, edges
