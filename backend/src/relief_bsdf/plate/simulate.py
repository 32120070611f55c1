"""`simulate`: run an Experiment on recording rows with either engine; `experiment_from_sample`."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from relief_bsdf.errors import InputError
from relief_bsdf.plate.description import SOURCE_Q, Bulk, Experiment, Instrument, Plate
from relief_bsdf.plate.faces import FlatFace, ReliefFace
from relief_bsdf.plate import deterministic, photon
from relief_bsdf.plate.choice import DEFAULT_METHOD, resolve_auto
from relief_bsdf.plate.uncertainty import rows_sigma, sigma_note
from relief_bsdf.plate.grid import TableGrid
from relief_bsdf.parallel.memory import trim_heap

ENGINES = ("deterministic", "photon")


@dataclass
class Simulated:
    """Simulated recording values (1/sr) per row, their 1-sigma (0 for the deterministic engine), and
    `info`: the physics used (engine, each face's method, bulk, instrument; photon losses)."""

    values_per_sr: np.ndarray
    sigma_per_sr: np.ndarray
    info: dict = field(default_factory=dict)


def describe(experiment: Experiment) -> dict:
    """What physics an Experiment stands for (for outputs: "which physics was used")."""
    p, b, ins = experiment.plate, experiment.plate.bulk, experiment.instrument
    return {"front": p.front.describe(), "back": p.back.describe(), "thickness_m": p.thickness_m,
            "index": p.index.describe(), "bulk": {"absorption_per_m": b.absorption_per_m,
                                                  "scatter_per_m": b.scatter_per_m, "hg_g": b.hg_g},
            "instrument": {"detector_half_angle_deg": ins.detector_half_angle_deg,
                           "polarization_q": ins.polarization_q, "blur_deg": ins.blur_deg, "tilt_deg": ins.tilt_deg,
                           "beam_divergence_deg": ins.beam_divergence_deg,
                           "background_per_sr": ins.background_per_sr}}


def simulate(experiment: Experiment, rows: Any, engine: str = "deterministic", photons: int = 200_000, seed: int = 0,
             grid: TableGrid | None = None, progress: Any = None, where: str = "recording",
             table_sigma_draws: int = 0) -> Simulated:
    """The plate as the instrument sees it, on every row (same order).

    engine "deterministic": radiative transfer over the faces' tables on `grid` (default
    TableGrid()); its sigma is the tables' own uncertainty carried through the plate when
    `table_sigma_draws` >= 2 (plate.uncertainty.rows_sigma), else 0.  "photon": photon Monte
    Carlo, `photons` per incidence, seeded per incidence, with its own sampling sigma.
    """
    grid = grid or TableGrid()
    experiment = resolve_auto(experiment, rows, grid)       # "auto" faces: the relief's own physics, once
    if engine == "deterministic":
        vals, info = deterministic.run(experiment, rows, grid, progress, where)
        sig = np.zeros_like(vals)
        if table_sigma_draws >= 2:
            sig = rows_sigma(experiment, rows, grid, table_sigma_draws, seed)
            info = {**info, "sigma": sigma_note(table_sigma_draws)}
    elif engine == "photon":
        vals, sig, info = photon.run(experiment, rows, photons=photons, seed=seed, grid=grid, where=where)
    else:
        raise InputError("engine", f"must be one of {', '.join(ENGINES)}, got {engine!r}")
    trim_heap(collect=False)        # what this evaluation freed is not held into the next (parallel.memory)
    return Simulated(vals, sig, {**info, "physics": describe(experiment)})


def experiment_from_sample(sample: Any, relief: Any, method: str = DEFAULT_METHOD, samples: int = 200_000,
                           seed: int = 0, options: dict | None = None) -> Experiment:
    """The Experiment of a sample.toml (`io.recording.Sample`): relief on its rough face, the other flat."""
    p, ins = sample.plate, sample.instrument
    try:
        a = getattr(p, "absorption_per_mm", None)
        face = ReliefFace(relief, method=method, samples=int(samples), seed=int(seed), options=dict(options or {}))
        front, back = (face, FlatFace()) if p.rough_face == "front" else (FlatFace(), face)
        plate = Plate(thickness_m=float(p.thickness_mm) * 1e-3, index=p.index, front=front, back=back,
                      bulk=Bulk(absorption_per_m=0.0 if a is None else float(a) * 1e3))
        instrument = Instrument(detector_half_angle_deg=float(ins.detector_half_angle_deg),
                                polarization_q=SOURCE_Q[str(ins.polarization)])
    except InputError as e:
        raise InputError(f"{sample.path}: {e.where}", e.message) from None
    return Experiment(plate, instrument)
