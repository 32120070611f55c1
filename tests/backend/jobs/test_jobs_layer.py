"""The application layer (relief_bsdf.jobs): typed jobs, cancellation, and the one forward-model decision
that simulate, fit and diagnose share (fit.baseline)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from relief_bsdf.errors import InputError
from relief_bsdf.io.heightmaps import read_relief, write_relief
from relief_bsdf.io.recording import Recording, read_recording, read_sample, write_recording, write_sample
from relief_bsdf.jobs import (CancelToken, FillJob, ReconstructJob, SimulateJob, run_fill, run_reconstruct,
                              run_simulate)
from relief_bsdf.progress import Cancelled
from relief_bsdf.surface.relief import Relief
from relief_bsdf.surface.synth import random_relief

SURROGATE = "microfacet+dw"        # the fast surrogate: plumbing, not physics, is tested here


def _tilted(relief: Relief, slope: float) -> Relief:
    """`relief` plus a plane of `slope` along x (an instrument's stage tilt), measured patch."""
    x = np.arange(relief.heights_m.shape[1]) * relief.dx_m
    return Relief(relief.heights_m + slope * x[None, :], relief.dx_m, relief.dy_m, periodic=False, source="tilted")


def _sample(tmp_path: Path, relief: Relief) -> Path:
    write_relief(tmp_path / "relief.npz", relief)
    ts = np.arange(1.0, 89.5, 8.0)
    rows = [(550.0, ti, 0.0, sd, t, ps) for ti in (0.0, 30.0) for sd in "RT" for ps in (0.0, 180.0) for t in ts]
    a = np.array(rows, dtype=object)
    rec = Recording(a[:, 0].astype(float), a[:, 1].astype(float), a[:, 2].astype(float), a[:, 3].astype(str),
                    a[:, 4].astype(float), a[:, 5].astype(float), np.ones(len(rows)), np.full(len(rows), 0.05))
    write_recording(tmp_path / "recording.csv", rec)
    write_sample(tmp_path / "sample.toml", {
        "plate": {"thickness_mm": 2.0, "rough_face": "front", "refractive_index": 1.5},
        "relief": {"file": "relief.npz", "periodic": False},
        "instrument": {"detector_half_angle_deg": 1.0, "polarization": "unpolarized"},
        "recording": {"file": "recording.csv"}})
    return tmp_path / "sample.toml"


def test_cancel_token_stops_a_job_before_its_output(tmp_path):
    r = random_relief(32, 0.5e-6, 30e-9, 2e-6, "gaussian", seed=1)
    h = r.heights_m.copy()
    h[4:6, 4:6] = np.nan
    write_relief(tmp_path / "holes.npz", Relief(h, r.dx_m, r.dy_m, periodic=True))
    token = CancelToken()
    token.cancel()
    with pytest.raises(Cancelled):
        run_fill(FillJob(tmp_path / "holes.npz", tmp_path / "filled.npz"), cancel=token)
    assert not (tmp_path / "filled.npz").exists()
    done = run_fill(FillJob(tmp_path / "holes.npz", tmp_path / "filled.npz"))         # uncancelled: written
    assert (done.missing, done.left) == (4, 0)
    assert np.all(np.isfinite(read_relief(tmp_path / "filled.npz").heights_m))


def test_cancel_during_the_work_lands_at_a_task_boundary(tmp_path):
    """A token set while the method runs stops it at its next task; no table file is written."""
    from relief_bsdf.core.index import ConstantIndex, Material
    from relief_bsdf.methods.request import Request
    write_relief(tmp_path / "r.npz", random_relief(32, 0.5e-6, 30e-9, 2e-6, "gaussian", seed=1))
    req = Request(wavelengths_nm=(550.0,), theta_i_deg=(0.0, 20.0, 40.0), incident_from=("outside",),
                  theta_s_edges_deg=tuple(np.linspace(0, 90, 31)), phi_s_edges_deg=tuple(-7.5 + 15 * np.arange(25)),
                  seed=0).validate()
    job = ReconstructJob(tmp_path / "r.npz", tmp_path / "t.h5", Material(ConstantIndex(1.5)), req, method="microfacet")
    token, calls = CancelToken(), []

    def progress(done, total, what=""):
        calls.append(done)
        token.cancel()                    # the user presses Esc after the first task
    with pytest.raises(Cancelled):
        run_reconstruct(job, progress, token)
    assert calls and not (tmp_path / "t.h5").exists()
    out = run_reconstruct(job)                                 # the same job, uncancelled
    assert out.out.is_file() and len(out.tables) == 1 and out.chosen is None


def test_reconstruct_job_refuses_a_wrong_output_before_reading(tmp_path):
    with pytest.raises(InputError, match="HDF5"):
        run_reconstruct(ReconstructJob(tmp_path / "missing.npz", tmp_path / "t.csv", None, None))


def test_simulate_levels_the_relief_as_fit_and_diagnosis_do(tmp_path):
    """One decision (fit.baseline): a stage tilt is removed before any table, so a tilted map simulates
    as the untilted one; and the simulate job's values and sigma are the fit's forward model's."""
    from relief_bsdf.fit.baseline import baseline
    from relief_bsdf.fit.optimise import Forward
    from relief_bsdf.plate import TableGrid
    r = random_relief(48, 0.125e-6, 30e-9, 1.0e-6, "gaussian", seed=2)
    flat_dir, tilt_dir = tmp_path / "flat", tmp_path / "tilt"
    flat_dir.mkdir()
    tilt_dir.mkdir()
    s_flat = _sample(flat_dir, Relief(r.heights_m, r.dx_m, r.dy_m, periodic=False, source="flat"))
    s_tilt = _sample(tilt_dir, _tilted(r, 0.2))                  # 11 degrees of stage tilt
    # `normals` uses the measured slopes as they are (no tilt removal of its own): only the baseline's
    # levelling makes the two agree
    a = run_simulate(SimulateJob(s_flat, flat_dir / "out", method="normals", samples=20000))
    b = run_simulate(SimulateJob(s_tilt, tilt_dir / "out", method="normals", samples=20000))
    va = read_recording(a.path).bsdf_sr
    vb = read_recording(b.path).bsdf_sr
    np.testing.assert_allclose(vb, va, rtol=1e-6, atol=1e-12)
    assert "levelled" in " ".join(b.relief.history)
    # the fit's forward model of the same sample, at the same parameters: the same rows and sigma
    base = baseline(read_sample(s_tilt), method="normals", samples=20000, grid=TableGrid())
    fwd = Forward(base.relief, base.experiment, base.recording, grid=base.grid, where=base.where)
    sim = fwd.simulated(1.0, 0.0)
    np.testing.assert_allclose(vb, sim.values_per_sr, rtol=1e-12)
    np.testing.assert_allclose(read_recording(b.path).sigma_sr, fwd.model_rel_sigma() * np.abs(sim.values_per_sr),
                               rtol=1e-9, atol=1e-15)


def test_diagnosis_baseline_is_the_fit_baseline(tmp_path):
    """The diagnosis's forward model starts from the same decision: levelled relief, resolved method."""
    from relief_bsdf.diagnose.forward import build_forward
    from relief_bsdf.fit.baseline import baseline
    r = random_relief(48, 0.125e-6, 30e-9, 1.0e-6, "gaussian", seed=2)
    s = _sample(tmp_path, _tilted(r, 0.2))
    fwd, _ = build_forward(s, SURROGATE, 20000, 0)
    b = baseline(read_sample(s), method=SURROGATE, grid=fwd.grid)
    np.testing.assert_array_equal(fwd.context.relief.heights_m, b.relief.heights_m)
    assert fwd.experiment.plate.front.method == b.experiment.plate.front.method
    gx = np.gradient(b.relief.heights_m, b.relief.dx_m, axis=1).mean()
    assert abs(gx) < 1e-3                      # the 0.2 stage tilt is gone
