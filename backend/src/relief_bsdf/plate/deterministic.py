"""The deterministic engine of the plate: radiative transfer between the faces' boundary tables.

Entry point: `run(experiment, rows, grid)` (used by `plate.simulate`): the Experiment's faces give
their tables (`plate.faces`), `solver_of` places them on the engine's two-face system, the rows
are read by the one detector (`plate.detector`).  The Experiment is the engine's only input: `setup_of`
adds the engine's own choices for it (`plate.setup.EngineSetup`); `PlateSolver` / `simulate_rows` work
on tables directly (tests, benchmarks).

Geometry (formats.md frame): the plate fills -t < z < 0, the lit face is z = 0, light comes
from z > 0.  The first face (the relief, or the front face when the relief is on the back) is
described by two `BsdfTable`s (light from outside, light from inside), each at one phi_i; a row lit
from incidence azimuth phi_i reads the outside table turned by phi_i, and from the far half of
azimuths (90 < phi_i < 270 in the sample's frame: a tilt at normal incidence, a scan lit from 180)
the outside table of the relief turned by a half turn (`PlateSolver.half_turn`, exact for one tile:
`plate.faces.half_turned_outside`); the second face is flat (exact cell-averaged Fresnel) or carries its
own inside table (its delta part replaces Fresnel and its cells add a second diffuse kernel K_B).  With the
relief on the back face the system is solved with the roles swapped (same equations).

Bulk.  Without volume scattering a traversal at internal angle theta keeps exp(-a t / cos theta)
(Beer-Lambert, diagonal).  With scattering (mu_s > 0, Henyey-Greenstein g) the traversal is the
slab's reflection and transmission operators per azimuthal mode (`plate.slab`, adding-doubling),
combined with the faces by the adding equations (`_slab_system`); delta beams are attenuated by
a + mu_s,j and shed what the slab scatters out of them as diffuse sources (`_slab_sources`).
Approximation: scalar phase function on S0, Stokes vector carried unchanged by a volume event.
Source polarisation: Stokes (1, q, 0, 0), q in [-1, 1] (`Instrument.polarization_q`).

Method (radiative transfer between two faces, discrete ordinates):

* Internal directions are discretised into rings of the inside table's theta cells and a
  uniform azimuth grid (A cells, centres at multiples of 360/A relative to the propagation
  azimuth of the incident beam).  The state is the power per cell (fraction of the incident
  power) leaving the rough face into the plate, X.  One round trip (absorb, reflect at the
  flat face with Fresnel R_F, absorb, scatter back at the rough face with the inside table's R
  cells K) gives X = S + K A R_F A X, so X = (I - K A R_F A)^-1 S: every internal
  reflection, including light trapped by total internal reflection (R_F = 1) that escapes
  after further scattering, is summed exactly (no truncated series).
* Isotropy makes K circulant in azimuth: a real FFT over the azimuth axis block-diagonalises
  it (azimuthal reduction), so the solve is A/2+1 small (N x N) systems instead of one
  (N A) x (N A) system.  A finite tile is never quite isotropic: the one table a ray-traced relief
  gives this loop can average the incidence azimuths around its own
  (`TableGrid.inside_azimuth_spread_deg`, `plate.faces.inside_face`; +-45 deg by default).  An anisotropic
  relief traced by rays gives its inside table over twelve incidence-azimuth sectors (every 15 deg
  by default, each the average over its sector, `inside_sectors`, `TableGrid.sector_step_deg`): light
  at propagation azimuth delta then scatters by the table of its sector, K = K_0 + sum_k (K_k - K_0) P_k
  is not circulant, and the loop is solved by GMRES preconditioned by the circulant system
  (`_sector_loop`).
* The delta parts of the tables (specular reflection and transmission of the flat fraction of
  the relief, or a flat face) are kept apart as exact beams: their chain between the faces is
  a 4x4 geometric series (Mueller matrices), and what they scatter diffusely feeds S.
* Polarisation: Stokes vectors (S0, S1 = I_s - I_p, S2, S3) in the s/p basis of the plane
  (direction, z) (bsdf.py frames).  At a flat face this plane is the plane of incidence, so
  Fresnel Mueller matrices (optics.mueller_interface) apply without rotation and a flat plate
  is exact for s and p separately.  When the tables carry Mueller matrices the diffuse loop
  runs on 4-vectors; otherwise the tables are taken as polarisation independent and
  *depolarising* for their diffuse part (M = f diag(1,0,0,0)) and polarisation preserving for
  their specular part (M = p I), and the diffuse loop is scalar (exact under that assumption,
  since the flat face's polarisation is destroyed at the next rough interaction).
* Output: the plate BSDF on an outgoing grid (theta cells x azimuth grid) per side, plus
  delta beams; rows are read by `plate.detector.grid_reading` (cone (x) Gaussian blur
  quadrature for the diffuse part, response(psi) P / (Omega cos theta_s) for a delta beam).
* Two grids (plate.grid).  When the outside table is on a finer grid than the
  engine's (`TableGrid` direct grid: 0.5-deg rings with the flat face's Snell pre-images, 1-deg
  azimuth cells around the plane of incidence), the loop is solved on the engine grid with the
  outside table's cell averages there (`_TableView.cells`: projected-solid-angle overlaps, power
  kept), and the two terms that carry the narrow lobes are read from the outside table's own
  cells: the direct reflection f_R and the first transmitted pass, which leaves through the flat
  face as f_T(theta_int) T_F(theta_int) (n0/n)^2 exp(-a t / cos theta_int) at the Snell
  pre-image theta_int of each exit direction (the radiance law; the same terms the engine grid
  carries, `_flat_exit`, subtracted there).  Applies with a flat second face and no volume
  scattering (otherwise everything is read on the engine grid, as before).  In the loop the first
  transmission is then only the source of the later passes, and its cell averages enter as point
  sources at the azimuth cells' centres weighted by the centre values (`detector.centre_values`,
  unclipped: each ring's power kept): a 5-deg cell's averaging would otherwise widen a lobe that is
  narrow across the plane of incidence by the cell's variance d^2 / 12 once more at every later exit
  (Sheppard's correction).  Measured against the independent photon Monte Carlo
  (bench_forward_accuracy): the real measured map's second pass (R minus the R of an opaque
  plate) reads 7 % low at 30 and 60 deg without it, 3.9 / 3.7 % with it (in-lobe R level 0.96 -> 0.98, rms z 1.35 ->
  1.18), nearly what 2.5-deg engine cells give (3.6 / 2.8 %) without their 1.2-1.5x cost.

Regime of validity: geometric optics between the faces (plate thick compared with the
coherence length: intensities add, no thin-film fringes), laterally infinite plate
(no edge loss), translation-invariant faces (the relief's statistics do not vary over the
lit spot), discretisation error of the order of the table's cell size (the direct grid's for the
direct terms, the engine grid's for the loop).
"""
from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.errors import InputError
from relief_bsdf.plate.faces import (FlatFace, MicrofacetFace, ReliefFace, TableFace, anisotropic_face, beam_in_table,
                                     half_turned_outside, inside_sectors, isotropy_warning, material_key)
