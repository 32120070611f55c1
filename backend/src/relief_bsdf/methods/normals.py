"""`normals`: Monte Carlo on the density of facet normals (random bump mapping), paper sec. 2.2.

The relief enters only through the *distribution* of its facet normals; positions, and so
real shadowing and inter-reflection geometry, are forgotten.  It is the fast approximate
method the paper criticises, implemented honestly so it can be compared with `ray`
(same table axes, same normalisation, same delta and `lost` bookkeeping).

Model
-----
- Facets: the two triangles of every grid cell of the height map (split along the
  h00-h11 diagonal, the piecewise-linear surface), each with slope (sx, sy); every triangle
  covers the same projected area dx dy / 2, so a uniform draw over triangles samples the
  slope density P22 weighted by projected area, which is the density behind a microfacet
  D(m) (D(m) cos(theta_m) dw_m = projected-area fraction).  Triangles with an invalid
  corner are dropped.  The measured slopes are used as they are (no tilt removal, as `ray`).
- Which facet a ray meets: a ray travelling along d meets a facet with a probability
  proportional to the facet's cross-section seen along the ray, (area / m_z) * max(0, -d.m)
  for the facet normal m facing the ray's medium, i.e. proportional to
  sigma (d_x sx + d_y sy - d_z) (sigma = +1 above, -1 below the boundary) per triangle.
  The facet is drawn by rejection sampling against the exact maximum over the convex hull
  of the slope set.  For the first hit this is the Smith visible-normal density
  G1(wi) max(0, wi.m) D(m) / cos(theta_i) (Heitz 2014, eq. 38), so single scattering reproduces
  Walter's BSDF with G = G1(wi) and no masking of the exit direction
  (`microfacet.walter_bsdf(..., Roughness(alpha, shadowing="incident"))`) - what this method should agree
  with, for gentle slopes where rescattering is rare.
- At the facet: unpolarised Fresnel reflectance F (optics.fresnel_unpolarized) decides
  reflect or refract by Russian roulette (weights stay 1: energy is conserved ray by ray in
  a lossless medium); Snell refraction; total internal reflection is F = 1.
- Invalid directions (paper sec. 2.2): a ray whose new direction points back into the
  boundary (reflected downward above it, or refracted upward below it) meets another
  facet drawn the same way, and again, until it leaves in a proper direction.
- Grazing heuristic (paper sec. 2.2, option `grazing_heuristic`, off by default): a ray
  leaving properly but near grazing is sent to another facet with probability p(theta),
  zero along the macroscopic normal and maximal at grazing.  "smith": p = 1 - G1(theta)
  = Lambda / (1 + Lambda) with the Beckmann Lambda of the relief's rms slope (the Smith
  probability that the exit direction is masked); "cosine": p = 1 - |cos theta|.  Only
  facets that face the ray can be met (if none does, the ray leaves).
- Detector: the exit direction is binned into the request's (theta_s, phi_s) cells; f =
  count / (N * projected solid angle) as in `ray`, so `hemispherical()` gives power
  fractions; exits within `specular_tol_rad` of the flat mean plane's mirror / refraction
  direction go to `specular_R/T` (only exactly flat facets produce them).
- `lost`: transmission into an absorbing medium, rays still bouncing after `max_bounces`,
  rays that can meet no facet; the split is in metadata.  Nothing is dropped silently.
- Uncertainty: sigma = Monte-Carlo noise combined with the finite tile's realisation uncertainty
  (option tile_uncertainty, default True): every path is tagged with the sub-tile of its first
  facet (sub-tiles of methods.realisation.subtile_grid, as `ray`) and the builder's sub-tile
  batch means (bsdf.builder) add the scatter another tile of the same statistics would give.
  Later facets are drawn from the whole tile, so their share of the realisation scatter is not
  seen: exact for single scattering (gentle slopes), low where rescattering matters.
Light from inside: the frame is mirrored (+z into the medium of incidence), which negates
the slopes.  Validity: geometric optics, and the assumption that successive facets are
statistically independent of each other and of the ray position (no correlation of
heights): wrong at grazing angles and high slopes, which is the paper's point.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from relief_bsdf.bsdf.builder import CellAccumulator, CellIndex, ExitSamples, specular_flags
from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.frames import direction
from relief_bsdf.errors import InputError, RequestError
from relief_bsdf.core.fresnel import fresnel_unpolarized, refract
from relief_bsdf.parallel import map_tasks, task_rng
from relief_bsdf.core.microfacet import smith_G1
from relief_bsdf.methods.options import HEURISTICS, NormalsOptions  # noqa: F401  (HEURISTICS: one list)
from relief_bsdf.methods.realisation import facet_groups, subtile_grid, uncertainty_meta

MIN_FACETS = 64


# ------------------------------------------------------------------ facets


def triangle_slopes(relief) -> tuple[np.ndarray, np.ndarray]:
    """Slopes (sx, sy) of the valid triangles of the piecewise-linear relief (2 per grid cell).

    The one facet definition, `surface.stats.facet_slopes` (the triangles of surface.mesh).
    """
    from relief_bsdf.surface.stats import facet_slopes
    sx, sy = facet_slopes(relief)
    sx, sy = sx.ravel(), sy.ravel()
    ok = np.isfinite(sx) & np.isfinite(sy)
    return sx[ok], sy[ok]


class SlopeSet:
    """Facet slopes and the convex hull of the slope points (for exact rejection bounds)."""

    def __init__(self, sx: np.ndarray, sy: np.ndarray, group: np.ndarray | None = None, n_groups: int = 0):
        self.sx = np.ascontiguousarray(sx, float)
        self.sy = np.ascontiguousarray(sy, float)
        self.group = None if group is None or n_groups < 2 else np.asarray(group, np.int64)   # sub-tile per facet
        self.n_groups = int(n_groups) if self.group is not None else 0
        if self.sx.size == 0:
            raise InputError("relief", "no valid facets (every triangle has an invalid corner)")
        pts = np.column_stack([self.sx, self.sy])
        try:
            hull = ConvexHull(pts)
            v = pts[hull.vertices]
        except (QhullError, ValueError):           # flat or collinear slopes: the bounding box bounds them
            v = np.array([[pts[:, 0].min(), pts[:, 1].min()], [pts[:, 0].min(), pts[:, 1].max()],
                          [pts[:, 0].max(), pts[:, 1].min()], [pts[:, 0].max(), pts[:, 1].max()]])
        self.hull = v                                # (H, 2)
        self.rms_slope = float(np.sqrt(np.mean(self.sx**2 + self.sy**2)))

    def cross_section(self, d: np.ndarray, sigma: np.ndarray, j: np.ndarray | None = None) -> np.ndarray:
        """sigma (d_x sx + d_y sy - d_z): relative cross-section of facet(s) j seen by rays d (or the hull max)."""
        if j is None:
            c = d[:, 0:1] * self.hull[None, :, 0] + d[:, 1:2] * self.hull[None, :, 1] - d[:, 2:3]
            return np.max(sigma[:, None] * c, axis=1)
        return sigma * (d[:, 0] * self.sx[j] + d[:, 1] * self.sy[j] - d[:, 2])


def _draw_facets(slopes: SlopeSet, d: np.ndarray, sigma: np.ndarray, rng, max_tries: int = 400,
                 same_direction: bool = False):
    """Facet index per ray by rejection; -1 where no facet faces the ray (or sampling gave up)."""
    n = d.shape[0]
    out = np.full(n, -1, np.int64)
    if same_direction:                   # first hit: one incident direction for the whole beam
        cmax = np.full(n, slopes.cross_section(d[:1], sigma[:1])[0])
    else:
        cmax = slopes.cross_section(d, sigma)
    todo = np.nonzero(cmax > 1e-15)[0]
    M = slopes.sx.size
    for _ in range(max_tries):
        if todo.size == 0:
            break
        j = rng.integers(0, M, size=todo.size)
        c = slopes.cross_section(d[todo], sigma[todo], j)
        acc = rng.random(todo.size) * cmax[todo] < c
        out[todo[acc]] = j[acc]
        todo = todo[~acc]
    return out


# ------------------------------------------------------------------ tracing


@dataclass(frozen=True)
class NormalsBeam:
    """A parallel beam on the boundary: `wi` toward the source (z > 0), the index of the medium
    it arrives in (`n_incident`, above in the frame of incidence) and of the other side
    (`n_other`, below), and the number of paths `n_rays` to trace."""

    wi: np.ndarray
    n_incident: complex
    n_other: complex
    n_rays: int


@dataclass
class _Run:
    """What every batch of one `trace_normals` call shares (the tallies are updated in place)."""

    slopes: SlopeSet
    opts: NormalsOptions
    n_idx: tuple                       # (index of the incidence medium, index of the other)
    absorbing: tuple                   # (incidence medium absorbs, other medium absorbs)
    specular: tuple                    # mirror direction, flat-plane refraction direction (or None)
    acc: CellAccumulator
    tally: dict


def trace_normals(slopes: SlopeSet, beam: NormalsBeam, rng, theta_edges_deg, phi_edges_deg,
                  opts: NormalsOptions = NormalsOptions()) -> dict:
    """Trace `beam.n_rays` paths arriving along beam.wi (module doc) with the options `opts`
    (grazing_heuristic, max_bounces, specular_tol_rad, batch).

    Returns counts (2, S, A) of exits per cell (R above, T below), the delta-part counts,
    and the lost counts (absorbed, max_bounces, no_facet) and the mean number of facet
    events per path.  Vectorised over rays; the loop runs over bounce number.
    """
    te = np.asarray(theta_edges_deg, float)
    pe = np.asarray(phi_edges_deg, float)
    S, A = te.size - 1, pe.size - 1
    n_a, n_b, n_rays = beam.n_incident, beam.n_other, int(beam.n_rays)
    absorbing = (np.imag(n_a) > 0, np.imag(n_b) > 0)
    wi = np.asarray(beam.wi, float)
    spec_R = np.array([-wi[0], -wi[1], wi[2]])
    wt, ok_t = refract(wi[None, :], np.array([[0.0, 0.0, 1.0]]), np.real(n_a) / np.real(n_b))
    spec_T = wt[0] if (bool(ok_t[0]) and not absorbing[1]) else None
    run = _Run(slopes, opts, (complex(n_a), complex(n_b)), absorbing, (spec_R, spec_T),
               CellAccumulator(CellIndex(te, pe), lost_names=("absorbed", "max_bounces", "no_facet"),
                               n_groups=slopes.n_groups),
               {"specular_R": 0, "specular_T": 0, "absorbed": 0, "max_bounces": 0, "no_facet": 0, "events": 0})
    for lo in range(0, n_rays, opts.batch):
        _trace_batch(run, np.tile(-wi, (min(opts.batch, n_rays - lo), 1)), rng)
    acc, tally = run.acc, run.tally
    for name in ("absorbed", "max_bounces", "no_facet"):
        acc.lose(name, tally[name])
    tally["specular_R"], tally["specular_T"] = float(acc.spec[0]), float(acc.spec[1])
    return {"counts": acc.sum_w.reshape(2, S, A), "n_rays": n_rays, **tally,
            "outside_table": acc.outside_table, "cells": acc.table_cells(n_rays),
            "events_per_path": tally["events"] / max(n_rays, 1)}


def _trace_batch(run: _Run, d: np.ndarray, rng) -> None:
    """Bounce the rays d (all in the incidence medium) until they leave or are lost; bin the exits."""
    med = np.zeros(d.shape[0], np.int8)              # 0: incidence medium (above), 1: other (below)
    grp = None                                       # sub-tile of each path's first facet (tile uncertainty)
    cos_tol = np.cos(run.opts.specular_tol_rad)
    for bounce in range(run.opts.max_bounces + 1):
        if d.shape[0] == 0:
            break
        sigma = np.where(med == 0, 1.0, -1.0)
        need = _needs_facet(run, d, sigma, bounce, rng)
        leave = ~need
        if leave.any():                               # the one table builder bins the exits
            dl, ml = d[leave], med[leave]
            run.acc.add(ExitSamples(dl, np.ones(dl.shape[0]), ml, None, specular_flags(dl, ml, run.specular, cos_tol),
                                    None if grp is None else grp[leave]))
        d, med, sigma = d[need], med[need], sigma[need]
        grp = None if grp is None else grp[need]
        if d.shape[0] == 0:
            break
        j = _draw_facets(run.slopes, d, sigma, rng, same_direction=bounce == 0)
        if bounce == 0 and run.slopes.group is not None:   # every path meets its first facet here
            grp = np.where(j >= 0, run.slopes.group[np.maximum(j, 0)], np.arange(j.size) % run.slopes.n_groups)
            run.acc.count_paths(grp)
        none = j < 0
        if none.any():
            run.tally["no_facet"] += int(none.sum())
            d, med, sigma, j = d[~none], med[~none], sigma[~none], j[~none]
            grp = None if grp is None else grp[~none]
        run.tally["events"] += d.shape[0]
        d, med, alive = _facet_event(run, d, med, sigma, j, rng)
        grp = None if grp is None else grp[alive]


def _needs_facet(run: _Run, d: np.ndarray, sigma: np.ndarray, bounce: int, rng) -> np.ndarray:
    """Rays that meet another facet: invalid directions, and grazing exits the heuristic sends back."""
    proper = sigma * d[:, 2] > 0                      # leaving the boundary in its own medium
    need = ~proper
    heuristic = run.opts.grazing_heuristic
    if heuristic and proper.any():
        cz = np.abs(d[proper, 2])
        p = (1.0 - smith_G1(cz, run.slopes.rms_slope, "beckmann")) if heuristic == "smith" else 1.0 - cz
        more = rng.random(cz.size) < p
        idx = np.nonzero(proper)[0][more]
        faces = run.slopes.cross_section(d[idx], sigma[idx]) > 1e-15
        need[idx[faces]] = True
    if bounce == run.opts.max_bounces:
        run.tally["max_bounces"] += int(need.sum())
        need[:] = False
    return need


def _facet_event(run: _Run, d: np.ndarray, med: np.ndarray, sigma: np.ndarray, j: np.ndarray, rng):
    """Fresnel roulette at facets j: reflect, refract (Snell; TIR keeps the mirror) or be absorbed.

    Returns the new unit directions and media of the rays still alive, and the mask of those.
    """
    nf = np.column_stack([-run.slopes.sx[j], -run.slopes.sy[j], np.ones(j.size)]) * sigma[:, None]
    nf /= np.linalg.norm(nf, axis=1, keepdims=True)   # facet normal facing the ray's medium
    cos_i = -np.einsum("ij,ij->i", d, nf)
    new_d = np.empty_like(d)
    new_med = med.copy()
    alive = np.ones(d.shape[0], bool)
    for k in (0, 1):
        sel = med == k
        if not sel.any():
            continue
        n1, n2 = run.n_idx[k], run.n_idx[1 - k]
        F = fresnel_unpolarized(np.clip(cos_i[sel], 0.0, 1.0), n1, n2)
        refl = rng.random(F.size) < F
        ds, ns, cs = d[sel], nf[sel], cos_i[sel]
        out = ds + 2.0 * cs[:, None] * ns
        if run.absorbing[1 - k] and (~refl).any():
            # transmitted into an absorbing medium (metal): absorbed, whatever Snell says
            a = alive[sel]
            a[~refl] = False
            alive[sel] = a
        elif (~refl).any():
            wt, ok = refract(-ds[~refl], ns[~refl], np.real(n1) / np.real(n2))
            tmp = out[~refl]
            tmp[ok] = wt[ok]                           # TIR (not ok) keeps the mirror direction
            out[~refl] = tmp
            moved = np.zeros(F.size, bool)
            moved[np.nonzero(~refl)[0][ok]] = True
            nm = new_med[sel]
            nm[moved] = 1 - k
            new_med[sel] = nm
        new_d[sel] = out
    run.tally["absorbed"] += int((~alive).sum())
    d, med = new_d[alive], new_med[alive]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d, med, alive


# ------------------------------------------------------------------ reconstruct


def check_request(relief, material, request) -> NormalsOptions:
    """Every reason to refuse, before any work; the typed options."""
    request.validate()
    opts = NormalsOptions.from_request(request)
    if relief is None:
        raise RequestError("the normals method needs a relief", "RELIEF")
    relief.require_valid()
    material.check_incidence(request.wavelengths_nm, request.incident_from)
    return opts


def _task(ctx: dict, task: tuple) -> dict:
    side_from, iw, ii, ip, key = task
    req = ctx["request"]
    wl = req.wavelengths_nm[iw]
    n_a, n_b = ctx["material"].n_pair(float(wl), side_from)
    slopes = ctx["slopes"][side_from]
    wi = direction(req.theta_i_deg[ii], req.phi_i_deg[ip])
    rng = task_rng(req.seed, *key)
    return trace_normals(slopes, NormalsBeam(wi, n_a, n_b, int(req.samples)), rng, req.theta_s_edges_deg,
                         req.phi_s_edges_deg, ctx["opts"])


def _uncertainty(side: str, vals, sig_tile, grid: tuple, areas, opts: NormalsOptions, edges) -> tuple[dict, list]:
    """metadata["uncertainty"] and the warnings (tile part of sigma above 10 % in the lobe: too few
    correlation areas for the cells asked for; methods.realisation.uncertainty_meta)."""
    if grid[0] * grid[1] < 2:
        why = " (option tile_uncertainty=False)" if not opts.tile_uncertainty else " (the tile holds one sub-tile)"
        return {"sigma": "Monte-Carlo only" + why}, []
    unc, warn = uncertainty_meta("normals", side, vals, sig_tile, "sub-tile batch means of the first facet, "
                                 "bsdf.builder", areas, edges, stacklevel=4)
    unc["sigma"] = "Monte-Carlo and " + unc["sigma"]
    unc["subtiles"] = list(grid)
    return unc, warn


def reconstruct(relief, material, request, progress=None) -> list[BsdfTable]:
    """Normal-density Monte Carlo tables for every side in `request.incident_from` (module doc).

    `request.samples` paths per incidence; options (NormalsOptions): grazing_heuristic (off | smith |
    cosine), max_bounces (100), specular_tol_rad (1e-5), batch.  Seeds: task_rng(seed, side, w, i, p).
    """
    opts = check_request(relief, material, request)
    t0 = time.perf_counter()
    sx, sy = triangle_slopes(relief)
    if sx.size < MIN_FACETS:
        raise RequestError(f"relief {relief.source or ''} has only {sx.size} valid facets; a slope distribution "
                           f"needs at least {MIN_FACETS}", "RELIEF")
    grid, areas, _ = subtile_grid(relief) if opts.tile_uncertainty else ((1, 1), None, None)
    G = grid[0] * grid[1]
    grp = facet_groups(relief, grid) if G >= 2 else None
    slopes = {"outside": SlopeSet(sx, sy, grp, G), "inside": SlopeSet(-sx, -sy, grp, G)}
    ctx = {"request": request, "material": material, "opts": opts,
           "slopes": {k: v for k, v in slopes.items() if k in request.incident_from}}
    W, I, P = len(request.wavelengths_nm), len(request.theta_i_deg), len(request.phi_i_deg)
    tasks = [(sf, iw, ii, ip, ({"outside": 0, "inside": 1}[sf], iw, ii, ip))
             for sf in request.incident_from for iw in range(W) for ii in range(I) for ip in range(P)]
    res = map_tasks(_task, tasks, ctx, progress=progress, label="normals")
    te, pe = np.asarray(request.theta_s_edges_deg, float), np.asarray(request.phi_s_edges_deg, float)
    N = float(request.samples)
    tables = []
    for sf in request.incident_from:
        vals = np.zeros((W, I, P, 2, te.size - 1, pe.size - 1))
        sig = np.zeros_like(vals)
        sig_tile = np.zeros_like(vals)
        spR, spT, lost = np.zeros((W, I, P)), np.zeros((W, I, P)), np.zeros((W, I, P))
        detail = []
        for (tsf, iw, ii, ip, _), r in zip(tasks, res):
            if tsf != sf:
                continue
            c = r["cells"]                                # the one table builder's rows
            vals[iw, ii, ip] = c.values_per_sr
            sig[iw, ii, ip] = c.sigma_per_sr
            if c.sigma_tile_per_sr is not None:
                sig_tile[iw, ii, ip] = c.sigma_tile_per_sr
            spR[iw, ii, ip] = c.specular_R
            spT[iw, ii, ip] = c.specular_T
            lost[iw, ii, ip] = c.lost
            detail.append({"wavelength_nm": float(request.wavelengths_nm[iw]),
                           "theta_i_deg": float(request.theta_i_deg[ii]), "phi_i_deg": float(request.phi_i_deg[ip]),
                           "absorbed": r["absorbed"] / N, "max_bounces": r["max_bounces"] / N,
                           "no_facet": r["no_facet"] / N, "events_per_path": r["events_per_path"]})
        unc, warn = _uncertainty(sf, vals, sig_tile, grid, areas, opts, (te, pe))
        desc = relief.describe()
        desc.update({"n_facets": int(sx.size), "rms_slope": slopes["outside"].rms_slope})
        tables.append(BsdfTable(request.wavelengths_nm, request.theta_i_deg, request.phi_i_deg, te, pe, vals,
                                incident_from=sf, specular_R=spR, specular_T=spT, lost=lost, sigma_per_sr=sig,
                                method="normals", material=material.describe(), relief=desc,
                                metadata={"model": "Monte Carlo on the density of facet normals (paper sec. 2.2)",
                                          "samples_per_incidence": int(request.samples), "seed": int(request.seed),
                                          "grazing_heuristic": opts.grazing_heuristic or "off",
                                          "max_bounces": opts.max_bounces, "lost_detail": detail,
                                          "uncertainty": unc, "warnings": warn,
                                          "seconds": time.perf_counter() - t0}))
    return tables
