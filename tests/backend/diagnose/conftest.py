"""Fixtures of the diagnosis tests: a small forward model on the plate API, no files."""
from __future__ import annotations

import numpy as np
import pytest


def in_plane_rows(tis, wavelengths=(550.0,), step_deg=10.0, sigma=0.01):
    """Recording rows at theta_s every `step_deg` (phi_s 0 and 180, R and T), sigma `sigma`, values 0."""
    from relief_bsdf.io.recording import Recording
    g = [(wl, ti, sd, t, ps) for wl in wavelengths for ti in tis for sd in ("R", "T") for ps in (0.0, 180.0)
         for t in np.arange(0.0, 90.0, step_deg) if not (t == 0.0 and ps == 180.0)]
    W, TI, SD, TS, PS = (np.array(c) for c in zip(*g))
    n = len(W)
    return Recording(W.astype(float), TI.astype(float), np.zeros(n), SD, TS.astype(float), PS.astype(float),
                     np.zeros(n), np.full(n, sigma))


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