from relief_bsdf.plate.faces.derive import _derive_outside
from relief_bsdf.plate.faces.sectors import _resolved_relief
from relief_bsdf.plate.memory import current_memory
from relief_bsdf.plate.readout import beam_incidences, beam_split, simulate_rows
from relief_bsdf.plate.reuse import _note_request, _reused_solver, drop_sector_table, held_for_request, refresh_solver
from relief_bsdf.plate.rows import azimuth_key, far_side, to_sample_frame
from relief_bsdf.plate.setup import EngineSetup
from relief_bsdf.plate.solver import PlateSolver


def setup_of(experiment: Any, grid: Any, rough_face: str = "front", beam_in_tables: bool = False) -> EngineSetup:
    """How this engine solves an Experiment on `grid` (`EngineSetup`: the experiment and the engine's choices);
    `beam_in_tables`: the front's outside table holds the beam divergence (`front_traces_beam`)."""
    return EngineSetup(experiment, rough_face=rough_face, azimuth_cells=grid.azimuth_cells,
                       relief_anisotropic=relief_anisotropic(experiment), beam_in_tables=bool(beam_in_tables),
                       inside_interpolation=grid.inside_interpolation, stokes_loop=grid.stokes_loop)


def relief_anisotropic(experiment: Any) -> bool:
    """Whether a face's relief is anisotropic beyond what isotropic tables stand for
    (`plate.faces.anisotropic_face`, the one test of it)."""
    return any(anisotropic_face(f) for f in (experiment.plate.front, experiment.plate.back))


