"""A relief face's tables by its method (`methods.reconstruct`, or the ray tracer on this process's threads),
kept by the forward model's one memory owner (`plate.memory.current_memory()`) under everything that
determines them: the relief's content digest, method, options, grid, material, wavelengths, incidences,
samples, seed."""
from __future__ import annotations

import json
from dataclasses import replace
from typing import Any

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.index import Material
from relief_bsdf.methods import entry, reconstruct
from relief_bsdf.parallel import current_settings, in_worker, parallel_settings
from relief_bsdf.plate.energy import closed
from relief_bsdf.plate.faces.base import _grid_key, material_key, relief_digest
from relief_bsdf.plate.grid import TableGrid
from relief_bsdf.plate.memory import current_memory
from relief_bsdf.surface.relief import Relief


TRACED_METHODS = ("ray",)          # methods whose photons trace the relief itself


THREADED_METHODS = ("microfacet",)  # analytic tables computed on this process's threads (numpy releases the GIL):


def _derive_outside(face: "ReliefFace", material: Material, grid: TableGrid, wavelengths_nm: Any,
                    theta_i_outside_deg: Any, progress: Any = None, beam_divergence_deg: float = 0.0) -> BsdfTable:
    """The outside table of a relief face whose method is resolved (`_derive`'s outside side, cached on its own)."""
    wl = tuple(float(w) for w in np.unique(np.asarray(wavelengths_nm, float)))
    th = tuple(float(t) for t in np.unique(np.asarray(theta_i_outside_deg, float)))
    beam = float(beam_divergence_deg) if face.method == "ray" else 0.0
    key = (face.cache_key(), material_key(material), _grid_key(grid), wl, "outside", th)
    return current_memory().get(key + (("beam", beam) if beam else ()),
                           lambda: _reconstruct_side(face, material, grid, wl, th, "outside", progress, beam))


def same_indices(material: Material, wavelengths_nm: Any, side: str) -> tuple[tuple, tuple]:
    """(representative wavelengths, ascending; the row of each wavelength among them): wavelengths whose
    index pair (light from `side`) is the same share one, the longest of them (a method's wavelength
    checks, such as the ray tracer's tile of at least so many wavelengths, see the longest)."""
    ws = [float(w) for w in wavelengths_nm]
    pair = [tuple(complex(x) for x in material.n_pair(w, side)) for w in ws]
    rep = {p: max(w for w, q in zip(ws, pair) if q == p) for p in pair}
    reps = tuple(sorted(set(rep.values())))
    return reps, tuple(reps.index(rep[p]) for p in pair)


def _reconstruct_side(face: "ReliefFace", material: Material, grid: TableGrid, wl: Any, theta: Any, side: str,
                      progress: Any, beam_divergence_deg: float = 0.0, phi_i_deg: tuple = (0.0,)) -> BsdfTable:
    """The face's table of light from `side`.  A geometric-optics method (`MethodEntry.wavelength_free`)
    traces once per distinct index pair: wavelengths where the indices are the same (no dispersion
    given) share the table traced at the longest of them (`same_indices`, `BsdfTable.at_wavelengths`):
    the same physics with the same random numbers, a third of the work for a recording at three
    wavelengths."""
    reps, rows = same_indices(material, wl, side)
    if len(reps) < len(tuple(wl)) and entry(face.method).wavelength_free:
        table = _reconstruct_side(face, material, grid, reps, theta, side, progress, beam_divergence_deg, phi_i_deg)
        return table.at_wavelengths(tuple(float(w) for w in wl), rows)
    req = face_request(face, material, grid, wl, theta, side)
    if beam_divergence_deg:
        req = replace(req, options={**req.options, "beam_divergence_deg": float(beam_divergence_deg)})
    if tuple(phi_i_deg) != (0.0,):
        req = replace(req, phi_i_deg=tuple(float(p) for p in phi_i_deg))
    if face.coherence_length_m is not None:
        req = replace(req, coherence_length_m=float(face.coherence_length_m))
    if face.method in TRACED_METHODS and _trace_here(face):
        from relief_bsdf.methods.ray.method import reconstruct_with
        req = replace(req, options={**req.options, "backend": "serial"})
        (table,) = reconstruct_with(_topology_tracer(face.relief, req), face.relief, material, req, progress=progress)
        return table
    if face.method in THREADED_METHODS and _trace_here(face):
        with parallel_settings(backend="serial"):          # threads here, no worker pool to start
            (table,) = reconstruct(face.relief, material, req, face.method, progress=progress)
    else:
        (table,) = reconstruct(face.relief, material, req, face.method, progress=progress)
    return closed(table)          # a wave model's energy defect is the model's, not absorption (plate.energy)


