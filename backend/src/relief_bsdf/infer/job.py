"""`infer`: a relief for a sample that has none, from its measured plate (the job of `relief infer`).

Steps (each a pure function of the step before, seeded):
  1. read the sample: [relief] file may be absent (it is what is made) and [plate] refractive_index
     may be absent (then the index starts at `DEFAULT_INDEX` and is fitted, infer.refine);
  2. the recording's transmitted rows at its incidence nearest the normal (<= `MAX_INVERSION_THETA_DEG`)
     -> the facet-slope density (infer.slopes, geometric optics through both faces); an in-plane scan at
     normal incidence is read as an isotropic lobe first (infer.slopes.isotropic_reading, its assumption
     stated in infer.json);
  3. the candidates (infer.families: the non-parametric density and the few-parameter families), each a
     periodic relief of random crossed lenslets (infer.synth, 512 x 512, lateral scale above the
     diffraction criterion), screened through the plate and chosen by the information criterion;
  4. the chosen one refined through the plate (infer.refine: height scale, and the index when not stated);
  5. OUT/relief.npz, OUT/sample.toml (the sample with that relief, periodic), then the plate of that
     sample through the one forward model on ALL the recording's rows (the path of `relief simulate`:
     fit.optimise.Forward -> plate.simulate, the default grid, read out `FINAL_CHUNK_ROWS` rows at a
     time), OUT/simulated.csv, the boundary tables, the report and OUT/infer.json with the metric
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
    """(T rows of the recording's incidence nearest the normal (one (theta_i, phi_i), one wavelength),
    theta_i, phi_i, wavelength, the rows the inversion reads, reading): those rows themselves when they
    cover the direction plane (a measured file's grid, or three or more planes of scatter); an in-plane
    scan at normal incidence read as isotropic (infer.slopes.isotropic_reading: its assumption is stated in
    `reading`); `reading` says which."""
    from relief_bsdf.infer.slopes import isotropic_reading
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
    off_pole = sel & (rec.theta_s_deg > 0)
    planes = np.unique(np.round(np.mod(rec.phi_s_deg[off_pole], 180.0), 6))
    rows = rec.subset(sel)
    if planes.size >= 3:
        return rows, ti, pi, wl, rows, {"reading": "the lobe over the direction plane"}
    if planes.size == 1 and ti == 0.0:
        try:
            lobe, facts = isotropic_reading(rows)
        except InputError as e:
            raise InputError(rec.path or "recording", e.message) from None
        return rows, ti, pi, wl, lobe, facts
    raise InputError(rec.path or "recording",
                     f"the transmitted rows at incidence {ti:g}/{pi:g} deg lie in {planes.size} plane(s) of "
                     "scatter: the slope inversion reads the lobe over the whole direction plane (a measured plate "
                     "file's full grid, rows at three or more scatter azimuths) or an in-plane scan at normal "
                     "incidence (read as isotropic)")


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
    from relief_bsdf.fit.optimise import Forward, process_relief
    from relief_bsdf.fit.residual import METRIC, rms_z
    from relief_bsdf.infer import refine as rf
    from relief_bsdf.infer.families import FAMILY_NAMES, candidates
    from relief_bsdf.infer.slopes import slope_density
    from relief_bsdf.infer.synth import density_check, lenslet_relief, plan_for
    from relief_bsdf.io.atomic import write_text_atomic
    from relief_bsdf.io.heightmaps import write_relief
    from relief_bsdf.io.recording import write_recording, write_sample
    from relief_bsdf.plate import FlatFace, TableGrid, experiment_from_sample, simulate
    from relief_bsdf.surface.preparation import ReliefOptions
    from relief_bsdf.surface.stats import rms_height, rms_slope, rms_slope_xy

    total = [STEPS]
    done = [0]

    def step(what: str, advance: bool = True) -> None:
        if advance:
            done[0] = min(done[0] + 1, total[0])
        if progress is not None:
            progress(done[0], total[0], what)

    out = Path(out_dir)
    step("reading", advance=False)
    sample, index_stated, relief_stated = read_infer_sample(sample_path)
    if sample.plate.rough_face != "front":
        raise InputError(sample.path, "plate.rough_face = \"back\": the slope inversion of this version takes "
                                      "the relief on the lit (front) face")
    rec = sample.load_recording()
    rows0, ti, pi, wl, lobe_rows, reading = inversion_rows(rec)
    n0 = float(np.real(sample.plate.index.n(wl)))
    step("inverting the lobe")
    density = slope_density(lobe_rows, n0)
    step("synthesising the candidates")
    plan = plan_for(wl, tile_px, seed=seed)
    cands = candidates(density)
    if "lobe_readings" in reading:     # an isotropic reading: the non-parametric density is the cut's readings
        cands = [replace(c, k=reading["lobe_readings"]) if c.name == "non-parametric" else c for c in cands]
    reliefs = [lenslet_relief(c.density, plan) for c in cands]
    fit_index = not index_stated
    kp = 2 if fit_index else 1                      # the plate's parameters: height scale (and index)
    meas = rf.refinement_rows(rec, ti, pi, wl)
    rows_r, inv_r = distinct_directions(meas)
    refine_grid = rf.refine_grid()

    def objective(relief) -> rf.Objective:
        forwards: dict = {}

        def forward_at(n: float):
            if n not in forwards:
                smp = replace(sample, plate=replace(sample.plate, index=ConstantIndex(n)))
                forwards.clear()                   # one index's tables at a time (the job's memory)
                forwards[n] = Forward(relief, experiment_from_sample(smp, relief, samples=samples, seed=seed),
                                      rows_r, grid=refine_grid, where=str(sample.recording_path))
            return forwards[n]
        return rf.Objective(forward_at, rows_r, inv_r, meas, n0, fit_index,
                            progress=lambda what: step(what, advance=False))

    screened = []
    for i, (c, (relief, facts)) in enumerate(zip(cands, reliefs)):
        step(f"screening the candidate {c.name}")
        same = [j for j in range(i) if rf.density_distance(c.density, cands[j].density) < rf.SAME_DENSITY_TV]
        if same:
            chi2, as_ = screened[same[0]]["chi2"], cands[same[0]].name
        else:
            chi2, as_ = rf.Objective.residuals(objective(relief), rf.x_start(n0, fit_index))[0], None
        screened.append({"name": c.name, "family": FAMILY_NAMES[c.name], "k": c.k + kp, "chi2": chi2,
                         "parameters": c.parameters, **({"same_density_as": as_} if as_ else {})})
    best, decisions = rf.choose(screened, len(meas))
    cand, (relief0, facts) = cands[best], reliefs[best]
    step(f"refining {cand.name} through the plate")
    obj = objective(relief0)
    ref = rf.polish_and_intervals(obj, rf.x_start(n0, fit_index))
    s_fit, n_fit = obj.point(ref.x)
    relief = process_relief(relief0, s_fit, 0.0)
    out.mkdir(parents=True, exist_ok=True)
    write_relief(out / "relief.npz", relief)
    plate = replace(sample.plate, index=ConstantIndex(n_fit)) if fit_index else sample.plate
    new = replace(sample, path=out / "sample.toml", plate=plate, relief_path=out / "relief.npz",
                  relief_options=ReliefOptions(periodic=True, stated_by="relief infer"))
    write_sample(out / "sample.toml", new)

    step("simulating the plate on every row")
    evaluations = obj.evaluations
    del obj, reliefs
    release_memory()                # the refinement's tables (other reliefs, the screening grid): not read again
    exp = experiment_from_sample(new, relief, samples=samples, seed=seed)
    distinct, inverse = distinct_directions(rec)       # the pole's repeated readings simulated once
    fwd = Forward(relief, exp, distinct, grid=TableGrid(), where=str(sample.recording_path))   # decided on every row
    _, values = _in_chunks(lambda rows: Forward(relief, fwd.experiment, rows, grid=TableGrid(),
                                                where=str(sample.recording_path)),
                           lambda f: f.simulated(1.0, 0.0).values_per_sr, distinct)
    values = values[inverse]
    after = rms_z(rec.bsdf_sr, rec.sigma_sr, values)
    flat = exp.with_plate(**{sample.plate.rough_face: FlatFace()})
    _, flat_values = _in_chunks(lambda rows: rows, lambda rows: simulate(flat, rows, where=str(sample.recording_path))
                                .values_per_sr, distinct)
    before = rms_z(rec.bsdf_sr, rec.sigma_sr, flat_values[inverse])
    write_recording(out / "simulated.csv", rec.with_values(values),
                    comments=[f"relief infer {Path(sample_path).name}: the inferred relief's plate",
                              f"metric (rms z) vs recording: {after:.6g}"])
    step("writing the boundary tables")
    files = {"relief": "relief.npz", "sample": "sample.toml", "simulated": "simulated.csv"}
    files.update(write_boundary_tables(out, fwd))
    rx, ry = rms_slope_xy(relief)
    face = getattr(fwd.experiment.plate, fwd.face_name)
    names = ["height_scale"] + (["refractive_index"] if fit_index else [])
    intervals = {nm: [float(ref.s_n[j] - ref.sd[j]), float(ref.s_n[j] + ref.sd[j])] if np.isfinite(ref.sd[j]) else None
                 for j, nm in enumerate(names)}
    if not fit_index:
        intervals["refractive_index"] = None
    family_params = {f"{k}": v for k, v in cand.parameters.items()}
    limitations = ["the facet-slope density is inverted from one incidence in single-pass geometric optics "
                   "(no shadowing, detector blur not deconvolved); the refinement fits the height scale"
                   + (" and the index" if fit_index else "") + " through the plate",
                   f"the relief reproduces the product of the density's marginals (separable lenslets); the "
                   f"density's distance from that product is {facts['separability_tv']:.3g} (total variation)",
                   f"the refinement reads the lobe (rows at or above {rf.LOBE_FRACTION:g} of its peak); the "
                   "halo around it enters the metric over every row but is not fitted",
                   "the candidates are ranked by their chi^2 at their slope-plane fit (height scale 1, the start "
                   "index); only the chosen one is polished through the plate",
                   "the refinement's evaluations run on the screening grid (no inside sector tables, a tenth of "
                   "the inside rays); the final simulation and the tables on the default grid"]
    if "assumption" in reading:
        limitations.insert(0, f"the inverted lobe is an {reading['reading']}: {reading['assumption']}")
    for j, nm in enumerate(names):
        lo, hi = (rf.LOWER[j], rf.UPPER[j]) if nm == "refractive_index" else (None, None)
        if lo is not None and (abs(n_fit - lo) < 1e-9 or abs(n_fit - hi) < 1e-9):
            limitations.insert(0, f"the fitted index ended at its bound {n_fit:g} (search range {lo:g}-{hi:g}): "
                                  "the lobe's level asks for an index outside it; the index is read from that level "
                                  "(the faces' Fresnel losses), so light the model sends outside the lobe, or a "
                                  "recording whose level no plate of this relief reaches, moves it")
    lobe = lobe_comparison(rec, values)
    doc = {
        "format": INFER_FORMAT,
        "family": FAMILY_NAMES[cand.name],
        "candidate": cand.name,
        "parameters": {**family_params, "height_scale": s_fit, "refractive_index": n_fit,
                       "rms_slope_x": rx, "rms_slope_y": ry, "mean_cell_um": facts["mean_cell_um"],
                       "pitch_um": facts["pitch_um"], "tile_px": facts["tile_px"],
                       "rms_height_m": rms_height(relief)},
        "intervals": intervals,
        "interval_level": "68 % (one standard deviation, fit.covariance)",
        "interval_notes": ref.notes,
        "correlation": np.where(np.isfinite(ref.correlation), ref.correlation, 0.0).tolist(),
        "rms_slope": rms_slope(relief),
        "rms_slope_interval": (None if not np.isfinite(ref.sd[0]) else
                               [rms_slope(relief) * (1 - ref.sd[0] / s_fit), rms_slope(relief) * (1 + ref.sd[0] / s_fit)]),
        "metric": METRIC,
        "rms_before": before,
        "rms_after": after,
        "before": "a flat plate (both faces flat) of the same index",
        "index_stated": index_stated,
        "index_fitted": fit_index,
        "inverted_from": {"theta_i_deg": ti, "phi_i_deg": pi, "wavelength_nm": wl, "rows": len(rows0),
                          "start_index": n0, **reading},
        "refinement": {"rows": len(meas), "lobe_fraction": rf.LOBE_FRACTION, "chi2": ref.chi2,
                       "evaluations": evaluations, "grid": "screening grid (no inside sector tables), inside rays x "
                                               f"{rf.REFINE_INSIDE_SAMPLES_SCALE:g}",
                       "coordinates": "width scale w = s (n - 1) / (n0 - 1) and n (infer.refine)"},
        "selection": {"criterion": "BIC = chi^2 + k ln n (criteria), QBIC margin "
                                   "criteria.BIC_MARGIN", "n_rows": len(meas),
                      "candidates": screened, "decisions": decisions, "chosen": cand.name},
        "density": {**density.moments(), "separability_tv": facts["separability_tv"], "notes": list(density.notes)},
        "synthesis": {**{k: v for k, v in facts.items() if k != "separability_tv"},
                      "check": density_check(relief0, cand.density)},
        "seed": int(seed),
        "physics": {"relief_face": sample.plate.rough_face, "method": face.method,
                    "chosen_by": getattr(face, "chosen_by", None), "samples": int(samples)},
        "lobe": lobe,
        "inside_table": inside_statement(fit_index, s_fit, n_fit, ref.sd),
        "limitations": limitations,
    }
    step("writing the report")
    from relief_bsdf.infer.report import write_infer_report
    files.update(write_infer_report(out, doc, rec, values))
    files["infer"] = "infer.json"
    doc["files"] = files
    write_text_atomic(out / "infer.json", json.dumps(doc, indent=2, default=float) + "\n")
    step("done")
    return doc


#: distinct rows per readout of the final simulation (`_in_chunks`)
FINAL_CHUNK_ROWS = 8000


def release_memory() -> None:
    """Drop what the forward model keeps (the job's memory owner) and hand freed heap back to the system:
    the allocator keeps large freed blocks for reuse (glibc's trim threshold grows with them), so
    without the trim the refinement's freed tables would still count in the job's peak while the final
    simulation builds its own."""
    from relief_bsdf.parallel.memory import trim_heap
    from relief_bsdf.plate.memory import current_memory
    current_memory().clear()
    trim_heap()


def _in_chunks(make: Any, read: Any, rows: Any) -> tuple[Any, np.ndarray]:
    """(the last chunk's reader, values of every row): `read(make(chunk))` over chunks of at most
    `FINAL_CHUNK_ROWS` rows.  The plate's tables and solver are kept by the memory owner and shared by
    the chunks; what a readout holds per row (each row's detector cone over the direction grid's
    sub-points) is then made for one chunk at a time, not for every row of a measured file at once
    (EDS10's 30 601 distinct rows: 0.55 GB less at the peak, the same values)."""
    out = np.zeros(len(rows))
    reader = None
    for a in range(0, len(rows), FINAL_CHUNK_ROWS):
        idx = np.arange(a, min(a + FINAL_CHUNK_ROWS, len(rows)))
        reader = make(rows.subset(idx))
        out[idx] = read(reader)
    return reader, out


STEPS = 12   # reading, inverting, synthesising, 5 candidates, refining, simulating, tables, report (+ done)


def write_boundary_tables(out: Path, fwd: Any) -> dict:
    """The inferred boundary's tables, both sides (light from outside and from inside the glass), as the fit
    writes them: OUT/boundary.h5 and one IS-BSDF file per side and scatter type."""
    from relief_bsdf.io.hdf5 import save_tables
    from relief_bsdf.io.isbsdf import export_isbsdf
    _, t_out, t_in = fwd.tables(1.0, 0.0)
    tables = [t for t in (t_out, t_in) if t is not None]
    save_tables(out / "boundary.h5", tables)
    files = {"boundary_table": "boundary.h5"}
    for t in tables:
        files[f"isbsdf_{t.incident_from}"] = [q.name for q in export_isbsdf(t, out / f"boundary_{t.incident_from}.bsdf")]
    return files


def inside_statement(fit_index: bool, s: float, n: float, sd: np.ndarray) -> str:
    """What the report says of the inside table (light from the glass, which no instrument measures)."""
    parts = [f"height scale {s:.4g} +- {sd[0]:.2g}"]
    if fit_index:
        parts.append(f"index {n:.4g} +- {sd[1]:.2g}")
    return ("The boundary's inside table (light arriving from the glass) is not measured: it is computed by the "
            "same ray tracer from the inferred relief, and carries the relief's uncertainty ("
            + ", ".join(parts) + ", 68 %) and the family's assumptions (limitations).")
