"""The plate closes a wave model's energy defect instead of reading it as absorption (plate.energy)."""
import warnings

import numpy as np
import pytest

from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.plate import ReliefFace, TableGrid
from relief_bsdf.plate.energy import closed
from relief_bsdf.surface.synth import random_relief

GRID = TableGrid(2.0, 10.0, 15.0)


def test_kirchhoff_faces_conserve_energy_and_keep_the_coherent_parts():
    relief = random_relief(128, 0.125e-6, 0.08e-6, 1.5e-6, "gaussian", seed=5)
    face = ReliefFace(relief, "kirchhoff", options={"band_limited": True})
    mat = Material(inside=ConstantIndex(1.5))
    from relief_bsdf.methods import reconstruct
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        out, ins = face.tables(mat, GRID, [550.0], [0.0, 30.0, 60.0])
        req = GRID.request([550.0], [0.0, 30.0, 60.0], "outside", "kirchhoff", 1, 0, {"band_limited": True})
        (raw,) = reconstruct(relief, mat, req, "kirchhoff")
    h, h0 = out.hemispherical(), raw.hemispherical()
    np.testing.assert_allclose(h["R"] + h["T"], 1.0, atol=1e-5)            # lossless: R + T = 1
    np.testing.assert_array_equal(out.specular_T, raw.specular_T)          # coherent parts untouched
    assert np.all(out.lost == 0)
    assert "energy_closure" in out.metadata and "energy_closure" in ins.metadata
    # the lobe's shape is kept: one factor per incidence
    ratio = out.values_per_sr[0, 1, 0] / np.where(raw.values_per_sr[0, 1, 0] > 0, raw.values_per_sr[0, 1, 0], np.nan)
    assert np.nanstd(ratio) < 1e-5 * np.nanmean(ratio)
    assert np.any(np.abs(1 - (h0["R"] + h0["T"])) > 1e-4)                  # there was a defect to close


def test_absorption_is_not_closed():
    from relief_bsdf.bsdf.table import BsdfTable
    t = BsdfTable([550.0], [0.0], [0.0], np.linspace(0, 90, 10), np.linspace(-5, 355, 37),
                  np.full((1, 1, 1, 2, 9, 36), 0.01), metadata={"energy_defect": {"meaning": "absorption"}})
    assert closed(t) is t


def test_a_large_closure_is_reported_as_outside_validity():
    from relief_bsdf.bsdf.table import BsdfTable
    t = BsdfTable([550.0], [80.0], [0.0], np.linspace(0, 90, 10), np.linspace(-5, 355, 37),
                  np.full((1, 1, 1, 2, 9, 36), 0.5), metadata={"energy_defect": {"meaning": "tangent-plane defect"}})
    with pytest.warns(RuntimeWarning, match="outside its validity"):
        c = closed(t)
    np.testing.assert_allclose(c.hemispherical()["R"] + c.hemispherical()["T"], 1.0)
