"""An inferred sample predicting measured files it was not inferred from (the proof of `relief infer`).

`predict_files`: the inferred sample (OUT/sample.toml) with its recording replaced by other measured
files, simulated through the one forward model (fit.optimise.Forward -> plate.simulate, the default grid),
one incidence at a time (the forward's memory), the pole's repeated readings simulated once.
`lobe_differences`: the issue's figures of a predicted lobe against the measured one (infer.lobe):
centroid (deg), the largest half-maximum edge difference (direction cosine), plateau (relative),
transmittance (absolute).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

#: the issue's targets for a predicted lobe (TARGETS[key] against lobe_differences' keys)
TARGETS = {"centroid_deg": 0.3, "edges_u": 0.005, "plateau_rel": 0.08, "transmittance": 0.02}


def predict_files(sample_path: str | Path, files: list[str | Path], samples: int = 100_000,
                  seed: int = 0) -> tuple[Any, np.ndarray]:
    """(recording of `files`, the sample's prediction on its rows) (module doc)."""
    from relief_bsdf.fit.optimise import Forward
    from relief_bsdf.infer.job import distinct_directions
    from relief_bsdf.io.heightmaps import read_sample_relief
    from relief_bsdf.io.recording import read_sample
    from relief_bsdf.plate import TableGrid, experiment_from_sample
    from relief_bsdf.plate.memory import ForwardMemory, job_memory_bytes
    inferred = read_sample(sample_path)
    other = replace(inferred, recording_paths=tuple(Path(f) for f in files))
    rec = other.load_recording()
    relief = read_sample_relief(other)
    sim = np.zeros(len(rec))
    for ti, pi in rec.incidences():
        sel = np.flatnonzero((rec.theta_i_deg == ti) & (rec.phi_i_deg == pi))
        rows, inverse = distinct_directions(rec.subset(sel))
        with ForwardMemory(job_memory_bytes() / 3).active():
            fwd = Forward(relief, experiment_from_sample(other, relief, samples=samples, seed=seed), rows,
                          grid=TableGrid())
            sim[sel] = fwd.simulate(1.0, 0.0)[inverse]
    return rec, sim


def lobe_figures_by_incidence(rec: Any, values: np.ndarray) -> dict:
    """infer.lobe's figures of the T rows of each incidence "theta_i/phi_i"."""
    from relief_bsdf.infer.lobe import lobe_figures
    out = {}
    for ti, pi in rec.incidences():
        sel = (rec.theta_i_deg == ti) & (rec.phi_i_deg == pi) & (rec.side == "T")
        out[f"{ti:g}/{pi:g}"] = lobe_figures(rec.subset(sel), values[sel])
    return out


def lobe_differences(measured: dict, predicted: dict) -> dict:
    """The module doc's differences of one incidence's figures."""
    return {"centroid_deg": abs(predicted["centroid_offset_deg"] - measured["centroid_offset_deg"]),
            "edges_u": float(np.max(np.abs(np.subtract(predicted["edges_u"], measured["edges_u"])))),
            "plateau_rel": abs(predicted["plateau_sr"] / measured["plateau_sr"] - 1.0),
            "transmittance": abs(predicted["transmittance"] - measured["transmittance"])}
