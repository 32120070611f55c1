"""`reconstruct(relief, material, request) -> [BsdfTable]` of the ray method: checks, tasks, tables.

Each (side, wavelength, incidence) is one `parallel.map_tasks` task (`_incidence_task`), so
local processes and `--dask` spread them; a worker builds the BVH once (`parallel.worker_cached`,
keyed by a digest of the heights and mesh options) and traces with one thread, while in this
process (serial backend, or a single incidence) every core works: on the chunks of one task at a
time, or, when a task has fewer chunks than there are threads (an inside table's many small
incidences), on several tasks at once (`map_tasks(..., threads=)`).  Rays are
traced in fixed chunks of CHUNK (own seed each: `parallel.task_rng(seed, side, wavelength,
theta, phi, chunk)`) whose sums are added in chunk order, so the numbers do not depend on the
backend, worker or thread count.  The beam's entry points are stratified over the tile and
sorted by 32 x 32 px blocks (BVH coherence).  A task returns its finished float32 table rows
(built by the one table builder, `bsdf.builder`), written straight into the tables.

Detector: every ray leaves the relief layer (above its highest or below its lowest point,
moving away); exits are binned into the request's (theta_s, phi_s) cells (builder: cell
averages in projected solid angle, 1/sr, so `BsdfTable.hemispherical()` equals the power
fractions of the incident beam, which irradiates the tile uniformly on the mean plane).  Exits
within `specular_tol_rad` of the mean plane's mirror / refraction direction (exactly flat
facets) go to the delta parts.  Max bounces, absorption, numerical leaks and exits outside
the table's cells are counted in `lost` with the detail in metadata.
Uncertainty: sigma = Monte-Carlo noise (per path) combined with the realisation uncertainty
of the finite tile (option tile_uncertainty, default True): every path is tagged with the
sub-tile of its first hit (a grid of sub-tiles at least SUBTILE_CORR correlation lengths wide,
up to MAX_SUBTILES per axis; a mirror-extended measured map folded back onto the map) and the
builder's sub-tile batch-means estimate (bsdf.builder module doc) adds the scatter that another
tile of the same statistics would give.  When the lobe's cells scatter by more than
TILE_WARN_REL between realisations (too few correlation areas for the cells asked for) the
table's metadata["warnings"] says so (and a RuntimeWarning is issued).
Frames: physical s = z x k, p = s x k; for light from inside the table's frame is mirrored
(z -> -z, bsdf/table.py), which maps the basis (s, p) to (s', -p'): M_table = D M D,
D = diag(1, 1, -1, -1).
"""
from __future__ import annotations

import math
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from relief_bsdf import kernels
from relief_bsdf.bsdf.builder import CellAccumulator, CellIndex, ExitSamples, specular_flags
from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.frames import beam_directions, cross_rows, direction, dot_rows, normalize, rotate_z_rows
from relief_bsdf.core.stokes import rotate_stokes_columns_cd, s_axis, s_axis_rows
from relief_bsdf.errors import RequestError
from relief_bsdf.methods.options import RayOptions
from relief_bsdf.methods.ray.cells import cell_index
from relief_bsdf.methods.ray.exits import BELOW, STATE_NAMES, Exits
from relief_bsdf.methods.realisation import MAX_SUBTILES, SUBTILE_CORR  # noqa: F401  (module doc)
from relief_bsdf.methods.realisation import subtile_grid as _subtile_grid
from relief_bsdf.methods.ray.tracer import CHUNK, ReliefTracer, cached_tracer, forget_tracer, relief_hash
from relief_bsdf.methods.ray.transport import ALONG_Z_XY2, Media, Rays, TraceSettings, carrier_for, trace_chunk
from relief_bsdf.parallel.memory import trim_heap
from relief_bsdf.parallel import (default_workers, in_task_thread, in_worker, last_run, map_tasks, task_rng,
                                  worker_cached)
from relief_bsdf.progress import silent
from relief_bsdf.surface.relief import Relief

F32 = np.float32
MIN_SAMPLES_PER_SIDE = 16
MIN_WAVELENGTHS_PER_TILE = 10.0
_MIRROR_DD = np.outer([1.0, 1.0, -1.0, -1.0], [1.0, 1.0, -1.0, -1.0])
_ROWS = ("vals", "sig", "mue", "specR", "specT", "lost", "smR", "smT")
TILE_WARN_REL = 0.10          # warn when the lobe's cells scatter more than this between tile realisations


