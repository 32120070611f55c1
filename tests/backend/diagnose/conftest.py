"""Fixtures of the diagnosis tests: a small forward model on the plate API, no files."""
from __future__ import annotations

import numpy as np
import pytest

from diagnosis_rows import in_plane_rows  # noqa: F401  (a uniquely named module: two conftest.py cannot both be imported as 'conftest')


def _coarse():
    from relief_bsdf.plate import TableGrid
    return TableGrid(theta_step_deg=2.0, phi_step_deg=10.0, inside_theta_i_step_deg=10.0)


COARSE = _coarse()      # 2 x 10 deg cells, inside incidences every 10 deg: fast tables for unit tests


@pytest.fixture
def plate_forward():
    """Factory: plate_forward(relief, tis=(0, 40), method="microfacet+dw", half_angle_deg=3.0, ...) ->
    DiagnosisForward of a 2 mm n = 1.5 plate with the relief on the front face (the diagnosis's baseline),
    on the COARSE table grid unless `grid` is given."""
    from relief_bsdf.core.index import ConstantIndex
    from relief_bsdf.diagnose.effects import ReliefContext
    from relief_bsdf.diagnose.forward import DiagnosisForward, _FaceBuilder
    from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate
    from relief_bsdf.surface.operations import scale_and_filter

    def make(relief, tis=(0.0, 40.0), method="microfacet+dw", half_angle_deg=3.0, wavelengths=(550.0,),
             samples=50_000, grid=COARSE):
        rows = in_plane_rows(tis, wavelengths)
        face = _FaceBuilder(samples, 1)
        plate = Plate(thickness_m=2e-3, index=ConstantIndex(1.5), front=face(relief, method), back=FlatFace())
        exp = Experiment(plate, Instrument(detector_half_angle_deg=half_angle_deg))
        ctx = ReliefContext(relief=relief, method=method, face=face, scale_and_filter=scale_and_filter,
                            wavelengths_nm=tuple(float(w) for w in wavelengths),
                            detector_half_angle_deg=half_angle_deg, samples=samples, seed=1)
        return DiagnosisForward(exp, rows, ctx, grid=grid)
    return make
