"""The job `relief export`: a BSDF table (the project's .h5, or a measured / exchanged file) written as
a recording CSV, Zemax IS-BSDF, WINDOW/Radiance XML or the project's HDF5.

Tables are read by `io.tables` (every format this project reads); a measured plate file exported
as recording-csv gives its own readings as rows (`io.measured`).  recording-csv: every tabulated
cell value as a recording.csv row (cell centres, sigma empty when unknown), the delta-like
specular parts in comments.  is-bsdf: one file per scatter type and wavelength (`io.isbsdf`).
radiance-xml: both sides, Klems or a tensor tree (`io.radiance_xml`), with checkBSDF's
reciprocity where Radiance is installed.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from relief_bsdf.errors import InputError
from relief_bsdf.jobs.control import CancelToken, check
from relief_bsdf.progress import Progress

FORMATS = ("recording-csv", "is-bsdf", "radiance-xml", "hdf5")
LOBE_ANISOTROPY_WARN = 1.2      # normal-incidence lobe this much wider along one axis: not isotropic


@dataclass(frozen=True)
class ExportJob:
    """Export `table` (a table file) as `format` (FORMATS) to `out`: the table of light from
    `incident_from` (None: outside if present; is-bsdf and recording-csv write one table), the
    is-bsdf BTDF centred on the `btdf_centre` direction, the radiance-xml `structure` (klems,
    tensor-tree) and tree `depth` (None: from the narrowest lobe), `wavelength_nm` (radiance-xml:
    the one written; reading an IS-BSDF file that does not state it: its wavelength), `n` the
    dielectric's index for a measured file that does not state it."""

    table: Path
    out: Path
    format: str
    incident_from: str | None = None
    btdf_centre: str = "refracted"
    structure: str = "klems"
    depth: int | None = None
    wavelength_nm: float | None = None
    n: float | None = None


@dataclass(frozen=True)
class ExportOutput:
    """The files written; `lines`, what the job says it wrote (for stdout); `notes`, the lines of its
    warnings and notes (for stderr, each beginning "relief: ")."""

    written: list
    lines: list = field(default_factory=list)
    notes: list = field(default_factory=list)


def table_rows(table):
    """Recording with one row per (wavelength, incidence, side, scatter cell) of the table."""
    from relief_bsdf.io.recording import Recording
    W, I, P, K, S, A = table.values_per_sr.shape
    grids = np.meshgrid(table.wavelength_nm, table.theta_i_deg, table.phi_i_deg % 360.0, np.arange(K),
                        table.theta_s_deg, table.phi_s_deg % 360.0, indexing="ij")
    wl, ti, pi, k, ts, ps = (g.ravel() for g in grids)
    sigma = table.sigma_per_sr.ravel() if table.sigma_per_sr is not None else np.full(wl.size, np.nan)
    return Recording(wavelength_nm=wl, theta_i_deg=ti, phi_i_deg=pi, side=np.where(k == 0, "R", "T"),
                     theta_s_deg=ts, phi_s_deg=ps, bsdf_sr=table.values_per_sr.ravel().astype(float),
                     sigma_sr=sigma)


def _write_recording_csv(job: ExportJob, table, out: Path) -> str:
    from relief_bsdf.io.recording import write_recording
    rec = table_rows(table)
    if np.any(~np.isfinite(rec.bsdf_sr)) or np.any(rec.bsdf_sr < 0):
        raise InputError(job.table, "table holds negative or non-finite BSDF values; cannot write a recording")
    comments = [f"exported from {job.table} (method {table.method}, light from {table.incident_from})",
                "rows are scatter-cell centres; values are cell averages in 1/sr",
                "specular (delta) parts are not rows: wavelength_nm, theta_i_deg, phi_i_deg, specular_R, specular_T"]
    for w, wl in enumerate(table.wavelength_nm):
        for i, ti in enumerate(table.theta_i_deg):
            for p, pi in enumerate(table.phi_i_deg):
                comments.append(f"specular {wl:g}, {ti:g}, {pi % 360:g}, {table.specular_R[w, i, p]:.6g}, "
                                f"{table.specular_T[w, i, p]:.6g}")
    write_recording(out, rec, comments=comments)
    return (f"wrote {out}: {len(rec)} rows ({table.wavelength_nm.size} wavelength(s), "
            f"{table.theta_i_deg.size * table.phi_i_deg.size} incidence(s), light from {table.incident_from})")