# ----------------------------------------------------------------------------- request checks


def _options(request) -> RayOptions:
    """The request's typed ray options (unknown or mistyped options: RequestError naming them)."""
    return RayOptions.from_request(request)


def check_request(relief: Relief, material, request) -> RayOptions:
    """Every reason to refuse, raised as RequestError/InputError before any tracing starts."""
    request.validate()
    opts = _options(request)
    where = relief.source or "relief"
    relief.require_valid()
    if not relief.valid.all() and opts.fill_holes in (None, False):
        raise RequestError(f"{(~relief.valid).sum()} height samples of {where} are invalid (NaN): the ray tracer "
                           "needs a closed surface; fill them: --fill-holes on the command line, `relief fill MAP "
                           "-o FILLED.x3p`, fill_holes = true under [relief] in a sample.toml, or the method option "
                           "fill_holes=true (or a largest gap in px)", where)
    ny, nx = relief.shape
    if min(nx, ny) < MIN_SAMPLES_PER_SIDE:
        raise RequestError(f"relief {where} of {ny} x {nx} samples is too small for ray tracing "
                           f"(need at least {MIN_SAMPLES_PER_SIDE} per side)", where)
    lam_max_m = max(request.wavelengths_nm) * 1e-9
    ext = min(nx * relief.dx_m, ny * relief.dy_m)
    if ext < MIN_WAVELENGTHS_PER_TILE * lam_max_m:
        raise RequestError(f"relief {where} spans {ext * 1e6:.3g} um, less than {MIN_WAVELENGTHS_PER_TILE:g} "
                           f"wavelengths ({lam_max_m * 1e9:g} nm): geometric optics does not apply; "
                           "use a wave method (kirchhoff, rayleigh-rice)", where)
    n_cells = 2 * (len(request.theta_s_edges_deg) - 1) * (len(request.phi_s_edges_deg) - 1)
    facets = 2 * nx * ny
    if facets < n_cells and not opts.sparse_cells:
        raise RequestError(f"relief {where} is too coarse for the request: its {facets} facets cannot fill "
                           f"{n_cells} scatter cells; use a larger map or coarser theta_s/phi_s cells", where)
    material.check_incidence(request.wavelengths_nm, request.incident_from)
    return opts


# ----------------------------------------------------------------------------- task context


class _RayContext:
    """What every incidence task needs, shipped once per worker (`parallel.map_tasks` context).

    `tracer` (an already built `ReliefTracer`, e.g. from `reconstruct_with`) is used where the
    tasks run in this process; it is not pickled: a worker process or Dask worker builds its own
    once (`parallel.worker_cached`, keyed by `tracer_key`).  `digest()` names everything that
    changes the numbers (checkpoint keys); the refractive indices travel with each task.
    """

    def __init__(self, relief: Relief, opts: RayOptions, request, tracer: ReliefTracer | None = None):
        self.relief = relief
        self.max_bounces = int(opts.max_bounces)
        self.fill_holes = opts.fill_holes
        self.polarized = bool(opts.polarized)
        self.first_hit_split = bool(opts.first_hit_split)
        self.cos_tol = math.cos(opts.specular_tol_rad)
        self.threads = opts.threads
        self.seed = int(request.seed)
        self.samples = int(request.samples)
        self.te = np.asarray(request.theta_s_edges_deg, float)
        self.pe = np.asarray(request.phi_s_edges_deg, float)
        self.tracer = tracer
        self.tile_uncertainty = bool(opts.tile_uncertainty)
        self.beam_divergence_deg = float(opts.beam_divergence_deg)
        self.phi_i_spread_deg = float(opts.phi_i_spread_deg)
        self.phi_i_turn_deg = float(opts.phi_i_turn_deg) % 360.0
        mesh_options = (self.max_bounces, repr(self.fill_holes))
        h = tracer.relief_key(relief, mesh_options) if tracer is not None else relief_hash(relief, mesh_options)
        self.tracer_key = ("ray.ReliefTracer", h.hexdigest())
        self.subtiles, self.corr_areas, self.corr_length_m = (
            worker_cached(("ray.subtiles", self.tracer_key[1]), lambda: _subtile_grid(relief))
            if self.tile_uncertainty else (None, None, None))
        h.update(repr((self.polarized, self.first_hit_split, float(opts.specular_tol_rad), self.seed,
                       self.samples, self.te.tolist(), self.pe.tolist(), self.subtiles)
                      + ((self.beam_divergence_deg,) if self.beam_divergence_deg else ())
                      + (("phi_i_spread", self.phi_i_spread_deg) if self.phi_i_spread_deg else ())
                      + (("phi_i_turn", self.phi_i_turn_deg) if self.phi_i_turn_deg else ())).encode())
        self._digest = h.hexdigest()

    def digest(self) -> str:
        return self._digest

    def __getstate__(self):
        d = dict(self.__dict__)
        d["tracer"] = None                       # an Embree scene does not travel: rebuilt per worker
        return d

    def threads_here(self, tracer: ReliefTracer | None) -> int:
        """Threads this process traces with: the option, else the tracer's, else every core."""
        return int(self.threads or (tracer.threads if tracer is not None else 0) or default_workers())

    def get_tracer(self) -> ReliefTracer:
        if self.tracer is not None:
            return self.tracer
        return cached_tracer(self.tracer_key, self.relief, self.max_bounces, self.fill_holes,
                             1 if in_worker() else self.threads)


