"""`infer`: a relief for a sample that has none, from its measured plate (the job of `relief infer`).

Steps (each a pure function of the step before, seeded):
  1. read the sample: [relief] file may be absent (it is what is made) and [plate] refractive_index
     may be absent (then n = `DEFAULT_INDEX`, reported as a limitation: this step does not fit it);
  2. the recording's transmitted rows at its incidence nearest the normal (<= `MAX_INVERSION_THETA_DEG`)
     -> the facet-slope density (infer.slopes, geometric optics through both faces);
  3. a periodic relief with that density (infer.synth: random crossed lenslets, 512 x 512, lateral
     scale above the diffraction criterion);
  4. OUT/relief.npz, OUT/sample.toml (the sample with that relief, periodic), then the plate of that
     sample through the one forward model on ALL the recording's rows (the path of `relief simulate`:
     fit.optimise.Forward -> plate.simulate), OUT/simulated.csv and OUT/infer.json with the metric
     (fit.residual.rms_z) for a flat plate (before) and the inferred relief (after).
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from relief_bsdf.errors import InputError

INFER_FORMAT = "relief-infer/1"
DEFAULT_INDEX = 1.5
MAX_INVERSION_THETA_DEG = 10.0
TILE_PX = 512
FAMILY = "random crossed lenslets"


def read_infer_sample(path: str | Path):
    """(Sample, index_stated, relief_stated): a sample.toml for infer, whose [relief] file and [plate]
    refractive_index may be absent (placeholders: OUT's relief, `DEFAULT_INDEX`)."""
    from relief_bsdf.io.recording import read_sample_doc, sample_from_doc
    path = Path(path)
    doc = read_sample_doc(path)
    plate = doc.get("plate") if isinstance(doc.get("plate"), dict) else None
    relief = doc.get("relief") if isinstance(doc.get("relief"), dict) else None
    index_stated = plate is None or "refractive_index" in plate or "cauchy" in plate
    relief_stated = relief is None or "file" in relief
    if plate is not None and not index_stated:
        doc["plate"] = {**plate, "refractive_index": DEFAULT_INDEX}
    if relief is not None and not relief_stated:
        doc["relief"] = {**relief, "file": "relief.npz"}
    sample = sample_from_doc(doc, path, check_files=False)
    for p in sample.recording_paths:
        if not Path(p).is_file():
            raise InputError(path, f"key recording.file: {Path(p).name!r} not found (looked for {p})")
    return sample, index_stated, relief_stated


def inversion_rows(rec: Any):
    """The T rows of the recording's incidence nearest the normal (one (theta_i, phi_i), one wavelength)."""
    T = rec.side == "T"
    if not T.any():
        raise InputError(rec.path or "recording", "no transmitted (T) rows: the slope inversion reads the "
                                                  "plate's transmitted lobe")
    ti = float(np.min(rec.theta_i_deg[T]))
    if ti > MAX_INVERSION_THETA_DEG:
        raise InputError(rec.path or "recording", f"the incidence nearest the normal is {ti:g} deg; the slope "
                                                  f"inversion needs one within {MAX_INVERSION_THETA_DEG:g} deg")
    sel = T & (rec.theta_i_deg == ti)
    pi = float(np.min(rec.phi_i_deg[sel]))
    sel &= rec.phi_i_deg == pi
    wl = float(np.min(rec.wavelength_nm[sel]))
    sel &= rec.wavelength_nm == wl
    return rec.subset(sel), ti, pi, wl


def distinct_directions(rec: Any) -> tuple[Any, np.ndarray]:
    """(rows, inverse): the recording's distinct readings (a reading at theta_s = 0 is one direction
    whatever its azimuth: RPC files repeat the pole once per azimuth of the scan) and the index of
    each row's distinct reading, so values of `rows` expand to the recording as values[inverse]."""
    phi = np.where(rec.theta_s_deg == 0.0, 0.0, rec.phi_s_deg)
    key = np.stack([rec.wavelength_nm, rec.theta_i_deg, rec.phi_i_deg, (rec.side == "T").astype(float),
                    rec.theta_s_deg, phi], axis=1)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return rec.subset(first), inverse.reshape(-1)


def lobe_comparison(rec: Any, values: np.ndarray) -> dict:
    """Per incidence "theta_i/phi_i": the lobe figures (infer.lobe) measured and simulated, for the T
    rows of incidences that form a full (theta_s, phi_s) grid (other recordings: none)."""
    from relief_bsdf.infer.lobe import full_grid, lobe_figures
    out = {}
    for ti, pi in rec.incidences():
        sel = (rec.theta_i_deg == ti) & (rec.phi_i_deg == pi) & (rec.side == "T")
        rows = rec.subset(sel)
        if sel.any() and full_grid(rows):
            out[f"{ti:g}/{pi:g}"] = {"measured": lobe_figures(rows, rec.bsdf_sr[sel]),
                                     "simulated": lobe_figures(rows, values[sel])}
    return out


def infer(sample_path: str | Path, out_dir: str | Path, seed: int = 0, progress: Any = None,
          samples: int = 100_000, tile_px: int = TILE_PX) -> dict:
    """Infer a relief for the sample (module doc); writes OUT/relief.npz, sample.toml, simulated.csv,
    infer.json; returns the infer.json object.  What the forward model keeps lives in the job's own
    memory owner (plate.memory, a third of the job's memory as in `relief fit`), dropped on return."""
    from relief_bsdf.plate.memory import ForwardMemory, job_memory_bytes
    with ForwardMemory(job_memory_bytes() / 3).active():
        return _infer(sample_path, out_dir, seed, progress, samples, tile_px)


def _infer(sample_path: str | Path, out_dir: str | Path, seed: int, progress: Any, samples: int,
           tile_px: int) -> dict:
    from relief_bsdf.core.index import ConstantIndex
    from relief_bsdf.fit.optimise import Forward
    from relief_bsdf.fit.residual import METRIC, rms_z
    from relief_bsdf.infer.slopes import slope_density
    from relief_bsdf.infer.synth import density_check, lenslet_relief, plan_for
    from relief_bsdf.io.atomic import write_text_atomic
    from relief_bsdf.io.heightmaps import write_relief
    from relief_bsdf.io.recording import write_recording, write_sample
    from relief_bsdf.plate import FlatFace, TableGrid, experiment_from_sample, simulate
    from relief_bsdf.surface.stats import rms_height, rms_slope, rms_slope_xy
    from relief_bsdf.surface.preparation import ReliefOptions

    def step(k: int, what: str) -> None:
        if progress is not None:
            progress(k, 5, what)

    out = Path(out_dir)
    step(0, "reading")
    sample, index_stated, relief_stated = read_infer_sample(sample_path)
    if sample.plate.rough_face != "front":
        raise InputError(sample.path, "plate.rough_face = \"back\": the slope inversion of this version takes "
                                      "the relief on the lit (front) face")
    rec = sample.load_recording()
    rows0, ti, pi, wl = inversion_rows(rec)
    n = float(np.real(sample.plate.index.n(wl)))
    step(1, "inverting the lobe")
    density = slope_density(rows0, n)
    step(2, "synthesising the relief")
    relief, facts = lenslet_relief(density, plan_for(wl, tile_px, seed=seed))
    out.mkdir(parents=True, exist_ok=True)
    write_relief(out / "relief.npz", relief)
    plate = sample.plate if index_stated else replace(sample.plate, index=ConstantIndex(n))
    new = replace(sample, path=out / "sample.toml", plate=plate, relief_path=out / "relief.npz",
                  relief_options=ReliefOptions(periodic=True, stated_by="relief infer"))
    write_sample(out / "sample.toml", new)
    step(3, "simulating the plate")
    exp = experiment_from_sample(new, relief, samples=samples, seed=seed)
    distinct, inverse = distinct_directions(rec)       # the pole's repeated readings simulated once
    fwd = Forward(relief, exp, distinct, grid=TableGrid(), where=str(sample.recording_path))
    values = fwd.simulated(1.0, 0.0).values_per_sr[inverse]
    after = rms_z(rec.bsdf_sr, rec.sigma_sr, values)
    flat = exp.with_plate(**{sample.plate.rough_face: FlatFace()})
    before = rms_z(rec.bsdf_sr, rec.sigma_sr,
                   simulate(flat, distinct, where=str(sample.recording_path)).values_per_sr[inverse])
    write_recording(out / "simulated.csv", rec.with_values(values),
                    comments=[f"relief infer {Path(sample_path).name}: the inferred relief's plate",
                              f"metric (rms z) vs recording: {after:.6g}"])
    step(4, "writing")
    rx, ry = rms_slope_xy(relief)
    face = getattr(fwd.experiment.plate, fwd.face_name)
    limitations = ["the relief is not yet refined through the forward model (no fit of family parameters, "
                   "height scale or index): intervals are not computed",
                   "the facet-slope density is inverted from one incidence in single-pass geometric optics "
                   "(no shadowing, detector blur not deconvolved)",
                   f"the relief reproduces the product of the density's marginals (separable lenslets); the "
                   f"density's distance from that product is {facts['separability_tv']:.3g} (total variation)"]
    if not index_stated:
        limitations.insert(0, f"[plate] refractive_index not given: n = {DEFAULT_INDEX:g} assumed (not fitted)")
    doc = {
        "format": INFER_FORMAT,
        "family": FAMILY,
        "parameters": {"rms_slope_x": rx, "rms_slope_y": ry, "mean_cell_um": facts["mean_cell_um"],
                       "pitch_um": facts["pitch_um"], "tile_px": facts["tile_px"], "refractive_index": n,
                       "rms_height_m": rms_height(relief)},
        "intervals": {k: None for k in ("rms_slope_x", "rms_slope_y", "refractive_index")},
        "rms_slope": rms_slope(relief),
        "metric": METRIC,
        "rms_before": before,
        "rms_after": after,
        "before": "a flat plate (both faces flat) of the same index",
        "index_stated": index_stated,
        "inverted_from": {"theta_i_deg": ti, "phi_i_deg": pi, "wavelength_nm": wl, "rows": len(rows0)},
        "density": {**density.moments(), "separability_tv": facts["separability_tv"], "notes": list(density.notes)},
        "synthesis": {**{k: v for k, v in facts.items() if k != "separability_tv"},
                      "check": density_check(relief, density)},
        "seed": int(seed),
        "physics": {"relief_face": sample.plate.rough_face, "method": face.method,
                    "chosen_by": getattr(face, "chosen_by", None), "samples": int(samples)},
        "lobe": lobe_comparison(rec, values),
        "limitations": limitations,
        "files": ["relief.npz", "sample.toml", "simulated.csv", "infer.json"],
    }
    write_text_atomic(out / "infer.json", json.dumps(doc, indent=2) + "\n")
    step(5, "done")
    return doc