def azimuth_notes(tables, fmt: str) -> list:
    """One warning line when the file will describe an isotropic boundary although the table is not:
    a table with one incidence azimuth is turned to every orientation by its consumers, which is
    only right when its normal-incidence lobe is round (`lobe_anisotropy` > 1.2: it is not)."""
    from relief_bsdf.io.radiance_xml import lobe_anisotropy
    for t in tables:
        ratio = lobe_anisotropy(t)
        if t.is_isotropic and ratio is not None and ratio > LOBE_ANISOTROPY_WARN:
            return [f"relief: warning: {fmt} from one incidence azimuth describes an isotropic boundary, but the "
                    f"table's normal-incidence lobe is {ratio:.2g}x wider along one axis; the azimuthal dependence "
                    "is dropped (reconstruct with --phi-i-deg 0,45,90,135,... to keep it)"]
    return []


def run_export(job: ExportJob, progress: Progress | None = None, cancel: CancelToken | None = None) -> ExportOutput:
    from relief_bsdf.io.measured import export_rows, is_measured
    from relief_bsdf.io.tables import pick_table, read_table_file
    out = Path(job.out)
    if job.format not in FORMATS:
        raise InputError("--format", f"unknown format {job.format!r}; choose from {', '.join(FORMATS)}")
    if job.depth is not None and not 1 <= job.depth <= 8:
        raise InputError("--depth", f"tensor-tree depth must be 1..8, got {job.depth}")
    if job.format == "recording-csv" and Path(job.table).is_file() and is_measured(job.table):
        export_rows(job.table, out, job.wavelength_nm, job.n)     # the file's own readings (io.measured)
        return ExportOutput([out])
    tables = read_table_file(job.table, wavelength_nm=job.wavelength_nm if job.format != "radiance-xml" else None,
                             n=job.n)
    check(cancel, "writing")
    if job.format == "radiance-xml":
        return _radiance_xml(job, tables, out)
    if job.format == "hdf5":
        from relief_bsdf.io.hdf5 import save_tables
        save_tables(out, tables)
        sides = ", ".join(t.incident_from for t in tables)
        return ExportOutput([out], [f"wrote {out}: {len(tables)} table(s) ({sides})"])
    table = pick_table(tables, job.incident_from, job.table)
    notes = azimuth_notes([table], job.format)
    if job.format == "recording-csv":
        return ExportOutput([out], [_write_recording_csv(job, table, out)], notes)
    from relief_bsdf.io.isbsdf import export_isbsdf
    written = list(export_isbsdf(table, out, btdf_centre=job.btdf_centre))
    return ExportOutput(written, [f"wrote {p}" for p in written], notes)


def _radiance_xml(job: ExportJob, tables, out: Path) -> ExportOutput:
    from relief_bsdf.io.radiance_xml import checkbsdf_reciprocity, write_radiance_xml
    notes: list = []
    write_radiance_xml(out, tables, wavelength_nm=job.wavelength_nm, structure=job.structure, depth=job.depth,
                       notes=notes)
    warned = azimuth_notes(tables, job.format)
    rec = checkbsdf_reciprocity(out)
    if rec:
        notes.append("note: checkBSDF reciprocity, mean (max) %: " + ", ".join(
            f"{k} {v[1]:.1f} ({v[2]:.0f})" for k, v in rec.items())
            + f" (transmission differs by n^2 by design between the two media; a table of "
            f"{len(tables[0].theta_i_deg)} incidences, interpolated between them, is only as reciprocal as "
            "that interpolation: tabulate every 5-10 deg to bring it down; io/radiance_xml doc)")
    return ExportOutput([out], [f"wrote {out} ({job.structure}, front = light from outside, back = light from inside)"],
                        warned + [f"relief: {line}" for line in notes])