def _beam_strata(n: int, Lx: float, Ly: float, block_px: float = 32.0):
    """Stratified beam: (nxs, nys) strata covering the tile, their order by 32 x 32 px blocks, and the
    row and column of each stratum in that order (`divmod(order, nxs)`, once per task, not per chunk)."""
    nxs = max(1, int(round(math.sqrt(n * Lx / Ly))))
    nys = max(1, -(-n // nxs))
    iy, ix = np.divmod(np.arange(nxs * nys, dtype=np.int64), nxs)
    bx = (ix * (Lx / nxs) // block_px).astype(np.int64)
    by = (iy * (Ly / nys) // block_px).astype(np.int64)
    order = np.argsort(by * (int(Lx // block_px) + 2) + bx, kind="stable")
    return nxs, nys, order, np.take(iy, order), np.take(ix, order)


@dataclass
class _Incidence:
    """One task's beam in the physical frame: propagation direction, media, frames, ideal directions."""

    side: str
    k_in: np.ndarray
    from_below: bool
    media: Media
    s_init: np.ndarray | None
    ideal_dirs: tuple                    # (mirror, refraction or None) of the flat mean plane
    side_of_state: tuple                 # (ABOVE ->, BELOW ->) table side
    settings: TraceSettings


def _incidence(side: str, n_out: complex, n_in: complex, ti: float, pi_: float, K: int, max_bounces: int,
               split: bool, subtiles: tuple | None = None) -> _Incidence:
    wi = direction(ti, pi_)                                    # table frame, toward the source
    k_in = -wi if side == "outside" else np.array([-wi[0], -wi[1], wi[2]])
    from_below = side == "inside"
    n_above = n_out.real
    n_below = n_in if n_in.imag > 0 else n_in.real
    s_init = s_axis(k_in[None, :], math.radians(pi_))[0] if K else None
    spec_R = np.array([k_in[0], k_in[1], -k_in[2]])
    n1, n2 = (n_above, n_below) if not from_below else (n_below, n_above)
    eta = float(np.real(n1) / np.real(n2))
    sin2t = eta**2 * (1 - k_in[2] ** 2)
    spec_T = None
    if sin2t < 1 and not (np.iscomplexobj(n2) and np.imag(n2) > 0):
        spec_T = np.array([eta * k_in[0], eta * k_in[1], math.copysign(math.sqrt(1 - sin2t), k_in[2])])
    return _Incidence(side, k_in, from_below, Media(n_above, n_below), s_init, (spec_R, spec_T),
                      (0, 1) if side == "outside" else (1, 0),
                      TraceSettings(max_bounces, split, math.radians(pi_ + 180.0), subtiles))


@dataclass
class _Tally:
    """A chunk's exits in table cells (builder) plus the engine's counters."""

    acc: CellAccumulator
    segments: int = 0
    paths: int = 0
    exits: int = 0
    bounce_sum: float = 0.0

    def merge(self, other: "_Tally") -> None:
        self.acc.merge(other.acc)
        self.segments += other.segments
        self.paths += other.paths
        self.exits += other.exits
        self.bounce_sum += other.bounce_sum


def _merged(total: _Tally | None, t: _Tally) -> _Tally:
    """total + t (the chunk's tally t itself when there is no total yet)."""
    if total is None:
        return t
    total.merge(t)
    return total


def _new_tally(cells: CellIndex, K: int, subtiles: tuple | None = None) -> _Tally:
    G = 0 if subtiles is None else int(subtiles[0] * subtiles[1])
    return _Tally(CellAccumulator(cells, bool(K), tuple(STATE_NAMES.values()), n_groups=G if G >= 2 else 0))


def _bin_exits(t: _Tally, ex: Exits, inc: _Incidence, cos_tol: float) -> None:
    """Hand one chunk's exits to the builder: lost states by name, the rest as exit samples."""
    t.segments += ex.segments
    t.paths += ex.n_paths
    k, w, state, nb, A = ex.records()
    by_path = bool(t.acc.n_groups) and ex.first_group is not None
    if by_path:
        t.acc.count_paths(ex.first_group)
    done, all_done = None, True
    if state.size and state.max() > BELOW:
        for code, name in STATE_NAMES.items():
            sel = state == code
            if sel.any():
                t.acc.lose(name, float(w[sel].sum(dtype=np.float64)))
        done = np.flatnonzero(state <= BELOW)
        all_done = done.size == state.size
    n_done = state.size if all_done else done.size
    t.exits += n_done
    t.bounce_sum += float(nb.sum(dtype=np.float64) if all_done else nb[done].sum(dtype=np.float64))
    if n_done == 0:
        return
    kd, wd, st = (k, w, state) if all_done else (k[done], w[done], state[done])
    grp = None
    if by_path:                          # the groups of the exits' paths, looked up in the binning (`ExitSamples`)
        grp = (ex.first_group, ex.ids[:ex.n] if all_done else ex.ids[:ex.n][done], ex.n_paths)
    side = st if inc.side_of_state[0] == 0 else (1 - st)        # ABOVE = 0, BELOW = 1
    M = compact = None
    if A is not None:
        M = A.reshape(16, -1) if all_done else np.take(A.reshape(16, -1), done, axis=1)
        if ex.compact is not None:
            compact = ex.compact[:ex.n] if all_done else ex.compact[done]
    t.acc.add(ExitSamples(kd, wd, side, M, specular_flags(kd, side, inc.ideal_dirs, cos_tol), None, compact, grp))


def _repeat_row(v: np.ndarray, n: int) -> np.ndarray:
    """(n, len(v)) C-contiguous array whose every row is v: written by doubling copies of the rows
    already filled (log2 n block copies; numpy's copy of a stride-0 broadcast is ~15x slower)."""
    out = np.empty((n, v.size), v.dtype)
    if n == 0:
        return out
    out[0] = v
    m = 1
    while m < n:
        c = min(m, n - m)
        out[m:m + c] = out[:c]
        m += c
    return out


def _beam(inc: _Incidence, sigma_deg: float, n: int, rng: np.random.Generator) -> tuple[np.ndarray, Any]:
    """((n, 3) float32 ray directions, s-axis of their Stokes basis) of one chunk's beam.

    Collimated (sigma 0): every ray along the incidence, the incidence's s-axis.  Divergent: each
    ray's direction drawn around it by `core.frames.beam_directions` (a 2-D Gaussian of 1-sigma
    `sigma_deg` per axis, the validation Monte Carlo's and the photon engine's law), and its s-axis
    the incidence's made normal to the ray: the source's polarisation is fixed in the laboratory,
    so a ray tilted off the plane of incidence keeps the lab's s direction, not that of its own plane.
    The table then holds the beam's average over its directions (power-weighted: every ray carries the
    same power), which is what a detector sees of a divergent source; a flat patch's mirror exit is
    spread with the beam and lands in the cells, not in the specular delta."""
    if sigma_deg <= 0:
        return _repeat_row(inc.k_in.astype(F32), n), inc.s_init
    k = beam_directions(inc.k_in, sigma_deg, n, rng)
    s0 = inc.s_init
    if s0 is not None:
        s0 = normalize(s0 - (k @ s0)[:, None] * k).astype(F32)
    return k.astype(F32), s0


def _azimuth_spread(k: np.ndarray, s_init: Any, half_width_deg: float,
                    rng: np.random.Generator, turn_deg: float = 0.0) -> tuple[np.ndarray, Any, np.ndarray]:
    """(directions, s-axes, (2, n) cos / sin of each ray's offset) of a beam whose incidence azimuths are
    spread uniformly over +-`half_width_deg` about z (`RayOptions.phi_i_spread_deg`): each ray and its
    polarisation basis turned by its own offset, the whole incidence rigidly about the mean plane's
    normal.  `_turn_exits_back` turns the exits by minus the same offsets, so that every ray is seen
    from the frame of the request's azimuth: the table is the average over the sector's incidence
    azimuths of what each scatters relative to its own incidence (a relief's response to a turned
    beam, sampled continuously in azimuth, not at the sector's centre only).  `turn_deg`
    (`RayOptions.phi_i_turn_deg`) adds one fixed offset to every ray: the relief lit from that azimuth,
    seen from the frame of its incidence (no random number drawn when the spread is 0)."""
    a = np.radians(rng.uniform(-half_width_deg, half_width_deg, k.shape[0])) if half_width_deg else np.zeros(k.shape[0])
    a = a + np.radians(turn_deg)
    cs = np.stack([np.cos(a), np.sin(a)]).astype(F32)
    k = rotate_z_rows(k, cs[0], cs[1])
    if s_init is not None:
        s_init = rotate_z_rows(np.broadcast_to(np.asarray(s_init, F32), k.shape), cs[0], cs[1])
    return k, s_init, cs


def _turn_exits_back(ex: Exits, cs: np.ndarray, phi_exit_rad: float) -> None:
    """Turn each exit record's direction by minus its input ray's offset (`_azimuth_spread`).  The
    Stokes columns are in the exit frame s = z x k, which turns with k about z: they stay as they are,
    except along z, where the frame is the fixed fallback azimuth `phi_exit_rad`
    (`TraceSettings.phi_exit_rad`), which did not turn with the ray: those columns are re-expressed in
    the fallback frame turned by the ray's offset, which the turn back brings onto the fixed one."""
    e = ex.n
    i = ex.ids[:e] % cs.shape[1]                  # the first-hit split's transmitted branch is id + n
    k = ex.k[:e]
    if ex.A is not None:
        zi = np.flatnonzero(k[:, 0] * k[:, 0] + k[:, 1] * k[:, 1] < ALONG_Z_XY2)
        if zi.size:
            c, sn = cs[0, i[zi]], cs[1, i[zi]]
            s_from = s_axis_rows(k[zi], phi_exit_rad)          # the frame the exit was written in
            s_to = rotate_z_rows(s_from, c, sn)
            cols = ex.A[:, :, zi]
            rotate_stokes_columns_cd(cols, dot_rows(s_from, s_to), dot_rows(cross_rows(s_from, k[zi]), s_to))
            ex.A[:, :, zi] = cols
    ex.k[:e] = rotate_z_rows(k, cs[0, i], -cs[1, i])


def _incidence_task(ctx: _RayContext, task: tuple) -> dict:
    """Trace one (side, wavelength, incidence) with `ctx.samples` rays; its finished table rows.

    Module-level `map_tasks` function.  The rays go in fixed chunks of CHUNK, each with its own
    generator `task_rng(seed, side, wavelength, theta, phi, chunk)`, over one Embree thread in a
    pool worker and `threads` (default every core) in this process; chunk results are summed in
    chunk order, so the numbers do not depend on the backend or the thread count.
    """
    si, side, iw, ii, ip, n_out, n_in, ti, pi_ = task
    tracer = ctx.get_tracer()
    threads = 1 if in_worker() or in_task_thread() else ctx.threads_here(tracer)
    K = 4 if ctx.polarized else 0
    cells = cell_index(ctx.te, ctx.pe)
    Lx, Ly = float(tracer.Lx), float(tracer.Ly)
    nxs, nys, _, strata_iy, strata_ix = worker_cached(("ray.strata", ctx.samples, Lx, Ly),
                                                      lambda: _beam_strata(ctx.samples, Lx, Ly))
    N = nxs * nys
    chunks = [(lo, min(N, lo + CHUNK)) for lo in range(0, N, CHUNK)]
    inc = _incidence(side, n_out, n_in, ti, pi_, K, tracer.max_bounces, ctx.first_hit_split, ctx.subtiles)

    def job(ci):
        lo, hi = chunks[ci]
        rng = task_rng(ctx.seed, si, iw, ii, ip, ci)
        iy, ix = strata_iy[lo:hi], strata_ix[lo:hi]
        jit = rng.random((hi - lo, 2))
        o = np.empty((hi - lo, 3), F32)
        sx, sy, z = tracer.Lx / nxs, tracer.Ly / nys, tracer.z_bot if inc.from_below else tracer.z_top
        kernels.beam_origins(ix.astype(np.int64, copy=False), iy.astype(np.int64, copy=False), jit, float(sx),
                             float(tracer.hx), float(sy), float(tracer.hy), z, o)
        k, s_init = _beam(inc, ctx.beam_divergence_deg, hi - lo, rng)
        turn = None
        if ctx.phi_i_spread_deg or ctx.phi_i_turn_deg:
            k, s_init, turn = _azimuth_spread(k, s_init, ctx.phi_i_spread_deg, rng, ctx.phi_i_turn_deg)
        rays = Rays(o, k, np.full(hi - lo, inc.from_below),
                    np.ones(hi - lo, F32), np.zeros(hi - lo, np.int16), np.arange(hi - lo, dtype=np.int64),
                    None)                      # polarised: None = the identity columns (StokesCarrier)
        ex = trace_chunk(tracer, rays, carrier_for(K), inc.media, inc.settings, rng, s_init=s_init)
        if turn is not None:
            _turn_exits_back(ex, turn, inc.settings.phi_exit_rad)
        t = _new_tally(cells, K, ctx.subtiles)
        _bin_exits(t, ex, inc, ctx.cos_tol)
        return t

    t0 = time.perf_counter()
    # chunk sums added in chunk order; the first chunk's tally is the total's start (what adding it to zeros gives:
    # 0 + x is x bit for bit, a sum that starts at +0 never being -0), without a zeroed total and one pass over it
    total = None
    if threads > 1 and len(chunks) > 1:
        with ThreadPoolExecutor(max_workers=min(threads, len(chunks))) as pool:
            for t in pool.map(job, range(len(chunks))):       # chunk order: deterministic sums
                total = _merged(total, t)
    else:
        for ci in range(len(chunks)):
            total = _merged(total, job(ci))
    if total is None:
        total = _new_tally(cells, K, ctx.subtiles)
    out = _task_rows(total, side, K)
    out["diag"] = {"wavelength_nm": None, "theta_i_deg": float(ti), "phi_i_deg": float(pi_), **out["diag"],
                   "trace_s": time.perf_counter() - t0, "build_s": tracer.build_s,
                   "ray_kernel": kernels.name()}       # where the task ran (a worker process: its own)
    m = tracer.mesh
    out["mesh"] = {"rays": int(N), "triangles": m.n_triangles, "tile_samples": list(m.shape),
                   "mirror_extended": m.mirrored, "history": list(m.history)}
    return out


def _task_rows(total: _Tally, side: str, K: int) -> dict:
    """The builder's rows of one task, in the table's frame (mirrored Mueller matrices from inside)."""
    c = total.acc.table_cells(float(total.paths))
    out = {"vals": c.values_per_sr, "sig": c.sigma_per_sr, "specR": c.specular_R, "specT": c.specular_T,
           "lost": c.lost, "mue": None, "smR": None, "smT": None}
    if K:
        dd = _MIRROR_DD if side == "inside" else 1.0
        # from outside the builder's float32 rows as they are (times 1.0 they would be the same numbers, copied twice)
        mue = c.mueller_per_sr
        out["mue"] = (mue * dd).astype(F32) if side == "inside" else mue.astype(F32, copy=False)
        out["smR"] = c.specular_mueller_R * dd
        out["smT"] = c.specular_mueller_T * dd
        out["vals"] = out["mue"][..., 0, 0].copy()
    out["diag"] = {"rays": int(total.paths), "segments": int(total.segments),
                   "mean_bounces": total.bounce_sum / max(total.exits, 1), "lost": c.lost_detail,
                   "outside_table": c.outside_table, "tile_scatter": _tile_scatter(c)}
    return out


def _tile_scatter(c) -> dict | None:
    """Relative realisation scatter of the lobe's cells (those holding the brightest half of the
    diffuse power): median of sigma_tile / value and of sigma_tile / sigma_total there."""
    if c.sigma_tile_per_sr is None:
        return None
    v = np.asarray(c.values_per_sr, np.float64).ravel()
    st = np.asarray(c.sigma_tile_per_sr, np.float64).ravel()
    sg = np.asarray(c.sigma_per_sr, np.float64).ravel()
    if not np.any(v > 0):
        return {"lobe_rel": 0.0, "lobe_tile_share": 0.0}
    order = np.argsort(v)[::-1]
    cum = np.cumsum(v[order])
    lobe = order[:int(np.searchsorted(cum, 0.5 * cum[-1])) + 1]
    return {"lobe_rel": float(np.median(st[lobe] / v[lobe])),
            "lobe_tile_share": float(np.median(st[lobe] / np.maximum(sg[lobe], 1e-300)))}


# ----------------------------------------------------------------------------- reconstruct


def reconstruct(relief: Relief, material, request, progress=None) -> list[BsdfTable]:
    """Ray-trace the relief for every (wavelength, incidence, side) of the request (package doc).

    Options (request.options): polarized (True: Mueller matrices per cell), max_bounces (100),
    first_hit_split (True), specular_tol_rad (1e-5), fill_holes (None: refuse NaN; True or max
    gap in px: Laplace filling), threads (this process; default every core), backend
    (map_tasks backend; default as configured).  `request.samples` rays per incidence.
    """
    opts = check_request(relief, material, request)
    return _reconstruct(None, relief, material, request, progress, opts)


def reconstruct_with(tracer: ReliefTracer, relief: Relief, material, request, progress=None) -> list[BsdfTable]:
    """`reconstruct` with an already built tracer (reuse one BVH across requests, e.g. in fits).

    The tracer is used for the tasks that run in this process (serial backend, a single
    incidence); worker processes build their own.
    """
    opts = check_request(relief, material, request)
    if opts.threads:
        tracer.threads = int(opts.threads)
    return _reconstruct(tracer, relief, material, request, progress, opts)


def _task_list(material, request) -> list[tuple]:
    tasks = []
    for si, side in enumerate(request.incident_from):
        for iw, wl in enumerate(request.wavelengths_nm):
            n_from, n_to = material.n_pair(wl, side)
            n_out, n_in = (n_from, n_to) if side == "outside" else (n_to, n_from)
            for ii, ti in enumerate(request.theta_i_deg):
                for ip, pi_ in enumerate(request.phi_i_deg):
                    tasks.append((si, side, iw, ii, ip, complex(n_out), complex(n_in), float(ti), float(pi_)))
    return tasks


def _empty_rows(request, K: int) -> dict:
    """One side's table arrays, filled task by task (float32 for the big arrays)."""
    W, I, P = len(request.wavelengths_nm), len(request.theta_i_deg), len(request.phi_i_deg)
    S, A_ = len(request.theta_s_edges_deg) - 1, len(request.phi_s_edges_deg) - 1
    return {"vals": np.zeros((W, I, P, 2, S, A_), F32), "sig": np.zeros((W, I, P, 2, S, A_), F32),
            "mue": np.zeros((W, I, P, 2, S, A_, 4, 4), F32) if K else None,
            "specR": np.zeros((W, I, P)), "specT": np.zeros((W, I, P)), "lost": np.zeros((W, I, P)),
            "smR": np.zeros((W, I, P, 4, 4)) if K else None, "smT": np.zeros((W, I, P, 4, 4)) if K else None,
            "diag": {}}


def _reconstruct(tracer, relief, material, request, progress, opts) -> list[BsdfTable]:
    t0 = time.perf_counter()
    ctx = _RayContext(relief, opts, request, tracer)
    tasks = _task_list(material, request)
    sides = [_empty_rows(request, 4 if opts.polarized else 0) for _ in request.incident_from]
    build_s = [tracer.build_s] if tracer is not None else []
    mesh_seen: list = []

    def collect(i, r):
        si, _, iw, ii, ip = tasks[i][:5]
        d = sides[si]
        for name in _ROWS:
            if d[name] is not None:
                d[name][iw, ii, ip] = r[name]
        diag = dict(r["diag"])
        diag["wavelength_nm"] = float(request.wavelengths_nm[iw])
        build_s.append(diag.pop("build_s"))
        if not mesh_seen:
            mesh_seen.append(r["mesh"])
        d["diag"][(iw, ii, ip)] = diag

    t_trace = time.perf_counter()
    threads = ctx.threads_here(tracer)
    chunks_per_task = -(-ctx.samples // CHUNK)     # about: the strata round the samples up a little
    try:
        map_tasks(_incidence_task, tasks, ctx, progress=progress or silent, label="ray tracing",
                  backend=opts.backend, on_result=collect,
                  threads=threads if chunks_per_task < threads else 1)   # else the chunks share the cores
    finally:
        if tracer is None:
            forget_tracer(ctx.tracer_key)             # a BVH built here is not kept past the request
        trim_heap(collect=False)                      # the bounce loop's kept temporaries go back
    mesh_info = dict(mesh_seen[0]) if mesh_seen else {}
    run = _Run(relief, material, request, opts, mesh_info, mesh_info.pop("rays", 0),
               {"build": max(build_s) if build_s else 0.0, "trace_all_sides": time.perf_counter() - t_trace}, t0,
               {"subtiles": None if ctx.subtiles is None else list(ctx.subtiles),
                "correlation_areas": ctx.corr_areas, "correlation_length_m": ctx.corr_length_m})
    return [_table(side, sides[si], run) for si, side in enumerate(request.incident_from)]


def _uncertainty_meta(side: str, diag: list, run: "_Run") -> tuple[dict, list]:
    """What sigma_per_sr contains, and the warning when the tile is too small for the cells."""
    t = run.tile
    if t["subtiles"] is None:
        return {"sigma": "Monte-Carlo only (option tile_uncertainty=False)"}, []
    rel = [d["tile_scatter"]["lobe_rel"] for d in diag if d.get("tile_scatter")]
    worst = max(rel) if rel else 0.0
    gx, gy = t["subtiles"]
    areas = "an unknown number of" if t["correlation_areas"] is None else f"{t['correlation_areas']:.0f}"
    info = {"sigma": "Monte-Carlo and the tile's realisation uncertainty (sub-tile batch means)",
            "subtiles": [gx, gy], "correlation_areas": t["correlation_areas"],
            "correlation_length_m": t["correlation_length_m"], "lobe_relative_tile_sigma_max": worst}
    warn = []
    if gx * gy < 16:
        warn.append(f"ray table ({side}): the tile holds only {gx} x {gy} sub-tiles of {SUBTILE_CORR:g} "
                    f"correlation lengths ({areas} correlation areas): its realisation "
                    "uncertainty is poorly known (sigma may be low); use a larger tile")
    if worst > TILE_WARN_REL:
        warn.append(f"ray table ({side}): the tile holds {areas} correlation areas, too few "
                    f"for the cells asked for: the lobe's cells scatter by up to {100 * worst:.0f} % between "
                    "tile realisations (included in sigma_per_sr); use a larger tile or coarser cells")
    for w in warn:
        warnings.warn(w, RuntimeWarning, stacklevel=4)
    return info, warn


@dataclass
class _Run:
    """What every table of a request shares: inputs, options, mesh facts, timings."""

    relief: Relief
    material: object
    request: object
    opts: RayOptions
    mesh_info: dict
    rays: int
    timing: dict
    t0: float
    tile: dict


def _table(side: str, d: dict, run: _Run) -> BsdfTable:
    """One side's BsdfTable from its filled rows and the run's metadata."""
    relief, material, request, opts = run.relief, run.material, run.request, run.opts
    diag = [d["diag"][key] for key in sorted(d["diag"])]
    uncertainty, warn = _uncertainty_meta(side, diag, run)
    meta = {"request": {"samples_requested": int(request.samples), "rays_per_incidence": run.rays,
                        "seed": int(request.seed), "options": opts.as_mapping()},
            "mesh": dict(run.mesh_info),
            "max_bounces": int(opts.max_bounces),
            "timing_s": {**run.timing, "total": time.perf_counter() - run.t0},
            "parallel": last_run(),
            "ray_kernel": "+".join(sorted({d["ray_kernel"] for d in diag})) if diag else kernels.name(),
            "tasks": diag,
            "uncertainty": uncertainty,
            "warnings": warn,
            "notes": ["geometric optics: valid when relief features >> wavelength",
                      "Stokes bases: s = z x k / |z x k|, p = s x k with k the propagation direction, "
                      "in the table's frame (mirrored for light from inside, as bsdf.py)",
                      "lost = max bounces + numerical leaks + absorbed + exits outside the table's cells"]}
    return BsdfTable(
        wavelength_nm=np.asarray(request.wavelengths_nm, float), theta_i_deg=np.asarray(request.theta_i_deg),
        phi_i_deg=np.asarray(request.phi_i_deg), theta_s_edges_deg=np.asarray(request.theta_s_edges_deg, float),
        phi_s_edges_deg=np.asarray(request.phi_s_edges_deg, float),
        values_per_sr=d["vals"], incident_from=side, specular_R=d["specR"], specular_T=d["specT"],
        lost=d["lost"], sigma_per_sr=d["sig"], mueller_per_sr=d["mue"], specular_mueller_R=d["smR"],
        specular_mueller_T=d["smT"], method="ray", material=material.describe(), relief=relief.describe(),
        metadata=meta)