def sample_incidences(experiment: Any, rows: Any, beam_traced: bool = False
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(wavelengths, theta, phi) of every outside incidence the engine solves for these rows, in the
    sample's frame: the rows' own, or under a sample tilt those the tilted sample sees; with a beam
    divergence the quadrature's incidences too, unless the outside table traces the beam itself
    (`beam_traced`, `front_traces_beam`); theta and phi one entry per incidence (not unique)."""
    wl = np.unique(np.asarray(rows.wavelength_nm, float))
    ti = np.abs(np.asarray(rows.theta_i_deg, float))
    pi = np.asarray(rows.phi_i_deg, float) + 0 * ti
    beam = 0.0 if beam_traced else experiment.instrument.beam_divergence_deg
    tilt = experiment.instrument.tilt_deg
    tq = pq = None
    if beam > 0:                      # the nominal incidences (delta parts) and the quadrature's
        tq, pq = (a.ravel() for a in beam_incidences(ti, pi, beam))
    q = 0 if tq is None else tq.size // max(ti.size, 1)
    if tilt:
        if tq is not None:
            tq, pq = to_sample_frame(tq, pq, np.full(tq.shape, "R"), tilt)
        ti, pi = to_sample_frame(ti, pi, np.full(ti.shape, "R"), tilt)
        ti, pi = np.round(ti, 9), np.round(pi, 9)
    if tq is not None:
        if relief_anisotropic(experiment):          # solved in the nominal plane (beam_split)
            tq, pq = beam_split(tq, pq, np.repeat(ti, q), np.repeat(pi, q))[:2]
        ti = np.concatenate([ti, np.round(tq, 9)])
        pi = np.concatenate([pi, np.round(pq, 9)])
    return wl, ti, pi


def table_incidences(experiment: Any, rows: Any, beam_traced: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(wavelengths, outside incidences) the faces' tables need for these rows (`sample_incidences`,
    every azimuth: the phi_i = 0 table serves any row where no half-turned table is made)."""
    wl, ti, _ = sample_incidences(experiment, rows, beam_traced)
    return wl, np.unique(ti)


def solver_of(experiment: Any, rows: Any, grid: Any, progress: Any = None, keep: bool = True) -> PlateSolver:
    """PlateSolver of an Experiment: the faces' tables placed on the engine's two-face system.

    Front non-flat: its (outside, inside) tables, the back face's inside table if it is not flat.
    Front flat, back non-flat: relief-on-back system (the back face's inside table).  Both flat:
    the flat face's Fresnel tables on the front.  A flat back face uses the engine's exact
    cell-averaged Fresnel (no table).  `keep` False: a new solver is not kept for reuse
    (`_reused_solver`; one-off tables such as the model sigma's perturbed draws).

    Before any table is derived, a held solver made for the same tables is looked up by what determines
    those tables (`request_key`: the faces' content, material, grid, wavelengths, incidences): a hit
    derives, resamples and even holds no table (`held_for_request`; its sector table may be gone,
    `drop_sector_table`)."""
    p = experiment.plate
    mat = p.material
    traced = front_traces_beam(experiment, rows, grid)
    memory = current_memory()
    request = request_key(experiment, rows, grid, traced) if keep else None
    front, back = p.front, p.back
    relief_on_back = front.is_flat and not back.is_flat
    model = setup_of(experiment, grid, "back" if relief_on_back else "front", traced)
    if request is not None:
        held = held_for_request(memory, request, model)
        if held is not None:
            return held
    wl, ti = table_incidences(experiment, rows, traced)
    if relief_on_back:
        _, b_in = back.tables(mat, grid, wl, ti, need_outside=False, progress=progress)
        solver = _reused_solver(model, b_in, None, None, keep=keep)
        _note_request(memory, request, solver, None)
        return solver
    f_out, f_in = front_tables(experiment, grid, wl, ti, traced, progress)
    b_in = None if back.is_flat else back.tables(mat, grid, wl, ti, need_outside=False, progress=progress)[1]
    sectors = inside_sectors(front, mat, grid, wl, ti, progress) if b_in is None else None
    solver = _reused_solver(model, f_in, f_out, b_in, sectors, keep)
    solver.half_turn = None
    t_out = half_turn_table(experiment, rows, grid, traced, progress)
    if t_out is not None:           # the same loop tables: only the outside part is new (`with_outside`)
        half = _reused_solver(model, f_in, t_out, b_in, sectors, keep)
        half.half_turn = None
        solver.half_turn = half
    solver.turned = {}
    for a, t in turned_tables(experiment, rows, grid, traced, progress).items():
        s = _reused_solver(model, f_in, t, b_in, sectors, keep)
        s.half_turn, s.turned = None, {}
        solver.turned[a] = s
    _note_request(memory, request, solver, solver.half_turn)
    return solver


def _face_token(face: Any) -> tuple | None:
    """What determines a face's tables, without deriving them (None: a face this does not know)."""
    if isinstance(face, FlatFace):
        return ("flat",)
    if isinstance(face, ReliefFace):
        return face.cache_key()
    if isinstance(face, MicrofacetFace):
        return ("microfacet", float(face.alpha), face.distribution, int(face.samples))
    if isinstance(face, TableFace):     # the tables themselves: a held solver holds them, so their ids stay theirs
        return ("table faces", id(face.inside), id(face.outside), id(face.half_turned))
    return None


def request_key(experiment: Any, rows: Any, grid: Any, traced: bool) -> tuple | None:
    """Everything that determines the tables `solver_of` places for these rows (faces' content, material,
    grid, wavelengths, the outside incidences of both half-turns, the beam traced into the outside table),
    computed without deriving a table; None where a face is of a kind this does not know."""
    p = experiment.plate
    faces = (_face_token(p.front), _face_token(p.back))
    if None in faces or turned_azimuths(experiment, rows, grid, traced):
        return None             # a face this does not know, or tables turned per azimuth: found by their keys
    wl, t_all, p_all = sample_incidences(experiment, rows, traced)
    far = tuple(float(t) for t in np.unique(t_all[far_side(t_all, p_all)]))
    beam = float(experiment.instrument.beam_divergence_deg) if traced else 0.0
    return ("request",) + faces + (material_key(p.material), repr(grid), tuple(float(w) for w in wl),
                                   tuple(float(t) for t in np.unique(t_all)), far, beam)


def half_turn_table(experiment: Any, rows: Any, grid: Any, traced: bool, progress: Any = None) -> BsdfTable | None:
    """The front face's half-turned outside table (`plate.faces.half_turned_outside`) at the incidences of
    these rows that the sample sees from the far half of azimuths (`far_side`), or None (none there, or a
    face without a relief to turn)."""
    wl, t_all, p_all = sample_incidences(experiment, rows, traced)
    far = np.unique(t_all[far_side(t_all, p_all)])
    if not far.size:
        return None
    beam = experiment.instrument.beam_divergence_deg if traced else 0.0
    return half_turned_outside(experiment.plate.front, experiment.plate.material, grid, wl, far, progress, beam)


TURNED_MAX = 8      # the most incidence azimuths given an outside table of their own (beyond: the turned table)


def turned_azimuths(experiment: Any, rows: Any, grid: Any, traced: bool) -> tuple:
    """The incidence azimuths (sample frame, `azimuth_key`) whose rows read an outside table traced from that
    azimuth (`turned_tables`): those other than 0 and 180 deg, for a front relief traced by rays, at most
    TURNED_MAX of them (else none: the rows read the turned phi_i = 0 table).

    Why: the engine reads a row lit from azimuth phi_i as its phi_i = 0 table turned by phi_i, exact for
    the ensemble of a relief whose statistics do not change under rotation.  A relief with a four-fold
    (or any other) structure that its rms-slope tensor cannot see turns into another relief: a square
    top-hat lobe turned by 45 deg is a diamond; at normal incidence, where phi_i only names the plane the
    source's polarisation is referred to, the lobe would turn with that name.  The ray method traces the
    relief lit from phi_i itself (option `phi_i_turn_deg`: the beam and its polarisation turned, the exits
    turned back), exact for any tile; 180 deg keeps the half-turned relief (docs/decisions/002)."""
    p = experiment.plate
    if not isinstance(p.front, ReliefFace) or p.front.method not in ("ray", "auto"):
        return ()
    wl, t_all, p_all = sample_incidences(experiment, rows, traced)
    out = tuple(float(a) for a in np.unique(azimuth_key(p_all)) if a not in (0.0, 180.0))
    if not out or len(out) > TURNED_MAX:
        return ()
    face = _resolved_relief(p.front, p.material, grid, wl, np.unique(t_all))
    return out if face is not None and face.method == "ray" else ()


def turned_tables(experiment: Any, rows: Any, grid: Any, traced: bool, progress: Any = None) -> dict:
    """{azimuth: the front relief's outside table for light arriving from that azimuth, in the frame of its
    incidence} at the incidences of the rows lit from it (`turned_azimuths`)."""
    azimuths = turned_azimuths(experiment, rows, grid, traced)
    if not azimuths:
        return {}
    p = experiment.plate
    wl, t_all, p_all = sample_incidences(experiment, rows, traced)
    face = _resolved_relief(p.front, p.material, grid, wl, np.unique(t_all))
    beam = experiment.instrument.beam_divergence_deg if traced else 0.0
    az = azimuth_key(p_all)
    out = {}
    for a in azimuths:
        theta = np.unique(t_all[az == a])
        turned = replace(face, options={**face.options, "phi_i_turn_deg": a})
        out[a] = _derive_outside(turned, p.material, grid, wl, theta, progress, beam)
    return out


def front_traces_beam(experiment: Any, rows: Any, grid: Any) -> bool:
    """Whether the front face's outside table holds the source's beam divergence itself: a relief
    traced by rays draws each ray's incidence from the beam (methods.ray, option beam_divergence_deg),
    exact for any relief, isotropic or not, and one table per nominal incidence instead of the
    quadrature's BEAM_RINGS x BEAM_AZIMUTHS; other methods (wave optics, surrogates) give tables of
    single incidences, which `simulate_rows` sums over the quadrature."""
    beam = experiment.instrument.beam_divergence_deg
    front = experiment.plate.front
    if beam <= 0 or front.is_flat or not hasattr(front, "traces_beam"):
        return False
    wl, ti = table_incidences(experiment, rows, True)
    if not front.traces_beam(experiment.plate.material, grid, wl, ti):
        return False
    held = beam_in_table(getattr(front, "outside", None))
    if held and abs(held - beam) > 1e-9:
        raise InputError("instrument.beam_divergence_deg",
                         f"the front face's outside table was traced with a beam divergence of {held:g} deg, "
                         f"the instrument states {beam:g} deg")
    return True


def front_tables(experiment: Any, grid: Any, wl: Any, ti: Any, traced: bool, progress: Any = None) -> tuple:
    """(outside, inside) tables of the front face, the beam traced into the outside one when `traced`."""
    p = experiment.plate
    beam = experiment.instrument.beam_divergence_deg if traced else 0.0
    return p.front.tables(p.material, grid, wl, ti, need_outside=True, progress=progress, beam_divergence_deg=beam)


def run(experiment: Any, rows: Any, grid: Any, progress: Any = None, where: str = "recording",
        keep_solver: bool = True) -> tuple[np.ndarray, dict]:
    """Deterministic plate BSDF of an Experiment on every row (detector included) and what was used;
    `keep_solver` False: its solver is not kept for reuse (`solver_of`)."""
    import warnings
    solver = solver_of(experiment, rows, grid, progress, keep_solver)
    t0 = time.perf_counter()
    vals = simulate_rows(solver.model, solver.inside, solver.outside, rows, solver=solver, where=where)
    if keep_solver:                          # the kernels exist: the sector table goes before the solver is measured
        drop_sector_table(solver)
    for s in (solver, solver.half_turn, *solver.turned.values()):
        if s is not None:
            refresh_solver(s, time.perf_counter() - t0)
    info = {"engine": "deterministic", "grid": grid.describe()}
    sectors = solver.inside_sectors
    if sectors is not None:                  # the loop meets the relief by azimuth sector (plate.faces.inside_sectors)
        spread = sectors.metadata.get("request", {}).get("options", {}).get("phi_i_spread_deg", 0.0)
        info["inside_sectors"] = {"centres_deg": [float(p) for p in sectors.phi_i_deg],
                                  "each": (f"the inside table averaged over its sector's incidence azimuths, +-{spread:g} deg"
                                           if spread else "the inside table at the sector's centre")}
    notes = [w for w in (isotropy_warning(f) for f in (experiment.plate.front, experiment.plate.back)) if w]
    for w in notes:
        warnings.warn(w, RuntimeWarning, stacklevel=2)
    if notes:
        info["warnings"] = notes
    return vals, info