def face_request(face: "ReliefFace", material: Material, grid: TableGrid, wavelengths_nm: Any, theta: Any,
                 side: str) -> Any:
    """The Request a relief face's tables are made with on `grid` (TableGrid.request): the outside side on
    the direct grid with the glass's exit-side edges.

    The direct grid may have more cells than the tile has facets (a 96 x 96 tile: 18 k facets, the
    direct grid ~60 k cells).  A flat facet sends a delta, so a small tile's BSDF is a sum of deltas
    whatever the cells; what the plate reads from these cells is their integral over a detector cone
    (~50 direct cells), not single cells, so the ray tables are asked for them anyway (ray option
    sparse_cells) rather than falling back to coarse cells, whose width broadens a narrow lobe
    (the reason for the direct grid).  Each cell's tile-realisation sigma says how little one cell
    is worth; the cone integral averages them."""
    options = dict(face.options)
    max_cells = 2 * face.relief.shape[0] * face.relief.shape[1]
    if side == "outside" and face.method == "ray":
        options["sparse_cells"], max_cells = True, None
    return grid.request(wavelengths_nm, theta, side, face.method, face.samples, face.seed, options,
                        index_ratio=_index_ratio(material, wavelengths_nm), max_cells=max_cells)


def _index_ratio(material: Material, wavelengths_nm: Any) -> float:
    """n_glass / n_outside at the middle wavelength (the exit-side edges of the direct grid)."""
    w = float(np.median(np.asarray(wavelengths_nm, float)))
    return float(np.real(material.inside.n(w)) / np.real(material.outside.n(w)))


def _trace_here(face: "ReliefFace") -> bool:
    """Trace a relief face's tables in this process (threads on one reused tracer; THREADED_METHODS on
    threads too) unless the run is spread over Dask or the face names its own backend: a fit re-traces
    the same grid with new heights every evaluation, and one tracer whose heights are rewritten in place (BVH refitted)
    costs ~0.03 s where worker processes rebuild a BVH each (~0.5-1 s per worker per side)."""
    if in_worker() or face.options.get("backend") is not None:
        return False
    return current_settings().backend not in ("dask",) and not current_settings().dask


def _topology_tracer(relief: Relief, request: Any) -> Any:
    """This process's ReliefTracer for the relief's grid (shape, pitch, periodicity, mesh options),
    its heights set to `relief` (`ReliefTracer.update_heights`: z rewritten, BVH refitted in place;
    `with_heights` where the Embree buffers are embreex's own), kept by the memory owner."""
    from relief_bsdf.methods.ray import ReliefTracer
    opts = request.options_for("ray")
    key = ("topology tracer", relief.shape, float(relief.dx_m), float(relief.dy_m), bool(relief.periodic),
           opts.max_bounces, json.dumps(opts.fill_holes))
    memory = current_memory()
    tr = memory.peek(key)
    if tr is None:
        tr = ReliefTracer(relief, opts.max_bounces, opts.fill_holes)
    elif tr.relief is not relief and relief_digest(tr.relief) != relief_digest(relief):
        try:
            tr.update_heights(relief)
        except RuntimeError:                 # buffers owned by embreex: a new scene on the same topology
            tr = tr.with_heights(relief)
    memory.put(key, tr, "tracer")
    return tr
